"""gamma = "auto": the gain γ of the composite term (21) from the loop's own Δ.

The composite term (21) contracts the parameter error at the rate γΔ²(t)Γ: with
ϑ_c = γΔ(𝒴 − Δθ̂) = γΔ²θ̃ + γΔ𝒲 (17), the adaptation law (11) gives
dθ̃/dt = −ΓΠᵀr − γΔ²Γθ̃ − γΔΓ𝒲.  The size of Δ = det(Ψ/(1 + ‖Ψ‖)) depends on the robot,
its trajectory and nθ (a determinant of an nθ×nθ matrix of small entries): about 8e-5
for the paper's arm and 2.5e-9 for a 3-link arm, so one fixed γ cannot suit every robot.

Rule (documented in docs/diagnostics.md): run the loop over a calibration horizon
``t_cal`` (default 2T: one window to fill the sliding window (15a), one to measure) with
the composite term off (γ tiny), take the mean of Δ² over [T, t_cal] and choose

    γ = κ / (λ_max(Γ) · mean Δ²),       κ = 0.5 s⁻¹ (``rate``),

so that the composite term's contraction rate γΔ²λ_max(Γ) is κ at the calibration level
of Δ: a time constant of 2 s, slow against the loop (λ_min(K) + δ_μ μ) and the filters
(l = 50), fast against the horizon.  γ is then one constant for the whole run, so the law
is exactly (21) and Theorem 2 applies unchanged.  For the paper's arm the rule gives γ of
the order of the paper's 1e10.
"""
from __future__ import annotations

import numpy as np

__all__ = ["calibrate_gamma", "gamma_from_delta", "DEFAULT_RATE"]

#: target contraction rate κ = γ Δ² λ_max(Γ) of the composite term, 1/s
DEFAULT_RATE = 0.5
#: γ of the calibration run: the composite term is off
_GAMMA_OFF = 1e-300


def _lambda_max(Gamma, ntheta):
    G = np.asarray(Gamma, dtype=float)
    if G.ndim == 0:
        return float(G)
    if G.ndim == 1:
        return float(np.max(G))
    return float(np.max(np.linalg.eigvalsh(0.5 * (G + G.T))))


def gamma_from_delta(t, delta, T, Gamma, *, rate=DEFAULT_RATE, ntheta=None):
    """γ = rate / (λ_max(Γ) · mean Δ² over [T, t_end]) of a recorded Δ(t); with the numbers.

    Raises ValueError when Δ is identically zero there (no excitation to scale by).
    """
    t = np.asarray(t, dtype=float)
    d = np.asarray(delta, dtype=float)
    t_from = T if t[-1] > T else 0.5 * t[-1]
    sel = t >= t_from
    if np.count_nonzero(sel) < 2:
        raise ValueError("gamma='auto': calibration run too short to measure Δ")
    d2 = d[sel] ** 2
    mean_d2 = float(np.trapezoid(d2, t[sel]) / (t[sel][-1] - t[sel][0]))
    lam = _lambda_max(Gamma, ntheta)
    if not np.isfinite(mean_d2) or mean_d2 <= 0.0:
        raise ValueError(
            "gamma='auto': Δ is zero over the calibration run (the regressor of (17) is "
            "not excited by this trajectory); choose another trajectory or a numeric gamma")
    gamma = rate / (lam * mean_d2)
    return {"gamma": float(gamma), "rule": f"gamma = {rate:g} / (lambda_max(Gamma) * mean Delta^2)",
            "rate": float(rate), "mean_Delta2": mean_d2, "lambda_max_Gamma": lam,
            "window": [float(t[sel][0]), float(t[sel][-1])]}


def calibrate_gamma(law, model, args, *, t_cal=None, rate=DEFAULT_RATE, passes=1,
                    engine="compiled", method="dp45", rtol=None, atol=None, h=1e-3,
                    h_max=0.01, dt_out=0.01):
    """Run the closed loop of ``law`` over ``t_cal`` (default 2T) and return the γ of the
    rule above, with the numbers it came from.

    The calibration runs with the composite term off.  Δ depends on the motion (φ is
    built from the measured q), and the motion on θ̂, so the Δ of the real run can differ:
    on the 3-link arm of examples/planar3.toml RMS Δ over [T, 2T] was 3.3e-10 with the
    term off and 4.9e-8 with it on, which makes that run stiff early on.  ``passes=2``
    reruns the calibration at pass 1's γ and rescales by the Δ it measures; measured on the
    same arm it removes the stiffness but the smaller γ then learns too little
    (‖θ̃(120 s)‖ = 2.91 against 0.295 with one pass), so one pass is the default.
    """
    from ..sim import simulate
    from .closed_loop import closed_loop

    T = float(args.get("T") or 20.0)
    t_cal = 2.0 * T if t_cal is None else float(t_cal)
    if not t_cal > 0:
        raise ValueError(f"gamma='auto': calibration horizon must be > 0, got {t_cal}")
    if passes not in (1, 2):
        raise ValueError(f"gamma='auto': passes must be 1 or 2, got {passes!r}")
    diagram = closed_loop(law, model, gamma=1.0, **args)
    gamma, history = _GAMMA_OFF, []
    for k in range(passes):
        resp = simulate(diagram, t_cal, engine=engine, method=method, rtol=rtol, atol=atol,
                        h=h, h_max=h_max, dt_out=dt_out, params={"gamma": gamma},
                        progress=False, return_states=False)
        labels = list(resp.output_labels)
        y = np.asarray(resp.outputs, dtype=float).reshape(len(labels), -1)
        delta = y[labels.index("Delta")]
        out = gamma_from_delta(resp.time, delta, T, args.get("Gamma", 0.01), rate=rate)
        history.append({"gamma_run": float(gamma), "mean_Delta2": out["mean_Delta2"],
                        "gamma": out["gamma"]})
        gamma = out["gamma"]
    out["t_cal"] = t_cal
    out["passes"] = history
    return out
