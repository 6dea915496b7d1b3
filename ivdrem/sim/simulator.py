"""ivdrem's simulator: transport delays, max-holds and growing stiffness (README, "How the
simulator works").

Two engines evaluate the same diagram with the same stepping code (``_template``):

* ``engine="reference"``: the right-hand side is python-control's own
  ``InterconnectedSystem`` evaluation, with the block kernels running in Python;
* ``engine="compiled"`` (default): one numba module generated from the diagram's
  subsystem list and connection map (:mod:`ivdrem.sim.compiled`), cached on disk.

The methods are step functions of the template, listed in :data:`METHOD_TABLE`; one loop
(``_template.integrate``) owns step-size control, outputs, the after-step work and the
divergence and stiffness checks.  Delay blocks are fed from a dense history of accepted
steps (cubic Hermite); max-holds sample lambda_min on their own fixed grid from the dense
output.  A state that becomes non-finite, exceeds ``x_limit`` or grows by orders of
magnitude within a second stops the run with :class:`SimulationError` naming the time and
the state.  An explicit method held back by stability rather than accuracy emits one
:class:`StiffnessWarning`.
"""
from __future__ import annotations

import math
import os
import sys
import time as _time
import warnings
from collections import namedtuple
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.linalg
import control as ct

from .plan import DiagramPlan
from . import _template as tpl
from ..blocks._core import active_feeds

__all__ = ["simulate", "Simulator", "SimulationError", "StiffnessWarning", "METHODS",
           "METHOD_TABLE", "DEFAULT_METHOD", "STIFF_METHOD", "ENGINES", "Workspace",
           "MethodInfo"]


@dataclass(frozen=True)
class MethodInfo:
    """One row of the method table."""
    name: str
    id: int               # dispatch id in the template (method_step)
    step: str             # the template's step function
    order: int
    error_order: int      # order of the embedded solution (0: no error estimate)
    adaptive: bool
    l_stable: bool
    dense_order: int      # order of the interpolant used for outputs / max-hold samples
    dense_outputs: bool   # outputs read from the dense output (else the steps land on them)
    description: str


#: The integration methods, by name (the first is the default).
METHOD_TABLE = {
    "rodas5p": MethodInfo("rodas5p", tpl.RODAS5P, "rodas5p_step", 5, 4, True, True, 4, True,
                          "Rodas5P: L-stable, stiffly accurate Rosenbrock 5(4) with a fresh "
                          "Jacobian each step, dense output of order 4"),
    "dp45": MethodInfo("dp45", tpl.DP45, "dp45_step", 5, 4, True, False, 3, False,
                       "Dormand-Prince 5(4), explicit, error-controlled"),
    "rk4": MethodInfo("rk4", tpl.RK4, "rk4_step", 4, 0, False, False, 3, False,
                      "classical Runge-Kutta 4, fixed step h"),
}
METHODS = tuple(METHOD_TABLE)
DEFAULT_METHOD = "rodas5p"
STIFF_METHOD = "rodas5p"
ENGINES = ("compiled", "reference")
_TEMPLATE_PATH = Path(tpl.__file__)

#: The workspace of a run (positions 0..8 are indexed by position in generated code).
Workspace = namedtuple("Workspace", ["hist_t", "hist_v", "hist_d", "hist_meta", "held", "score",
                                     "ys", "us", "u_ext", "hold_dt", "hold_mode", "hold_time",
                                     "hold_vec", "probing", "clock"])


def method_info(method) -> MethodInfo:
    """The table row of a method name; an unknown name is an error naming the valid ones."""
    if not isinstance(method, str) or method not in METHOD_TABLE:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    return METHOD_TABLE[method]


class StiffnessWarning(RuntimeWarning):
    """An explicit method's steps are limited by stability, not accuracy: use a stiff one."""


class SimulationError(RuntimeError):
    """A run that diverged, hit a singular model, or could not continue."""


#: Default (rtol, atol) per method: for the stiff method, the paper run's theta_hat(300 s)
#: is within 1e-6 relative of a 100x tighter run (benchmarks/bench_paper.py measures it).
DEFAULT_TOLERANCES = {"rodas5p": (1e-4, 1e-6), "dp45": (1e-6, 1e-8), "rk4": (1e-6, 1e-8)}


def _check_positive(name, v):
    if v is None:
        return v
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}")
    if not (f > 0 and math.isfinite(f)):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return f


# --------------------------------------------------------------------------- reference
class ReferenceEngine:
    """python-control evaluates the diagram; the stepping template runs in Python."""

    name = "reference"

    def __init__(self, plan: DiagramPlan, params=None):
        self.plan = plan
        d = plan.diagram
        d._update_params(params or {})
        ns = {"__name__": "ivdrem_reference_template"}
        exec(compile(_TEMPLATE_PATH.read_text(), str(_TEMPLATE_PATH), "exec"), ns)
        ns["diagram_eval"] = self._eval
        ns["diagram_jacobian"] = self._jacobian
        ns["newton_factor"] = self._factor
        ns["newton_solve"] = self._solve
        self.ns = ns
        self.integrate = ns["integrate"]
        self.P = ()
        self._est = _slope_flags(plan)
        self._feeds = {}

    def _eval(self, mode, t, x, P, W, out):
        """The template's single entry point into the diagram (see _template)."""
        if mode == tpl.RHS:
            self._rhs(t, x, P, W, out)
            return tpl.OK
        if mode == tpl.AFTER_STEP or mode == tpl.AFTER_STEP_EVALUATED:
            return self._after_step(t, x, P, W)
        self._record(t, x, P, W, out)
        return tpl.OK

    def _rhs(self, t, x, P, W, dx):
        try:
            dx[:] = self.plan.diagram._rhs(t, x, W[8])
        except RuntimeError as e:
            # The plan has already shown the diagram has no algebraic loop, so python-control's
            # fixed-point sweep failing to settle means a NaN in a signal (NaN != NaN): return
            # NaN like the compiled path, and the step control reports the divergence.
            if "algebraic loop" not in str(e):
                raise
            dx[:] = np.nan

    def _jacobian(self, t, x, P, W, J):
        """df/dx of python-control's right-hand side by forward differences (the delay and
        max-hold outputs come from the history and the held values, as in _rhs)."""
        n = x.size
        f0 = np.empty(n)
        fp = np.empty(n)
        self._rhs(t, x, P, W, f0)
        xp = x.copy()
        for j in range(n):
            d = 1.4901161193847656e-08 * max(1.0, abs(x[j]))
            xp[j] = x[j] + d
            d = xp[j] - x[j]
            self._rhs(t, xp, P, W, fp)
            J[:, j] = (fp - f0) / d
            xp[j] = x[j]
        return tpl.OK

    @staticmethod
    def _factor(J, c, LU, piv):
        """LAPACK LU (scipy) of c I - J into LU, piv."""
        A = c * np.eye(J.shape[0]) - J
        if not np.all(np.isfinite(A)):
            return tpl.SINGULAR
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)
            lu, p = scipy.linalg.lu_factor(A, check_finite=False)
        d = np.abs(np.diag(lu))
        if not (np.all(d > 0) and np.all(np.isfinite(d))):
            return tpl.SINGULAR
        LU[:] = lu
        piv[:] = p
        return tpl.OK

    @staticmethod
    def _solve(LU, piv, b):
        b[:] = scipy.linalg.lu_solve((LU, piv), b, check_finite=False)

    def _after_step(self, t, x, P, W):
        plan = self.plan
        ulist, _ = plan.diagram._compute_static_io(t, x, W[8])
        if plan.delays and not W.probing[0]:
            v = np.empty(plan.nd)
            dv = np.zeros(plan.nd)
            for d in plan.delays:
                v[d["off"]:d["off"] + d["size"]] = ulist[d["u"]:d["u"] + d["size"]]
                if d["hermite"]:
                    dv[d["off"]:d["off"] + d["size"]] = ulist[d["du"]:d["du"] + d["size"]]
            st = self.ns["hist_push"](W, t, v, dv, self._est)
            if st != tpl.OK:
                return st
            self.ns["hist_trim"](W, t - plan.T_max)
        upd = 0
        for hd in plan.holds:
            u = ulist[hd["u"]:hd["u"] + hd["size"]]
            upd |= self.ns["hold_update"](W, hd["k"], hd["off"], hd["size"], hd["nvec"],
                                         hd["nmat"], u, hd["eps"])
        return tpl.HOLD_UPDATED if upd else tpl.OK

    def _record(self, t, x, P, W, row):
        row[:] = self.plan.diagram._out(t, x, W[8])

    def block_failure(self, exc):
        """(BlockError, cause) naming the block whose function raised `exc`, found in the
        traceback (python-control evaluates each block in its ``_rhs`` / ``_out``); None
        when no block's evaluation is on the traceback."""
        blocks = {id(b.sys): b for b in self.plan.blocks}
        found = None
        tb = exc.__traceback__
        while tb is not None:
            frame = tb.tb_frame
            if frame.f_code.co_name in ("_rhs", "_out") and \
                    id(frame.f_locals.get("self")) in blocks:
                found = (blocks[id(frame.f_locals["self"])], frame.f_locals.get("t"))
            tb = tb.tb_next
        if found is None:
            return None
        from .compiled import BlockError
        b, t = found
        err = BlockError(f"block '{b.sys.name}' raised at t = {float(t):.9g} s: "
                         f"{type(exc).__name__}: {exc}")
        err.block, err.t = b.sys.name, float(t)
        return err, exc

    def install_feeds(self, W_ref):
        """Let the delay / max-hold nlsys blocks read the simulator's history."""
        feeds = active_feeds()
        plan = self.plan
        lookup = self.ns["hist_lookup"]
        for d in plan.delays:
            spec = plan.blocks[d["block"]].spec

            def f(t, d=d):
                out = np.empty(d["size"])
                lookup(W_ref[0], t - d["T"], d["off"], d["size"], out)
                return out
            feeds[id(spec)] = f
            self._feeds[id(spec)] = f
        for hd in plan.holds:
            spec = plan.blocks[hd["block"]].spec

            def g(t, hd=hd):
                W = W_ref[0]
                return np.concatenate([W[4][hd["off"]:hd["off"] + hd["size"]],
                                       [W[5][hd["k"]]]])
            feeds[id(spec)] = g
            self._feeds[id(spec)] = g

    def remove_feeds(self):
        feeds = active_feeds()
        for k in self._feeds:
            feeds.pop(k, None)
        self._feeds = {}

    def after_step(self, t, x, W):
        return self._after_step(t, x, self.P, W)

    def record(self, t, x, W, row):
        self._record(t, x, self.P, W, row)


def _validate_params(diagram, params):
    """Check overrides with each block's own validator (errors name the parameter)."""
    if not isinstance(params, dict):
        raise TypeError(f"params must be a dict, got {type(params).__name__}")
    known = set()
    for block in diagram.syslist:
        known |= set(block.params)
        spec = getattr(block, "ivdrem", None)
        relevant = {k: v for k, v in params.items() if k in block.params}
        if relevant and spec is not None and spec.validate is not None:
            spec.validate({**block.params, **relevant})
    unknown = set(params) - known
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)}; the diagram's blocks "
                         f"take {sorted(known)}")


def _slope_flags(plan):
    est = np.zeros(plan.nd, dtype=np.int64)
    for d in plan.delays:
        if not d["hermite"]:
            est[d["off"]:d["off"] + d["size"]] = 1
    return est


# --------------------------------------------------------------------------- driver
def _workspace(plan, cap, nu_ext, ny, nu):
    nmh = len(plan.holds)
    nmat = max([hd["nmat"] for hd in plan.holds] + [1])
    return Workspace(
        hist_t=np.zeros(cap), hist_v=np.zeros((cap, plan.nd)), hist_d=np.zeros((cap, plan.nd)),
        hist_meta=np.array([0, 0, cap, 0], dtype=np.int64), held=np.zeros(plan.nh),
        score=np.zeros(nmh), ys=np.zeros(ny), us=np.zeros(nu), u_ext=np.zeros(nu_ext),
        hold_dt=np.array([float(hd["dt"]) for hd in plan.holds]).reshape(nmh),
        hold_mode=np.full(nmh, tpl.HOLD_COMMIT, dtype=np.int64),
        hold_time=np.full(nmh, np.nan), hold_vec=np.zeros((nmh, nmat)),
        probing=np.zeros(1, dtype=np.int64), clock=np.zeros(1))


def _grow(W):
    ht, hv, hd, meta = W.hist_t, W.hist_v, W.hist_d, W.hist_meta
    cap, cnt, start = int(meta[2]), int(meta[1]), int(meta[0])
    idx = (start + np.arange(cnt)) % cap
    ncap = 2 * cap
    nt = np.zeros(ncap)
    nv = np.zeros((ncap, hv.shape[1]))
    nd = np.zeros((ncap, hd.shape[1]))
    nt[:cnt], nv[:cnt], nd[:cnt] = ht[idx], hv[idx], hd[idx]
    return W._replace(hist_t=nt, hist_v=nv, hist_d=nd,
                      hist_meta=np.array([0, cnt, ncap, 0], dtype=np.int64))


class Simulator:
    """A resumable simulation of one diagram (use :func:`simulate` for one-shot runs).

    ``advance(t_to, u=None)`` integrates to ``t_to`` holding the diagram's external inputs
    at ``u`` (used by the FMU co-simulation runner); the history of delays and max-holds
    carries over between calls.
    """

    def __init__(self, diagram, *, method=DEFAULT_METHOD, engine="compiled", h=1e-3,
                 rtol=None, atol=None, h_max=None, params=None, x0=None, x_limit=1e10,
                 max_steps=50_000_000, t0=0.0):
        self.info = info = method_info(method)
        if engine not in ENGINES:
            raise ValueError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
        if params:
            _validate_params(diagram, params)
        self.plan = plan = DiagramPlan.from_diagram(diagram, x0, params)
        self.method, self.engine_name = method, engine
        rtol_d, atol_d = DEFAULT_TOLERANCES[method]
        self.h = _check_positive("h", h)
        self.rtol = _check_positive("rtol", rtol_d if rtol is None else rtol)
        self.atol = _check_positive("atol", atol_d if atol is None else atol)
        self.x_limit = _check_positive("x_limit", x_limit)
        self.max_steps = int(max_steps)
        T_min = min((d["T"] for d in plan.delays), default=math.inf)
        if h_max is None:
            # explicit methods: a cap that keeps the first steps sane; the stiff method is
            # limited only by the delays (a stage must not read the history beyond t)
            h_max = min(0.05, T_min / 4) if not info.l_stable else \
                (T_min / 2 if plan.delays else math.inf)
        if not (isinstance(h_max, (int, float)) and h_max == math.inf):
            h_max = _check_positive("h_max", h_max)
        self.h_max = float(h_max)
        if plan.delays and (self.h_max >= T_min or (not info.adaptive and self.h >= T_min)):
            raise ValueError(f"the step must stay below the shortest transport delay "
                             f"T = {T_min} s (h = {self.h}, h_max = {self.h_max})")
        c0 = _time.perf_counter()
        if engine == "reference":
            self.engine = ReferenceEngine(plan, params)
            self._integrate = self.engine.integrate
        else:
            from .compiled import CompiledEngine
            self.engine = CompiledEngine(plan, params)
            self._integrate = self.engine.module.integrate
        self.compile_s = _time.perf_counter() - c0
        d = plan.diagram
        self.ny, self.nu = sum(b.sys.noutputs for b in plan.blocks), \
            sum(b.sys.ninputs for b in plan.blocks)
        cap = 4096 if plan.delays else 4
        self.W = _workspace(plan, cap, d.ninputs, self.ny, self.nu)
        self._Wref = [self.W]
        self.x = plan.x0.copy()
        self.t = float(t0)
        self.t0 = float(t0)
        self.tf = np.zeros(tpl.N_TF)
        self.tf[tpl.F_T], self.tf[tpl.F_H], self.tf[tpl.F_T0] = self.t, self.h, self.t0
        self.tf[tpl.F_GROW_T] = self.t
        self.ctl = np.array([self.rtol, self.atol, self.h_max, float(self.max_steps),
                             self.x_limit, float(info.adaptive), float(info.dense_outputs),
                             float(not info.l_stable and info.adaptive)])
        self.stats = np.zeros(tpl.N_STATS, dtype=np.int64)
        self.wall = 0.0          # integration only (sim_s); compile_s apart
        self._warned_stiff = False
        self._started = False

    @property
    def state_labels(self):
        return self.plan.state_labels()

    def _set_u(self, u):
        d = self.plan.diagram
        if d.ninputs == 0:
            if u is not None and np.size(u):
                raise ValueError("this diagram has no external inputs")
            return
        if u is None:
            raise ValueError(f"this diagram has {d.ninputs} external inputs "
                             f"({', '.join(d.input_labels)}): pass u")
        u = np.asarray(u, float).reshape(-1)
        if u.size != d.ninputs:
            raise ValueError(f"u has {u.size} entries, the diagram has {d.ninputs} inputs")
        if not np.all(np.isfinite(u)):
            raise ValueError("u has non-finite entries")
        self.W[8][:] = u

    def _start(self):
        if self.engine_name == "reference":
            self.engine.install_feeds(self._Wref)
        c0 = _time.perf_counter()
        self.W.clock[0] = self.t
        self.W.hold_mode[:] = tpl.HOLD_COMMIT      # t0 is a sampling time of every hold
        self._after_step_with_room()
        if self.engine_name == "compiled":
            # compile (or load from numba's cache) the loop now, with a zero-length run on
            # copies, so that compile_s and sim_s are reported apart
            W = self.W._replace(ys=self.W.ys.copy(), us=self.W.us.copy())
            tf = self.tf.copy()
            tf[tpl.F_T] = self.t
            self._run_integrate(self.info.id, tf, self.t, self.x.copy(), self.engine.P, W,
                            np.zeros(0), np.zeros((0, self.plan.diagram.noutputs)),
                            np.zeros((0, 0)), np.zeros(2, dtype=np.int64),
                            np.zeros(tpl.N_STATS, dtype=np.int64), self.ctl)
        self.compile_s += _time.perf_counter() - c0
        self._started = True

    def _after_step_with_room(self):
        """The after-step update at the current point, growing the delay history until
        the point fits."""
        while self.engine.after_step(self.t, self.x, self.W) == tpl.HISTORY_FULL:
            self.W = _grow(self.W)
            self._Wref[0] = self.W

    def outputs_at_current(self):
        row = np.zeros(self.plan.diagram.noutputs)
        self.engine.record(self.t, self.x, self.W, row)
        return row

    def advance(self, t_to, u=None, out_t=None, out_y=None, out_x=None, progress=None):
        """Integrate to t_to; fills out_y rows (and out_x) at the requested times out_t."""
        self._set_u(u)
        if not self._started:
            self._start()
        if t_to < self.t:
            raise ValueError(f"cannot go back in time (t = {self.t}, t_to = {t_to})")
        if out_t is None:
            out_t = np.zeros(0)
            out_y = np.zeros((0, self.plan.diagram.noutputs))
        if out_x is None:
            out_x = np.zeros((out_t.size, 0))
        io = np.array([0, out_t.size], dtype=np.int64)
        self._emit_due(out_t, out_y, out_x, io)
        span = t_to - self.t
        nchunk = 1 if progress is None else 200
        t_start = self.t
        wall0 = _time.perf_counter()
        try:
            for c in range(1, nchunk + 1):
                t_stop = t_to if c == nchunk else t_start + span * c / nchunk
                while self.t < t_stop - 1e-12 * max(1.0, abs(t_stop)):
                    st = self._chunk(t_stop, out_t, out_y, out_x, io)
                    if st == tpl.OK:
                        break
                    self._handle(st, out_t, out_y, io, out_x)
                if progress is not None:
                    progress(self.t)
        finally:
            self.wall += _time.perf_counter() - wall0
        return io[0]

    def _emit_due(self, out_t, out_y, out_x, io):
        while io[0] < io[1] and out_t[io[0]] <= self.t + 1e-12 * max(1.0, abs(self.t)):
            self.engine.record(self.t, self.x, self.W, out_y[io[0]])
            if out_x.shape[1]:
                out_x[io[0]] = self.x
            io[0] += 1

    def _run_integrate(self, *args):
        try:
            return self._integrate(*args)
        except Exception as e:
            # a block's own exception inside the compiled loop: name the block and the time
            named = getattr(self.engine, "block_failure", lambda e: None)(e)
            if named is not None:
                raise named[0] from named[1]
            if not isinstance(e, (ValueError, ZeroDivisionError, FloatingPointError,
                                  np.linalg.LinAlgError)):
                raise
            raise SimulationError(f"simulation stopped after t = {self.tf[0]:.6g} s: {e}") \
                from e

    def _chunk(self, t_stop, out_t, out_y, out_x, io):
        self.tf[tpl.F_T] = self.t
        if not self.info.adaptive:
            self.tf[tpl.F_H] = self.h
        st = self._run_integrate(self.info.id, self.tf, t_stop, self.x, self.engine.P, self.W,
                                 out_t, out_y, out_x, io, self.stats, self.ctl)
        self.t = float(self.tf[tpl.F_T])
        if self.stats[tpl.S_STIFF] and not self._warned_stiff:
            self._warned_stiff = True
            warnings.warn(
                f"the loop has become stiff at t = {self.tf[tpl.F_T_STIFF]:.6g} s: method "
                f"{self.method}'s steps are limited by stability (h*rho(J) ~ "
                f"{self.tf[tpl.F_HRHO_STIFF]:.3g}, its stability bound is ~3.3), not accuracy; "
                f"use method=\"{STIFF_METHOD}\"", StiffnessWarning, stacklevel=4)
        return int(st)

    def _handle(self, st, out_t, out_y, io, out_x):
        if st == tpl.HISTORY_FULL:
            meta = self.W.hist_meta
            if meta[1] + 2 > meta[2]:
                self.W = _grow(self.W)
                self._Wref[0] = self.W
            self._after_step_with_room()
            self._emit_due(out_t, out_y, out_x, io)
            return
        if st in (tpl.DIVERGED, tpl.DIVERGED_GROWTH):
            i = int(self.stats[tpl.S_BAD])
            order = np.argsort(-np.nan_to_num(np.abs(self.x), nan=np.inf))[:5]
            worst = ", ".join(f"{self.plan.state_owner(j)} = {float(self.x[j]):.3g}" for j in order)
            if st == tpl.DIVERGED:
                what = (f"state {self.plan.state_owner(i)} is {float(self.x[i])!r} "
                        f"(limit {self.x_limit:g})")
            else:
                what = (f"state {self.plan.state_owner(i)} = {float(self.x[i]):.3g} grew by "
                        f"more than {tpl.GROWTH_FACTOR:g}x within {tpl.GROWTH_WINDOW:g} s "
                        f"(e-folding rate {self.tf[tpl.F_GROW_RATE]:.3g} /s)")
            raise SimulationError(
                f"simulation diverged at t = {self.t:.6g} s: {what}; largest states: {worst}. "
                f"The closed loop may be unstable for these gains, or the step too large for "
                f"the stiffness mu(t) reaches (method {self.method}, h = {self.tf[1]:.3g}).")
        if st == tpl.STEP_TOO_SMALL:
            raise SimulationError(f"step size fell below 1e-13 s at t = {self.t:.6g} s "
                                  "(the solution is probably blowing up)")
        if st == tpl.MAX_STEPS:
            raise SimulationError(f"more than max_steps = {self.max_steps} steps before "
                                  f"t = {self.t:.6g} s")
        raise SimulationError(f"unexpected status {st} at t = {self.t:.6g} s")

    def close(self):
        if self.engine_name == "reference":
            self.engine.remove_feeds()

    def stats_dict(self):
        """Counters of the run; wall_s = sim_s + compile_s (kept for older callers)."""
        st = self.stats
        return {"method": self.method, "engine": self.engine_name,
                "steps": int(st[tpl.S_STEPS]), "rejected": int(st[tpl.S_REJECTED]),
                "rhs_calls": int(st[tpl.S_RHS]), "jacobians": int(st[tpl.S_JAC]),
                "factorizations": int(st[tpl.S_LU]), "hold_cuts": int(st[tpl.S_CUTS]),
                "hold_samples": int(st[tpl.S_PROBES]),
                "explicit_steps": int(st[tpl.S_EXPLICIT]),
                "stiff_at": float(self.tf[tpl.F_T_STIFF]) if st[tpl.S_STIFF] else None,
                "sim_s": self.wall, "compile_s": self.compile_s,
                "wall_s": self.wall + self.compile_s, "rtol": self.rtol,
                "atol": self.atol, "h": self.h if not self.info.adaptive else float(self.tf[1]),
                "h_max": self.h_max}

    def hold_times(self):
        """Time t_e of the last update of each max-hold (nan before the first)."""
        return self.W.hold_time.copy()


def _output_times(t0, t_end, dt_out):
    n = (t_end - t0) / dt_out
    k = int(round(n))
    if abs(n - k) < 1e-9 * max(1.0, n):
        return t0 + dt_out * np.arange(k + 1)
    ts = t0 + dt_out * np.arange(int(math.floor(n)) + 1)
    return np.append(ts, t_end)


def _progress_bar(enabled, t0, t_end, desc):
    if not enabled:
        return None, None
    try:
        from tqdm import tqdm
    except ImportError:        # pragma: no cover - tqdm is a dependency
        return None, None
    bar = tqdm(total=round(t_end - t0, 6), unit="s", desc=desc, file=sys.stderr,
               bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.0f} s "
                          "[{elapsed}<{remaining}]", leave=False)
    last = [t0]

    def update(t):
        bar.update(round(t - last[0], 6))
        last[0] = t
    return bar, update


def simulate(diagram, t_end, *, method=DEFAULT_METHOD, engine="compiled", h=1e-3, rtol=None,
             atol=None, h_max=None, dt_out=0.01, params=None, x0=None, u=None,
             progress=None, return_states=True, x_limit=1e10, max_steps=50_000_000,
             desc=None, allow_long=False):
    """Simulate a closed diagram from t = 0 to t_end; returns ct.TimeResponseData.

    Parameters
    ----------
    method : a name of :data:`METHOD_TABLE`: "rodas5p" (L-stable Rosenbrock 5(4), the
        default), "dp45" (Dormand-Prince 5(4)) or "rk4" (fixed step h).
    engine : "compiled" (numba, default) or "reference" (python-control evaluation).
    h : RK4 step, or the initial step of an adaptive method.
    rtol, atol : tolerances of an adaptive method (default per method,
        ``DEFAULT_TOLERANCES``).
    h_max : largest step (default: min(0.05, T/4) for an explicit method, T/2 for the stiff
        one, T the shortest transport delay).
    dt_out : spacing of the returned samples.
    params : parameter overrides, passed to every block that has a parameter of that name
        (python-control semantics), validated by the blocks.
    progress : show a progress bar; default: when stderr is a terminal.
    allow_long : run beyond the cost limits of :mod:`ivdrem.sim.guards` (memory, steps).

    The response carries ``.stats`` (steps, rejected, rhs_calls, jacobians, sim_s,
    compile_s, wall_s = sim_s + compile_s, ...) and ``.hold_times`` (t_e of each max-hold).
    """
    t_end = _check_positive("t_end", t_end)
    dt_out = _check_positive("dt_out", dt_out)
    if dt_out > t_end:
        dt_out = t_end
    from .guards import check_diagram_cost
    check_diagram_cost(diagram, t_end, method=method, engine=engine, h=h, h_max=h_max,
                       dt_out=dt_out, return_states=return_states, max_steps=max_steps,
                       allow_long=allow_long)   # refuse before compiling (ivdrem.sim.guards)
    sim = Simulator(diagram, method=method, engine=engine, h=h, rtol=rtol, atol=atol,
                    h_max=h_max, params=params, x0=x0, x_limit=x_limit, max_steps=max_steps)
    out_t = _output_times(0.0, t_end, dt_out)
    ny = diagram.noutputs
    out_y = np.full((out_t.size, ny), np.nan)
    out_x = np.full((out_t.size, diagram.nstates), np.nan) if return_states else None
    if progress is None:
        progress = sys.stderr.isatty() and not os.environ.get("CI")
    bar, update = _progress_bar(progress, 0.0, t_end, desc or diagram.name)
    try:
        n = sim.advance(t_end, u=u, out_t=out_t, out_y=out_y, out_x=out_x, progress=update)
    finally:
        if bar is not None:
            bar.close()
        sim.close()
    if n != out_t.size:
        raise SimulationError(f"recorded {n} of {out_t.size} output samples")
    resp = ct.TimeResponseData(
        out_t, out_y.T, out_x.T if out_x is not None else None, None,
        output_labels=list(diagram.output_labels),
        state_labels=list(diagram.state_labels) if out_x is not None else None,
        sysname=diagram.name, params=params, issiso=False)
    resp.stats = sim.stats_dict()
    resp.hold_times = sim.hold_times()
    return resp
