"""Sampled (discrete-time) blocks in a continuous diagram, with python-control's semantics
x[k+1] = f(t_k, x[k], u[k]), y[k] = g(t_k, x[k], u[k]) at t_k = t0 + k h: the steps land on
every t_k, where the stepper calls :meth:`Sampling.sample` (update in the state vector, then
outputs and inputs held until t_{k+1}); between samples the block is a constant source whose
states have derivative 0.  docs/simulation.md, "Sampled blocks", says what it guarantees.
"""
from __future__ import annotations

import copy
import math

import numpy as np
import control as ct

from ..blocks._core import effective_params
from .errors import BlockError
from .foreign import ForeignSpec, _exec_functions, _ports, declare_feedthrough, direct_inputs

__all__ = ["sampled", "continuous_diagram", "sample_period", "Sampling", "SAMPLED_ATTRIBUTE"]

#: the attribute of a stand-in naming its discrete-time system and period
SAMPLED_ATTRIBUTE = "ivdrem_sampled"


def sample_period(sys):
    """h of a sampled block or a discrete-time system (0.0 for a continuous one)."""
    info = getattr(sys, SAMPLED_ATTRIBUTE, None)
    if info is not None:
        return info.dt
    dt = getattr(sys, "dt", 0)
    if dt in (None, 0, False):
        return 0.0
    if dt is True or not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"block '{sys.name}' has dt = {dt!r}: a sampled block needs a "
                         "positive, finite sample period")
    return float(dt)


class _SampledInfo:
    """A stand-in's discrete-time system, period, and the held outputs of the run evaluating
    it (set by :meth:`Sampling.bind`; None outside a run)."""

    def __init__(self, sys, dt):
        self.sys, self.dt, self.held = sys, dt, None


def sampled(sys):
    """The continuous-time stand-in of discrete-time block `sys` (dt = h > 0) for a
    continuous diagram: same name, signals, states and parameters; ivdrem's simulator
    updates it at t0 + k h and holds its outputs in between.  Its output function reads u
    directly exactly when `sys`'s does (its declaration, else the numerical probe)."""
    if getattr(sys, SAMPLED_ATTRIBUTE, None) is not None:
        return sys
    if not isinstance(sys, ct.InputOutputSystem) or isinstance(sys, ct.InterconnectedSystem):
        raise TypeError(f"sampled() takes one discrete-time block, got {type(sys).__name__}")
    h = sample_period(sys)
    if h == 0.0:
        raise ValueError(f"block '{sys.name}' is continuous-time (dt = 0); sampled() takes a "
                         "discrete-time system (dt = h > 0)")
    if isinstance(sys, ct.TransferFunction):
        sys = ct.ss(sys)
    info = _SampledInfo(sys, h)
    nx = sys.nstates

    def held_outputs(t, x, u, params):
        if info.held is None:
            raise RuntimeError(f"block '{sys.name}' is a sampled block (dt = {h}): simulate "
                               "its diagram with ivdrem.sim.simulate")
        return info.held.copy()

    stand_in = ct.nlsys(lambda t, x, u, params: np.zeros(nx), held_outputs,
                        inputs=list(sys.input_labels), outputs=list(sys.output_labels),
                        states=list(sys.state_labels), name=sys.name,
                        params=dict(getattr(sys, "params", {}) or {}), dt=0)
    setattr(stand_in, SAMPLED_ATTRIBUTE, info)
    declare_feedthrough(stand_in, list(direct_inputs(sys, getattr(sys, "params", None))))
    return stand_in


def continuous_diagram(diagram):
    """`diagram` itself if no block is discrete-time, else a copy whose discrete-time blocks
    are their :func:`sampled` stand-ins (the wiring is python-control's, unchanged)."""
    syslist = list(diagram.syslist)
    if not any(sample_period(s) > 0 and getattr(s, SAMPLED_ATTRIBUTE, None) is None
               for s in syslist):
        return diagram
    out = copy.copy(diagram)
    out.syslist = [sampled(s) if sample_period(s) > 0 else s for s in syslist]
    out.dt = 0
    return out


def kernel_spec(sys, address):
    """The compiled engine's kernels of a stand-in: the outputs copied from the run's held
    values (at `address`), state derivatives 0."""
    nx, ny = sys.nstates, sys.noutputs
    info = getattr(sys, SAMPLED_ATTRIBUTE)
    src_out = ("from numba import carray\nfrom ivdrem._native_call import float_pointer\n"
               f"def sampled_output_{ny}(t, x, u, out, address):\n"
               f"    held = carray(float_pointer(np.int64(address)), {ny})\n"
               f"    for i in range({ny}):\n        out[i] = held[i]\n")
    src_upd = (f"def sampled_update_{nx}(t, x, u, dx, address):\n"
               f"    for i in range({nx}):\n        dx[i] = 0.0\n")
    sources = {"output": (f"sampled_output_{ny}", src_out)}
    if nx:
        sources["update"] = (f"sampled_update_{nx}", src_upd)
    py = {"output": lambda t, x, u, out, address: out.__setitem__(slice(None), info.held),
          "update": _exec_functions(src_upd)[f"sampled_update_{nx}"]}
    ins, outs, states = _ports(sys)
    direct = direct_inputs(sys)
    return ForeignSpec(
        name=sys.name, inputs=ins, outputs=outs, states=states, x0=np.zeros(nx),
        param_names=("address",), output=py["output"], update=py["update"] if nx else None,
        direct=tuple(ins[i][0] for i in direct),
        validate=lambda p: {"address": float(address)}, sources=sources, runs="numba")


def _functions(sys, params):
    """{"update": f(t, x, u) -> x[k+1], "output": g(t, x, u) -> y[k]} of a discrete-time
    system, called as python-control calls them (a StateSpace's A, B, C, D)."""
    if isinstance(sys, ct.StateSpace):
        A, B, C, D = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
        return {"update": lambda t, x, u: A @ x + B @ u, "output": lambda t, x, u: C @ x + D @ u}
    upd, out = sys.updfcn, sys.outfcn
    return {"update": lambda t, x, u: upd(t, x, u, params),
            "output": (lambda t, x, u: out(t, x, u, params)) if out is not None else
            (lambda t, x, u: x)}


class Sampling:
    """The sampled blocks of one run: their held outputs and inputs, and the sample
    function the stepper calls at every sample time (see the module doc)."""

    def __init__(self, plan, t0):
        self.plan, self.t0 = plan, float(t0)
        self.blocks = [plan.blocks[k] for k in plan.order
                       if getattr(plan.blocks[k].sys, SAMPLED_ATTRIBUTE, None) is not None]
        self.info = [getattr(b.sys, SAMPLED_ATTRIBUTE) for b in self.blocks]
        self.fns = [_functions(i.sys, effective_params(b.sys, plan.diagram, plan.params))
                    for b, i in zip(self.blocks, self.info)]
        self.direct = [len(b.direct_inputs) > 0 for b in self.blocks]
        ys = np.cumsum([0] + [b.sys.noutputs for b in self.blocks])
        self.y = np.zeros(ys[-1])                   # held outputs, one buffer for the run
        self.y_of = [self.y[ys[i]:ys[i + 1]] for i in range(len(self.blocks))]
        self.u_of = [np.zeros(b.sys.ninputs) for b in self.blocks]
        self.last = [None] * len(self.blocks)       # the block's last sample time
        self.periods = np.array(sorted({i.dt for i in self.info}), dtype=float)
        self.period_of = [int(np.searchsorted(self.periods, i.dt)) for i in self.info]
        self.inputs_at = None     # f(t, x) -> every block's inputs, set by the simulator
        # the blocks whose inputs a sampled block's outputs reach at the same instant
        # (through continuous blocks with direct feedthrough): where the inputs must be
        # evaluated again after its output function
        owner = plan.output_owner()
        in_owner = {i: b.index for b in plan.blocks for i in range(b.u.start, b.u.stop)}
        fed = {b.index: set() for b in plan.blocks}
        for i, sources in enumerate(plan.conn):
            for j, _ in sources:
                fed[int(owner[j])].add(in_owner[i])
        sampled_idx = {b.index for b in self.blocks}
        self.reach = []
        for b in self.blocks:
            seen, todo = set(), list(fed[b.index])
            while todo:
                k = todo.pop()
                if k not in seen:
                    seen.add(k)
                    if k not in sampled_idx and len(plan.blocks[k].direct_inputs):
                        todo += fed[k]
            self.reach.append(seen)

    def __bool__(self):
        return bool(self.blocks)

    def address(self, b):
        """Address of block b's held outputs (read by its compiled output kernel)."""
        i = [e.index for e in self.blocks].index(b.index)
        return self.y_of[i].ctypes.data if self.y_of[i].size else self.y.ctypes.data

    def bind(self):
        """Let the stand-ins' Python output functions read this run's held outputs."""
        for info, y in zip(self.info, self.y_of):
            info.held = y

    def unbind(self):
        for info in self.info:
            info.held = None

    def check_fixed_step(self, h):
        for dt in self.periods:
            k = round(dt / h)
            if k < 1 or abs(dt - k * h) > 1e-9 * dt:
                raise ValueError(f"a fixed-step run needs its step h = {h} to divide every "
                                 f"sample period; the diagram has a sampled block with "
                                 f"dt = {dt}")

    def _call(self, i, what, t, x, u):
        n = self.blocks[i].sys.nstates if what == "update" else self.blocks[i].sys.noutputs
        try:
            r = np.asarray(self.fns[i][what](t, x, u), dtype=float).reshape(-1)
            if r.size != n:
                raise ValueError(f"it returned {r.size} values, expected {n}")
            return r
        except Exception as e:
            err = BlockError(f"block '{self.blocks[i].sys.name}' (sampled) raised at "
                             f"t = {t:.9g} s: {type(e).__name__}: {e} (in its {what} function)")
            err.block, err.t = self.blocks[i].sys.name, t
            raise err from e

    def sample(self, t, x, due_periods=None):
        """At sample time t: update the due blocks' states in x (x[k] from x[k-1] and the
        inputs held since t_{k-1}), then hold their outputs y[k] and inputs u[k].
        ``due_periods[k]`` says whether ``periods[k]`` is on the grid at t (the stepper's
        test); None: every block is due (t0)."""
        due = [i for i in range(len(self.blocks))
               if due_periods is None or due_periods[self.period_of[i]]]
        for i in due:
            b = self.blocks[i]
            if self.last[i] is not None and self.last[i] < t and b.sys.nstates:
                x[b.x] = self._call(i, "update", self.last[i], x[b.x].copy(),
                                    self.u_of[i].copy())
        for i in due:
            if not self.direct[i]:      # y[k] from x[k] alone
                self.y_of[i][:] = self._call(i, "output", t, x[self.blocks[i].x].copy(),
                                             self.u_of[i].copy())
        us, due_blocks = self.inputs_at(t, x), {self.blocks[i].index for i in due}
        for i in due:                   # in evaluation order: the inputs are final
            if self.direct[i]:
                b = self.blocks[i]
                self.y_of[i][:] = self._call(i, "output", t, x[b.x].copy(), us[b.u].copy())
                if self.reach[i] & due_blocks:
                    us = self.inputs_at(t, x)
        for i in due:
            self.u_of[i][:] = us[self.blocks[i].u]
            self.last[i] = t
