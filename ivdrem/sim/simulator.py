"""ivdrem's simulator: transport delays, max-holds and growing stiffness (SPEC section 9).

Two engines evaluate the same diagram with the same stepping code (``_template``):

* ``engine="reference"``: the right-hand side is python-control's own
  ``InterconnectedSystem`` evaluation, with the block kernels running in Python;
* ``engine="compiled"`` (default): one numba module generated from the diagram's
  subsystem list and connection map (:mod:`ivdrem.sim.compiled`), cached on disk.

Delay blocks are fed from a dense history of accepted steps (cubic Hermite); max-holds are
updated after each accepted step.  A state that becomes non-finite or exceeds ``x_limit``
stops the run with :class:`SimulationError` naming the time and the signals.
"""
from __future__ import annotations

import math
import os
import sys
import time as _time
from pathlib import Path

import numpy as np
import control as ct

from .plan import DiagramPlan
from . import _template as T
from ..blocks._core import active_feeds

__all__ = ["simulate", "Simulator", "SimulationError", "METHODS", "ENGINES"]

METHODS = ("dp45", "rk4")
ENGINES = ("compiled", "reference")
_TEMPLATE_PATH = Path(T.__file__)


class SimulationError(RuntimeError):
    """A run that diverged, hit a singular model, or could not continue."""


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
        self.ns = ns
        self.P = ()
        self._est = _slope_flags(plan)
        self._feeds = {}

    def _eval(self, mode, t, x, P, W, out):
        """The template's single entry point into the diagram (see _template)."""
        if mode == T.RHS:
            self._rhs(t, x, P, W, out)
            return T.OK
        if mode == T.AFTER_STEP or mode == T.AFTER_STEP_EVALUATED:
            return self._after_step(t, x, P, W)
        self._record(t, x, P, W, out)
        return T.OK

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

    def _after_step(self, t, x, P, W):
        plan = self.plan
        ulist, _ = plan.diagram._compute_static_io(t, x, W[8])
        if plan.delays:
            v = np.empty(plan.nd)
            dv = np.zeros(plan.nd)
            for d in plan.delays:
                v[d["off"]:d["off"] + d["size"]] = ulist[d["u"]:d["u"] + d["size"]]
                if d["hermite"]:
                    dv[d["off"]:d["off"] + d["size"]] = ulist[d["du"]:d["du"] + d["size"]]
            st = self.ns["hist_push"](W, t, v, dv, self._est)
            if st != T.OK:
                return st
            self.ns["hist_trim"](W, t - plan.T_max)
        upd = 0
        for hd in plan.holds:
            u = ulist[hd["u"]:hd["u"] + hd["size"]]
            upd |= self.ns["hold_update"](W, hd["k"], hd["off"], hd["size"], hd["nvec"],
                                         hd["nmat"], u, hd["eps"])
        return T.HOLD_UPDATED if upd else T.OK

    def _record(self, t, x, P, W, row):
        row[:] = self.plan.diagram._out(t, x, W[8])

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

    def chunk(self, method, *args):
        fn = self.ns["rk4_chunk"] if method == "rk4" else self.ns["dp45_chunk"]
        return fn(*args)

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
    return (np.zeros(cap), np.zeros((cap, plan.nd)), np.zeros((cap, plan.nd)),
            np.array([0, 0, cap, 0], dtype=np.int64), np.zeros(plan.nh),
            np.zeros(len(plan.holds)), np.zeros(ny), np.zeros(nu), np.zeros(nu_ext))


def _grow(W):
    ht, hv, hd, meta = W[0], W[1], W[2], W[3]
    cap, cnt, start = int(meta[2]), int(meta[1]), int(meta[0])
    idx = (start + np.arange(cnt)) % cap
    ncap = 2 * cap
    nt = np.zeros(ncap)
    nv = np.zeros((ncap, hv.shape[1]))
    nd = np.zeros((ncap, hd.shape[1]))
    nt[:cnt], nv[:cnt], nd[:cnt] = ht[idx], hv[idx], hd[idx]
    return (nt, nv, nd, np.array([0, cnt, ncap, 0], dtype=np.int64)) + tuple(W[4:])


class Simulator:
    """A resumable simulation of one diagram (use :func:`simulate` for one-shot runs).

    ``advance(t_to, u=None)`` integrates to ``t_to`` holding the diagram's external inputs
    at ``u`` (used by the FMU co-simulation runner); the history of delays and max-holds
    carries over between calls.
    """

    def __init__(self, diagram, *, method="dp45", engine="compiled", h=1e-3, rtol=1e-6,
                 atol=1e-8, h_max=None, params=None, x0=None, x_limit=1e10,
                 max_steps=50_000_000, t0=0.0):
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        if engine not in ENGINES:
            raise ValueError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
        if params:
            _validate_params(diagram, params)
        self.plan = plan = DiagramPlan.from_diagram(diagram, x0, params)
        self.method, self.engine_name = method, engine
        self.h = _check_positive("h", h)
        self.rtol = _check_positive("rtol", rtol)
        self.atol = _check_positive("atol", atol)
        self.x_limit = _check_positive("x_limit", x_limit)
        self.max_steps = int(max_steps)
        T_min = min((d["T"] for d in plan.delays), default=math.inf)
        if h_max is None:
            h_max = min(0.05, T_min / 4)
        self.h_max = _check_positive("h_max", h_max)
        if plan.delays and (self.h_max >= T_min or (method == "rk4" and self.h >= T_min)):
            raise ValueError(f"the step must stay below the shortest transport delay "
                             f"T = {T_min} s (h = {self.h}, h_max = {self.h_max})")
        if engine == "reference":
            self.engine = ReferenceEngine(plan, params)
        else:
            from .compiled import CompiledEngine
            self.engine = CompiledEngine(plan, params)
        d = plan.diagram
        self.ny, self.nu = sum(b.sys.noutputs for b in plan.blocks), \
            sum(b.sys.ninputs for b in plan.blocks)
        cap = 4096 if plan.delays else 4
        self.W = _workspace(plan, cap, d.ninputs, self.ny, self.nu)
        self._Wref = [self.W]
        self.x = plan.x0.copy()
        self.t = float(t0)
        self.t0 = float(t0)
        self.tf = np.array([self.t, self.h, self.t0])
        self.stats = np.zeros(4, dtype=np.int64)
        self.wall = 0.0
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
        self._after_step_with_room()
        self._started = True

    def _after_step_with_room(self):
        """The after-step update at the current point, growing the delay history until
        the point fits."""
        while self.engine.after_step(self.t, self.x, self.W) == T.HISTORY_FULL:
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
                    if st == T.OK:
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

    def _chunk(self, t_stop, out_t, out_y, out_x, io):
        self.tf[0] = self.t
        args_common = (self.tf, t_stop, self.x, self.engine.P, self.W, out_t, out_y, out_x,
                       io, self.stats, self.x_limit)
        try:
            if self.method == "rk4":
                self.tf[1] = self.h
                st = self.engine.chunk("rk4", *args_common)
            else:
                st = self.engine.chunk("dp45", *args_common, self.rtol, self.atol,
                                       self.h_max, self.max_steps)
        except (ValueError, ZeroDivisionError, FloatingPointError, np.linalg.LinAlgError) as e:
            raise SimulationError(f"simulation stopped after t = {self.tf[0]:.6g} s: {e}") \
                from e
        self.t = float(self.tf[0])
        return int(st)

    def _handle(self, st, out_t, out_y, io, out_x):
        if st == T.HISTORY_FULL:
            self._after_step_with_room()
            self._emit_due(out_t, out_y, out_x, io)
            return
        if st == T.DIVERGED:
            i = int(self.stats[3])
            order = np.argsort(-np.nan_to_num(np.abs(self.x), nan=np.inf))[:5]
            worst = ", ".join(f"{self.plan.state_owner(j)} = {float(self.x[j]):.3g}" for j in order)
            raise SimulationError(
                f"simulation diverged at t = {self.t:.6g} s: state "
                f"{self.plan.state_owner(i)} is {float(self.x[i])!r} (limit {self.x_limit:g}); "
                f"largest states: {worst}. The closed loop may be unstable for these gains, "
                f"or the step too large for the stiffness mu(t) reaches "
                f"(method {self.method}, h = {self.tf[1]:.3g}).")
        if st == T.STEP_TOO_SMALL:
            raise SimulationError(f"step size fell below 1e-13 s at t = {self.t:.6g} s "
                                  "(the solution is probably blowing up)")
        if st == T.MAX_STEPS:
            raise SimulationError(f"more than max_steps = {self.max_steps} steps before "
                                  f"t = {self.t:.6g} s")
        raise SimulationError(f"unexpected status {st} at t = {self.t:.6g} s")

    def close(self):
        if self.engine_name == "reference":
            self.engine.remove_feeds()

    def stats_dict(self):
        return {"method": self.method, "engine": self.engine_name,
                "steps": int(self.stats[0]), "rejected": int(self.stats[1]),
                "rhs_calls": int(self.stats[2]), "wall_s": self.wall, "rtol": self.rtol,
                "atol": self.atol, "h": self.h if self.method == "rk4" else float(self.tf[1]),
                "h_max": self.h_max}


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


def simulate(diagram, t_end, *, method="dp45", engine="compiled", h=1e-3, rtol=1e-6,
             atol=1e-8, h_max=None, dt_out=0.01, params=None, x0=None, u=None,
             progress=None, return_states=True, x_limit=1e10, max_steps=50_000_000,
             desc=None, allow_long=False):
    """Simulate a closed diagram from t = 0 to t_end; returns ct.TimeResponseData.

    Parameters
    ----------
    method : "dp45" (Dormand-Prince 5(4), error-controlled, default) or "rk4" (fixed h).
    engine : "compiled" (numba, default) or "reference" (python-control evaluation).
    h : RK4 step, or the initial DP45 step.  rtol, atol : DP45 tolerances.
    h_max : largest DP45 step (default min(0.05, T/4) for the shortest delay T).
    dt_out : spacing of the returned samples.
    params : parameter overrides, passed to every block that has a parameter of that name
        (python-control semantics), validated by the blocks.
    progress : show a progress bar; default: when stderr is a terminal.
    allow_long : run beyond the cost limits of :mod:`ivdrem.sim.guards` (memory, steps).

    The response carries ``.stats`` (steps, rejected, rhs_calls, wall_s, ...).
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
    return resp
