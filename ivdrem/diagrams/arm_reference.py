"""The default experiment for a robot arm other than the paper's two-link arm.

docs/experiment.md ("The real-arm experiment") states the rules; in short:

- reference: a finite Fourier series per joint (:func:`ivdrem.blocks.sources.fourier_trajectory`,
  Swevers et al. 1997) of :data:`HARMONICS` harmonics of ω_f = 2π/:data:`PERIOD`, centred in
  each joint's position range, scaled so that the bounds of
  :func:`~ivdrem.blocks.sources.fourier_bounds` keep q_d inside the position limits and q̇_d
  inside the velocity limits with the margin :data:`LIMIT_MARGIN`; Σ_l a_il = 0 so that
  q̇_d(0) = 0.  Among :data:`CANDIDATES` seeded random coefficient sets the one with the
  smallest condition number of the regressor Φ(q_d, q̇_d, q̇_d, q̈_d) stacked along one period
  is kept (the excitation criterion of identification practice): full column rank means
  every base parameter is excited.
- q(0) = q_d(0), q̇(0) = 0 = q̇_d(0): the arm starts on its reference.
- disturbance: the paper's form τ_d,i = A_i sin(ω_i t) with A_i = :data:`DISTURBANCE_FRACTION`
  of the largest torque |τ_i| the reference needs (inverse dynamics, true θ), at most
  :data:`EFFORT_FRACTION` of the joint's effort limit; the ω_i are the paper's 0.5π and
  0.05π rad/s, then further multiples of π/20 rad/s, none a harmonic of ω_f (KA3: the
  instrument must not share a frequency with the disturbance).
- gains: K_i = 2 max(1, M_ii(q(0))) (N m s/rad): the paper's K = 2 as the floor, and a joint
  bandwidth K_i / M_ii of at least 2 1/s on heavy joints.
- window: T of (15a) (IV-DREM's, and composite learning's (35) alike) is the shortest
  common period of the reference and the disturbance of at least the paper's 20 s
  (:func:`design_window`; 40 s for the designed pair): over a whole common period every
  product of an instrument harmonic with a disturbance sinusoid integrates to zero, so the
  window's share of the disturbance, W of (16), leaves the averaged regression like 1/F
  (Proposition 2 with the window's term gone) instead of like Ḟ/F.

Joints without limits (the planar arms) use the range ±:data:`FREE_HALF_RANGE` rad around 0
and the velocity limit :data:`FREE_VELOCITY` rad/s.
"""
from __future__ import annotations

import math

import numpy as np

from ..blocks.sources import fourier_bounds, fourier_series

__all__ = ["joint_names", "joint_limits", "design_trajectory", "initial_state",
           "design_disturbance", "design_gains", "design_window", "trajectory_series", "check_limits",
           "LimitError", "excitation"]

#: Period 2π/ω_f of the reference (s); four periods fill the window T = 40 s
#: (:func:`design_window`).
PERIOD = 10.0
#: Harmonics per joint.
HARMONICS = 5
#: Fraction of each joint's range and velocity limit kept free (both sides).
LIMIT_MARGIN = 0.1
#: Random coefficient sets compared by the excitation criterion; the seed of the first.
CANDIDATES = 4
SEED = 0
#: Samples per period of the stacked regressor (excitation criterion, disturbance scale).
SAMPLES = 100
#: Disturbance amplitude as a fraction of the largest torque the reference needs
#: (the paper: 7.5 and 1.5 N m against 13-18 and 4 N m of gravity torque: about 0.4).
DISTURBANCE_FRACTION = 0.4
#: ... and at most this fraction of the joint's effort limit.
EFFORT_FRACTION = 0.2
#: Position half-range (rad) and velocity limit (rad/s) of a joint the model gives no limit.
FREE_HALF_RANGE = math.pi / 2
FREE_VELOCITY = 2.5
#: The window T of (15a) the design starts from (the paper's) and the longest it gives: a
#: common period above it is not looked for (the delay history and the calibration over
#: [0, 2T] grow with T).
WINDOW_MIN = 20.0
WINDOW_MAX = 60.0
#: Disturbance frequencies, in units of π/20 rad/s, in order of preference (the paper's
#: 0.5π and 0.05π first).
_DIST_STEPS = (10, 1, 5, 3, 7, 9, 2, 6, 11, 13, 14, 15, 17, 18, 19, 21, 22, 23, 25, 26)


class LimitError(ValueError):
    """A reference trajectory leaves a joint's position or velocity limits."""


def joint_names(model) -> list[str]:
    """Names of the model's joints (the URDF's, for an arm), else ``"joint 1"``, ...."""
    names = getattr(model, "joint_names", None)
    if names is not None and len(names) == model.n:
        return [str(s) for s in names]
    return [f"joint {i + 1}" for i in range(model.n)]


def joint_limits(model):
    """(lower, upper, velocity, effort) limits per joint, each (n,), ±inf / inf where the
    model has none (models without limit attributes have none)."""
    n = model.n
    pos = getattr(model, "position_limits", None)
    pos = np.tile([-np.inf, np.inf], (n, 1)) if pos is None else np.asarray(pos, float).reshape(n, 2)
    vel = getattr(model, "velocity_limits", None)
    vel = np.full(n, np.inf) if vel is None else np.asarray(vel, float).reshape(n)
    eff = getattr(model, "effort_limits", None)
    eff = np.full(n, np.inf) if eff is None else np.asarray(eff, float).reshape(n)
    vel = np.where(vel > 0, vel, np.inf)     # a URDF's 0 means "not given"
    eff = np.where(eff > 0, eff, np.inf)
    return pos[:, 0].copy(), pos[:, 1].copy(), vel, eff


def _design_ranges(model):
    lo, hi, vel, _ = joint_limits(model)
    r = FREE_HALF_RANGE      # a missing side: 2r from the other one, or ±r around 0
    lo, hi = (np.where(np.isfinite(lo), lo, np.where(np.isfinite(hi), hi - 2 * r, -r)),
              np.where(np.isfinite(hi), hi, np.where(np.isfinite(lo), lo + 2 * r, r)))
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * (1 - LIMIT_MARGIN)
    vcap = np.where(np.isfinite(vel), vel, FREE_VELOCITY) * (1 - LIMIT_MARGIN)
    return centre, half, vcap


def _stacked_regressor(model, q, dq, ddq):
    return np.vstack([model.regressor(q[k], dq[k], dq[k], ddq[k]) for k in range(q.shape[0])])


def excitation(model, trajectory, samples=SAMPLES):
    """(rank, condition number) of Φ(q_d, q̇_d, q̇_d, q̈_d) stacked at `samples` times over one
    period of a Fourier `trajectory` (a dict with omega_f, a, b, offset); rank with the
    relative tolerance 1e-10 of the largest singular value."""
    t = np.linspace(0.0, 2 * np.pi / float(trajectory["omega_f"]), samples, endpoint=False)
    q, dq, ddq = fourier_series(t, trajectory["omega_f"], trajectory["a"], trajectory["b"],
                                trajectory["offset"])
    s = np.linalg.svd(_stacked_regressor(model, q, dq, ddq), compute_uv=False)
    rank = int(np.sum(s > 1e-10 * s[0]))
    return rank, float(s[0] / s[-1]) if s[-1] > 0 else math.inf


#: Designed references by model key (the design evaluates the regressor 400 times).
_DESIGNS: dict = {}


def _design(model):
    n = model.n
    centre, half, vcap = _design_ranges(model)
    omega_f = 2 * math.pi / PERIOD
    best = None
    for c in range(CANDIDATES):
        rng = np.random.default_rng(SEED + c)
        a = rng.standard_normal((n, HARMONICS))
        b = rng.standard_normal((n, HARMONICS))
        a -= a.mean(axis=1, keepdims=True)           # Σ_l a_il = 0: q̇_d(0) = 0
        pos, vel = fourier_bounds(omega_f, a, b)
        scale = np.minimum(half / pos, vcap / vel)[:, None]
        traj = {"omega_f": omega_f, "a": a * scale, "b": b * scale, "offset": centre.copy()}
        rank, cond = excitation(model, traj)
        if best is None or (rank, -cond) > (best[0], -best[1]):
            best = (rank, cond, traj)
    return best


def design_trajectory(model) -> dict:
    """The default Fourier reference of `model` (module docstring): {"kind": "fourier",
    "omega_f", "a" (n×H lists), "b", "offset"} plus "rank" and "cond" of the excitation."""
    key = model.key() if callable(getattr(model, "key", None)) else None
    best = _DESIGNS.get(key) if key is not None else None
    if best is None:
        best = _design(model)
        if key is not None:
            _DESIGNS[key] = best
    rank, cond, traj = best
    return {"kind": "fourier", "omega_f": float(traj["omega_f"]),
            "a": traj["a"].tolist(), "b": traj["b"].tolist(),
            "offset": traj["offset"].tolist(), "rank": rank, "cond": cond}


def trajectory_series(trajectory, t):
    """(q_d, q̇_d, q̈_d) at times `t` ((len(t), n) each) of a configured trajectory: a
    [trajectory] table of either kind ("sinusoid": amplitude, omega, phase, offset;
    "fourier": omega_f, a, b, offset)."""
    t = np.atleast_1d(np.asarray(t, float))
    if trajectory.get("kind", "sinusoid") == "fourier":
        return fourier_series(t, trajectory["omega_f"], trajectory["a"], trajectory["b"],
                              trajectory["offset"])
    A, w, ph, c = (np.asarray(trajectory[k], float) for k in ("amplitude", "omega", "phase", "offset"))
    arg = np.outer(t, w) + ph
    s, co = np.sin(arg), np.cos(arg)
    return A * s + c, A * w * co, -A * w * w * s


def initial_state(trajectory) -> tuple[list, list]:
    """q(0) = q_d(0) and q̇(0) = q̇_d(0) of a configured trajectory."""
    q, dq, _ = trajectory_series(trajectory, [0.0])
    dq = np.where(np.abs(dq[0]) < 1e-12, 0.0, dq[0])    # the designed reference's Σ a = 0
    return q[0].tolist(), dq.tolist()


def _periods(trajectory):
    if trajectory.get("kind", "sinusoid") == "fourier":
        w = float(trajectory["omega_f"])
        return 2 * np.pi / w, w * len(trajectory["a"][0])
    w = np.abs(np.asarray(trajectory["omega"], float))
    w_max = float(w.max()) if w.size else 0.0
    if np.all(w > 0):
        # common period only if the frequencies are commensurate; the longest joint
        # period covers each joint's own extremes
        return 2 * np.pi / float(w.min()), w_max
    return math.inf, w_max


def check_limits(model, trajectory, t_end, samples_per_cycle=200):
    """Raise :class:`LimitError` naming the joint and the first time at which the
    configured `trajectory` leaves the model's position or velocity limits over
    [0, t_end] (sampled at 1/`samples_per_cycle` of the fastest harmonic's period, over
    one period of the trajectory when it repeats within t_end).  Models without limits
    pass."""
    lo, hi, vel, _ = joint_limits(model)
    if not (np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)) or np.any(np.isfinite(vel))):
        return
    period, w_max = _periods(trajectory)
    horizon = float(min(t_end, period))
    dt = (2 * np.pi / w_max) / samples_per_cycle if w_max > 0 else horizon
    n_pts = int(min(max(2, math.ceil(horizon / dt) + 1), 2_000_000))
    names = joint_names(model)
    for start in range(0, n_pts, 100_000):       # chunks: bounded memory on long horizons
        t = np.linspace(0.0, horizon, n_pts)[start:start + 100_000]
        q, dq, _ = trajectory_series(trajectory, t)
        bad = (q < lo) | (q > hi) | (np.abs(dq) > vel)
        if bad.any():
            k, i = divmod(int(np.flatnonzero(bad.ravel())[0]), model.n)
            if q[k, i] < lo[i] or q[k, i] > hi[i]:
                what = (f"its position limits [{lo[i]:.6g}, {hi[i]:.6g}] rad "
                        f"(q_d = {q[k, i]:.6g} rad)")
            else:
                what = f"its velocity limit {vel[i]:.6g} rad/s (dq_d = {dq[k, i]:.6g} rad/s)"
            raise LimitError(f"the reference trajectory leaves {what} at joint {i + 1} "
                             f"('{names[i]}') at t = {t[k]:.6g} s")


def _harmonic(w, trajectory, tol=0.02):
    if trajectory.get("kind", "sinusoid") == "fourier":
        wf = float(trajectory["omega_f"])
        return any(abs(w - l * wf) < tol for l in range(1, len(trajectory["a"][0]) + 1))
    return any(abs(w - abs(x)) < tol for x in trajectory["omega"])


def design_disturbance(model, trajectory, theta=None) -> dict:
    """The paper's form τ_d = A sin(ω t) scaled to the arm (module docstring)."""
    _, _, _, eff = joint_limits(model)
    period, _ = _periods(trajectory)
    span = period if math.isfinite(period) else PERIOD
    t = np.linspace(0.0, span, SAMPLES, endpoint=False)
    q, dq, ddq = trajectory_series(trajectory, t)
    th = np.asarray(model.theta_values if theta is None else theta, float)
    tau = np.array([model.regressor(q[k], dq[k], dq[k], ddq[k]) @ th for k in range(t.size)])
    amp = DISTURBANCE_FRACTION * np.max(np.abs(tau), axis=0)
    amp = np.minimum(amp, np.where(np.isfinite(eff), EFFORT_FRACTION * eff, np.inf))
    omegas = []
    steps = list(_DIST_STEPS) + list(range(27, 27 + 4 * model.n))
    for s in steps:
        w = s * math.pi / 20
        if not _harmonic(w, trajectory) and len(omegas) < model.n:
            omegas.append(w)
    n = model.n
    return {"amplitude": amp.tolist(), "omega": omegas, "phase": [0.0] * n,
            "offset": [0.0] * n}


def design_window(trajectory, disturbance, *, t_min=WINDOW_MIN, t_max=WINDOW_MAX):
    """The window T (s) of the extension (15a) for a Fourier `trajectory` and a sinusoidal
    `disturbance` ([trajectory] and [disturbance] tables): the shortest common period of the
    reference's fundamental ω_f and every disturbance frequency that is at least `t_min`,
    or None where there is none up to `t_max` (incommensurate frequencies, or a sinusoid
    reference).  ζ of (14) is periodic with the reference and w of (13) a sum of the
    disturbance's sinusoids, so over such a window each product ζ_i w_j integrates to zero
    (none of the disturbance's frequencies is a harmonic of ω_f: :func:`design_disturbance`)
    and the window contributes nothing to W of (16) once it is full."""
    if trajectory.get("kind", "sinusoid") != "fourier":
        return None
    amp = np.abs(np.asarray(disturbance["amplitude"], float))
    omegas = [float(trajectory["omega_f"])] + [
        abs(float(w)) for w, a in zip(disturbance["omega"], amp) if a > 0 and w != 0]
    slowest = min(omegas)
    if not slowest > 0:
        return None
    period = 2 * math.pi / slowest
    for k in range(1, int(t_max / period + 1e-9) + 1):
        T = k * period
        cycles = [w * T / (2 * math.pi) for w in omegas]
        if all(abs(c - round(c)) <= 1e-9 * max(1.0, c) for c in cycles):
            # a common period: its multiples are too; the first one at least t_min
            T *= max(1, math.ceil(t_min / T - 1e-9))
            return float(T) if T <= t_max + 1e-9 else None
    return None


def design_gains(model, q0, theta=None) -> list:
    """K_i = 2 max(1, M_ii(q(0))) (module docstring)."""
    th = np.asarray(model.theta_values if theta is None else theta, float)
    M = np.empty((model.n, model.n))
    model.functions.M(np.asarray(q0, float), th, M)
    return [2.0 * max(1.0, float(m)) for m in np.diag(M)]
