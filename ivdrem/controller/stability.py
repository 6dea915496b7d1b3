"""Will the sampled loop hold at h?  The growth per step of the controller closed around a
zero-order-hold plant, predicted from the model and the gains before any export or run.

A controller that runs every h seconds and a plant that holds its torque over the step make
one discrete-time system, the *one-step map* x_{k+1} = P(t_k, x_k).  Its linearisation
about the arm on its reference has a spectral radius ρ: an error grows by ρ per step, so the
loop diverges when ρ > 1 (the velocity loop alone: |1 - h k / λ_min(M(q))|, unstable
beyond h k / λ_min(M) = 2, docs/controller.md).  :func:`sampled_stability` computes ρ by
finite differences of the same code a run uses, one controller step
(:meth:`SampledController.step <ivdrem.controller.sampled.SampledController.step>`) and one
plant step (RK4 sub-steps of the plant FMU's ``cs_substep``, torque held), so a change of the
algorithm changes the prediction with it:

* state: the plant's q, q̇ at t_k, the torque u the plant holds over [t_k, t_k+1] (delay 1:
  τ_{k-1}; delay 0: none), and the controller's states that move within a step: every
  n-vector of :meth:`SampledController.state` (the observer's u_f of (7), the filtered
  torque z_f of (13) ...) and every n × nθ filter (Φ_f, Φ_Mf of (7), ξ, η of (13), ζ of
  (14)) seen through θ̂ (its coordinate S θ̂: the torque (9) reads these filters only as
  Πᵀθ̂, and each is affine in itself, so S θ̂ is a state of its own), Φ_Mf through
  θ_nominal under the injection "nominal" (the torque reads Φ_Mf θ_nominal then);
  ``gravity = "robot"``: the plant adds G(q) itself, as the robot does;
* frozen: θ̂ (the adaptation (11) moves it at the rate Γ, far slower than a sample), the window (15a), the averaging (15b) and the mixing (17)
  (they reach the torque through θ̂ only, so the map is computed with the law's composite
  term left out: the controller of law "none" with the same gains);
* operating points, two kinds: (a) states of the closed loop itself, simulated over the
  gradient phase (:func:`closed_loop_prefix`: until the window (15a) is full the composite
  term of (21) is 0, and θ̂ moves by the gradient term Γ Π r of (11) alone), each with the
  run's own θ̂: with the injection "estimate" the map depends on θ̂ through the observer's
  injection μ Φ_Mᵀ(q, r) θ̂ = μ M(q, θ̂) r of (8), a velocity feedback whose per-step gain
  h μ ν(θ̂) (ν the largest generalised eigenvalue of M(q, θ̂) against M(q)) is what made
  the iiwa and the xArm7 diverge with the FMU's one-sample delay while the reference
  points said 0.999, and the xArm7 again past T (docs/controller.md, "Sampled designs");
  (b) the arm on the reference, q = q_d(t),
  q̇ = q̇_d(t), holding the torque the reference needs (the inverse dynamics with the true
  θ, less the disturbance, so the plant's q̈ = q̈_d), at :data:`POINTS` times spread over
  the horizon (μ(t) of (7)-(9) grows with t) with θ̂₀ and θ.  Every filter of the
  controller is affine in its own state, so the linearisation does not depend on their
  values, only on q, q̇, the held torque and θ̂.

A loop is predicted unstable when the largest ρ over the points exceeds
:data:`UNSTABLE_GROWTH`; :meth:`SampledStability.reason` says it in one line with the
numbers and what to change (a smaller h, found by the same prediction, or the gains).
Checked against runs (tests/test_controller_export.py): the paper's design on the Panda at
1 ms is predicted at ρ ≈ 2 and diverges within tens of milliseconds; the paper's 2-link
design is predicted stable and runs; on the 2-link arm a K between the two sides of the
predicted boundary diverges or does not, as predicted, and the one-sample delay halves
that boundary (tests/test_sampled_stability.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..laws import get_law

__all__ = ["SampledStability", "sampled_stability", "loop_growth", "closed_loop_prefix",
           "UNSTABLE_GROWTH", "POINTS", "PREFIX_POINTS", "PREFIX_PAST_T", "PREFIX_FLAGS",
           "UnstableDesignError"]

#: The growth per step from which a sampled loop is refused: an error then grows at least
#: 1e6-fold within 1400 steps (1.4 s at 1 kHz).  Slightly above 1 so that finite-difference
#: noise and the slow modes (e^{-α h}, the integral action of u_f) never decide.
UNSTABLE_GROWTH = 1.01

#: Operating points along the reference (times spread over the horizon).
POINTS = 4

#: States of the simulated closed loop (the prefix) the map is linearised at.
PREFIX_POINTS = 8

#: The default prefix of a windowed law, in windows T: the gradient phase (until T) and a
#: quarter window of the composite term (21) (its ramp is 0.1 T), which the law itself runs
#: from T on when the C library runs it (the Python reference's mixing is too slow for it:
#: then T at most).  It flags the xArm7 with the observer's injection at θ̂ (diverged at
#: 42.79 s; predicted 1.08 per step at 42.6 s) and passes it with the injection at
#: θ_nominal (0.9998, converges over 300 s) and example-robot-data's UR3 (0.9991;
#: converged around PyBullet, benchmarks/bullet_harness.py); docs/controller.md.
PREFIX_PAST_T = 1.25

#: The C compiler's flags of the controller library the prefix runs: -O3 steps the Panda's
#: IV-DREM 1.3-1.6 times as fast as -O2 (benchmarks/bench_predict.py) with the same bits:
#: without -ffast-math GCC vectorises only where the order of the operations is kept
#: (tests/test_sampled_stability.py checks the points against -O2's).
PREFIX_FLAGS = ("-O3",)

#: Relative finite-difference step of the linearisation.
_EPS = 1e-7


class UnstableDesignError(ValueError):
    """A sampled loop predicted unstable (its message: the numbers, what to change)."""

    def __init__(self, stability):
        super().__init__(stability.reason())
        self.stability = stability


def _rk4_plant(model, theta, q, dq, u, h, substep, gravity=False):
    """The plant FMU's step: ceil(h / substep) equal RK4 sub-steps of
    M(q) q̈ + C(q, q̇) q̇ + F(q̇) + G(q) = u with u held; ``gravity``: the robot adds its own
    G(q) to u at every stage (gravity "robot", as :class:`~ivdrem.controller.loop.ModelPlant`)."""
    fd = model.jit_functions.forward_dynamics
    G = model.jit_functions.G
    k = max(1, math.ceil(h / substep - 1e-9))
    s = h / k
    a = np.empty(model.n)
    g = np.zeros(model.n)

    def f(q, dq):
        if gravity:
            G(q, theta, g)
        fd(q, dq, u + g, theta, a)
        return a.copy()
    for _ in range(k):
        k1q, k1v = dq, f(q, dq)
        k2q, k2v = dq + 0.5 * s * k1v, f(q + 0.5 * s * k1q, dq + 0.5 * s * k1v)
        k3q, k3v = dq + 0.5 * s * k2v, f(q + 0.5 * s * k2q, dq + 0.5 * s * k2v)
        k4q, k4v = dq + s * k3v, f(q + s * k3q, dq + s * k3v)
        q = q + s / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
        dq = dq + s / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return q, dq


def _coordinates(controller, state, theta_hat):
    """[(key, direction)] of the controller's fast states: direction None for an n-vector,
    or the nθ-vector p an n × nθ filter S is seen through (its coordinate S p): θ̂ for
    every filter, except Φ_Mf of (7) under the injection "nominal", which the torque (9)
    reads as Φ_Mf θ_nominal; θ̂ itself and everything else are frozen."""
    n, nth = controller.n, controller.ntheta
    out = []
    nominal = getattr(controller, "injection", "estimate") == "nominal"
    for key, v in state.items():
        if key == "theta_hat" or not isinstance(v, np.ndarray):
            continue
        if v.shape == (n,):
            out.append((key, None))
        elif v.shape == (n, nth):
            p = controller.theta_nominal if nominal and key == "Phi_Mf" else theta_hat
            if np.any(p != 0):
                out.append((key, np.asarray(p, dtype=float)))
    return out


def loop_growth(controller, theta, t, *, theta_hat, disturbance=None, substep=None,
                at=None):
    """ρ of the one-step map at time t (a sample time) with θ̂ frozen at ``theta_hat``:
    (spectral radius, the map's Jacobian).  The operating point is the arm on the
    reference holding the torque the reference needs, or ``at`` = (q, q̇, u): a state of
    the closed loop (u: the torque the plant holds over the step, delay 1)."""
    from ..fmu import DEFAULT_SUBSTEP
    model, h, n = controller.model, controller.h, controller.n
    substep = DEFAULT_SUBSTEP if substep is None else float(substep)
    theta = np.asarray(theta, dtype=float)
    theta_hat = np.asarray(theta_hat, dtype=float)
    k = int(round(t / h))
    t = k * h
    tau_d = np.zeros(n) if disturbance is None else np.asarray(disturbance(t), dtype=float)
    robot_gravity = getattr(controller, "gravity", "controller") == "robot"
    if at is None:
        qd, dqd, ddqd = (np.asarray(x, dtype=float) for x in controller.reference(t))
        u0 = model.inverse_dynamics(qd, dqd, ddqd, theta) - tau_d
        if robot_gravity:       # the command: the robot adds G(q) itself
            Gq = np.empty(n)
            model.jit_functions.G(qd, theta, Gq)
            u0 = u0 - Gq
    else:
        qd, dqd, u0 = (np.asarray(x, dtype=float) for x in at)
    controller.reset()
    base = controller.state()
    base["k"] = np.array(k)
    base["theta_hat"] = theta_hat.copy()
    coords = _coordinates(controller, base, theta_hat)
    delay = getattr(controller, "delay", 0)

    def pack(q, dq, u, s):
        parts = [q, dq] + ([u] if delay else [])
        for key, p in coords:
            parts.append(s[key] if p is None else s[key] @ p)
        return np.concatenate(parts)

    def unpack(x):
        q, dq = x[:n], x[n:2 * n]
        o = 2 * n
        u = None
        if delay:
            u, o = x[o:o + n], o + n
        s = {kk: (np.copy(v) if isinstance(v, np.ndarray) else v) for kk, v in base.items()}
        for key, p in coords:
            seg = x[o:o + n]
            o += n
            if p is None:
                s[key] = seg.copy()
            else:           # move S so that S p = seg (the nearest S along p)
                s[key] = base[key] + np.outer(seg - base[key] @ p, p / float(p @ p))
        if delay:           # the controller's own record of the torque held (its filters'
            s["tau_prev"] = u.copy()        # input, (7) and (13)) is the plant's, and
            s["tau"] = u.copy()             # so is its last command (gravity "robot")
        return q, dq, u, s

    def step(x):
        q, dq, u, s = unpack(x)
        controller.set_state(s)
        tau = controller.step(t, q, dq)
        applied = u if delay else tau
        q1, dq1 = _rk4_plant(model, theta, q, dq, applied + tau_d, h, substep,
                             robot_gravity)
        return pack(q1, dq1, tau, controller.state())

    if delay:               # the held torque is a state of its own (u above)
        coords = [c for c in coords if c[0] not in ("tau_prev", "tau")]
    x0 = pack(qd, dqd, u0, base)
    y0 = step(x0)
    J = np.empty((x0.size, x0.size))
    for j in range(x0.size):
        e = _EPS * max(1.0, abs(x0[j]))
        x = x0.copy()
        x[j] += e
        J[:, j] = (step(x) - y0) / e
    controller.reset()
    if not np.all(np.isfinite(J)):
        return math.inf, J
    # a state the step leaves as it is and that nothing reads (e.g. the instrument's ζ of
    # (14) under a law without it) is an eigenvalue 1 of no consequence: left out
    eye = np.eye(x0.size)
    keep = ~(np.all(np.abs(J - eye) <= 1e-9, axis=0) & np.all(np.abs(J - eye) <= 1e-9, axis=1))
    J = J[np.ix_(keep, keep)]
    return float(np.max(np.abs(np.linalg.eigvals(J)))), J


def closed_loop_prefix(model, law, theta, t_end, *, disturbance=None, substep=None,
                       checkpoints=8, backend="c", compiled=True, flags=PREFIX_FLAGS,
                       pieces=None, progress=None, **gains):
    """The sampled loop itself over [0, t_end]: the controller of ``law`` (``gains`` as
    :class:`~ivdrem.controller.sampled.SampledController`'s, its ``delay`` included) around
    the plant FMU's RK4 (``substep``; torque and ``disturbance`` held), started on the
    reference q_d(0), q̇_d(0) as the FMU hosts start it.  Returns (points, diverged):
    ``checkpoints`` states (t, q, q̇, u held, θ̂) spread over the run, and None or
    (t, the state 0.1 s before) where the plant's state stopped being finite.
    ``backend`` "c": the generated C library (:class:`~ivdrem.controller.clib.CController`;
    the Python reference if it cannot be loaded), "python": SampledController.
    ``compiled``: the C library's loop compiled (:func:`_compiled_prefix`, the same points),
    run in pieces of about :data:`PIECE_S` s so that Ctrl-C and SIGTERM stop it
    (``pieces``: that many steps per piece instead, the same points; ``progress``: a bar of
    its steps, None: on a terminal); False: step by step from Python (the check of the
    compiled loop).
    ``flags``: the C library's compiler flags (:data:`PREFIX_FLAGS`)."""
    from ..fmu import DEFAULT_SUBSTEP
    from .loop import ModelPlant
    from .sampled import SampledController
    cls = SampledController
    if backend == "c":
        try:
            from .clib import CController
            ctl = CController(model, law, flags=flags, **gains)
            cls = CController
        except Exception:       # no compiler, or a model the generator does not take
            cls = SampledController
    if cls is SampledController:
        ctl = cls(model, law, **gains)
    h, n = ctl.h, ctl.n
    substep = DEFAULT_SUBSTEP if substep is None else float(substep)
    nsub = max(1, math.ceil(h / substep - 1e-9))
    q0, dq0, _ = (np.asarray(x, dtype=float) for x in SampledController(
        model, "none", **{**gains, "T": gains.get("block", 10) * h}).reference(0.0))
    plant = ModelPlant(model, q0, dq0, theta=theta, substeps=nsub,
                       gravity=gains.get("gravity", "controller") == "robot")
    N = int(round(t_end / h))
    marks = set(np.linspace(0, N, max(2, checkpoints) + 1, dtype=int)[1:].tolist())
    delay = ctl.delay
    if compiled and cls is not SampledController:
        return _compiled_prefix(model, ctl, plant, N, marks, disturbance, pieces, progress)
    u = np.zeros(n)
    points, recent = [], []
    for k in range(N + 1):
        t = k * h
        q, dq = plant.outputs()
        if k % 100 == 0:
            recent = recent[-1:] + [(t, q, dq, u.copy(), np.array(ctl.theta_hat))]
        if k in marks:
            points.append((t, q, dq, u.copy(), np.array(ctl.theta_hat)))
        if k == N:
            break
        try:
            tau = ctl.step(t, q, dq)
            applied = tau if delay == 0 else u
            plant.step(t, h, applied,
                       np.zeros(n) if disturbance is None else disturbance(t))
        except (FloatingPointError, ValueError, RuntimeError):
            return points, (t, recent[0])
        u = np.asarray(tau, dtype=float)
    return points, None


def _compiled_prefix(model, ctl, plant, N, marks, disturbance, pieces=None,
                     progress=None):
    """closed_loop_prefix's loop compiled (the C controller ``ctl`` around the RK4 of
    ``plant``: :func:`~ivdrem.controller.loop.compiled_closed_loop`), the same steps as the
    Python loop, so the same points to the last bit (tests/test_sampled_stability.py); the
    loop's Python per step, not its arithmetic, was a third of the prefix's time.  Run in
    pieces of about :data:`PIECE_S` seconds (``pieces``: a fixed number of steps per
    piece instead), between which Python handles Ctrl-C and SIGTERM: one call of the
    whole prefix (6-12 s on the Panda) ignored them until it returned.  ``progress``: a bar
    of the steps on stderr (None: on a terminal, :func:`ivdrem._progress.want_progress`)."""
    from .loop import compiled_closed_loop
    h, n = ctl.h, ctl.n
    tau_d = np.zeros((N, n))
    if disturbance is not None:         # held over step k: τ_d(t_k), as the plant takes it
        for k in range(N):
            tau_d[k] = disturbance(k * h)
    keep = np.zeros(N + 1, dtype=np.bool_)
    keep[::100] = True                  # the states 0.1-0.2 s before a divergence
    keep[sorted(marks)] = True
    rows = int(keep.sum())
    rec_q, rec_dq, rec_u = (np.zeros((rows, n)) for _ in range(3))
    rec_theta_hat = np.zeros((rows, ctl.ntheta))
    at = np.zeros(2, dtype=np.int64)                # the next step k, the next record row
    step, outputs, handle = ctl.entry_points()
    loop = compiled_closed_loop(model)
    u = np.zeros(n)                                 # the torque held (delay 1)

    def piece(k_stop):
        return loop(step, outputs, handle, plant.q, plant.dq, u, plant.theta, tau_d,
                    float(h), plant.substeps, plant.gravity, int(ctl.delay), keep, rec_q,
                    rec_dq, rec_u, rec_theta_hat, at, k_stop)
    bar = _steps_bar(progress, N, f"stability prediction, the loop's first {N * h:g} s")
    try:
        status = run_in_pieces(piece, at, N + 1, pieces,
                               report=None if bar is None else lambda k: bar.update(k - bar.n))
    except ValueError:                  # M(q) singular along a diverged motion
        status = 2
    finally:
        if bar is not None:
            bar.close()
    ks = np.flatnonzero(keep)
    last = int(at[0])
    points = [(k * h, rec_q[j], rec_dq[j], rec_u[j], rec_theta_hat[j])
              for j, k in enumerate(ks) if k in marks and k <= last]
    if status == 0:
        return points, None
    recent = [j for j, k in enumerate(ks) if k % 100 == 0 and k <= last][-2:]
    j = recent[0]
    return points, (last * h, (ks[j] * h, rec_q[j], rec_dq[j], rec_u[j], rec_theta_hat[j]))


#: Wall time of one piece of a compiled loop (:func:`run_in_pieces`): a Ctrl-C or SIGTERM
#: waits at most about this long; a call costs 20-30 µs (benchmarks/bench_pieces.py), so
#: the pieces cost about 0.02 % of the loop.
PIECE_S = 0.1

#: Steps of a compiled loop's first piece, before its speed is known.
FIRST_PIECE = 64

#: A compiled loop's status "stopped at k_stop, call again" (loop.compiled_closed_loop).
_GO_ON = 3


def _steps_bar(progress, N, desc):
    """A tqdm bar of N steps on stderr if :func:`ivdrem._progress.want_progress` says so
    (``progress`` None: on a terminal, not in CI), else None."""
    from .._progress import want_progress
    if N < 1 or not want_progress(progress):
        return None
    import sys

    from tqdm import tqdm
    return tqdm(total=N, unit="step", desc=desc, file=sys.stderr, leave=False)


def run_in_pieces(piece, progress, stop, pieces=None, piece_s=PIECE_S, report=None):
    """Run a compiled loop over steps progress[0] .. stop - 1 as calls ``piece(k_stop)``,
    each going on from progress[0] (which it advances) and returning the loop's status,
    :data:`_GO_ON` when it reached k_stop; returns the first other status.  Python handles
    a pending Ctrl-C or SIGTERM between two calls only: each call is sized to last about
    ``piece_s`` seconds from the speed of the last (a loop whose steps vary in cost, the
    mixing (17) every few samples, is measured over many of them); ``pieces``: that many
    steps per call instead (the tests: 1, or ``stop``: one call); ``report(k)`` after each
    piece but the last (a progress bar).  The pieces change nothing the loop computes, only
    where it returns to Python."""
    import time
    size = FIRST_PIECE if pieces is None else max(1, int(pieces))
    while True:
        start = int(progress[0])
        t0 = time.perf_counter()
        status = piece(min(stop, start + size))
        if status != _GO_ON:
            return status
        if report is not None:
            report(int(progress[0]))
        if pieces is None:
            done = int(progress[0]) - start
            spent = time.perf_counter() - t0
            size = max(1, min(4 * size, int(done * piece_s / spent) if spent > 0 else 4 * size))


@dataclass(frozen=True)
class SampledStability:
    """The prediction of :func:`sampled_stability`.

    ``growth``: the largest spectral radius of the one-step map over the points;
    ``points``: (t, which θ̂, ρ) per point; ``worst``: the point of ``growth``;
    ``stable_h``: the largest of a few smaller steps dividing T predicted stable at the
    worst point (None if none was looked for or none holds).
    """
    model: str
    law: str
    h: float
    growth: float
    points: tuple
    worst: tuple
    stable_h: float | None = None
    threshold: float = UNSTABLE_GROWTH
    delay: int = 0
    diverged: float | None = None
    injection: str = "estimate"

    @property
    def stable(self) -> bool:
        return self.growth <= self.threshold

    def margin(self) -> float:
        """1 - ρ: how far the worst point is from the stability limit (negative: unstable)."""
        return 1.0 - self.growth

    def reason(self) -> str:
        t, which, g = self.worst
        head = (f"the sampled loop ({self.law} on {self.model}, h = {self.h * 1e3:g} ms, "
                f"delay {self.delay}) is "
                f"predicted {'stable' if self.stable else 'unstable'}: an error grows by "
                f"{g:.4g} per step (spectral radius of the linearised one-step map, "
                f"largest at t = {t:g} s with theta_hat = {which}")
        if self.stable:
            return head + f"; refused above {self.threshold:g})"
        if math.isfinite(g):
            steps = (math.log(1e6) / math.log(g)) if g > 1 else math.inf
            text = head + f"; 1e6-fold within {steps:.0f} steps = {steps * self.h * 1e3:.3g} ms)"
        else:
            text = head + ")"
        fix = []
        if self.diverged is not None and self.injection == "estimate":
            fix.append("injection = 'nominal' (the observer's injection of (8) at the "
                       "nominal parameters: the loop's inertia M(q, theta_nominal) instead "
                       "of M(q, theta_hat), docs/controller.md)")
        if self.stable_h is not None:
            fix.append(f"h = {self.stable_h * 1e3:g} ms (--h {self.stable_h:g}, predicted "
                       "stable)")
        fix.append("smaller gains ([controller] K, mu1, mu0, delta_mu, mu_max; Gamma if it "
                   "diverges along the run: the gradient term moves theta_hat, "
                   "docs/controller.md 'Sampled designs')")
        return text + "; change: " + ", or ".join(fix)


def _c_library(model, law, gains):
    """Whether the generated C library runs the controller of ``law`` for ``model``."""
    try:
        from .clib import CController
        CController(model, law, flags=PREFIX_FLAGS, **gains)   # the prefix's build
        return True
    except Exception:       # no compiler, or a model the generator does not take
        return False


def _reference_points(t_end, h, count):
    """0, t_end and count - 2 times between at golden-ratio spacing: evenly spaced points
    share the phase of a periodic reference whose period divides the spacing (the real-arm
    experiment's 10 s against a 120 s horizon), these do not."""
    t_end = float(t_end)
    ts = [0.0, t_end] + [((i * 0.6180339887498949) % 1.0) * t_end for i in range(1, count - 1)]
    return sorted({round(t / h) * h for t in ts})


def sampled_stability(model, law="iv-drem", *, theta=None, t_end=300.0, disturbance=None,
                      points=POINTS, substep=None, suggest=True, controller_class=None,
                      prefix=None, prefix_points=PREFIX_POINTS, backend="c",
                      progress=None, **gains) -> SampledStability:
    """Predict the growth per step of the sampled controller of ``law`` for ``model``
    (``gains``: the arguments of :class:`~ivdrem.controller.sampled.SampledController`, h
    and ``delay`` among them: the controller FMU's hosts have delay 1) closed around the
    model's plant (true parameters ``theta``, default the model's): the largest spectral
    radius of the one-step map (module docstring)

    * along the closed loop itself: the loop simulated over the first ``prefix`` seconds
      (default :data:`PREFIX_PAST_T` windows T: the phase where θ̂ moves by the gradient
      term of (11) alone; :func:`closed_loop_prefix`, C library unless
      ``backend="python"``; past T the law itself, C library only), linearised at
      ``prefix_points`` of its states with their own θ̂; a prefix that diverges is
      unstable, its growth taken 0.1 s before;
    * on the reference at ``points`` times in [0, t_end] (μ(t) grows to μ_max), for
      θ̂ = θ̂₀, θ̂ = θ and the θ̂ the prefix ended with.

    ``disturbance``: t -> τ_d(t) held by the plant.  ``suggest``: look for a smaller h
    predicted stable at the worst point (h/2, h/4, h/5, h/10 that divide T).  ``progress``:
    a bar of the prefix's steps on stderr (None: on a terminal, not in CI; False: never)."""
    from .loop import default_period
    from .sampled import SampledController
    make = SampledController if controller_class is None else controller_class
    design = make(model, law, **gains)        # the design as given: every check
    T, block = getattr(design, "T", None), int(getattr(design, "block", 1))
    del design

    def short(h):
        # θ̂ is frozen, so the law's composite term, which moves θ̂ only (11), does not
        # enter the map: the controller of the same gains without it (law "none": no
        # window (15a), no mixing (17)) has the same torque (9) and fast states, at a
        # fraction of the cost of a step (Panda: 1.2 ms against 45 ms in Python)
        return make(model, "none", **{**gains, "h": h, "T": block * h})
    controller = short(float(default_period() if gains.get("h") is None else gains["h"]))
    model = controller.model
    theta = np.asarray(model.theta_values if theta is None else theta, dtype=float)
    h = controller.h
    rows, ops = [], []

    def look(t, which, th, at=None, c=None):
        g, _ = loop_growth(controller if c is None else c, theta, t, theta_hat=th,
                           disturbance=disturbance, substep=substep, at=at)
        return g

    # the loop itself over the gradient phase and the start of the composite term: until
    # the window is full (t < T) the term of (21) is 0 and a windowed law moves θ̂ as the
    # law "none" does; from T on it drives θ̂ to the window's estimate, which on a light
    # wrist can be far from θ where M is small (the xArm7: docs/controller.md)
    Tw = float(T if T else 20.0)
    windowed = get_law(law).windowed
    with_c = backend == "c" and _c_library(model, law, gains)
    horizon = min(float(t_end), PREFIX_PAST_T * Tw if prefix is None else float(prefix))
    if windowed and not with_c:
        horizon = min(horizon, Tw)
    diverged, theta_end = None, None
    plaw = "none" if windowed and horizon <= Tw else law
    if horizon >= h and prefix_points > 0:
        pgains = {**gains, "T": block * h} if plaw == "none" else dict(gains)
        run, div = closed_loop_prefix(model, plaw, theta, horizon, disturbance=disturbance,
                                      substep=substep, checkpoints=prefix_points,
                                      backend=backend, progress=progress, **pgains)
        for t, q, dq, u, th in run:
            rows.append((t, "theta_hat(t) of the run", look(t, None, th, (q, dq, u))))
            ops.append((th, (q, dq, u)))
            theta_end = th
        if div is not None:
            t_div, (t, q, dq, u, th) = div
            g = look(t, None, th, (q, dq, u))
            rows.append((t, f"theta_hat(t) of the run, which diverged at t = {t_div:.4g} s",
                         g if g > UNSTABLE_GROWTH else math.inf))
            ops.append((th, (q, dq, u)))
            diverged = t_div
    cases = [("theta_hat0", controller.theta_hat0), ("theta", theta)]
    if theta_end is not None and diverged is None and not windowed:
        # a law without the window keeps moving θ̂ by the gradient term (and σ): its θ̂ at
        # the end of the run is looked at under the larger μ to come; a windowed law's θ̂
        # is taken to θ by the composite term (21) from t = T on (Theorem 1)
        cases.append((f"theta_hat({horizon:g} s) of the run", theta_end))
    for t in _reference_points(t_end, h, points):
        for which, th in cases:
            rows.append((t, which, look(t, which, th)))
            ops.append((th, None))
    iw = max(range(len(rows)), key=lambda i: rows[i][2])
    worst = rows[iw]
    stable_h = None
    if suggest and worst[2] > UNSTABLE_GROWTH and diverged is None:
        t = worst[0]
        th, at = ops[iw]
        for div in (2, 4, 5, 10):
            N = round(T / (h / div)) if T else block
            if T and (abs(N * h / div - T) > 1e-9 * T or N % block):
                continue                # h / div does not divide the window T
            g = look(t, None, th, at, c=short(h / div))
            if g <= UNSTABLE_GROWTH:
                stable_h = h / div
                break
    return SampledStability(model=model.name, law=law, h=h, growth=worst[2],
                            points=tuple(rows), worst=worst, stable_h=stable_h,
                            delay=int(getattr(controller, "delay", 0)), diverged=diverged,
                            injection=getattr(controller, "injection", "estimate"))
