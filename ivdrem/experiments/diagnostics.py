"""The assumptions of Theorem 2, checked numerically on a finished run.

ivdrem knows every signal of the loop, the true θ and the true disturbance, so it can
evaluate the conditions the paper judges by eye.  :func:`diagnose` takes one law's run
(its response), the configuration and the model, and returns one *check* per condition,
each with the numbers it rests on, a verdict and the figure that shows it:

=========  ===================================================================  ========
id         condition                                                              figure
=========  ===================================================================  ========
KA1        Δ ∉ L2 (Remark 4, C2 of Theorem 2): ∫₀ᵗ Δ² ds keeps growing            (a)
PE         excitation (18): β = min |det ∫_{t−T}^t ζφᵀ| and whether Δ vanishes     (a)
KA2        λ = μ⁻¹τ̇_d ∈ L2 (Property 4.1): ∫₀ᵗ ‖τ̇_d‖²/μ² ds levels off           (b)
KA3        condition (19): ∫₀ᵗ ζ_kj w_j ds bounded; shared frequencies            (c)
           of ζ and τ_d
P2         Proposition 2, eq. (20): |𝒲_i| F/Ḟ bounded                             (d)
P4.2       Property 4.2 for the chosen μ(t) and δ_μ: ρ, δ_ρ, μ_LB                  –
RATE       ‖θ̃(t)‖ ≈ C t^(−a) over the last half                                  (e)
V          Lyapunov function (23) against the bound of the proof of Theorem 2     (f)
ACTIVE     the composite term γΔ²λ_max(Γ) is large enough to act on this          (a)
           horizon
LEARN      the run learns: ‖θ̃‖ does not grow (and is halved, laws with Δ);       (e)
           the bias floor ‖𝒲‖/|Δ| of (17) stays below half of ‖θ̃(0)‖;
           otherwise a warning naming the cause and a remedy
=========  ===================================================================  ========

Verdicts are "holds", "fails", "not decided" (the horizon is too short to tell, e.g. a
decay exponent near the L2 border) or "not applicable" (the law has no such signal).
What each verdict means and how it is computed: docs/diagnostics.md.  The thresholds are
the module constants below.

The building blocks (:func:`decay_exponent`, :func:`check_ka1`, ...) take plain arrays,
so each is tested against signals with a known answer (tests/test_diagnostics.py).
"""
from __future__ import annotations

import math
from typing import Mapping

import numpy as np
from scipy.integrate import cumulative_trapezoid

from .metrics import gamma_choice_and_mixing, law_horizon_note, short_horizon_note

__all__ = ["diagnose", "measured_label", "diagnose_run", "tau_d_decomposition", "observer_error_true_theta", "decay_exponent", "power_fit", "check_ka1", "check_pe",
           "check_ka2", "check_ka3", "check_prop2", "check_property42", "check_rate",
           "check_lyapunov", "check_active", "check_learning", "learning_warnings", "filtered_disturbance", "excitation_beta",
           "HOLDS", "FAILS", "UNDECIDED", "NA", "to_json", "format_diagnostics",
           "short_horizon_note", "HORIZON_CHECKS"]

#: The verdicts of a check: it holds, it fails, the horizon is too short to decide, or the
#: law has no such signal.
HOLDS, FAILS, UNDECIDED, NA = "holds", "fails", "not decided", "not applicable"

#: decay exponents k of a windowed mean ~ t^(-k): k <= L2_HOLD -> not square integrable
#: (the integral grows at least like log t); k >= L2_FAIL -> integrable; between: the
#: horizon cannot tell.
L2_HOLD, L2_FAIL = 1.05, 1.30
#: |Δ| (or β) bounded away from zero: decay exponent of |Δ| below PE_HOLD; vanishing above PE_FAIL
PE_HOLD, PE_FAIL = 0.10, 0.25
#: condition (19): normalised mean |mean(ζ_kj w_j)| / rms(ζ_kj w_j) over the last half
KA3_HOLD, KA3_FAIL = 0.05, 0.25
#: Proposition 2: growth of max |𝒲_i| F/Ḟ from the second to the last quarter
P2_GROWTH = 1.5
#: the composite term acts on the horizon when γ λ_max(Γ) ∫Δ² ds >= ACTIVE_EFOLDS
ACTIVE_EFOLDS = 1.0
#: number of windows the last half is cut into for the windowed means
N_BINS = 8
#: LEARN: ‖θ̃‖ grows when its last window's mean exceeds the first window's of the last
#: half by this factor (or ‖θ̃(t_end)‖ ≥ ‖θ̃(0)‖)
LEARN_GROWTH = 1.5
#: LEARN: decades of |Δ| over [T, t_end] past which a fixed γ cannot hold the rate γΔ²
DELTA_SPAN_DECADES = 4.0
#: LEARN: a bias floor ‖𝒲‖/|Δ| at this share of ‖θ̃(0)‖ or more is comparable to the
#: initial error: θ̂ can at best settle that far from θ, which is not learning
LEARN_FLOOR_SHARE = 0.5
#: LEARN (laws with Δ): ‖θ̃(t_end)‖ must be below this share of ‖θ̃(0)‖ (θ̃ at least halved)
LEARN_REDUCTION = 0.5


# --------------------------------------------------------------------------- helpers
def _cum(t, y):
    return cumulative_trapezoid(np.asarray(y, dtype=float), np.asarray(t, dtype=float), initial=0.0)


def _bins(t, t_from, nb=N_BINS):
    t = np.asarray(t, dtype=float)
    edges = np.linspace(t_from, t[-1], nb + 1)
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (t >= a) & (t <= b)
        if np.count_nonzero(sel) >= 2:
            out.append(sel)
    return out


def power_fit(t, y):
    """Least-squares fit y ≈ C t^(-a) in log-log: (a, C, R²); y > 0, t > 0."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    ok = (t > 0) & (y > 0) & np.isfinite(y)
    if np.count_nonzero(ok) < 2:
        return float("nan"), float("nan"), float("nan")
    lx, ly = np.log(t[ok]), np.log(y[ok])
    slope, icpt = np.polyfit(lx, ly, 1)
    res = ly - (slope * lx + icpt)
    ss = np.sum((ly - ly.mean()) ** 2)
    r2 = 1.0 - np.sum(res ** 2) / ss if ss > 0 else 1.0
    return float(-slope), float(math.exp(icpt)), float(r2)


def decay_exponent(t, y, t_from=None, *, stat="mean"):
    """k of y ~ t^(-k), fitted to windowed means (or maxima) of y >= 0 over [t_from, t_end].

    The windows (N_BINS over the last half by default) average out oscillations, so a
    sinusoid gives k ≈ 0, 1/(t+1) gives k ≈ 1.  Returns nan if y vanishes in a window.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    t_from = t[0] + 0.5 * (t[-1] - t[0]) if t_from is None else t_from
    centers, vals = [], []
    for sel in _bins(t, t_from):
        v = np.mean(y[sel]) if stat == "mean" else np.max(y[sel])
        centers.append(np.mean(t[sel]))
        vals.append(v)
    vals = np.asarray(vals)
    if vals.size < 2 or np.any(vals <= 0) or not np.all(np.isfinite(vals)):
        return float("nan")
    return power_fit(np.asarray(centers), vals)[0]


def _check(cid, name, condition, verdict, measured, criterion, figure=None, note=""):
    return {"id": cid, "name": name, "condition": condition, "verdict": verdict,
            "measured": measured, "criterion": criterion, "figure": figure, "note": note}


def _l2_verdict(k, *, want_l2):
    """Verdict from a decay exponent k: 'in L2' needs k >= L2_FAIL, 'not in L2' k <= L2_HOLD."""
    if not np.isfinite(k):
        return UNDECIDED
    if k <= L2_HOLD:
        return FAILS if want_l2 else HOLDS
    if k >= L2_FAIL:
        return HOLDS if want_l2 else FAILS
    return UNDECIDED


def _half(t):
    return t[0] + 0.5 * (t[-1] - t[0])


# --------------------------------------------------------------------------- KA1 and (18)
def check_ka1(t, delta, figure=None):
    """KA1, Δ ∉ L2: ∫Δ² keeps growing; decided by the decay exponent of windowed Δ²."""
    t = np.asarray(t, dtype=float)
    d2 = np.asarray(delta, dtype=float) ** 2
    S = _cum(t, d2)
    tm = _half(t)
    im = int(np.searchsorted(t, tm))
    growth = float(S[-1] - S[im])
    k = decay_exponent(t, d2, tm)
    if S[-1] == 0.0:
        verdict, k = FAILS, float("inf")
    else:
        verdict = _l2_verdict(k, want_l2=False)
    return _check("KA1", "Δ ∉ L2", "Remark 4 KA1 (condition C2 of Theorem 2)", verdict,
                  {"int_Delta2_end": float(S[-1]), "int_Delta2_growth_last_half": growth,
                   "slope_last_half": growth / max(t[-1] - tm, 1e-300),
                   "decay_exponent_Delta2": k},
                  f"windowed mean of Δ² ~ t^(-k) over the last half: k ≤ {L2_HOLD} holds "
                  f"(∫Δ² grows at least like log t), k ≥ {L2_FAIL} fails", figure), S


def excitation_beta(t, zeta, phi, n, ntheta, T):
    """|det ∫_{t−T}^t ζ φᵀ ds| of (18) for t >= T (nan before), from recorded ζᵀ, φᵀ
    (n×nθ row-major, one row per sample pair of the response)."""
    t = np.asarray(t, dtype=float)
    Z = np.asarray(zeta, dtype=float).reshape(n, ntheta, -1)
    P = np.asarray(phi, dtype=float).reshape(n, ntheta, -1)
    beta = np.full(t.size, np.nan)
    ok = t >= T + t[0] - 1e-9 * max(t[-1], 1.0)
    if not ok.any():     # a run shorter than the window: no window to integrate (the
        return beta      # nθ² products below cost 0.2 s of a 1 s Panda run for nothing)
    # entry by entry of ζφᵀ (nθ×nθ per sample): one window array of nθ² × samples, not the
    # four a whole-array evaluation holds at once (1.2 GB at nθ = 36 over 300 s)
    win = np.empty((ntheta, ntheta, int(ok.sum())))
    for k in range(ntheta):
        for l in range(ntheta):
            prod = np.einsum("jt,jt->t", Z[:, k, :], P[:, l, :])     # (ζᵀ)ᵀ φᵀ, entry (k, l)
            cum = cumulative_trapezoid(prod, t, initial=0.0)
            win[k, l] = cum[ok] - np.interp(t[ok] - T, t, cum)      # ∫_{t−T}^t, interpolated
    chunk = max(1, (1 << 21) // max(ntheta * ntheta, 1))            # samples per det call
    where = np.flatnonzero(ok)
    for a in range(0, win.shape[2], chunk):
        beta[where[a:a + chunk]] = np.abs(np.linalg.det(
            np.moveaxis(win[:, :, a:a + chunk], 2, 0)))
    return beta


def check_pe(t, delta, beta=None, T=None, figure=None):
    """Excitation (18) / Proposition 1: is |Δ| (and β) bounded away from zero?"""
    t = np.asarray(t, dtype=float)
    a = np.abs(np.asarray(delta, dtype=float))
    tm = _half(t)
    last = t >= tm
    k = decay_exponent(t, a, tm)
    lb = float(np.min(a[last]))
    measured = {"Delta_min_last_half": lb, "decay_exponent_abs_Delta": k}
    if beta is not None:
        b = np.asarray(beta, dtype=float)
        okb = np.isfinite(b)
        measured["beta_min"] = float(np.min(b[okb])) if okb.any() else float("nan")
        measured["beta_min_last_half"] = float(np.min(b[okb & last])) if (okb & last).any() else float("nan")
        kb = decay_exponent(t, np.where(okb, b, 0.0), tm)
        measured["decay_exponent_beta"] = kb
        k = max(k, kb) if np.isfinite(kb) else k
    if lb <= 0.0:
        verdict = FAILS
    elif not np.isfinite(k):
        verdict = UNDECIDED
    elif k <= PE_HOLD:
        verdict = HOLDS
    elif k >= PE_FAIL:
        verdict = FAILS
    else:
        verdict = UNDECIDED
    return _check("PE", "excitation (18)", "Proposition 1 (PE-like, stronger than KA1)", verdict,
                  measured, f"|Δ| (and β) bounded away from 0: decay exponent ≤ {PE_HOLD} holds, "
                  f"≥ {PE_FAIL} fails (vanishing, not PE; KA1 may still hold)", figure)


# --------------------------------------------------------------------------- KA2
def check_ka2(t, tau_d, mu, figure=None, dtau_d=None):
    """KA2 / Property 4.1, λ = μ⁻¹τ̇_d ∈ L2: ∫‖τ̇_d‖²/μ² levels off.

    τ̇_d is ``dtau_d`` if given (analytic), else second-order differences of τ_d.
    """
    t = np.asarray(t, dtype=float)
    tau = np.atleast_2d(np.asarray(tau_d, dtype=float))
    dtau = np.gradient(tau, t, axis=1, edge_order=2) if dtau_d is None else np.atleast_2d(dtau_d)
    g = np.sum(dtau * dtau, axis=0) / np.asarray(mu, dtype=float) ** 2
    L = _cum(t, g)
    tm = _half(t)
    k = decay_exponent(t, g, tm)
    if np.max(g) == 0.0:
        verdict, k = HOLDS, float("inf")
    else:
        verdict = _l2_verdict(k, want_l2=True)
    last = t >= t[-1] - (t[-1] - tm) / N_BINS
    tail = (float(np.mean(g[last]) * t[-1] / (k - 1.0))
            if np.isfinite(k) and k > 1.0 else float("inf"))
    return _check("KA2", "λ = μ⁻¹τ̇_d ∈ L2", "Remark 4 KA2 (Property 4.1)", verdict,
                  {"int_lambda2_end": float(L[-1]), "decay_exponent_integrand": k,
                   "tail_estimate": tail},
                  f"windowed mean of ‖τ̇_d‖²/μ² ~ t^(-k): k ≥ {L2_FAIL} holds (levels off), "
                  f"k ≤ {L2_HOLD} fails", figure), L, g


# --------------------------------------------------------------------------- KA3
def filtered_disturbance(t, tau_d, l):
    """w of (13), ẇ = l(−τ_d − w), w(0) = 0, from samples of τ_d: exact for τ_d linear
    between samples (first-order hold), so second order in the sample step."""
    t = np.asarray(t, dtype=float)
    u = -np.atleast_2d(np.asarray(tau_d, dtype=float))
    w = np.zeros_like(u)
    for k in range(1, t.size):
        h = t[k] - t[k - 1]
        e = math.exp(-l * h)
        b1 = 1.0 - e                                   # weight of u_{k-1} (ZOH part)
        b2 = 1.0 - (1.0 - e) / (l * h)                 # weight of the slope (FOH part)
        w[:, k] = e * w[:, k - 1] + b1 * u[:, k - 1] + b2 * (u[:, k] - u[:, k - 1])
    return w


def _dominant_freqs(t, x, rel=0.1, max_peaks=6):
    """Angular frequencies of the largest spectral peaks of each row of x (Hann window)."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    dt = float(np.median(np.diff(t)))
    nfft = 1 << int(math.ceil(math.log2(max(8 * x.shape[1], 16))))
    win = np.hanning(x.shape[1])
    freqs = 2 * np.pi * np.fft.rfftfreq(nfft, dt)
    out = []
    for row in x:
        if not np.any(row):
            continue
        spec = np.abs(np.fft.rfft((row - row.mean()) * win, nfft))
        spec[0] = 0.0
        top = spec.max()
        if top <= 0:
            continue
        inner = spec[1:-1]
        pk = 1 + np.flatnonzero((inner >= rel * top) & (inner >= spec[:-2])
                                & (inner >= spec[2:]))
        pk = pk[np.argsort(-spec[pk], kind="stable")][:max_peaks]   # ties in index order
        out += [float(freqs[i]) for i in pk]
        if row.mean() != 0 and abs(row.mean()) >= rel * np.sqrt(np.mean(row ** 2)):
            out.append(0.0)
    return sorted(set(round(f, 6) for f in out))


def check_ka3(t, zeta, w, n, ntheta, tau_d=None, figure=None, instrument="ζ"):
    """KA3, condition (19): the running integrals ∫ζ_kj w_j ds stay bounded.

    A product of signals without a common frequency has mean → 0, so its integral stays
    bounded; one with a common frequency has a non-zero mean and its integral grows
    linearly.  Decided on the normalised mean |mean p| / rms p of each product over the
    last half.  Also: the closest pair of dominant frequencies of ζ and τ_d.
    """
    t = np.asarray(t, dtype=float)
    Z = np.asarray(zeta, dtype=float).reshape(n, ntheta, -1)   # ζᵀ: [j, k] = ζ_kj
    W = np.atleast_2d(np.asarray(w, dtype=float))
    prods = Z * W[:, None, :]                                     # ζ_kj w_j, [j, k, t]
    tm = _half(t)
    last = t >= tm
    flat = prods.reshape(n * ntheta, -1)
    # Hann-weighted mean over the last half: the leakage of a product without a common
    # frequency then falls like (L Δω)^-3 instead of (L Δω)^-1
    hann = np.hanning(np.count_nonzero(last))
    rms = np.sqrt(np.sum(hann * flat[:, last] ** 2, axis=1) / np.sum(hann))
    mean = np.sum(hann * flat[:, last], axis=1) / np.sum(hann)
    live = rms > 1e-9 * max(float(np.max(rms)), 1e-300)
    ratio = np.where(live, np.abs(mean) / np.where(live, rms, 1.0), 0.0)
    worst = int(np.argmax(ratio)) if live.any() else 0
    D = float(ratio[worst]) if live.any() else 0.0
    integrals = cumulative_trapezoid(flat, t, axis=1, initial=0.0)
    measured = {"normalised_mean_max": D,
                "worst_pair": f"{instrument}_{worst % ntheta + 1},{worst // ntheta + 1} · "
                              f"w_{worst // ntheta + 1}",
                "max_abs_integral": float(np.max(np.abs(integrals))) if integrals.size else 0.0}
    if tau_d is not None:
        fz = _dominant_freqs(t[last], Z.reshape(n * ntheta, -1)[:, last])
        fw = _dominant_freqs(t[last], np.atleast_2d(tau_d)[:, last])
        res = 2 * np.pi / max(t[-1] - tm, 1e-300)
        gaps = [(abs(a - b), a, b) for a in fz for b in fw]
        if gaps:
            gap, a, b = min(gaps)
            measured.update(closest_frequencies=[a, b], frequency_gap=float(gap),
                            frequency_resolution=float(res),
                            shared_frequency=bool(gap < 2 * res))
    if not live.any():
        verdict = HOLDS
    elif D <= KA3_HOLD:
        verdict = HOLDS
    elif D >= KA3_FAIL:
        verdict = FAILS
    else:
        verdict = UNDECIDED
    return _check("KA3", "condition (19)", "Remark 4 KA3, Proposition 2 (19)", verdict, measured,
                  f"max over k, j of |mean(ζ_kj w_j)| / rms(ζ_kj w_j) over the last half "
                  f"(Hann-weighted): "
                  f"≤ {KA3_HOLD} holds (integrals bounded), ≥ {KA3_FAIL} fails (they grow "
                  f"linearly)", figure), integrals


# --------------------------------------------------------------------------- Proposition 2
def check_prop2(t, calW, p, F0, T, figure=None):
    """Proposition 2 (20): max_i |𝒲_i(t)| F(t)/Ḟ(t) stays bounded (t >= T)."""
    t = np.asarray(t, dtype=float)
    W = np.atleast_2d(np.asarray(calW, dtype=float))
    F = t ** p + F0
    dF = p * t ** (p - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        R = np.where((t >= T) & (dF > 0), np.max(np.abs(W), axis=0) * F / dF, np.nan)
    t0, d = t[0], t[-1] - t[0]
    q2 = (t >= t0 + 0.25 * d) & (t <= t0 + 0.5 * d) & np.isfinite(R)
    q4 = (t >= t0 + 0.75 * d) & np.isfinite(R)
    if not q2.any() or not q4.any():
        return _check("P2", "|𝒲_i| F/Ḟ bounded", "Proposition 2, eq. (20)", UNDECIDED, {},
                      "run shorter than the window", figure), R
    m2, m4 = float(np.max(R[q2])), float(np.max(R[q4]))
    growth = m4 / m2 if m2 > 0 else (0.0 if m4 == 0 else float("inf"))
    k = decay_exponent(t, np.where(np.isfinite(R), R, 0.0), _half(t), stat="max")
    if growth <= P2_GROWTH:
        verdict = HOLDS
    elif np.isfinite(k) and k < -0.3:
        verdict = FAILS
    else:
        verdict = UNDECIDED
    return _check("P2", "|𝒲_i| F/Ḟ bounded", "Proposition 2, eq. (20)", verdict,
                  {"max_second_quarter": m2, "max_last_quarter": m4, "growth": growth,
                   "growth_exponent": -k if np.isfinite(k) else k},
                  f"max of |𝒲_i| F/Ḟ over the last quarter ≤ {P2_GROWTH} × over the second "
                  "quarter holds; growing like a power of t fails", figure), R


# --------------------------------------------------------------------------- Property 4.2
def check_property42(t, mu, delta_mu, dmu=None):
    """Property 4.2: ρ, δ_ρ > 0 with (ρ − 1/δ_μ)μ + ρμ̇/μ − ρ/δ_ρ ≥ μ_LB > 0, μ_LB ∉ L1.

    Searches ρ over (1e-2 … 1e3)/δ_μ for the largest min_t of a(t) = (ρ − 1/δ_μ)μ + ρμ̇/μ;
    if it is positive, δ_ρ = 2ρ / min a gives μ_LB = a − min a / 2 ≥ min a / 2 > 0.
    """
    t = np.asarray(t, dtype=float)
    mu = np.asarray(mu, dtype=float)
    if np.any(mu <= 0):
        return _check("P4.2", "Property 4.2", "Property 4.2 (μ > 0, δ_μ)", FAILS,
                      {"mu_min": float(np.min(mu))}, "μ(t) > 0 is required", None), None
    dmu = np.gradient(mu, t, edge_order=2) if dmu is None else np.asarray(dmu, dtype=float)

    def left(rho):
        a = (rho - 1.0 / delta_mu) * mu + rho * dmu / mu
        return float(np.min(a)), a

    # ρ = 2/δ_μ (Remark 1: any ρ > 1/δ_μ works for a constant or linear μ) keeps the
    # observer term of V (23) and the bound small; otherwise the best ρ of a grid
    rho = 2.0 / delta_mu
    amin, a = left(rho)
    if amin <= 0:
        for r in np.logspace(-2, 3, 400) / delta_mu:
            m, ar = left(r)
            if m > amin:
                rho, amin, a = float(r), m, ar
    if amin <= 0:
        return _check("P4.2", "Property 4.2", "Property 4.2 (for the chosen μ(t), δ_μ)", FAILS,
                      {"best_rho": rho, "min_left_side": amin},
                      "no ρ in (0.01, 1000)/δ_μ makes (ρ − 1/δ_μ)μ + ρμ̇/μ positive over the run",
                      None), None
    delta_rho = 2.0 * rho / amin
    mu_lb = a - amin / 2.0
    k = decay_exponent(t, mu_lb, _half(t))
    verdict = HOLDS if (not np.isfinite(k) or k < 1.0) else UNDECIDED
    return _check("P4.2", "Property 4.2", "Property 4.2 (for the chosen μ(t), δ_μ)", verdict,
                  {"rho": rho, "delta_rho": delta_rho, "mu_LB_min": float(np.min(mu_lb)),
                   "int_mu_LB_end": float(_cum(t, mu_lb)[-1])},
                  "ρ, δ_ρ found with μ_LB ≥ min/2 > 0 on the whole run (so μ_LB ∉ L1 there)",
                  None), {"rho": rho, "delta_rho": delta_rho, "mu_LB": mu_lb}


# --------------------------------------------------------------------------- rate
def check_rate(t, theta_err_norm, figure=None, calW_over_Delta=None):
    """‖θ̃(t)‖ ≈ C t^(−a), fitted to windowed means over the last half (they average out
    the oscillation 𝒲 imprints on θ̃), and a floor c₀ of c₀ + C t^(−b)."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(theta_err_norm, dtype=float)
    tm = _half(t)
    centers, means = [], []
    for sel in _bins(t, tm):
        centers.append(float(np.mean(t[sel])))
        means.append(float(np.mean(y[sel])))
    centers, means = np.asarray(centers), np.asarray(means)
    if means.size == 0:
        # a run too short to hold a sample in any of the last half's windows (dt_out
        # against t_end): nothing to fit, and nothing the run shows either way
        return _check("RATE", "θ̃ → 0, rate", "Theorem 2 statement 2", UNDECIDED,
                      {"windows_with_samples": int(means.size)},
                      f"windowed means of ‖θ̃‖ over the last half (×{N_BINS})", figure,
                      note=f"not evaluated: none of the last half's {N_BINS} windows holds a "
                      "sample (the run is too short for its output step)"), \
            (float("nan"), float("nan"))
    a, C, r2 = power_fit(centers, means)
    floor = _floor_fit(centers, means)
    im = int(np.searchsorted(t, tm))
    drop = means[-1] / means[0] if means.size and means[0] > 0 else float("nan")
    if not np.isfinite(a):
        verdict = UNDECIDED
    elif a <= 0.02:
        verdict = FAILS
    elif a >= 0.1 and drop <= 0.7 and floor <= 0.25 * means[-1]:
        verdict = HOLDS
    else:
        verdict = UNDECIDED
    measured = {"a": a, "C": C, "r2": r2, "floor": floor, "window_mean_first": float(means[0]),
                "window_mean_last": float(means[-1]), "theta_err_norm_mid": float(y[im]),
                "theta_err_norm_end": float(y[-1])}
    if calW_over_Delta is not None:
        last = t >= t[-1] - (t[-1] - tm) / N_BINS
        vals = np.asarray(calW_over_Delta)[last]
        vals = vals[np.isfinite(vals)]
        measured["calW_over_Delta_last_window"] = float(np.mean(vals)) if vals.size else float("nan")
    return _check("RATE", "θ̃ → 0, rate", "Theorem 2 statement 2", verdict, measured,
                  f"windowed means of ‖θ̃‖ over the last half (×{N_BINS}) fitted by C t^(−a) and "
                  "c₀ + C t^(−b): a ≥ 0.1, last/first window ≤ 0.7 and c₀ ≤ 0.25 × last window "
                  "holds; a ≤ 0.02 fails (no convergence); otherwise not decided at this horizon",
                  figure), (a, C)


def _floor_fit(t, y):
    """c₀ ≥ 0 of the best least-squares fit y ≈ c₀ + C t^(−b), b on a grid (0.05 … 4)."""
    ok = (t > 0) & np.isfinite(y)
    t, y = t[ok], y[ok]
    if t.size < 3:
        return float("nan")
    best = (np.inf, float("nan"))
    for b in np.linspace(0.05, 4.0, 80):
        A = np.column_stack([np.ones_like(t), t ** -b])
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        c0 = max(float(coef[0]), 0.0)
        Cb = float(np.linalg.lstsq(A[:, 1:], y - c0, rcond=None)[0][0])
        res = float(np.sum((y - c0 - Cb * t ** -b) ** 2))
        if res < best[0]:
            best = (res, c0)
    return best[1]


# --------------------------------------------------------------------------- Lyapunov (23)
def lyapunov(r, M, theta_err, Gamma, tau_d_err, mu, rho):
    """V of (23): ½rᵀMr + ½θ̃ᵀΓ⁻¹θ̃ + ρ/2‖f̃_n‖², with f̃_n = −tau_d_err/μ.

    ``tau_d_err`` is τ_d − τ̂_d where τ̂_d = −f̂ of (7) evaluated with the true θ (the
    proof's f̃_n); :func:`observer_error_true_theta` forms it from a run.
    """
    Gi = np.linalg.inv(np.asarray(Gamma, dtype=float))
    kin = 0.5 * np.einsum("it,ijt,jt->t", r, M, r)
    par = 0.5 * np.einsum("it,ij,jt->t", theta_err, Gi, theta_err)
    obs = 0.5 * rho * np.sum((tau_d_err / mu) ** 2, axis=0)
    return kin + par + obs


def check_lyapunov(t, V, calW=None, gamma=None, lam2_int=None, rho=None, delta_rho=None,
                   figure=None):
    """V(t) against the bound of the proof, V(t0) + γ∫‖𝒲‖² + ρδ_ρ∫‖λ‖² (δ_𝒲 → 1)."""
    t = np.asarray(t, dtype=float)
    V = np.asarray(V, dtype=float)
    measured = {"V_0": float(V[0]), "V_end": float(V[-1]), "V_max": float(np.max(V))}
    if calW is None or gamma is None or lam2_int is None or rho is None:
        return _check("V", "Lyapunov function (23)", "proof of Theorem 2", NA, measured,
                      "the bound of the proof is for the composite term (21) only", figure), None
    W2 = _cum(t, np.sum(np.atleast_2d(calW) ** 2, axis=0))
    bound = V[0] + gamma * W2 + rho * delta_rho * np.asarray(lam2_int)
    ratio = V / bound
    i = int(np.argmax(ratio))
    measured.update(bound_end=float(bound[-1]), max_V_over_bound=float(ratio[i]),
                    t_max_ratio=float(t[i]))
    verdict = HOLDS if ratio[i] <= 1.0 + 1e-9 else FAILS
    return _check("V", "Lyapunov function (23)", "proof of Theorem 2 (statement 1)", verdict,
                  measured, "V(t) ≤ V(0) + γ∫‖𝒲‖² + ρδ_ρ∫‖λ‖² on the whole run (δ_𝒲 → 1; "
                  "f̃_n from τ̂_d of the run)", figure), bound


def _model_at_samples(model, name, shape, *signals, theta=None):
    """The model function `name` (out of `shape`) at every sample of `signals` (each
    n x samples), as a shape + (samples,) array: one compiled loop over the samples (the
    compiled engine's model module, `*_samples`); the Python functions sample by sample for
    a model without one.  Both evaluate the same generated code."""
    args = [np.ascontiguousarray(np.atleast_2d(s).T) for s in signals]
    if theta is not None:
        args.append(np.ascontiguousarray(theta, dtype=float))
    out = np.empty((args[0].shape[0], *shape))
    try:
        from ..sim.compiled import model_module
        loop = getattr(model_module(model), f"{name}_samples")
    except Exception:  # noqa: BLE001 - no compiled module (numba missing, a model of one's own)
        loop = None
    if loop is not None:
        loop(*args, out)
    else:
        fn, nt, rest = getattr(model.functions, name), out.shape[0], args[len(signals):]
        for k in range(nt):
            fn(*(a[k] for a in args[:len(signals)]), *rest, out[k])
    return np.ascontiguousarray(np.moveaxis(out, 0, -1))


def observer_error_true_theta(resp, model, theta):
    """τ_d − τ̂_d(θ): the observer error (7) with the true θ, as the proof of Theorem 2 uses.

    The loop's τ̂_d uses θ̂; by (7) and Π of (8), f̂(θ) − f̂(θ̂) = (Πᵀ − Φᵀ(q, q̇, v, v̇)) θ̃,
    so τ̂_d(θ) = τ̂_d(θ̂) − (Πᵀ − Φᵀ)θ̃ from the recorded Π, q, q̇, v, v̇.
    """
    tau_d = np.atleast_2d(_sig(resp, "tau_d"))
    n, nt = tau_d.shape
    ntheta = theta.size
    th_err = theta.reshape(-1, 1) - _sig(resp, "theta_hat")
    Pi = _sig(resp, "Pi").reshape(n, ntheta, nt)
    q, dq = np.atleast_2d(_sig(resp, "q")), np.atleast_2d(_sig(resp, "dq"))
    v, dv = np.atleast_2d(_sig(resp, "v")), np.atleast_2d(_sig(resp, "dv"))
    Phi = _model_at_samples(model, "Phi", (n, ntheta), q, dq, v, dv)
    hat_theta = np.atleast_2d(_sig(resp, "tau_d_hat")) - np.einsum("jkt,kt->jt", Pi - Phi, th_err)
    return tau_d - hat_theta


# --------------------------------------------------------------------------- activity
def check_active(t, delta, gamma, lam_max_Gamma, T, figure=None, *, gamma_auto=False,
                 mixing=None):
    """Is the composite term (21) active: γ λ_max(Γ) ∫Δ² ds, the e-folds it can give θ̃
    (the weakest channel for a per-channel Δ_i, γ_i)."""
    from ..diagrams.gamma_auto import DEFAULT_RATE, gamma_from_delta

    t = np.asarray(t, dtype=float)
    D2 = np.atleast_2d(np.asarray(delta, dtype=float)) ** 2
    g = np.atleast_1d(np.asarray(gamma, dtype=float)).reshape(-1, 1)
    per = g * lam_max_Gamma * _cum(t, D2)[:, -1:] if D2.shape[0] > 1 else None
    k = int(np.argmin(per[:, 0])) if per is not None else 0
    gamma = float(g[min(k, g.shape[0] - 1), 0])
    d2 = D2[k]
    delta = np.sqrt(d2)
    efolds = float(gamma * lam_max_Gamma * _cum(t, d2)[-1])
    rate = gamma * lam_max_Gamma * float(np.mean(d2[t >= _half(t)]))
    measured = {"gamma": float(gamma), "efolds_over_run": efolds,
                "rate_last_half": rate, "one_over_t_end": 1.0 / t[-1]}
    note = ""
    try:
        suggest = gamma_from_delta(t, delta, T, lam_max_Gamma, rate=DEFAULT_RATE)["gamma"]
        measured["gamma_auto_from_this_run"] = suggest
    except ValueError:
        suggest = None
    verdict = HOLDS if efolds >= ACTIVE_EFOLDS else FAILS
    chan = f" (channel {k + 1}, the weakest)" if per is not None else ""
    if verdict == FAILS and gamma_auto:
        # "auto" is what left it inactive: Δ fell below its calibration level
        note = (f"composite term inactive{chan}: γ λ_max(Γ) ∫Δ² ds = {efolds:.3g} e-folds over "
                f"the run (< {ACTIVE_EFOLDS:g}) with the γ \"auto\" calibrated over [T, 2T]: "
                "Δ fell below its calibration level"
                + ("; set iv_drem.mixing = \"eigen\" (Δ near 1 keeps the calibrated rate, "
                   "docs/mixing.md)" if mixing in (None, "paper") else
                   f"; a numeric gamma ≈ {suggest:.3g} (from this run's Δ)" if suggest else ""))
    elif verdict == FAILS:
        note = (f"composite term inactive{chan}: γ λ_max(Γ) ∫Δ² ds = {efolds:.3g} e-folds over "
                f"the run (< {ACTIVE_EFOLDS:g}); set iv_drem.gamma = \"auto\""
                + (f" (γ ≈ {suggest:.3g} from this run's Δ)" if suggest else "")
                + " or a larger number")
    return _check("ACTIVE", "composite term active", "γΔ²λ_max(Γ) against the horizon", verdict,
                  measured, f"γ λ_max(Γ) ∫₀^t_end Δ² ds ≥ {ACTIVE_EFOLDS:g} (at least one e-fold "
                  "of θ̃ from the composite term over the run)", figure, note)


# --------------------------------------------------------------------------- learning
def check_learning(t, theta_err_norm, T, *, calW_over_Delta=None, delta_log10=None,
                   mixing=None, gamma=None, gamma_auto=False):
    """Does the run learn?  It does not where ‖θ̃‖ grows (‖θ̃(t_end)‖ ≥ ‖θ̃(0)‖, or the
    last window's mean is LEARN_GROWTH × the first of the last half), where the bias
    floor ‖𝒲‖/|Δ| of (17) (= ‖Ψ⁻¹W‖ in every mixing, docs/mixing.md) over the last window
    is comparable to the initial error (at least LEARN_FLOOR_SHARE ‖θ̃(0)‖: θ̂ can then at
    best settle that far from θ), or, for a law with Δ (`mixing` given), where θ̃ has not
    been reduced below LEARN_REDUCTION ‖θ̃(0)‖.  The note names the cause and a remedy that addresses it: the
    bias floor is the excitation's (no mixing changes 𝒲/Δ); a |Δ| spanning
    DELTA_SPAN_DECADES or more under one γ is the paper's mixing's ("eigen" keeps Δ near 1);
    growth under a calibrated γ with a mixing that keeps Δ near 1 asks for a smaller γ."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(theta_err_norm, dtype=float)
    e0, e_end = float(y[0]), float(y[-1])
    bins = _bins(t, _half(t))
    means = [float(np.mean(y[b])) for b in bins]
    growth = means[-1] / means[0] if len(means) >= 2 and means[0] > 0 else float("nan")
    measured = {"theta_err_0": e0, "theta_err_end": e_end, "growth_last_half": growth}
    floor = float("nan")
    if calW_over_Delta is not None and bins:
        v = np.asarray(calW_over_Delta, dtype=float)[bins[-1]]
        v = v[np.isfinite(v)]
        floor = float(np.median(v)) if v.size else float("nan")
        measured["bias_floor_last_window"] = floor
    span = float("nan")
    if delta_log10 is not None:
        L = np.atleast_2d(np.asarray(delta_log10, dtype=float))[:, t >= min(T, _half(t))]
        L = L[:, np.all(L > -399.0, axis=0)] if L.size else L
        if L.size:
            span = float(np.max(np.max(L, axis=1) - np.min(L, axis=1)))
            measured["log10_Delta_span_decades"] = span
    grows = e_end >= e0 or (np.isfinite(growth) and growth >= LEARN_GROWTH)
    biased = np.isfinite(floor) and floor >= LEARN_FLOOR_SHARE * e0
    measured["bias_floor_share_of_theta_err_0"] = floor / e0 if e0 > 0 else float("nan")
    measured["theta_err_ratio"] = e_end / e0 if e0 > 0 else float("nan")
    note = ""
    if biased:
        where = (f"above ‖θ̃(0)‖ = {e0:.3g}" if floor >= e0 else
                 f"{floor / e0:.0%} of ‖θ̃(0)‖ = {e0:.3g}, comparable to the initial error")
        note = (f"the run does not learn: the bias floor ‖𝒲‖/|Δ| of (17) over the last window "
                f"is {floor:.3g}, {where}, so θ̂ can at best settle near θ + Ψ⁻¹W "
                f"(‖θ̃(t_end)‖ = {e_end:.3g}); the disturbance W of (16) outweighs the excitation "
                "of Ψ, and no mixing changes 𝒲/Δ: give every joint a reference frequency of "
                "its own that τ_d does not have (condition (19), check KA3; "
                "examples/planar3.toml), or run longer (𝒲 decays like Ḟ/F, Proposition 2)")
    elif mixing is not None and not grows and e_end > LEARN_REDUCTION * e0:
        note = (f"the run has not learned (yet): ‖θ̃‖ went from {e0:.3g} to {e_end:.3g} "
                f"({e_end / e0:.2f} of its start, more than {LEARN_REDUCTION:g}); the composite "
                "term needs more of the horizon (check ACTIVE; with mixing \"eigen\" or "
                "\"channel\" it starts at t = T, docs/mixing.md): run longer")
    elif grows:
        what = (f"‖θ̃‖ grows from {e0:.3g} to {e_end:.3g}" if e_end >= e0 else
                f"‖θ̃‖ grows by {growth:.2f}x over the last half (to {e_end:.3g})")
        if mixing == "paper" and np.isfinite(span) and span >= DELTA_SPAN_DECADES:
            note = (f"the run does not learn: {what}; the paper's Δ spans {span:.1f} decades "
                    f"over the run, so the rate γΔ²λ_max(Γ) of the one γ"
                    + (" that \"auto\" calibrated" if gamma_auto else "")
                    + " does too (stiff where Δ is large, inactive where it is small); set "
                    "iv_drem.mixing = \"eigen\" (Δ = ∏σ_j/(σ_j + f₀) stays near 1, docs/mixing.md)")
        elif mixing == "paper":
            note = (f"the run does not learn: {what}; set iv_drem.mixing = \"eigen\" "
                    "(docs/mixing.md) with gamma = \"auto\"")
        else:
            g = np.atleast_1d(np.asarray(gamma, dtype=float)) if gamma is not None else None
            gtxt = (f" (γ = {np.max(g):.3g} now; try {np.max(g) / 100:.3g})"
                    if g is not None and g.size else "")
            note = (f"the run does not learn: {what} with mixing {mixing!r}; the composite term "
                    f"drives θ̂ faster than Ψ settles: a numeric iv_drem.gamma 100x below "
                    + ("the calibrated one" if gamma_auto else "this one") + gtxt)
    verdict = FAILS if note else HOLDS
    if verdict == HOLDS and not np.isfinite(growth):
        # the last half holds fewer than two windows with samples: whether θ̃ grows there
        # cannot be judged, so the run is not said to learn (a 0.1 s run of 7 steps)
        verdict = UNDECIDED
        held = ("none" if not means else f"only {len(means)}")
        note = (f"not evaluated: {held} of the last half's {N_BINS} windows holds a sample "
                "(the run is too short for its output step)")
    return _check("LEARN", "the run learns", "θ̃ → 0 (Theorem 2) observed, not presumed",
                  verdict, measured,
                  f"‖θ̃(t_end)‖ < ‖θ̃(0)‖ (< {LEARN_REDUCTION:g} ‖θ̃(0)‖ for a law with Δ), "
                  f"last/first window of the last half < {LEARN_GROWTH}, and the bias floor "
                  f"‖𝒲‖/|Δ| (last window, median) < {LEARN_FLOOR_SHARE:g} ‖θ̃(0)‖", None, note)


# --------------------------------------------------------------------------- a whole run
def _sig(resp, name):
    from .metrics import signal
    return signal(resp, name)


def _has(resp, name):
    from .metrics import signal_names
    return name in signal_names(resp)


def _gamma_matrix(config, ntheta):
    g = config["controller"]["Gamma"]
    return np.diag(np.asarray(g, float)) if isinstance(g, list) else float(g) * np.eye(ntheta)


def diagnose(lawrun, config, model=None, *, theta=None, figure=None):
    """The checks of one law's run; returns {"law", "checks": [...], "warnings", "series"}.

    ``series`` holds the arrays the figures draw (not JSON); :func:`to_json` drops it.
    """
    from ..laws import LAWS as registry

    resp = getattr(lawrun, "response", lawrun)
    law = getattr(lawrun, "law", "?")
    spec = registry.get(law)
    t = np.asarray(resp.time, dtype=float)
    theta = np.asarray(config["model"]["theta"] if theta is None else theta, dtype=float)
    ntheta = theta.size
    ctl = config["controller"]
    Gamma = _gamma_matrix(config, ntheta)
    lam_max = float(np.max(np.linalg.eigvalsh(Gamma)))
    ivd = config["iv_drem"]
    T = float(ivd["T"])
    l = float(config["filters"]["l"])
    mu = _sig(resp, "mu")
    tau_d = np.atleast_2d(_sig(resp, "tau_d"))
    n = tau_d.shape[0]
    th_err = theta.reshape(-1, 1) - _sig(resp, "theta_hat")
    checks, series, warnings = [], {"t": t}, []

    has_delta = _has(resp, "Delta")
    choice, mixing = gamma_choice_and_mixing(lawrun, ivd)
    if has_delta:
        delta_all = np.atleast_2d(_sig(resp, "Delta"))       # one row, or one per channel
        # KA1 and (18) on the weakest channel (the smallest ∫Δ_i²) of a per-channel Δ_i
        weakest = int(np.argmin(_cum(t, delta_all ** 2)[:, -1])) if delta_all.shape[0] > 1 else 0
        delta = delta_all[weakest]
        c, S = check_ka1(t, delta, figure)
        if delta_all.shape[0] > 1:
            c["measured"]["channel"] = weakest + 1
        checks.append(c)
        series.update(Delta=delta, Delta_channels=delta_all, int_Delta2=S)
        beta = None
        inst = spec.instrument if spec is not None else None
        if inst and _has(resp, inst) and _has(resp, "phi"):
            beta = excitation_beta(t, _sig(resp, inst), _sig(resp, "phi"), n, ntheta, T)
            series["beta"] = beta
        checks.append(check_pe(t, delta, beta, T, figure))
    else:
        checks += [_check("KA1", "Δ ∉ L2", "Remark 4 KA1", NA, {}, "law has no Δ (17)"),
                   _check("PE", "excitation (18)", "Proposition 1", NA, {}, "law has no Δ (17)")]

    c, lam2, g = check_ka2(t, tau_d, mu, figure)
    checks.append(c)
    series.update(int_lambda2=lam2)

    inst = spec.instrument if spec is not None else None
    if inst and _has(resp, inst) and _has(resp, "z") and _has(resp, "phi"):
        phiT = _sig(resp, "phi").reshape(n, ntheta, -1)
        w = _sig(resp, "z").reshape(n, -1) - np.einsum("jkt,k->jt", phiT, theta)  # (13)
        c, ints = check_ka3(t, _sig(resp, inst), w, n, ntheta, tau_d, figure,
                            instrument="ζ" if inst == "zeta" else "φ")
        checks.append(c)
        series.update(ka3_integrals=ints, w=w)
    else:
        checks.append(_check("KA3", "condition (19)", "Remark 4 KA3", NA, {},
                             "law has no instrument"))

    if has_delta and _has(resp, "calY"):
        from .metrics import calW as calW_fn
        W = calW_fn(resp, theta)
        c, R = check_prop2(t, W, float(ivd["p"]), float(ivd["F0"]), T, figure)
        checks.append(c)
        series.update(prop2_ratio=R)
    else:
        W = None
        checks.append(_check("P2", "|𝒲_i| F/Ḟ bounded", "Proposition 2", NA, {}, "law has no 𝒲"))

    dmu = np.full_like(mu, float(ctl["mu0"]))
    c, p42 = check_property42(t, mu, float(ctl["delta_mu"]), dmu)
    checks.append(c)

    ratio = None
    if W is not None:
        # ‖(𝒲_i/Δ_i)_i‖ = ‖Ψ⁻¹W‖: ‖𝒲‖/|Δ| for one Δ, per channel for Δ_i
        D = series["Delta_channels"]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(np.all(np.abs(D) > 0, axis=0),
                             np.sqrt(np.sum((W / D) ** 2, axis=0)), np.nan)
    c, fit = check_rate(t, np.sqrt(np.sum(th_err ** 2, axis=0)), figure, ratio)
    checks.append(c)
    series.update(theta_err_norm=np.sqrt(np.sum(th_err ** 2, axis=0)), rate_fit=fit)

    gamma = getattr(lawrun, "gamma", None)
    if gamma is None or isinstance(gamma, str):
        gamma = ivd["gamma"] if not isinstance(ivd["gamma"], str) else None
    gvec = None if gamma is None else np.atleast_1d(np.asarray(gamma, dtype=float))
    if model is not None and _has(resp, "r") and _has(resp, "q"):
        q = np.atleast_2d(_sig(resp, "q"))
        Mq = _model_at_samples(model, "M", (n, n), q, theta=theta)
        rho = p42["rho"] if p42 else 2.0 / float(ctl["delta_mu"])
        exact = all(_has(resp, s) for s in ("Pi", "v", "dv", "dq"))
        err = (observer_error_true_theta(resp, model, theta) if exact
               else tau_d - np.atleast_2d(_sig(resp, "tau_d_hat")))
        V = lyapunov(np.atleast_2d(_sig(resp, "r")), Mq, th_err, Gamma, err, mu, rho)
        use_bound = has_delta and W is not None and gamma is not None and p42 is not None
        if use_bound and gvec.size > 1:
            # per-channel γ_i: the proof's γ‖𝒲‖² term is Σ γ_i 𝒲_i²
            W_b, g_b = W * np.sqrt(gvec)[:, None], 1.0
        else:
            W_b, g_b = W, (float(gvec[0]) if gvec is not None else None)
        c, bound = check_lyapunov(t, V, W_b if use_bound else None, g_b if use_bound else None,
                                  lam2 if use_bound else None, rho,
                                  p42["delta_rho"] if p42 else None, figure)
        c["measured"]["f_n_from"] = "true θ (as in the proof)" if exact else "θ̂ of the run"
        c["measured"]["rho"] = rho
        checks.append(c)
        series.update(V=V, V_bound=bound)

    if has_delta and gamma is not None:
        c = check_active(t, series["Delta_channels"], gvec if gvec.size > 1 else float(gvec[0]),
                         lam_max, T, figure, gamma_auto=choice is not None, mixing=mixing)
        checks.append(c)
        if c["note"]:
            warnings.append(c["note"])
    logd = _sig(resp, "Delta_log10") if _has(resp, "Delta_log10") else None
    c = check_learning(t, series["theta_err_norm"], T, calW_over_Delta=ratio,
                       delta_log10=logd, mixing=mixing if has_delta else None, gamma=gamma,
                       gamma_auto=choice is not None)
    checks.append(c)
    if c["note"] and c["verdict"] == FAILS:
        warnings.insert(0, c["note"])
    short = law_horizon_note(lawrun, config)
    if short:
        # a horizon that ends before the composite term could act judges nothing about it:
        # its checks are not decided, and no warning speaks of learning
        for c in checks:
            if c["id"] in HORIZON_CHECKS and c["verdict"] != NA:
                if c["note"] in warnings:
                    warnings.remove(c["note"])
                c["verdict"], c["note"] = UNDECIDED, short
    return {"law": law, "checks": checks, "warnings": warnings, "series": series}


#: the checks a run must outlive the window (15a) (and the start of the composite term)
#: to judge: they measure Δ, the excitation of a full window, 𝒲 or the decay of θ̃
HORIZON_CHECKS = ("KA1", "PE", "P2", "RATE", "ACTIVE", "LEARN")


def learning_warnings(diag: Mapping) -> list:
    """The warning of the LEARN check of one law's diagnostics (empty when the run learns,
    and when its horizon is too short to tell: :func:`short_horizon_note`)."""
    return [c["note"] for c in diag["checks"]
            if c["id"] == "LEARN" and c["note"] and c["verdict"] == FAILS]


def diagnose_run(run, *, figure_prefix="figD-"):
    """diagnose() for every law of a PaperRun: {law: diagnostics}; computed once per run
    (kept as ``run.diagnostics``) so that the report's tables and figures share it."""
    cached = getattr(run, "diagnostics", None)
    if isinstance(cached, dict) and set(cached) == set(run.runs):
        return cached
    out = {law: diagnose(lr, run.config, getattr(run, "model", None), theta=run.theta,
                         figure=f"{figure_prefix}{law}")
           for law, lr in run.runs.items()}
    try:
        run.diagnostics = out
    except AttributeError:  # pragma: no cover - a frozen duck type
        pass
    return out


def tau_d_decomposition(lawrun, model, theta, last_fraction=0.2):
    """Why τ̃_d is large when θ̂ does not converge: τ̂_d is built from θ̂ in (7), so
    τ̃_d = [τ_d − τ̂_d(θ)] + (Πᵀ − Φᵀ(q, q̇, v, v̇)) θ̃ (observer error with the true θ, plus
    the part carried by θ̃, which μ(t) amplifies through Π).  RMS of ‖·‖ of each over the
    last ``last_fraction`` of the run; None when the run lacks Π, v, v̇."""
    from .metrics import rms, window
    resp = getattr(lawrun, "response", lawrun)
    if model is None or not all(_has(resp, s) for s in ("Pi", "v", "dv", "dq")):
        return None
    t = np.asarray(resp.time, dtype=float)
    theta = np.asarray(theta, dtype=float)
    last = window(t, t[-1] - last_fraction * (t[-1] - t[0]))
    total = np.atleast_2d(_sig(resp, "tau_d")) - np.atleast_2d(_sig(resp, "tau_d_hat"))
    true_obs = observer_error_true_theta(resp, model, theta)
    carried = total - true_obs

    def r(x):
        return rms(t[last], np.sqrt(np.sum(x * x, axis=0))[last])
    th = theta.reshape(-1, 1) - _sig(resp, "theta_hat")
    return {"tau_d_err_rms": r(total), "observer_error_true_theta_rms": r(true_obs),
            "theta_err_part_rms": r(carried),
            "theta_err_norm_end": float(np.sqrt(np.sum(th[:, -1] ** 2))),
            "mu_end": float(_sig(resp, "mu")[-1])}


def _plain(v):
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, float)):
        x = float(v)
        return x if math.isfinite(x) else (None if math.isnan(x) else ("inf" if x > 0 else "-inf"))
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def to_json(diag: Mapping) -> dict:
    """The JSON-safe part of diagnose(): checks and warnings, no arrays (inf as a string)."""
    return _plain({"checks": diag["checks"], "warnings": diag["warnings"]})


#: what the diagnostics' measured quantities are, for a reader (docs/diagnostics.md)
_MEASURED_LABELS = {
    "int_Delta2_end": "∫Δ² dt to t_end", "int_Delta2_growth_last_half": "its growth, last half",
    "slope_last_half": "slope, last half", "decay_exponent_Delta2": "decay exponent of Δ²",
    "decay_exponent_abs_Delta": "decay exponent of |Δ|", "Delta_min_last_half": "min |Δ|, last half",
    "beta_min": "min β", "beta_min_last_half": "min β, last half",
    "decay_exponent_beta": "decay exponent of β", "int_lambda2_end": "∫λ² dt to t_end",
    "decay_exponent_integrand": "decay exponent of λ²", "tail_estimate": "tail estimate",
    "normalised_mean_max": "max normalised mean", "worst_pair": "worst pair",
    "max_abs_integral": "max |∫|", "frequency_gap": "frequency gap",
    "max_second_quarter": "max, second quarter", "max_last_quarter": "max, last quarter",
    "growth_exponent": "growth exponent", "rho": "ρ", "delta_rho": "δ_ρ", "best_rho": "best ρ",
    "mu_LB_min": "min μ_LB", "int_mu_LB_end": "∫μ_LB dt to t_end", "mu_min": "min μ",
    "mu_end": "μ(t_end)", "a": "fitted exponent a", "r2": "r²", "floor": "floor",
    "V_0": "V(0)", "V_end": "V(t_end)", "bound_end": "bound at t_end", "gamma": "γ",
    "efolds_over_run": "e-folds over the run", "rate_last_half": "rate, last half",
    "one_over_t_end": "1/t_end", "calW_over_Delta_last_window": "‖𝒲‖/|Δ|, last window",
    "gamma_auto_from_this_run": "γ \"auto\" from this run",
    "theta_err_norm_end": "‖θ̃(t_end)‖", "theta_err_norm_mid": "‖θ̃(t_end/2)‖",
    "tau_d_err_rms": "RMS ‖τ̃_d‖", "observer_error_true_theta_rms": "RMS observer error (true θ)",
    "theta_err_part_rms": "RMS part carried by θ̃", "window_mean_first": "mean, first window",
    "window_mean_last": "mean, last window", "min_left_side": "min of the left side",
    "f_n_from": "f_n from", "V_max": "max V", "growth_last_half": "growth, last half",
    "theta_err_0": "‖θ̃(0)‖", "theta_err_end": "‖θ̃(t_end)‖", "mu_LB": "μ_LB",
}


def measured_label(key: str) -> str:
    """A reader's name for a measured quantity of the diagnostics (its key otherwise,
    without underscores)."""
    return _MEASURED_LABELS.get(key, key.replace("_", " "))


def format_diagnostics(diag: Mapping) -> str:
    """Plain-text verdict table of one law, for terminals."""
    lines = [f"diagnostics of {diag['law']}:"]
    for c in diag["checks"]:
        key = ", ".join(f"{measured_label(k)} = {_fmt(v)}"
                        for k, v in list(c["measured"].items())[:3])
        lines.append(f"  {c['id']:<6} {c['verdict']:<14} {c['name']}: {key}")
    for w in diag["warnings"]:
        lines.append(f"  WARNING: {w}")
    horizon = {c["note"] for c in diag["checks"]
               if c["verdict"] == UNDECIDED and c["note"].startswith("not evaluated")}
    lines += [f"  note: {n}" for n in sorted(horizon)]
    return "\n".join(lines)


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)
