"""``simulate`` and ``Simulator``, and the reference engine: python-control's evaluation of
the diagram called back by the C stepper (``stepper.c``) that the compiled engine
(:mod:`ivdrem.sim.compiled`) runs too.  docs/simulation.md says what a run guarantees
(delays, max-holds, sampled blocks, divergence and stiffness, progress and Ctrl-C).
"""
from __future__ import annotations

import ctypes
import functools
import math
import os
import sys
import time as _time
import warnings

import numpy as np
import control as ct

from .plan import DiagramPlan, check_params
from ._control import PrivateDiagram, flatten
from . import _diagram, _stepper_codes as tpl
from .methods import (METHOD_TABLE, METHODS, DEFAULT_METHOD, STIFF_METHOD,  # noqa: F401
                      DEFAULT_TOLERANCES, MethodInfo, method_info)  # (re-exported)
from .tables import hold_nmat, pack as pack_tables, scratch_size
from .layout import WORKSPACE_LAYOUT, Workspace  # noqa: F401  (WORKSPACE_LAYOUT re-exported)
from .errors import BlockError, SimulationError, StiffnessWarning, BLOCK_RAISED_MESSAGE  # noqa: F401
from .guards import check_bounds, check_diagram_cost
from .compiled import CompiledEngine, load_c_stepper
from .foreign import _view
from .sampled import Sampling, continuous_diagram
from .tables import reference_tables
from ..blocks._core import active_feeds

__all__ = ["simulate", "Simulator", "SimulationError", "StiffnessWarning", "METHODS",
           "METHOD_TABLE", "DEFAULT_METHOD", "STIFF_METHOD", "ENGINES", "Workspace",
           "MethodInfo"]


#: The engines of :func:`simulate`: tables and numba kernels, or python-control's own
#: evaluation of the diagram (both run the one C stepper).
ENGINES = ("compiled", "reference")

def _check_positive(name, v):
    if v is None:
        return v
    if isinstance(v, (bool, np.bool_)):
        raise ValueError(f"{name} must be a number, got {v!r}")
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {v!r}")
    if not (f > 0 and math.isfinite(f)):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return f


def check_solver_settings(method=DEFAULT_METHOD, h=1e-3, rtol=None, atol=None,
                          h_max=None, x_limit=1e10, max_steps=50_000_000):
    """Refuse solver settings outside a sensible range, naming the key, before any work:
    0 < rtol < 1 (a relative tolerance of 1 or more controls nothing), atol > 0, h > 0,
    h_max > 0 (inf allowed) and not below h, x_limit > 0, max_steps >= 1; every number
    finite.  Otherwise a run ends in a misleading error far from its cause ("singular
    inertia", "step size fell below 1e-13 s")."""
    info = method if isinstance(method, MethodInfo) else method_info(method)
    h = _check_positive("h", h)
    if rtol is not None:
        r = _check_positive("rtol", rtol)
        if not r < 1.0:
            raise ValueError(f"rtol must be below 1 (a relative tolerance; {info.name}"
                             f"'s default is {info.rtol:g}), got {rtol!r}")
    _check_positive("atol", atol)
    if h_max is not None and not (isinstance(h_max, (int, float)) and h_max == math.inf):
        hm = _check_positive("h_max", h_max)
        check_bounds(h_max=hm)          # its documented lower bound first
        if hm < h:
            raise ValueError(f"h_max = {hm:g} s is below h = {h:g} s (the "
                             f"{'initial ' if info.adaptive else ''}step): lower h too, or "
                             "raise h_max")
    _check_positive("x_limit", x_limit)
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer, float)) or \
            not (max_steps >= 1 and math.isfinite(max_steps)):
        raise ValueError(f"max_steps must be a whole number >= 1, got {max_steps!r}")
    return info


def _catch_callback_interrupts():
    """Route an exception that Python raises as one of a Simulator's C callbacks is entered
    (a Ctrl-C lands before the callback's own ``try``, and ctypes would print "Exception
    ignored") to that simulator, which stops its run with it; other unraisable
    exceptions go to the hook that was there before.  Installed once per process."""
    previous = sys.unraisablehook
    if getattr(previous, "_ivdrem", False):
        return

    def hook(unraisable):
        sim = getattr(unraisable.object, "__self__", None)
        if isinstance(sim, Simulator) and unraisable.exc_value is not None:
            sim._stopped_by = unraisable.exc_value
            return
        previous(unraisable)
    hook._ivdrem = True
    sys.unraisablehook = hook


# --------------------------------------------------------------------------- reference
class ReferenceEngine:
    """python-control evaluates the diagram; the C stepper (the compiled engine's) steps it,
    calling that evaluation back through a ctypes function as the compiled engine calls a
    Python block.  The delay history, the max-holds, the forward-difference Jacobian and the
    dense LU of the Newton matrix are the stepper's own (``stepper.c``)."""

    name = "reference"

    def __init__(self, plan: DiagramPlan, params=None):
        self.plan = plan
        self.control = pc = PrivateDiagram(plan.diagram, params)
        d = plan.diagram
        self.module = load_c_stepper()
        self.stepper = self.module.name
        self.tables, self.P = reference_tables(plan)
        self.n_kernels = 0
        self._feeds = {}
        self._W = None            # the workspace of the current run (set by install_feeds)
        self._error = []          # the exception a callback caught, re-raised after the call
        n, ny, nu = d.nstates, d.noutputs, sum(b.sys.ninputs for b in plan.blocks)
        nue = d.ninputs

        def evaluate(mode, t, px, pue, pout):
            x, ue = _view(px, n), _view(pue, nue)
            if mode == tpl.RHS:
                out = _view(pout, n)
                try:
                    out[:] = pc.rhs(t, x, ue)
                except RuntimeError as e:
                    # The plan has already shown the diagram has no algebraic loop, so
                    # python-control's fixed-point sweep failing to settle means a NaN in a
                    # signal (NaN != NaN): return NaN like the compiled path, and the step
                    # control reports the divergence.
                    if "algebraic loop" not in str(e):
                        raise
                    out[:] = np.nan
            elif mode == tpl.RECORD:
                _view(pout, ny)[:] = pc.out(t, x, ue)
            else:                   # the block inputs, for the history and the max-holds
                _view(pout, nu)[:] = pc.block_inputs(t, x, ue)

        def callback(mode, t, px, pue, pout):
            try:
                evaluate(mode, t, px, pue, pout)
                return 0
            except BaseException as e:      # noqa: BLE001 - re-raised by integrate
                self._error[:] = [e]
                return 1
        self._callback = _DIAGRAM_CALLBACK(callback)       # kept alive with the engine
        self.address = ctypes.cast(self._callback, ctypes.c_void_p).value

    def bind(self, W):
        """Put this engine's diagram function into workspace W."""
        W.callbacks[0] = self.address

    def _run(self, fn, *args):
        """fn(*args), the exception a callback caught re-raised (its traceback names the
        block python-control was evaluating)."""
        try:
            return fn(*args)
        except RuntimeError:
            if self._error:
                e = self._error.pop()
                raise e
            raise

    def integrate(self, *args):
        return self._run(self.module.integrate, *args)

    def after_step(self, t, x, W):
        return self._run(self.module.diagram_eval, W, self.P, tpl.AFTER_STEP, t, x, x)

    def record(self, t, x, W, row):
        self._run(self.module.diagram_eval, W, self.P, tpl.RECORD, t, x, row)

    def block_failure(self, exc, W=None):
        """(BlockError, cause) naming the block whose function raised `exc`, found in the
        traceback; None when no block's evaluation is on the traceback."""
        found = self.control.raising_block(exc)
        if found is None:
            return None
        b, t = self.plan.blocks[found[0]], found[1]
        err = BlockError(f"block '{b.sys.name}' raised at t = {float(t):.9g} s: "
                         f"{type(exc).__name__}: {exc}")
        err.block, err.t = b.sys.name, float(t)
        return err, exc

    def install_feeds(self, W_ref):
        """Let the delay / max-hold nlsys blocks read the stepper's history and records."""
        plan = self.plan
        lookup = self.module.hist_lookup
        for d in plan.delays:

            def f(t, d=d):
                out = np.empty(d["size"])
                lookup(W_ref[0], t - d["T"], d["off"], d["size"], out)
                return out
            self._feeds[id(plan.blocks[d["block"]].spec)] = f
        for hd in plan.holds:

            def g(t, hd=hd):
                W = W_ref[0]
                return np.concatenate([W[4][hd["off"]:hd["off"] + hd["size"]],
                                       [W[5][hd["k"]]]])
            self._feeds[id(plan.blocks[hd["block"]].spec)] = g
        active_feeds().update(self._feeds)

    def remove_feeds(self):
        feeds = active_feeds()
        for k in self._feeds:
            feeds.pop(k, None)
        self._feeds = {}


#: the stepper's report function: int32 f(t) (stepper.c's report_fn)
_REPORT_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_double)

#: reports per advance: the progress bar's updates, and the moments a pending Ctrl-C is
#: handled while the stepper runs without calling Python
REPORTS = 200

#: wall seconds between two reports at most (about: from the speed of the last two), also
#: where a 200th of the run takes longer: a Ctrl-C or SIGTERM waits no longer than this
REPORT_WALL_S = 0.1

#: the sampled blocks' sample function: int32 f(t, x*) (stepper.c's sample_fn)
_SAMPLE_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_double, ctypes.c_int64)

#: the reference engine's diagram function: int32 f(mode, t, x*, ue*, out*) (stepper.c)
_DIAGRAM_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_int64, ctypes.c_double,
                                     ctypes.c_int64, ctypes.c_int64, ctypes.c_int64)


# --------------------------------------------------------------------------- driver
@functools.lru_cache(maxsize=None)
def _dsyevd_address():
    """Address of LAPACK's dsyevd in scipy (the compiled max-hold calls it by address, see
    _diagram.lowest_eigenpair; a runtime value, so cached machine code stays valid)."""
    from numba.extending import get_cython_function_address
    return get_cython_function_address("scipy.linalg.cython_lapack", "dsyevd")


def _workspace(plan, cap, nu_ext, ny, nu, n_kernels, tables):
    nmh = len(plan.holds)
    nmat = hold_nmat(plan)
    return Workspace(
        hist_t=np.zeros(cap), hist_v=np.zeros((cap, plan.nd)), hist_d=np.zeros((cap, plan.nd)),
        hist_meta=np.array([0, 0, cap, 0], dtype=np.int64), held=np.zeros(plan.nh),
        score=np.zeros(nmh), ys=np.zeros(ny), us=np.zeros(nu), u_ext=np.zeros(nu_ext),
        hold_dt=np.array([float(hd["dt"]) for hd in plan.holds]).reshape(nmh),
        hold_mode=np.full(nmh, tpl.HOLD_COMMIT, dtype=np.int64),
        hold_time=np.full(nmh, np.nan), hold_vec=np.zeros((nmh + 1, nmat)),
        probing=np.zeros(1, dtype=np.int64), clock=np.zeros(1),
        u_times=np.zeros(0), u_values=np.zeros((0, nu_ext)),
        kernels=np.zeros(max(n_kernels, 1), dtype=np.int64),
        failure=np.full(2 + max([b.sys.nstates for b in plan.blocks] + [0]), -1.0),
        **dict(zip(("table_ints", "table_floats"),
                   pack_tables(tables))),
        # the compiled engine's work arrays (no allocation per step)
        scratch=np.zeros(scratch_size(tables)),
        lapack=np.array([_dsyevd_address() if nmh else 0],
                        dtype=np.int64),
        lapack_chars=np.array([ord("V"), ord("L")], dtype=np.uint8),
        # dsyevd's five scalar arguments, then its integer work
        lapack_ints=np.zeros(5 + _diagram.dsyevd_liwork(nmat), dtype=np.int32),
        callbacks=np.zeros(3, dtype=np.int64), sample_dt=plan.sampling.periods.copy(),
        sample_due=np.zeros(plan.sampling.periods.size, dtype=np.int64),
        record_row=np.zeros(plan.diagram.noutputs), jac_dirty=np.zeros(1, dtype=np.int64))


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
    at ``u`` (used by the FMU co-simulation runner), or following the table of
    ``set_inputs(values, times)``; the history of delays and max-holds carries over between
    calls.
    """

    def __init__(self, diagram, *, method=DEFAULT_METHOD, engine="compiled", h=1e-3,
                 rtol=None, atol=None, h_max=None, params=None, x0=None, x_limit=1e10,
                 max_steps=50_000_000, t0=0.0):
        # a name of a user method, or a registry row (the generic method suite runs the
        # stepper-internal methods this way)
        self.info = info = check_solver_settings(method, h, rtol, atol, h_max, x_limit,
                                                 max_steps)
        method = info.name
        if engine not in ENGINES:
            raise ValueError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
        diagram = continuous_diagram(diagram)       # discrete-time blocks: sampled
        self.plan = plan = DiagramPlan.from_diagram(diagram, x0, params)
        plan.sampling = self.sampling = Sampling(plan, t0)
        self.sampling.bind()
        if self.sampling and not info.adaptive:
            self.sampling.check_fixed_step(h)
        self.method, self.engine_name = method, engine
        # (checked by check_solver_settings above)
        self.h, self.x_limit = float(h), float(x_limit)
        self.rtol = float(info.rtol if rtol is None else rtol)
        self.atol = float(info.atol if atol is None else atol)
        self.max_steps = int(max_steps)
        T_min = min((d["T"] for d in plan.delays), default=math.inf)
        if h_max is None:
            # explicit methods: a cap that keeps the first steps sane; the stiff method is
            # limited only by the delays (a stage must not read the history beyond t)
            h_max = min(0.05, T_min / 4) if not info.l_stable else \
                (T_min / 2 if plan.delays else math.inf)
        self.h_max = float(h_max)
        if plan.delays and (self.h_max >= T_min or (not info.adaptive and self.h >= T_min)):
            raise ValueError(f"the step must stay below the shortest transport delay "
                             f"T = {T_min} s (h = {self.h}, h_max = {self.h_max})")
        c0 = _time.perf_counter()
        self.engine = (ReferenceEngine if engine == "reference" else CompiledEngine)(plan, params)
        self._integrate = self.engine.integrate
        self.compile_s = _time.perf_counter() - c0
        d = plan.diagram
        self.ny, self.nu = sum(b.sys.noutputs for b in plan.blocks), \
            sum(b.sys.ninputs for b in plan.blocks)
        cap = 4096 if plan.delays else 4
        self.W = _workspace(plan, cap, d.ninputs, self.ny, self.nu, self.engine.n_kernels,
                            self.engine.tables)
        self.engine.bind(self.W)
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
        self._inputs_set = False
        self._kinks = np.zeros(0)       # times where the input interpolant's slope changes
        self._on_report = None          # the current advance's report (see advance)
        self._stopped_by = None         # the exception that stopped the run in the report
        _catch_callback_interrupts()
        # the stepper calls it by address (kept alive with the simulator)
        self._report_c = _REPORT_CALLBACK(self._report_trampoline)
        self._report_address = ctypes.cast(self._report_c, ctypes.c_void_p).value
        if self.sampling:
            self.sampling.inputs_at = self._block_inputs
            self._sample_c = _SAMPLE_CALLBACK(self._sample_trampoline)
            self.W.callbacks[2] = ctypes.cast(self._sample_c, ctypes.c_void_p).value

    @property
    def state_labels(self):
        return self.plan.state_labels()

    def _set_u(self, u):
        """advance(u=...): hold the external inputs at u (None: keep what is set)."""
        d = self.plan.diagram
        if u is None:
            if d.ninputs and not self._inputs_set:
                raise ValueError(f"this diagram has {d.ninputs} external inputs "
                                 f"({', '.join(d.input_labels)}): pass u")
            return
        if d.ninputs == 0:
            if np.size(u):
                raise ValueError("this diagram has no external inputs")
            return
        u = np.asarray(u, float).reshape(-1)
        if u.size != d.ninputs:
            raise ValueError(f"u has {u.size} entries, the diagram has {d.ninputs} inputs")
        if not np.all(np.isfinite(u)):
            raise ValueError("u has non-finite entries")
        self.set_inputs(u)

    def set_inputs(self, values, times=None):
        """The diagram's external inputs from now on: held at the vector `values`, or with
        `times` (increasing, n_t) the linear interpolant of the columns of `values`
        (ninputs x n_t), extrapolated linearly beyond the table's ends, as
        ``ct.input_output_response`` interpolates its inputs.  Adaptive steps are cut at the
        table times where the interpolant's slope changes, so that every step sees a smooth
        right-hand side and keeps the method's order (a fixed-step RK4 steps on its own grid).
        """
        nu = self.plan.diagram.ninputs
        values = np.asarray(values, float)
        if not np.all(np.isfinite(values)):
            raise ValueError("inputs have non-finite entries")
        if times is None:
            values = values.reshape(-1)
            if values.size != nu:
                raise ValueError(f"inputs have {values.size} entries, the diagram has {nu}")
            self.W[8][:] = values
            if self.W.u_times.size:             # drop the table (cheap when there is none:
                self.W = self.W._replace(       # co-simulation sets u every step)
                    u_times=np.zeros(0), u_values=np.zeros((0, nu)))
            self._kinks = np.zeros(0)
        else:
            times = np.asarray(times, float).reshape(-1)
            if values.shape != (nu, times.size) or times.size < 2 or \
                    not np.all(np.diff(times) > 0):
                raise ValueError(f"an input table needs increasing times (n_t >= 2) and "
                                 f"values of shape ({nu}, n_t), got {times.size} times and "
                                 f"values of shape {values.shape}")
            self.W = self.W._replace(u_times=np.ascontiguousarray(times),
                                     u_values=np.ascontiguousarray(values.T))
            self._kinks = input_kinks(times, values)
        self._Wref[0] = self.W
        self._inputs_set = True

    def _segment_end(self, t_stop):
        """End of the next integrate call towards t_stop: the first kink of the input
        interpolant after the current time (adaptive methods), else t_stop."""
        k = self._kinks
        if k.size and self.info.adaptive:
            # beyond the loop's own end-of-interval tolerance, so that a kink just reached
            # is not found again
            tol = 4e-12 * max(1.0, abs(self.t))
            i = int(np.searchsorted(k, self.t + tol, side="right"))
            if i < k.size and k[i] < t_stop - tol:
                return float(k[i])
        return t_stop

    def _start(self):
        if self.engine_name == "reference":
            self.engine.install_feeds(self._Wref)
        c0 = _time.perf_counter()
        self.W.clock[0] = self.t
        self.W.hold_mode[:] = tpl.HOLD_COMMIT      # t0 is a sampling time of every hold
        if self.sampling:                          # and of every sampled block
            self.sampling.bind()
            self.sampling.sample(self.t, self.x)
        self._after_step_with_room()
        self.compile_s += _time.perf_counter() - c0
        self._started = True

    def _after_step_with_room(self):
        """The after-step update at the current point, growing the delay history until
        the point fits."""
        while self._naming_blocks(self.engine.after_step, self.t, self.x, self.W) == \
                tpl.HISTORY_FULL:
            self.W = _grow(self.W)
            self._Wref[0] = self.W

    def outputs_at_current(self):
        row = np.zeros(self.plan.diagram.noutputs)
        self._naming_blocks(self.engine.record, self.t, self.x, self.W, row)
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
        t_start, span = self.t, t_to - self.t
        reported = [t_start]
        due = [t_start + span / REPORTS]        # the next of the REPORTS equally spaced times
        last = [t_start, _time.perf_counter()]  # the last report's t and wall clock

        def report(t):
            # called by the stepper after the first accepted step at or past tf[F_REPORT]:
            # the steps are those of a run without it (docs/simulation.md, "Progress")
            if t >= due[0]:
                if progress is not None:
                    progress(t)
                    reported[0] = t
                # the first of the REPORTS equally spaced times after t (t_to at the end)
                k = min(REPORTS, math.floor((t - t_start) / span * REPORTS) + 1) \
                    if span > 0 else REPORTS
                while k < REPORTS and t_start + span * k / REPORTS <= t:
                    k += 1
                due[0] = t_start + span * k / REPORTS if k < REPORTS else t_to
            # and back to Python (a pending Ctrl-C or SIGTERM) about every REPORT_WALL_S of
            # wall time, however long a 200th of the run takes: at the speed of the last
            now = _time.perf_counter()
            ahead = t + (t - last[0]) * REPORT_WALL_S / (now - last[1]) if now > last[1] \
                else t
            last[0], last[1] = t, now
            self.tf[tpl.F_REPORT] = ahead if t < ahead < due[0] else due[0]
        # the first report soon, to measure the speed
        self.tf[tpl.F_REPORT] = t_start + span / (REPORTS * 64)
        self._on_report = report
        self.W.callbacks[1] = self._report_address
        wall0 = _time.perf_counter()
        try:
            while self.t < t_to - 1e-12 * max(1.0, abs(t_to)):
                t_seg = self._segment_end(t_to)
                st = self._chunk(t_seg, out_t, out_y, out_x, io)
                if self._stopped_by is not None:
                    st = tpl.STOPPED
                if st == tpl.OK:
                    if t_seg == t_to:
                        break
                    continue
                self._handle(st, out_t, out_y, io, out_x)
            if progress is not None and reported[0] < self.t:
                progress(self.t)
        finally:
            self.W.callbacks[1] = 0
            self._on_report = None
            self.wall += _time.perf_counter() - wall0
            self.recorded = int(io[0])      # the samples written, also when the run stops
        return io[0]

    def _emit_due(self, out_t, out_y, out_x, io):
        while io[0] < io[1] and out_t[io[0]] <= self.t + 1e-12 * max(1.0, abs(self.t)):
            row = out_y[io[0]]
            direct = row.flags.c_contiguous
            if not direct:                      # a response's (outputs x samples) array
                row = self.W.record_row[:out_y.shape[1]]
            self._naming_blocks(self.engine.record, self.t, self.x, self.W, row)
            if not direct:
                out_y[io[0]] = row
            if out_x.shape[1]:
                out_x[io[0]] = self.x
            io[0] += 1

    def _naming_blocks(self, fn, *args):
        """fn(*args) (the loop, an after-step, a record), a block's exception raised as a
        BlockError naming the block and the time."""
        try:
            return fn(*args)
        except Exception as e:
            # a block's own exception (in the loop, or a record or after-step called from
            # here): name the block and the time
            named = self.engine.block_failure(e, self.W)
            if named is not None:
                if named[1] is not None and not isinstance(named[1], Exception):
                    raise named[1]  # Ctrl-C (KeyboardInterrupt), SystemExit: not the block's
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
        st = self._naming_blocks(self._integrate, self.info.id, self.tf, t_stop, self.x,
                                 self.engine.P, self.W, out_t, out_y, out_x, io, self.stats,
                                 self.ctl)
        self.t = float(self.tf[tpl.F_T])
        if self.stats[tpl.S_STIFF] and not self._warned_stiff:
            self._warned_stiff = True
            warnings.warn(
                f"the loop has become stiff at t = {self.tf[tpl.F_T_STIFF]:.6g} s: method "
                f"{self.method}'s steps are limited by stability (h*rho(J) ~ "
                f"{self.tf[tpl.F_HRHO_STIFF]:.3g}, its stability bound is ~3.3), not accuracy; "
                f"use method=\"{STIFF_METHOD}\"", StiffnessWarning, stacklevel=4)
        return int(st)

    def _report_trampoline(self, t):
        """The stepper's report function: the current advance's report (progress) run in
        Python, where a pending Ctrl-C becomes a KeyboardInterrupt; an exception stops the
        run (status STOPPED) and is raised again by _handle."""
        try:
            if self._stopped_by is not None:    # a Ctrl-C at the callback's entry
                return 1
            if self._on_report is not None:
                self._on_report(t)
            return 0
        except BaseException as e:      # noqa: BLE001 - raised again by _handle
            self._stopped_by = e
            return 1

    def _sample_trampoline(self, t, px):
        """The stepper's sample function (the sampled blocks' updates at a sample time);
        an exception stops the run (status STOPPED) and is raised again by _handle."""
        try:
            if self._stopped_by is not None:    # a Ctrl-C at the callback's entry
                return 1
            self.sampling.sample(t, _view(px, self.x.size), self.W.sample_due)
            return 0
        except BaseException as e:      # noqa: BLE001 - raised again by _handle
            self._stopped_by = e
            return 1

    def _block_inputs(self, t, x):
        """Every block's inputs at (t, x), by the run's engine (for the sampled blocks)."""
        if self.engine_name == "reference":
            return np.asarray(self.engine.control.block_inputs(
                t, x, self._external_inputs(t)), dtype=float)
        self.engine.rhs(t, x, self.W)       # fills every block input (a record only some)
        return self.W.us.copy()

    def _external_inputs(self, t):
        """The diagram's external inputs at t (held, or the table's interpolant)."""
        if self.W.u_times.size:
            return interpolate_inputs(self.W.u_times, self.W.u_values.T, np.array([t]))[:, 0]
        return np.array(self.W.u_ext)

    def _handle(self, st, out_t, out_y, io, out_x):
        if st == tpl.STOPPED:
            e, self._stopped_by = self._stopped_by, None
            raise e if e is not None else KeyboardInterrupt()
        if st == tpl.HISTORY_FULL:
            meta = self.W.hist_meta
            if meta[1] + 2 > meta[2]:
                self.W = _grow(self.W)
                self._Wref[0] = self.W
            self._after_step_with_room()
            self._emit_due(out_t, out_y, out_x, io)
            return
        if st in (tpl.DIVERGED, tpl.STEP_TOO_SMALL):
            nan = self._nan_source()
            if nan is not None:
                raise SimulationError(f"simulation stopped at t = {self.t:.6g} s: {nan}")
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
        if st == tpl.UNKNOWN_METHOD:
            raise NotImplementedError(
                f"method {self.info.name!r} (dispatch id {self.info.id} in "
                "ivdrem.sim.methods) has no step function in the stepper's method_step")
        raise SimulationError(f"unexpected status {st} at t = {self.t:.6g} s")

    def _signals_at(self, t, x):
        """(dx/dt, block outputs, block inputs) of the diagram at (t, x), evaluated by the
        run's own engine; None if the evaluation raises."""
        ue = self._external_inputs(t)
        try:
            if self.engine_name == "reference":
                return self.engine.control.signals(self.plan, t, x, ue)
            dx = self.engine.rhs(t, x, self.W)
            return dx, np.array(self.W.ys), np.array(self.W.us)
        except Exception:       # noqa: BLE001 - a diagnosis, not the run's error
            return None

    def _nan_source(self):
        """The block that produced a NaN (or inf) where the run stopped, as a sentence, or
        None: the diagram is evaluated at the last accepted point and at Euler points
        ahead of it (where the rejected steps' stages were), and the first block in
        evaluation order whose outputs, or whose derivatives, are not finite while its
        inputs and states are is named."""
        t, x = self.t, self.x.copy()
        if not np.all(np.isfinite(x)):
            return None
        first = self._signals_at(t, x)
        if first is None:
            return None
        f0 = np.nan_to_num(first[0], nan=0.0, posinf=0.0, neginf=0.0)
        probes = [(t, x)] + [(t + dt, x + dt * f0) for dt in np.logspace(-13, -1, 25)]
        for tp, xp in probes:
            ev = first if tp == t else self._signals_at(tp, xp)
            if ev is None:
                continue
            dx, ys, us = ev
            if np.all(np.isfinite(dx)) and np.all(np.isfinite(ys)):
                continue
            blocks = [self.plan.blocks[k] for k in self.plan.order]
            for b in blocks:
                yb, ub = ys[b.y], us[b.u]
                if np.all(np.isfinite(ub)) and not np.all(np.isfinite(yb)):
                    j = int(np.flatnonzero(~np.isfinite(yb))[0])
                    return (f"block '{b.sys.name}' output {b.sys.output_labels[j]} is "
                            f"{float(yb[j])!r} (not a number) at t = {tp:.9g} s with finite "
                            "inputs and states (its output function)")
            for b in blocks:
                db, ub, xb = dx[b.x], us[b.u], xp[b.x]
                if np.all(np.isfinite(ub)) and np.all(np.isfinite(xb)) and \
                        not np.all(np.isfinite(db)):
                    j = int(np.flatnonzero(~np.isfinite(db))[0])
                    return (f"block '{b.sys.name}' gives d{b.sys.state_labels[j]}/dt = "
                            f"{float(db[j])!r} (not a number) at t = {tp:.9g} s with finite "
                            "inputs and states (its update function)")
            return None
        return None

    def close(self):
        self.sampling.unbind()
        if self.engine_name == "reference":
            self.engine.remove_feeds()

    def stats_dict(self):
        """Counters of the run; wall_s = sim_s + compile_s (kept for older callers)."""
        st = self.stats
        return {"method": self.method, "engine": self.engine_name,
                "stepper": self.engine.stepper,       # "c": stepper.c, for both engines
                "steps": int(st[tpl.S_STEPS]), "rejected": int(st[tpl.S_REJECTED]),
                "rhs_calls": int(st[tpl.S_RHS]), "jacobians": int(st[tpl.S_JAC]),
                "factorizations": int(st[tpl.S_LU]), "hold_cuts": int(st[tpl.S_CUTS]),
                "hold_samples": int(st[tpl.S_PROBES]),
                "explicit_steps": int(st[tpl.S_EXPLICIT]),
                "stiff_at": float(self.tf[tpl.F_T_STIFF]) if st[tpl.S_STIFF] else None,
                "sim_s": self.wall, "compile_s": self.compile_s,
                "wall_s": self.wall + self.compile_s, "rtol": self.rtol,
                "atol": self.atol, "h": self.h if not self.info.adaptive else float(self.tf[1]),
                "last_error": float(self.tf[tpl.F_ERR]),
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
    from tqdm import tqdm
    bar = tqdm(total=round(t_end - t0, 6), unit="s", desc=desc, file=sys.stderr,
               bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.0f} s "
                          "[{elapsed}<{remaining}]", leave=False)
    last = [t0]

    def update(t):
        bar.update(round(t - last[0], 6))
        last[0] = t
    return bar, update


def input_kinks(times, values):
    """Interior table times at which the slope of the piecewise-linear input changes
    (beyond the rounding of the slopes of sampled straight lines): where a step ends so
    that the right-hand side is smooth on every step."""
    if times.size < 3 or values.shape[0] == 0:
        return np.zeros(0)
    dt = np.diff(times)
    slope = np.diff(values, axis=1) / dt
    jump = np.abs(np.diff(slope, axis=1))
    size = np.max(np.abs(values), axis=1, keepdims=True)
    noise = 64 * np.finfo(float).eps * (np.maximum(np.abs(slope[:, 1:]), np.abs(slope[:, :-1]))
                                        + size / np.minimum(dt[1:], dt[:-1]))
    return times[1:-1][np.any(jump > noise, axis=0)]


def interpolate_inputs(times, values, t):
    """python-control's input interpolant (input_output_response's ``ufun``): linear in
    each interval of `times`, extrapolated linearly beyond the ends; `values` is
    (ninputs, n_t), `t` an array of times; returns (ninputs, len(t))."""
    idx = np.clip(np.searchsorted(times, t, side="left"), 1, len(times) - 1)
    s = (t - times[idx - 1]) / (times[idx] - times[idx - 1])
    return values[:, idx - 1] * (1.0 - s) + values[:, idx] * s


def _increasing_times(name, v):
    """v as a 1-D float array of finite, strictly increasing times (else a ValueError
    naming the argument)."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of times, got {v!r}") from None
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"{name} must be a 1-D array of times, got shape {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}] is {float(a[bad[0]])!r}: times must be finite")
    back = np.flatnonzero(np.diff(a) <= 0)
    if back.size:
        i = int(back[0])
        raise ValueError(f"{name} must be strictly increasing: {name}[{i}] = {float(a[i])!r}, "
                         f"{name}[{i + 1}] = {float(a[i + 1])!r}")
    return a


def _time_span(timepts, t_end):
    """(t0, t_end, timepts array or None) of simulate's time arguments."""
    if timepts is not None and t_end is not None:
        raise TypeError("give timepts or t_end (its older name), not both")
    if timepts is None and t_end is None:
        raise TypeError("simulate() needs timepts: an end time (the run starts at 0) or an "
                        "array of times")
    if timepts is None or np.ndim(timepts) == 0:
        v = t_end if timepts is None else timepts
        try:
            return 0.0, _check_positive("t_end", v), None
        except ValueError as e:
            raise ValueError(f"{e} (timepts as a number is the end time; the run starts at "
                             "t = 0)") from None
    T = _increasing_times("timepts", timepts)
    if T.size < 2:
        raise ValueError(f"timepts must hold at least 2 times (start and end), got {T.size}")
    return float(T[0]), float(T[-1]), T


def _output_grid(t0, t_end, T, t_eval, dt_out):
    """The output times given as an array (t_eval, else an array timepts), or None with
    the spacing of the dt_out grid from t0 (its arrays are made after the cost guard)."""
    if t_eval is not None:
        if dt_out is not None:
            raise TypeError("give t_eval or dt_out, not both")
        te = _increasing_times("t_eval", t_eval)
        tol = 1e-12 * max(1.0, abs(t0), abs(t_end))
        if te[0] < t0 - tol or te[-1] > t_end + tol:
            raise ValueError(f"t_eval must lie within the simulated interval [{t0!r}, "
                             f"{t_end!r}], got [{float(te[0])!r}, {float(te[-1])!r}]")
        return np.clip(te, t0, t_end), None
    if T is not None and dt_out is None:
        return T.copy(), None
    dt_out = _check_positive("dt_out", 0.01 if dt_out is None else dt_out)
    return None, min(dt_out, t_end - t0)


def _input_table(diagram, inputs, T):
    """The external inputs as (values, times): a constant vector (times None) or an
    (ninputs, len(timepts)) table over timepts, after python-control's conventions (a
    scalar broadcast to every input; a list of per-input parts, each a constant or a time
    series; an array over timepts)."""
    nu = diagram.ninputs
    labels = list(diagram.input_labels)
    nT = None if T is None else T.size
    if inputs is None:
        inputs = 0.0
    if isinstance(inputs, (list, tuple)) and (nT is None or len(inputs) != nT):
        parts = []
        for i, part in enumerate(inputs):
            a = _numbers(f"inputs[{i}]", part)
            if a.ndim == 0 or (a.ndim == 1 and (nT is None or a.size != nT)):
                parts.append(np.outer(a.reshape(-1), np.ones(nT or 1)))
            elif nT is not None and ((a.ndim == 1 and a.size == nT) or
                                     (a.ndim == 2 and a.shape[1] == nT)):
                parts.append(a.reshape(-1, nT))
            else:
                raise ValueError(f"inputs[{i}] has shape {a.shape}: each part of a list of "
                                 "inputs is a constant, a vector of constants, or a time "
                                 f"series over timepts ({nT if nT else 'no'} times)")
        U = np.vstack(parts) if parts else np.zeros((0, nT or 1))
        if U.shape[0] != nu:
            raise ValueError(f"inputs (a list) give {U.shape[0]} inputs, the diagram has "
                             f"{nu}: {labels}")
        if nT is None:
            U = U[:, 0]
    else:
        U = _numbers("inputs", inputs)
        if U.ndim == 0:
            U = np.full(nu, float(U))
        elif U.ndim == 1 and U.size == nu and not (nu == 1 and nT == 1):
            pass                                   # a constant vector
        elif U.ndim == 1 and nu == 1 and nT is not None and U.size == nT:
            U = U.reshape(1, nT)
        elif U.ndim == 2 and nT is not None and U.shape == (nu, nT):
            pass
        else:
            if nu == 0:
                raise ValueError(f"inputs has shape {U.shape}, but the diagram has no "
                                 "external inputs (leave inputs at 0)")
            want = f"a number, a vector of {nu} constants"
            if nT is not None:
                want += f" or an array of shape ({nu}, {nT}) over timepts"
            elif U.ndim == 2:
                want += " (an input over time needs timepts as an array of times)"
            hint = " (transposed?)" if U.ndim == 2 and nT is not None and \
                U.shape == (nT, nu) else ""
            raise ValueError(f"inputs has shape {U.shape}{hint}; the diagram has {nu} "
                             f"external inputs {labels}: give {want}")
    bad = np.argwhere(~np.isfinite(U))
    if bad.size:
        i = tuple(int(k) for k in bad[0])
        where = f"{labels[i[0]]}" + (f" at timepts[{i[1]}]" if len(i) > 1 else "")
        raise ValueError(f"inputs has a non-finite entry ({float(U[i])!r}) for input {where}")
    return (U, None) if U.ndim == 1 else (U, T)


def _numbers(name, v):
    try:
        return np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers, got {v!r}") from None


def _initial_state(diagram, initial_state, name, params):
    """The full initial state from simulate's `initial_state`: None (each block's own
    initial state), a number (every state), a full vector, or python-control's list of
    parts (concatenated), or one entry per subsystem with None for a block's own state."""
    if initial_state is None:
        return None
    n = diagram.nstates
    subs = diagram.syslist
    if isinstance(initial_state, (list, tuple)) and len(initial_state) == len(subs) and \
            any(e is None for e in initial_state):
        own = DiagramPlan.from_diagram(diagram, None, params).x0
        parts, i = [], 0
        for k, (e, sub) in enumerate(zip(initial_state, subs)):
            if e is None:
                parts.append(own[i:i + sub.nstates])
            else:
                a = _numbers(f"{name}[{k}]", e).reshape(-1)
                if a.size != sub.nstates:
                    raise ValueError(f"{name}[{k}] has {a.size} entries, subsystem "
                                     f"'{sub.name}' has {sub.nstates} state(s)")
                parts.append(a)
            i += sub.nstates
        x0 = np.concatenate(parts) if parts else np.zeros(0)
    elif isinstance(initial_state, (list, tuple)):
        parts = [_numbers(f"{name}[{k}]", e).reshape(-1) for k, e in enumerate(initial_state)]
        x0 = np.concatenate(parts) if parts else np.zeros(0)
    else:
        x0 = _numbers(name, initial_state)
        x0 = np.full(n, float(x0)) if x0.ndim == 0 else x0.reshape(-1)
    if x0.size != n:
        names = ", ".join(f"{s.name} ({s.nstates})" for s in subs)
        raise ValueError(f"{name} has {x0.size} entries, the diagram has {n} states (give "
                         f"all of them, or a list with one entry per subsystem, None for a "
                         f"block's own initial state: {names})")
    bad = np.flatnonzero(~np.isfinite(x0))
    if bad.size:
        labels = list(diagram.state_labels)
        raise ValueError(f"{name} has a non-finite entry ({float(x0[bad[0]])!r}) for state "
                         f"{labels[bad[0]]}")
    return x0


def _as_diagram(system):
    """`system` as a ``ct.InterconnectedSystem``: a diagram as given; a single
    continuous-time block (``ct.nlsys``, ``ct.ss``, ``ct.tf``) as a diagram of that one block
    with the same inputs, outputs and states (``ivdrem.pycontrol.flatten``); anything else
    refused, pointing to ``ivdrem.pycontrol.input_output_response``, which takes every
    python-control system with python-control's own arguments."""
    if isinstance(system, ct.InterconnectedSystem):
        return system
    if isinstance(system, (ct.NonlinearIOSystem, ct.TransferFunction)) \
            and not ct.isdtime(system, strict=True) \
            and None not in (system.ninputs, system.nstates, system.noutputs):
        return flatten(system)
    why = ("a discrete-time system" if isinstance(system, ct.InputOutputSystem)
           and ct.isdtime(system, strict=True) else
           "a system whose sizes are left open" if isinstance(system, ct.InputOutputSystem)
           else f"a {type(system).__name__}")
    raise TypeError(f"simulate() runs a python-control diagram (ct.interconnect, "
                    f"ivdrem.diagrams) or a continuous-time block, got {why}; "
                    f"ivdrem.pycontrol.input_output_response(sys, T, U, X0) runs any "
                    f"python-control system on ivdrem's simulator with "
                    f"ct.input_output_response's arguments")


def simulate(diagram, timepts=None, inputs=0.0, initial_state=None, params=None, *,
             t_eval=None, method=DEFAULT_METHOD, engine="compiled", h=1e-3, rtol=None,
             atol=None, h_max=None, dt_out=None, progress=None, return_states=True,
             x_limit=1e10, max_steps=50_000_000, desc=None, allow_long=False,
             t_end=None, x0=None, u=None, partial=False):
    """Simulate a closed diagram; returns ct.TimeResponseData.

    The arguments follow ``ct.input_output_response`` (docs/simulation.md, "Calling
    convention").  Every argument is checked before the plan, the compile and the run.

    Parameters
    ----------
    diagram : ct.InterconnectedSystem
        The diagram (from ``ct.interconnect`` or :func:`ivdrem.diagrams.closed_loop`);
        discrete-time blocks in it are sampled (:func:`ivdrem.sim.sampled`).
    timepts : float or array_like
        An end time (the run covers [0, timepts]) or an array of increasing times (the run
        covers [timepts[0], timepts[-1]]; outputs at timepts unless t_eval or dt_out says
        otherwise).
    inputs : float or array_like
        The diagram's external inputs: a number (every input), a vector of ninputs
        constants, or an (ninputs, len(timepts)) array over timepts, linearly interpolated
        as python-control does (steps of the adaptive methods end at the interpolant's
        kinks); a list of per-input parts as python-control accepts.
    initial_state : array_like or list, optional
        None (each block's own initial state), a full state vector, a number, or a list
        with one entry per subsystem (None: that block's own initial state).
    params : dict, optional
        Parameter overrides, passed to every block that has a parameter of that name
        (python-control semantics), validated by the blocks.

    Returns
    -------
    ct.TimeResponseData
        The response, which also carries ``inputs`` (the inputs at the output times),
        ``params``, ``.stats`` (steps, rejected, rhs_calls, jacobians, sim_s, compile_s,
        wall_s = sim_s + compile_s, ...) and ``.hold_times`` (t_e of each max-hold).

    Other Parameters
    ----------------
    t_eval : array_like, optional
        Output times (within the simulated interval); default timepts (an array) or a grid
        of spacing dt_out (default 0.01 s) from the start.
    method : str
        A name of :data:`METHOD_TABLE`: "rodas5p" (L-stable Rosenbrock 5(4), the default),
        "dp45" (Dormand-Prince 5(4)) or "rk4" (fixed step h).
    engine : str
        "compiled" (tables and numba kernels, default) or "reference" (python-control
        evaluation); both run the C stepper.
    h : float
        RK4 step, or the initial step of an adaptive method.
    rtol, atol : float, optional
        Tolerances of an adaptive method (default per method, ``DEFAULT_TOLERANCES``).
    h_max : float, optional
        Largest step (default: min(0.05, T/4) for an explicit method, T/2 for the stiff
        one, T the shortest transport delay).
    dt_out : float, optional
        Spacing of the returned samples (when neither t_eval nor an array timepts gives
        them).
    progress : bool, optional
        Show a progress bar; default: when stderr is a terminal.
    return_states : bool
        Whether the response holds the states, as in python-control.
    x_limit : float
        A state beyond this magnitude stops the run with a SimulationError.
    max_steps : int
        The most steps a run may take.
    desc : str, optional
        The progress bar's label.
    allow_long : bool
        Run beyond the cost limits of :mod:`ivdrem.sim.guards` (memory, steps).
    partial : bool
        A run stopped by a SimulationError returns the samples before the stop, with
        ``success`` False and the error as ``message`` (python-control's ignore_errors).
    t_end, x0, u
        Older names that keep working: ``t_end`` (= a number timepts), ``x0``
        (= initial_state), ``u`` (= constant inputs).
    """
    # every argument is checked here, before the plan, the compile and the run
    diagram = _as_diagram(diagram)
    diagram = continuous_diagram(diagram)       # discrete-time blocks: sampled
    check_solver_settings(method, h, rtol, atol, h_max, x_limit, max_steps)
    t0, t_end, T = _time_span(timepts, t_end)
    out_t, dt_grid = _output_grid(t0, t_end, T, t_eval, dt_out)
    if u is not None:
        if not (np.ndim(inputs) == 0 and inputs == 0):
            raise TypeError("give inputs or u (its older name), not both")
        if np.ndim(u) > 1:
            raise ValueError(f"u (constant inputs) must be a vector, got shape {np.shape(u)}")
        inputs = u
    u_values, u_times = _input_table(diagram, inputs, T)
    if x0 is not None and initial_state is not None:
        raise TypeError("give initial_state or x0 (its older name), not both")
    if params is not None:
        check_params(diagram, params)
    state0 = _initial_state(diagram, x0 if x0 is not None else initial_state,
                            "x0" if x0 is not None else "initial_state", params)
    check_diagram_cost(diagram, t_end - t0, method=method, engine=engine, h=h, h_max=h_max,
                       dt_out=dt_grid, samples=None if out_t is None else out_t.size,
                       return_states=return_states, max_steps=max_steps,
                       allow_long=allow_long)   # refuse before compiling (ivdrem.sim.guards)
    if out_t is None:
        out_t = _output_times(t0, t_end, dt_grid)
    sim = Simulator(diagram, method=method, engine=engine, h=h, rtol=rtol, atol=atol,
                    h_max=h_max, params=params, x0=state0, x_limit=x_limit,
                    max_steps=max_steps, t0=t0)
    sim.set_inputs(u_values, u_times)
    # the response is made first and the run records into its own arrays (outputs x
    # samples), through their transposes: TimeResponseData copies what it is given, and a
    # copy of the recorded arrays would double a long run's memory.  Its placeholders are
    # never written, so they cost no memory either.
    def response(t, y, x, u, **status):
        return ct.TimeResponseData(
            t, y, x, u, output_labels=list(diagram.output_labels),
            input_labels=list(diagram.input_labels),
            state_labels=list(diagram.state_labels) if x is not None else None,
            sysname=diagram.name, params=dict(params or {}), issiso=diagram.issiso(), **status)

    # the placeholders are one number broadcast to the response's shapes: copying them
    # reads one entry, where copying fresh np.empty arrays first faulted in each of their
    # pages (a 300 s run's 45 MB) only to read zeros
    resp = response(out_t, np.broadcast_to(0.0, (diagram.noutputs, out_t.size)),
                    np.broadcast_to(0.0, (diagram.nstates, out_t.size)) if return_states
                    else None,
                    np.broadcast_to(0.0, (diagram.ninputs, out_t.size)))
    out_y = resp.y.T
    out_x = resp.x.T if return_states else None
    if progress is None:
        progress = sys.stderr.isatty() and not os.environ.get("CI")
    bar, update = _progress_bar(progress, t0, t_end, desc or diagram.name)
    failure = None
    try:
        n = sim.advance(t_end, out_t=out_t, out_y=out_y, out_x=out_x, progress=update)
    except SimulationError as e:
        if not partial:
            raise
        failure, n = e, sim.recorded
        out_t, out_y = out_t[:n], out_y[:n]
        out_x = out_x[:n] if out_x is not None else None
    finally:
        if bar is not None:
            bar.close()
        sim.close()
    if n != out_t.size:
        raise SimulationError(f"recorded {n} of {out_t.size} output samples")
    # the inputs at the output times (a fixed-step run reports the step times it used)
    if u_times is None:
        u_out = np.repeat(u_values.reshape(-1, 1), out_t.size, axis=1)
    else:
        u_out = interpolate_inputs(u_times, u_values, out_t)
    if failure is None:
        resp.t[...] = out_t
        resp.u[...] = u_out
    else:                         # the samples recorded before the failure, with its reason
        resp = response(out_t, out_y.T, out_x.T if out_x is not None else None, u_out,
                        success=False, message=str(failure))
    resp.stats = sim.stats_dict()
    resp.hold_times = sim.hold_times()
    return resp
