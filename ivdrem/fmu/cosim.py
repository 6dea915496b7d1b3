"""Co-simulation of ivdrem's controller with the plant FMU.

The controller (every block of :func:`ivdrem.diagrams.closed_loop` but the plant, built with
``external_plant=True``) runs in ivdrem's :class:`~ivdrem.sim.Simulator`; the robot plant is
the co-simulation interface of an FMU exported by :func:`ivdrem.fmu.export_fmu` (fmpy
``FMU2Slave``).  The two are coupled at a fixed communication step ``H``.

Coupling: explicit (Jacobi) sample-and-hold
-------------------------------------------
At the communication points ``t_k = k H`` (``k = 0 .. N``, ``N H = t_end``):

1. the **plant** side is read: ``q(t_k), q'(t_k)`` are the FMU outputs after the previous
   ``fmi2DoStep`` (at ``t_0``: after initialization with the start values ``q0, dq0``);
2. the **controller** receives these as its diagram inputs ``q, dq`` and evaluates its outputs
   at ``t_k`` from its own state ``x_c(t_k)`` and these inputs: ``tau(t_k)``,
   ``tau_d(t_k)`` (the disturbance source is part of the controller diagram), and all the
   recorded signals;
3. both sides then advance over ``[t_k, t_k + H]`` *in parallel*, each holding the other's
   values from ``t_k`` constant (zero-order hold):

   * the controller integrates its states with ``q, q'`` held at ``q(t_k), q'(t_k)``
     (``Simulator.advance``; fixed RK4 sub-steps of at most ``ctrl_step``, or DP45);
   * the FMU receives ``tau(t_k)``, ``tau_d(t_k)`` (``fmi2SetReal``) and integrates with them
     held (``fmi2DoStep(t_k, H)``: RK4 sub-steps of at most ``cs_substep <= H``).

Neither side sees a value computed after ``t_k`` during the step (Jacobi, not Gauss-Seidel),
so the order in which the two are advanced does not matter.  The recorded sample at ``t_k``
is ``[q(t_k), q'(t_k)]`` from the FMU plus the controller outputs of step 2, i.e. exactly the
values exchanged at ``t_k``.

Accuracy: each side's inputs are off by ``O(H)`` during a step (a held value versus the true
continuous signal), so the local error of one step is ``O(H^2)`` and the global error over a
fixed horizon is ``O(H)``: **first order** in the communication step.  The integrators inside
each side are fourth order with sub-steps ``<= H``, so their error is negligible against the
coupling error (the FMU's RK4 at ``cs_substep = 1e-3`` is ~1e-9 over 2 s).  Halving ``H``
should roughly halve the difference to the all-Python closed loop (observed order ~1, see
:func:`compare_to_python`).

Stability: the explicit coupling delays the feedback by up to one step, so ``H`` must stay
well below the fastest closed-loop time constant, about ``m_min / (lambda_max(K) +
delta_mu mu(t))`` (docs/performance.md).  For the paper's gains and ``mu = t + 15`` this is
~2.4 ms at 40 s and ~0.43 ms at 300 s: ``H = 1e-3`` is fine for the 40 s runs here, long
runs need a smaller ``H`` (the all-Python loop, with error-controlled steps, does not).
Measured: the paper loop co-simulated at ``H = 1e-3`` diverges at t = 261 s
(``mu = 276``, ``H (2 + 0.8 mu) / 0.11 = 2.0``); the error then says so.

Why 2: with θ̂ = 0 (its start, θ̂0 = 0), a perturbation of the plant's velocity changes
``tau = (K + delta_mu mu) r + Pi^T theta_hat - u_f`` of (9) by ``-(K + delta_mu mu) dq'``,
which the FMU holds over the step, so the velocity is multiplied by
``I - H M(q)^-1 (K + delta_mu mu)`` per step: an eigenvalue ``lambda`` of
``M^-1 (K + delta_mu mu)`` with ``H lambda > 2`` overshoots by more than it corrects.  The
observer's ``u_f`` of (7) adds an integral action (``u_f' = -mu (K + delta_mu mu) r``: its own
term cancels), the position enters through ``r = e' + alpha e``;
:func:`coupling_stability` takes all three into account (one 3 x 3 map per eigenvalue,
``_one_step_map``) and predicts, from the model and the configuration only, the growth per
step of the linearized coupling at t = 0.  At least :data:`DIVERGING_GROWTH` = 1.5 (and a
million-fold growth within the horizon) is taken as a divergence: the report's FMU check is
then not run (``ivdrem.cli.report.fmu_check``).  On the Panda (examples/panda.toml) at
``H = 1 ms``: ``lambda_max = 2994 /s`` (the wrist, smallest eigenvalue of M(q0) 0.0047),
growth 1.98 per step, against an observed e-folding rate of 776 /s (a factor 2.2 per step)
in the co-simulation, which diverges at t = 21 ms.  On the 2-link arm with a larger K:
predicted 1.12 (K = 330) and more diverged within 0.1 s, 1.03-1.09 (K = 315-325) ran 1 s
(q_2 moves from 0.3 pi towards q_d,2(0) = 0.6 pi, where M's smallest eigenvalue is larger:
from 0.35 pi on the same gain's growth is below 1); the threshold 1.5 (K = 390) diverges at
25 ms (tests/test_cosim.py).  The prediction is at t = 0 only: mu(t) grows, so a coupling
stable at the start can diverge later, as the paper's loop at 261 s; then
:func:`compare_to_python`, which co-simulates at its coarsest step first, stops with that
run's error before the all-Python loop is built.
"""
from __future__ import annotations

import ctypes
import gc
import math
import sys
import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import control as ct
from .._progress import want_progress
from ..sim.methods import REFERENCE_METHOD, method_info
from .describe import read_description
from .instance import FmuError, FmuInstance

__all__ = ["cosimulate", "compare_to_python", "controller_diagram", "coupling_stability",
           "CosimComparison", "CosimError", "CouplingStability", "COMPARED_SIGNALS",
           "EXPECTED_ORDER", "DIVERGING_GROWTH"]

#: Signals compared by :func:`compare_to_python` (q, theta_hat, tau_d_hat).
COMPARED_SIGNALS = ("q", "theta_hat", "tau_d_hat")

#: Range of the observed order of convergence accepted as "first order" (sample-and-hold).
EXPECTED_ORDER = (0.7, 1.5)

#: Default bound of the controller's RK4 sub-step inside one communication step (s).
DEFAULT_CTRL_STEP = 1e-3


class CosimError(FmuError):
    """The FMU reported an error during the co-simulation (message from its logger)."""


# ----------------------------------------------------------------------------- FMU side
def _read_fmu(path: Path):
    """Model description of the FMU at ``path`` (co-simulation); clear errors otherwise."""
    return read_description(path, "co-simulation")


def _check_interface(path, md, model):
    """Value references of q, dq (outputs), tau, tau_d (inputs) and the theta parameters."""
    variables = {v.name: v for v in md.modelVariables}
    n_fmu = 0
    while f"q[{n_fmu}]" in variables:
        n_fmu += 1
    n = model.n
    if n_fmu != n:
        raise ValueError(f"{path}: the FMU's plant has n = {n_fmu} degrees of freedom "
                         f"(outputs q[0..{n_fmu - 1}]), the model {model.name!r} has n = {n}")
    for s in [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]:
        v = variables.get(s)
        if v is None or v.causality != "output" or v.type != "Real":
            raise ValueError(f"{path}: missing Real output {s}")
    for s in [f"tau[{i}]" for i in range(n)] + [f"tau_d[{i}]" for i in range(n)]:
        v = variables.get(s)
        if v is None or v.causality != "input" or v.type != "Real":
            raise ValueError(f"{path}: missing Real input {s}")
    missing = [nm for nm in model.theta_names
               if nm not in variables or variables[nm].causality != "parameter"]
    if missing:
        raise ValueError(f"{path}: the FMU has no parameter(s) {', '.join(missing)} of model "
                         f"{model.name!r}; is it the plant of this model?")
    return variables


class _Slave:
    """The co-simulation FMU (:class:`~ivdrem.fmu.instance.FmuInstance`), initialized, with
    preallocated ctypes buffers for the stepping loop."""

    def __init__(self, path: Path, md, variables, start: dict, in_names, out_names):
        self.path = path
        self.instance = FmuInstance(path, "co-simulation", instance_name="plant", md=md)
        try:
            try:
                self.instance.initialize(start)
            except FmuError as exc:
                raise CosimError(str(exc)) from None
            nin, nout = len(in_names), len(out_names)
            self.in_vr = (ctypes.c_uint * nin)(*[variables[s].valueReference for s in in_names])
            self.out_vr = (ctypes.c_uint * nout)(*[variables[s].valueReference for s in out_names])
            self.in_buf = (ctypes.c_double * nin)()
            self.out_buf = (ctypes.c_double * nout)()
            self.nin, self.nout = nin, nout
            # numpy views of the ctypes buffers (no copies in the stepping loop)
            self.u = np.ctypeslib.as_array(self.in_buf)
            self.y = np.ctypeslib.as_array(self.out_buf)
        except BaseException:
            self.close()
            raise

    @property
    def fmu(self):
        return self.instance.fmu

    @property
    def messages(self):
        return self.instance.messages

    def _call(self, what, fn, *args):
        try:
            return self.instance.call(what, fn, *args)
        except FmuError as exc:
            raise CosimError(str(exc)) from None

    def close(self):
        self.instance.close()           # terminate, freeInstance, remove the files


# ----------------------------------------------------------------------------- helpers
def _steps(t_end, H, what="comm_step"):
    t_end, H = float(t_end), float(H)
    if not (math.isfinite(t_end) and t_end > 0):
        raise ValueError(f"t_end must be a finite number > 0, got {t_end!r}")
    if not (math.isfinite(H) and H > 0):
        raise ValueError(f"{what} must be a finite number > 0, got {H!r}")
    N = int(round(t_end / H))
    if N < 1 or abs(N * H - t_end) > 1e-9 * max(1.0, t_end):
        raise ValueError(f"t_end = {t_end:g} s must be a whole number of communication steps "
                         f"{what} = {H:g} s (t_end / {what} = {t_end / H:.6g})")
    return N


def _initial_state(model, config):
    """q0, dq0 of the Python plant of closed_loop(law, model, **config) (same defaults)."""
    n = model.n
    q0 = config.get("q0")
    if q0 is None:
        from .._default_config import paper_experiment
        q0 = paper_experiment()["q0"] if (model.name == "two-link" and n == 2) else np.zeros(n)
    dq0 = config.get("dq0")
    dq0 = np.zeros(n) if dq0 is None else dq0
    out = []
    for name, v in (("q0", q0), ("dq0", dq0)):
        a = np.asarray(v, dtype=float).reshape(-1)
        if a.size != n or not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be {n} finite numbers, got {v!r}")
        out.append(a)
    return out


def _want_progress(progress):
    # one rule for every bar (ivdrem._progress): a terminal, not CI, not quiet
    return want_progress(progress)


def controller_diagram(law, model, **config):
    """The co-simulation's controller: every block of ``closed_loop(law, model, **config)``
    but the plant (inputs q, dq; the FMU gets the plant's start values and θ)."""
    from ivdrem.diagrams import closed_loop
    ctrl_cfg = {k: v for k, v in config.items() if k not in ("q0", "dq0", "theta")}
    return closed_loop(law, model, external_plant=True, **ctrl_cfg)


# ----------------------------------------------------------------------------- cosimulate
def cosimulate(fmu_path, t_end, *, law="iv-drem", comm_step=1e-3, model=None,
               engine="compiled", method="rk4", ctrl_step=DEFAULT_CTRL_STEP, rtol=1e-8,
               atol=1e-10, fmu_substep=None, progress=None, desc=None, controller=None,
               **config):
    """Co-simulate the controller of ``law`` (ivdrem Simulator) with the plant FMU at ``fmu_path``.

    Parameters
    ----------
    fmu_path : path-like
        FMI 2.0 co-simulation FMU of the plant, e.g. from :func:`ivdrem.fmu.export_fmu`
        (variables ``q[i]``, ``dq[i]`` outputs, ``tau[i]``, ``tau_d[i]`` inputs, parameters
        named like the model's theta).
    t_end : float
        Horizon (s); a whole number of communication steps.
    law : str
        Composite term, as for :func:`ivdrem.diagrams.closed_loop`.
    comm_step : float
        Communication step ``H`` (s).  Coupling: explicit (Jacobi) sample-and-hold, see the
        module docstring; the error against the all-Python loop is first order in ``H``.
    model : EulerLagrangeModel, optional
        Robot model (default :func:`ivdrem.models.two_link`); the FMU must have its ``n``.
    engine : "compiled" (default) or "reference"
        Controller simulator engine.
    method : a name of :data:`ivdrem.sim.METHODS`, default "rk4"
        Controller integrator.  A fixed-step method (RK4) takes ``ceil(H / ctrl_step)``
        equal sub-steps per communication step; an adaptive one (DP45) uses ``rtol``,
        ``atol`` and lands on every ``t_k``.
    fmu_substep : float, optional
        The FMU's ``cs_substep`` (RK4 sub-step bound in ``fmi2DoStep``); default
        ``min(FMU start value, H)``.  Must be ``<= H``.
    progress : bool, optional
        tqdm progress bar on stderr, drawn only on a terminal and not in CI
        (:func:`ivdrem._progress.want_progress`); False: never.
    controller : ct.InterconnectedSystem, optional
        The controller diagram, ``controller_diagram(law, model, **config)``, if the caller
        has built it already (default: built here).
    **config
        Keyword arguments of :func:`~ivdrem.diagrams.closed_loop` (gains, ``theta_hat0``,
        trajectory, disturbance ...).  ``q0``, ``dq0`` (default: the Python plant's, i.e.
        the paper's ``q(0) = (0, 0.3 pi)``, ``q'(0) = 0`` for the 2-link arm) and ``theta``
        (true parameters, default ``model.theta_values``) are set on the FMU as start values
        before initialization.

    Returns
    -------
    ct.TimeResponseData
        Samples at every communication point ``t_k = k H`` (``k = 0 .. N``), with the output
        names of the all-Python ``closed_loop(law)``: ``q, dq, q_d, e, r, tau, tau_d,
        tau_d_hat, theta_hat, mu`` (+ ``Delta, calY`` or ``lambda_min_held``).  ``tau`` and
        ``tau_d`` at ``t_k`` are the values the FMU holds over ``[t_k, t_k + H]``.
        ``.stats``: comm_step, comm_steps, fmu_substep, controller (Simulator stats), wall_s
        (total), wall_loop_s (stepping loop), us_per_step (per communication step, first
        step excluded).

    Raises
    ------
    FileNotFoundError  the FMU file does not exist.
    ValueError         not an FMU, no co-simulation interface, ``n`` differs from the model,
                       bad ``comm_step`` / ``t_end`` / ``fmu_substep``.
    CosimError         the FMU returned an error during the run (with its log message).
    ivdrem.sim.SimulationError  the controller diverged (e.g. ``H`` too large).
    """
    from ivdrem.models import two_link
    from ivdrem.sim import Simulator, SimulationError

    wall0 = _time.perf_counter()
    path = Path(fmu_path)
    md = _read_fmu(path)
    model = two_link() if model is None else model
    variables = _check_interface(path, md, model)
    H = float(comm_step)
    N = _steps(t_end, H)
    n = model.n

    # start values of the FMU: the Python plant's initial state and true parameters
    q0, dq0 = _initial_state(model, config)
    theta = config.get("theta")
    theta = model.theta_values if theta is None else theta
    theta = np.asarray(theta, dtype=float).reshape(-1)
    if theta.size != model.ntheta or not np.all(np.isfinite(theta)):
        raise ValueError(f"theta must be {model.ntheta} finite numbers, got {config['theta']!r}")
    start = {f"q[{i}]": float(q0[i]) for i in range(n)}
    start.update({f"dq[{i}]": float(dq0[i]) for i in range(n)})
    start.update({nm: float(v) for nm, v in zip(model.theta_names, theta)})
    if "cs_substep" in variables:
        s0 = float(variables["cs_substep"].start or H)
        sub = min(s0, H) if fmu_substep is None else float(fmu_substep)
        if not (math.isfinite(sub) and 0 < sub <= H * (1 + 1e-12)):
            raise ValueError(f"fmu_substep must be in (0, comm_step = {H:g}], got {fmu_substep!r}")
        start["cs_substep"] = sub
    elif fmu_substep is not None:
        raise ValueError(f"{path}: the FMU has no parameter cs_substep")
    else:
        sub = float("nan")

    # the controller: all blocks of the closed loop but the plant
    ctrl = controller_diagram(law, model, **config) if controller is None else controller
    in_labels = list(ctrl.input_labels)            # q[0..n-1], dq[0..n-1]
    if sorted(in_labels) != sorted([f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]):
        raise ValueError(f"controller inputs {in_labels} are not q, dq")
    c_labels = list(ctrl.output_labels)
    fmu_in = [f"tau[{i}]" for i in range(n)] + [f"tau_d[{i}]" for i in range(n)]
    take = [c_labels.index(s) for s in fmu_in]
    # tau, tau_d are adjacent in closed_loop's outputs: copy a slice (no per-step allocation)
    t_lo = take[0] if take == list(range(take[0], take[0] + len(take))) else None
    take = np.array(take)
    labels = in_labels + c_labels                  # = closed_loop(law).output_labels order
    if method_info(method).fixed_step:     # equal sub-steps that land on every t_k
        h = H / max(1, math.ceil(H / float(ctrl_step) - 1e-9))
    else:
        h = min(H, float(ctrl_step))
    sim = Simulator(ctrl, method=method, engine=engine, h=h, rtol=rtol, atol=atol)

    ny = len(labels)
    times = H * np.arange(N + 1)
    times[-1] = float(t_end)
    nq = len(in_labels)
    Yp = np.full((N + 1, nq), np.nan)               # plant: q, dq from the FMU
    Yc = np.full((N + 1, ny - nq), np.nan)          # controller outputs (C-contiguous rows,
                                                    # the layout the compiled engine expects)
    out_t = np.zeros(1)
    out_x = np.zeros((1, 0))
    show = _want_progress(progress)
    bar = slave = None
    every = max(1, N // 200)
    wall_loop = 0.0
    try:
        if show:
            from tqdm import tqdm
            bar = tqdm(total=N, unit="step", file=sys.stderr, leave=False,
                       desc=desc or f"co-sim {law} H={H:g}")
        slave = _Slave(path, md, variables, start, fmu_in, in_labels)
        fmu = slave.fmu
        do_step, get_real, set_real = fmu.fmi2DoStep, fmu.fmi2GetReal, fmu.fmi2SetReal
        comp = fmu.component
        yp, up = slave.y, slave.u
        out_vr, in_vr, out_buf, in_buf = slave.out_vr, slave.in_vr, slave.out_buf, slave.in_buf
        t_loop = _time.perf_counter()
        slave._call("fmi2GetReal", get_real, comp, out_vr, nq, out_buf)
        for k in range(N):
            tk = times[k]
            Yp[k] = yp
            # controller: inputs q(t_k), dq(t_k) held; record its outputs at t_k (before
            # stepping, with these inputs), then integrate to t_{k+1}
            out_t[0] = tk
            sim.advance(times[k + 1], u=yp, out_t=out_t, out_y=Yc[k:k + 1], out_x=out_x)
            # plant: tau(t_k), tau_d(t_k) held over [t_k, t_{k+1}]
            if t_lo is not None:
                up[:] = Yc[k, t_lo:t_lo + 2 * n]
            else:
                np.take(Yc[k], take, out=up)
            try:
                set_real(comp, in_vr, slave.nin, in_buf)
                do_step(comp, tk, times[k + 1] - tk, 1)
                get_real(comp, out_vr, nq, out_buf)
            except Exception as exc:
                raise CosimError(f"FMU {path.name}: step at t = {tk:.6g} s failed: "
                                 f"{' '.join(slave.messages[-3:]) or 'no message'} ({exc})") \
                    from None
            if bar is not None and (k + 1) % every == 0:
                bar.update(every)
            if k == 0:      # the first step loads the compiled code: not in the per-step time
                t_loop1 = _time.perf_counter()
        # last sample: plant outputs at t_N, controller outputs with them
        Yp[N] = yp
        out_t[0] = times[N]
        sim.advance(times[N], u=yp, out_t=out_t, out_y=Yc[N:N + 1], out_x=out_x)
        t_done = _time.perf_counter()
        wall_loop = t_done - t_loop
        us_step = 1e6 * (t_done - t_loop1) / max(1, N - 1)
    except (SimulationError, CosimError) as exc:
        t_fail = sim.t
        raise type(exc)(f"co-simulation with comm_step H = {H:g} s failed near t = "
                        f"{t_fail:.6g} s: {exc} -- The explicit coupling is only stable while H "
                        f"is well below the fastest closed-loop time constant (about m_min / "
                        f"(lambda_max(K) + delta_mu mu(t)), which shrinks as mu grows): use a "
                        f"smaller comm_step for long runs.") from exc
    finally:
        if bar is not None:
            bar.close()
        if slave is not None:
            slave.close()                           # terminate, freeInstance, remove files
        sim.close()
    Y = np.concatenate([Yp, Yc], axis=1)
    resp = ct.TimeResponseData(times, Y.T, None, None, output_labels=labels,
                               sysname=f"cosim[{law}]", issiso=False)
    resp.stats = {"comm_step": H, "comm_steps": N, "fmu_substep": sub,
                  "controller": sim.stats_dict(), "wall_loop_s": wall_loop,
                  "wall_s": _time.perf_counter() - wall0,
                  "us_per_step": us_step}
    return resp


# ----------------------------------------------------------------------------- stability
#: Growth per communication step of the coupling's linearization at t = 0 (see
#: :func:`coupling_stability`) from which on the co-simulation is predicted to diverge.  1
#: is the stability limit; the margin covers what the linearization leaves out (θ̂'s
#: adaptation, gravity's and M(q)'s dependence on q within a step, Coriolis and friction).
DIVERGING_GROWTH = 1.5

#: ... and the growth over the horizon that the prediction needs as well: the simulator
#: stops a run whose state grows more than 1e6-fold (ivdrem.sim, divergence check).
DIVERGING_HORIZON_GROWTH = 1e6


@dataclass(frozen=True)
class CouplingStability:
    """Result of :func:`coupling_stability`: the explicit coupling at ``comm_step``,
    linearized at t = 0.

    ``growth``: spectral radius of the one-step map (None: no prediction, ``not_analysed``
    says why); ``rate``: its fastest mode's rate λ_max(M(q0)⁻¹(K + δ_μ μ(0))) in 1/s;
    ``m_min``: smallest eigenvalue of M(q0); ``mu``: μ(0); ``limit``, ``limit_end``:
    2 / λ_max at t = 0 and at ``t_end`` (μ(t_end), M(q0)), the largest communication steps
    at which the fastest mode's velocity loop alone is stable (u_f's integral action moves
    the limit of the whole map up by a factor 2 / (2 - H μ)).
    """
    comm_step: float
    t_end: float
    growth: float | None
    rate: float
    m_min: float
    mu: float
    mu_end: float
    limit: float
    limit_end: float
    not_analysed: str | None = None

    @property
    def diverges(self) -> bool:
        """True if the co-simulation at ``comm_step`` is predicted to diverge within
        ``t_end``: growth >= :data:`DIVERGING_GROWTH` per step and growth^N >=
        :data:`DIVERGING_HORIZON_GROWTH` over the N steps of the horizon."""
        if self.growth is None or not self.growth >= DIVERGING_GROWTH:
            return False
        steps = round(self.t_end / self.comm_step)
        return steps * math.log(self.growth) >= math.log(DIVERGING_HORIZON_GROWTH)

    def reason(self) -> str:
        """The prediction in words, with its numbers."""
        H = self.comm_step
        if self.growth is None:
            return f"no prediction for comm_step H = {H:g} s: {self.not_analysed}"
        text = (f"the explicit coupling at H = {H * 1e3:g} ms, linearized at t = 0, grows by "
                f"{self.growth:.3g} per step (spectral radius of the one-step map): the "
                f"fastest closed-loop mode, lambda_max(M(q0)^-1 (K + delta_mu mu(0))) = "
                f"{self.rate:.4g} 1/s (smallest eigenvalue of M(q0) {self.m_min:.3g}, "
                f"mu(0) = {self.mu:g}), has H lambda_max = {H * self.rate:.3g}")
        if not self.diverges:
            return text + f"; no divergence predicted (it takes {DIVERGING_GROWTH:g} per step)"
        steps = math.log(DIVERGING_HORIZON_GROWTH) / math.log(self.growth)
        above = " (above 2)" if H * self.rate > 2 else ""
        return (text + f"{above}; an error grows {DIVERGING_HORIZON_GROWTH:.0g}-fold within "
                f"{steps:.0f} steps ({steps * H * 1e3:.2g} ms of the {self.t_end:g} s).  A "
                f"stable coupling needs H below 2 / lambda_max = {self.limit * 1e3:.2g} ms at "
                f"t = 0 and {self.limit_end * 1e3:.2g} ms at t = {self.t_end:g} s (mu = "
                f"{self.mu_end:g}, with M(q0))")


def _one_step_map(rate, H, mu, alpha):
    """The co-simulation's one-step map of one mode (eigenvalue `rate`) of
    M⁻¹(K + δ_μ μ), linearized at t = 0 with θ̂ = 0 (module docstring, "Stability"): state
    (δq, δq', δw) with w = M⁻¹ u_f of the observer (7), and δr = -(δq' + alpha δq)
    (r = e' + alpha e, docs/conventions.md).  The FMU integrates the plant exactly under the
    held force M⁻¹ δtau = -rate (alpha δq + δq') - δw (tau of (9)); the controller
    integrates u_f' = mu (u - u_f), u = -tau of (7), whose rate -mu (K + δ_μ μ) δr (u_f's
    own term cancels) is constant with q, q' held."""
    f = np.array([-rate * alpha, -rate, -1.0])
    P = np.zeros((3, 3), dtype=complex)
    P[0] = np.array([1.0, H, 0.0]) + 0.5 * H * H * f
    P[1] = np.array([0.0, 1.0, 0.0]) + H * f
    P[2] = np.array([0.0, 0.0, 1.0]) + H * mu * rate * np.array([alpha, 1.0, 0.0])
    return P


def coupling_stability(model, comm_step, t_end, **config) -> CouplingStability:
    """Predict from the model and the configuration alone (no diagram, no run) whether the
    explicit coupling of :func:`cosimulate` at ``comm_step`` diverges within ``t_end``.

    The one-step map of the co-simulation is linearized at t = 0, at the plant's start
    (q0, q'0) with θ̂ = θ̂0 = 0: the FMU integrates M(q) q'' = tau + ... with tau of (9),
    tau = (K + δ_μ μ) r + Πᵀθ̂ - u_f, held over the step, and the controller integrates
    u_f of (7) with q, q' held.  With θ̂ = 0 a perturbation of (q, q', u_f) sees only
    A = M(q0)⁻¹(K + δ_μ μ(0)), α and μ(0), and the map of each eigenvalue of A
    (:func:`_one_step_map`) gives the growth per step; the fastest mode's is close to
    |1 - H λ_max(A)| (module docstring, "Stability").  Left out: θ̂'s adaptation (gain Γ),
    the dependence of M and G on q within a step, Coriolis and friction at q'0; hence the
    margin :data:`DIVERGING_GROWTH`.

    ``config``: keyword arguments of :func:`~ivdrem.diagrams.closed_loop` (its defaults
    for what is not given).  No prediction (``growth`` None) for a nonzero ``theta_hat0``
    (then Πᵀθ̂ adds a filtered velocity gain μ M(q, θ̂0) the map leaves out) or user blocks
    (``replace``).
    """
    from ivdrem.blocks import _validate as checks
    from ivdrem.diagrams.closed_loop import LOOP_ARGUMENTS as defaults

    H = float(comm_step)
    _steps(t_end, H)

    def given(key):
        v = config.get(key)
        return defaults[key] if v is None else v
    n = model.n
    q0, _ = _initial_state(model, config)
    theta = config.get("theta")
    theta = np.asarray(model.theta_values if theta is None else theta, dtype=float)
    K = checks.square("control_law", "K", 2.0 if given("K") is None else given("K"), n,
                      pd=True)   # closed_loop: K = 2 unless given (the paper's)
    delta_mu, alpha = float(given("delta_mu")), float(given("alpha"))
    mu0, mu1 = float(given("mu0")), float(given("mu1"))
    M = np.empty((n, n))
    model.functions.M(q0, theta, M)
    m_eig = np.linalg.eigvalsh(0.5 * (M + M.T))
    if not (np.all(np.isfinite(M)) and m_eig[0] > 0):
        raise ValueError(f"the inertia matrix M(q0) of model {model.name!r} is not positive "
                         f"definite (smallest eigenvalue {m_eig[0]:.3g})")

    def rates(mu):
        return np.linalg.eigvals(np.linalg.solve(M, K + delta_mu * mu * np.eye(n)))
    mu, mu_end = mu1, mu0 * float(t_end) + mu1
    lam = rates(mu)
    rate = float(np.max(np.abs(lam)))
    limit_end = 2.0 / float(np.max(np.abs(rates(mu_end))))
    common = dict(comm_step=H, t_end=float(t_end), rate=rate, m_min=float(m_eig[0]), mu=mu,
                  mu_end=mu_end, limit=2.0 / rate, limit_end=limit_end)
    theta_hat0 = config.get("theta_hat0")
    if theta_hat0 is not None and np.any(np.asarray(theta_hat0, dtype=float) != 0):
        return CouplingStability(growth=None, not_analysed="theta_hat0 is not zero", **common)
    if config.get("replace"):
        return CouplingStability(growth=None, not_analysed="blocks are replaced", **common)
    growth = max(float(np.max(np.abs(np.linalg.eigvals(_one_step_map(a, H, mu, alpha)))))
                 for a in lam)
    return CouplingStability(growth=growth, **common)


# ----------------------------------------------------------------------------- comparison
@dataclass
class CosimComparison:
    """Result of :func:`compare_to_python`.

    ``errors[signal][i]``: max over time and components of |co-sim - Python| at
    ``comm_steps[i]``; ``orders[signal][i]``: observed order between ``comm_steps[i]`` and
    ``comm_steps[i + 1]`` = log(err_i / err_{i+1}) / log(H_i / H_{i+1}).
    """
    law: str
    t_end: float
    comm_steps: tuple
    signals: tuple
    errors: dict
    orders: dict
    reference: object = field(repr=False)
    results: list = field(repr=False)
    wall: dict = field(default_factory=dict)
    expected_order: tuple = EXPECTED_ORDER

    @property
    def ok(self) -> bool:
        lo, hi = self.expected_order
        return all(np.all(np.isfinite(self.errors[s])) for s in self.signals) and \
            all(lo <= o <= hi for s in self.signals for o in self.orders[s])

    def table(self) -> str:
        rows = [("signal", "H [s]", "max |co-sim - Python|", "order")]
        for s in self.signals:
            for i, H in enumerate(self.comm_steps):
                o = "" if i == 0 else f"{self.orders[s][i - 1]:.2f}"
                rows.append((s if i == 0 else "", f"{H:.4g}", f"{self.errors[s][i]:.3e}", o))
        w = [max(len(r[j]) for r in rows) for j in range(4)]
        line = "  ".join("-" * x for x in w)
        out = []
        for i, r in enumerate(rows):
            out.append(f"{r[0]:<{w[0]}}  {r[1]:>{w[1]}}  {r[2]:>{w[2]}}  {r[3]:>{w[3]}}")
            if i == 0:
                out.append(line)
        return "\n".join(out)

    def verdict(self) -> str:
        lo, hi = self.expected_order
        allo = [o for s in self.signals for o in self.orders[s]]
        rng = f"{min(allo):.2f}..{max(allo):.2f}" if allo else "n/a"
        if self.ok:
            return (f"OK: the co-simulation converges to the all-Python closed loop at first "
                    f"order in H (observed orders {rng}, expected {lo}..{hi} for "
                    f"sample-and-hold coupling)")
        return (f"CHECK: observed orders {rng} outside the expected {lo}..{hi} for "
                f"sample-and-hold coupling (or non-finite errors)")

    def __str__(self):
        return self.table() + "\n" + self.verdict()


def compare_to_python(fmu_path, t_end, comm_steps=(1e-3, 5e-4, 2.5e-4), *, law="iv-drem",
                      model=None, engine="compiled", ref_method=REFERENCE_METHOD, ref_h=None,
                      ref_rtol=1e-11, ref_atol=1e-13, signals=COMPARED_SIGNALS,
                      progress=None, allow_long=False, **config):
    """Co-simulate at each communication step and compare with the all-Python closed loop.

    The reference is ``simulate(closed_loop(law, model, **config), t_end, method="rk4",
    h=ref_h)`` (default ``ref_h`` = the smallest communication step; RK4's error,
    ``O(h^4)``, is then orders of magnitude below the coupling error) or, with
    ``ref_method="dp45"``, error-controlled with ``ref_rtol``, ``ref_atol``.  It is sampled at
    the smallest communication step; every step in ``comm_steps`` must be a whole multiple of
    it, and ``t_end`` a whole multiple of every step.

    For each signal in ``signals`` (default q, theta_hat, tau_d_hat) the result holds the max
    abs difference over the run (all components, all communication points) and the observed
    order of convergence between successive steps, ``log(e_i / e_{i+1}) / log(H_i / H_{i+1})``
    (``log2`` of the error ratio for halvings).

    What to expect: the explicit sample-and-hold (zero-order hold) coupling holds each side's
    inputs at their value at ``t_k`` over ``[t_k, t_k + H]``, an ``O(H)`` perturbation of
    the continuous closed loop, so the global error is ``O(H)``: the error should roughly
    halve when ``H`` halves, observed order close to 1 (accepted range
    :data:`EXPECTED_ORDER` = 0.7 .. 1.5).  The integrators (RK4 in the FMU and the
    controller, reference RK4 at the finest ``H``) are fourth order and do not show.

    Order of the work (the cheap, decisive part first): the arguments, the controller
    diagram (the signals are checked on its outputs) and the reference run's cost
    (:mod:`ivdrem.sim.guards`, from the controller's sizes plus the plant's q, q'; ``allow_long``
    lifts the limits); then the co-simulation at the coarsest step, which is the one the
    explicit coupling is least stable at (module docstring, "Stability").  If it fails
    (divergence, FMU error), its error (the time, ``H`` and the cause) is raised before the
    all-Python loop is built or run.  Then the reference, then the other steps; each
    closed loop is built only when it is about to run, and this function keeps none of them
    after its run.
    """
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import two_link
    from ivdrem.sim import simulate

    model = two_link() if model is None else model
    comm_steps = tuple(float(H) for H in comm_steps)
    if not comm_steps:
        raise ValueError("comm_steps must not be empty")
    h_min = min(comm_steps)
    strides = []
    for H in comm_steps:
        _steps(t_end, H)
        r = H / h_min
        if not (h_min > 0 and abs(r - round(r)) < 1e-9 * r):
            raise ValueError(f"communication step {H:g} is not a whole multiple of the "
                             f"smallest one, {h_min:g}")
        strides.append(int(round(r)))
    fixed_ref = method_info(ref_method).fixed_step
    if fixed_ref:
        h = h_min if ref_h is None else float(ref_h)
        r = h_min / h if h > 0 else math.nan
        if not (math.isfinite(h) and h > 0 and abs(r - round(r)) < 1e-9 * max(1.0, r)):
            raise ValueError(f"ref_h = {h:g} s must divide the smallest communication step "
                             f"{h_min:g} s (the reference is sampled there)")
    # the controller of the first co-simulation; its outputs with q, dq in front are the
    # closed loop's (checked again on the full diagram below)
    ctrl = controller_diagram(law, model, **config)
    labels = list(ctrl.input_labels) + list(ctrl.output_labels)
    idx = {}
    for s in signals:
        cols = [i for i, lab in enumerate(labels) if lab == s or lab.startswith(s + "[")]
        if not cols:
            names = sorted({lab.split("[")[0] for lab in labels})
            raise ValueError(f"unknown signal {s!r}; outputs are {', '.join(names)}")
        idx[s] = cols
    _check_reference_cost(ctrl, t_end, method=ref_method, h=h if fixed_ref else 1e-3,
                          dt_out=h_min, engine=engine, allow_long=allow_long)

    show = _want_progress(progress)
    wall = {}
    results = [None] * len(comm_steps)

    def run_cosim(i, controller=None):
        t0 = _time.perf_counter()
        res = cosimulate(fmu_path, t_end, law=law, comm_step=comm_steps[i], model=model,
                         engine=engine, progress=show, controller=controller, **config)
        wall[f"cosim H={comm_steps[i]:g}"] = _time.perf_counter() - t0
        if list(res.output_labels) != labels:
            raise RuntimeError(f"co-simulation outputs {res.output_labels} differ from the "
                               f"closed loop's {labels}")  # pragma: no cover
        results[i] = res

    coarsest = comm_steps.index(max(comm_steps))
    run_cosim(coarsest, ctrl)           # raises here if the coupling diverges at this H
    del ctrl
    _release_diagrams()

    full = closed_loop(law, model, **config)
    if list(full.output_labels) != labels:
        raise RuntimeError(f"closed-loop outputs {full.output_labels} differ from the "
                           f"co-simulation's {labels}")  # pragma: no cover
    t0 = _time.perf_counter()
    if fixed_ref:
        ref = simulate(full, t_end, method=ref_method, h=h, dt_out=h_min, engine=engine,
                       return_states=False, progress=show, desc=f"Python {law}",
                       allow_long=allow_long)
    else:
        ref = simulate(full, t_end, method=ref_method, rtol=ref_rtol, atol=ref_atol,
                       dt_out=h_min, engine=engine, return_states=False, progress=show,
                       desc=f"Python {law}", allow_long=allow_long)
    wall["python"] = _time.perf_counter() - t0
    del full
    _release_diagrams()
    for i in range(len(comm_steps)):
        if results[i] is None:
            run_cosim(i)
            _release_diagrams()
    Yref = np.asarray(ref.outputs)
    errors = {s: np.zeros(len(comm_steps)) for s in signals}
    for i, res in enumerate(results):
        Yc = np.asarray(res.outputs)
        Yr = Yref[:, ::strides[i]]
        if Yr.shape != Yc.shape:  # pragma: no cover - guarded by _steps
            raise RuntimeError(f"sample mismatch {Yr.shape} vs {Yc.shape}")
        for s in signals:
            errors[s][i] = float(np.max(np.abs(Yc[idx[s]] - Yr[idx[s]])))
    orders = {}
    for s in signals:
        e = errors[s]
        orders[s] = np.array([
            math.log(e[i] / e[i + 1]) / math.log(comm_steps[i] / comm_steps[i + 1])
            if e[i] > 0 and e[i + 1] > 0 and comm_steps[i] != comm_steps[i + 1] else math.nan
            for i in range(len(comm_steps) - 1)])
    # wall times listed as before: the reference, then the steps in the order given
    wall = {"python": wall["python"],
            **{k: wall[k] for k in (f"cosim H={H:g}" for H in comm_steps)}}
    return CosimComparison(law=law, t_end=float(t_end), comm_steps=comm_steps,
                           signals=tuple(signals), errors=errors, orders=orders,
                           reference=ref, results=results, wall=wall)


def _release_diagrams():
    """Free the closed loops no longer referenced before the next one is built: a diagram
    holds python-control's dense connection map (1.2 GiB on the Panda) and its own reference
    cycles (the InterconnectedSystem's closures), so it waits for a full collection, which
    a few large arrays do not trigger."""
    gc.collect()


def _check_reference_cost(controller, t_end, **kwargs):
    """The guard (:func:`ivdrem.sim.guards.check_cost`) of the all-Python reference run,
    priced before anything runs from the controller diagram: the closed loop is the
    controller plus the plant, whose states and outputs are its inputs q, q' (the same
    guard runs again in ``simulate`` on the full diagram)."""
    from ivdrem.sim.guards import check_cost
    from ivdrem.sim.sampled import sample_period
    periods = [p for p in map(sample_period, getattr(controller, "syslist", ())) if p > 0]
    return check_cost(t_end, noutputs=controller.noutputs + controller.ninputs,
                      nstates=controller.nstates + controller.ninputs, return_states=False,
                      sample_period=min(periods, default=None),
                      what="the all-Python reference run", **kwargs)
