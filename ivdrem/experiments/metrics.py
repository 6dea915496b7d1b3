"""Measured numbers of a paper run: errors, the disturbance 𝒲, conclusions C1-C4.

Results arrive as ``PaperRun`` objects (``ivdrem.experiments.paper``); this module only
uses their duck type:

* ``run.config``: the validated configuration dict, ``run.theta``: true θ;
* ``run.runs``: dict law -> LawRun with ``.law``, ``.response`` (a python-control
  ``TimeResponseData`` with named outputs ``q[i]``, ``q_d[i]``, ``e[i]``, ``r[i]``,
  ``tau[i]``, ``tau_d[i]``, ``tau_d_hat[i]``, ``theta_hat[j]``, ``mu``; ``Delta`` and
  ``calY[j]`` for "iv-drem"/"drem"; ``lambda_min_held`` for "composite-learning") and
  ``.stats`` (solver statistics).

Conclusions, each a dict with keys id, statement, criterion, law(s),
measured, threshold, verdict (True/False; None when a needed law was not run, or when the
run ends before the composite term of one of its laws could act: :func:`law_horizon_note`):

* C1 (composite learning, θ̃ bounded, no convergence): over the last half of the run
  max and min of ‖θ̃‖ stay within 10 % of ‖θ̃‖ at mid-run, and ‖θ̃(t_end)‖ > 0.1‖θ̃(0)‖.
* C2 (IV-DREM, θ̃ → 0): ‖θ̃(t_end)‖ <= 0.1‖θ̃(0)‖ and max ‖θ̃‖ over the last quarter
  < max over the second quarter.
* C3 (IV-DREM estimates τ_d better): RMS of ‖τ̃_d‖ over the last 20 % of the run is at
  most half that of composite learning.
* C4 (the instrument matters, measured, not presumed): DREM with φ in place of the
  instrument ζ ends with ‖θ̃(t_end)‖ at least twice IV-DREM's.  Also reported: both
  errors at the end of the first quarter (the early transient).
"""
from __future__ import annotations

import re
from typing import Any, Mapping

import numpy as np

__all__ = [
    "signal",
    "signal_names",
    "theta_error",
    "tau_d_error",
    "calW",
    "norm",
    "window",
    "rms",
    "summary",
    "conclusions",
    "law_horizon_note",
    "format_conclusions",
    "verdict_text",
    "key_numbers",
    "C1_REL_DEV",
    "C1_END_RATIO",
    "C2_END_RATIO",
    "C3_RMS_RATIO",
    "C4_RATIO",
    "LAST_FRACTION",
]

#: C1: max relative deviation of ‖θ̃‖ over the last half from its mid-run value.
C1_REL_DEV = 0.10
#: C1: ‖θ̃(t_end)‖ must stay above this fraction of ‖θ̃(0)‖.
C1_END_RATIO = 0.10
#: C2: ‖θ̃(t_end)‖ must reach this fraction of ‖θ̃(0)‖.
C2_END_RATIO = 0.10
#: C3: RMS ‖τ̃_d‖ of IV-DREM at most this fraction of composite learning's.
C3_RMS_RATIO = 0.5
#: C4: DREM without the instrument must end at least this many times worse than IV-DREM.
C4_RATIO = 2.0
#: The "last 20 %" of the run used by C3 and summary().
LAST_FRACTION = 0.2

PROPOSED = "iv-drem"
BASELINE = "composite-learning"
NO_INSTRUMENT = "drem"

_INDEXED = re.compile(r"^(.*)\[(\d+)\]$")


# --------------------------------------------------------------------------- signals
def _response(obj):
    return getattr(obj, "response", obj)


def _outputs(resp) -> np.ndarray:
    y = getattr(resp, "y", None)
    if y is None:
        y = resp.outputs
    y = np.asarray(y, dtype=float)
    n_t = np.asarray(resp.time).size
    return y.reshape(-1, n_t)


def signal_names(resp) -> list[str]:
    """Base names of the outputs of a response ('theta_hat', 'mu', ...), in order."""
    seen: dict[str, None] = {}
    for lab in _response(resp).output_labels:
        m = _INDEXED.match(lab)
        seen[m.group(1) if m else lab] = None
    return list(seen)


def signal(resp, name: str) -> np.ndarray:
    """An output of a response (or LawRun) by name.

    An exact label ('mu', 'e[0]') gives a 1-D array over time; a base name of indexed
    outputs ('theta_hat') gives a matrix, one row per index (nθ × n_t), in index order.
    """
    resp = _response(resp)
    labels = list(resp.output_labels)
    y = _outputs(resp)
    if name in labels:
        return y[labels.index(name)].copy()
    rows = {}
    for k, lab in enumerate(labels):
        m = _INDEXED.match(lab)
        if m and m.group(1) == name:
            rows[int(m.group(2))] = k
    if not rows:
        raise KeyError(
            f"response has no output {name!r}; available: {', '.join(signal_names(resp))}"
        )
    idx = sorted(rows)
    if idx != list(range(len(idx))):
        raise KeyError(f"outputs {name}[i] are not numbered 0..{len(idx) - 1}: {idx}")
    return y[[rows[i] for i in idx]].copy()


def _time(obj) -> np.ndarray:
    return np.asarray(_response(obj).time, dtype=float)


def norm(x: np.ndarray) -> np.ndarray:
    """Euclidean norm over the rows of a (k × n_t) signal, per time sample."""
    x = np.asarray(x, dtype=float)
    return np.abs(x) if x.ndim == 1 else np.sqrt(np.sum(x * x, axis=0))


def window(t: np.ndarray, start: float, stop: float | None = None) -> np.ndarray:
    """Boolean mask of the samples with start <= t <= stop (stop defaults to the end)."""
    t = np.asarray(t, dtype=float)
    span = max(t[-1] - t[0], 1.0)
    tol = 1e-9 * span
    stop = t[-1] if stop is None else stop
    return (t >= start - tol) & (t <= stop + tol)


def rms(t: np.ndarray, x: np.ndarray) -> float:
    """Time-weighted RMS of a 1-D signal (trapezoidal rule; plain RMS for one sample)."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    if t.size < 2 or t[-1] <= t[0]:
        return float(np.sqrt(np.mean(x * x)))
    x2 = x * x
    return float(np.sqrt(np.sum(0.5 * (x2[1:] + x2[:-1]) * np.diff(t)) / (t[-1] - t[0])))


# --------------------------------------------------------------------------- errors
def _per_law(run_or_lawrun, fn, *args):
    if hasattr(run_or_lawrun, "runs"):
        return {law: fn(lr, *args) for law, lr in run_or_lawrun.runs.items()}
    return fn(run_or_lawrun, *args)


def theta_error(run_or_lawrun, theta=None):
    """θ̃ = θ − θ̂ (nθ × n_t); for a PaperRun a dict law -> θ̃ (θ defaults to run.theta)."""
    if theta is None:
        theta = getattr(run_or_lawrun, "theta", None)
        if theta is None:
            raise TypeError("theta_error of a LawRun needs the true theta")
    theta = np.asarray(theta, dtype=float).reshape(-1, 1)
    return _per_law(run_or_lawrun, lambda lr: theta - signal(lr, "theta_hat"))


def tau_d_error(run_or_lawrun):
    """τ̃_d = τ_d − τ̂_d (n × n_t); for a PaperRun a dict law -> τ̃_d."""
    return _per_law(run_or_lawrun, lambda lr: signal(lr, "tau_d") - signal(lr, "tau_d_hat"))


def calW(lawrun, theta):
    """𝒲 = 𝒴 − Δθ (nθ × n_t) of an "iv-drem" or "drem" run (𝒴_i = Δ_iθ_i + 𝒲_i; one Δ, or
    one Δ_i per channel for the "channel" mixing)."""
    theta = np.asarray(theta, dtype=float).reshape(-1, 1)
    return signal(lawrun, "calY") - np.atleast_2d(signal(lawrun, "Delta")) * theta


# --------------------------------------------------------------------------- summary
def summary(lawrun, theta) -> dict:
    """Numbers of one law's run (the JSON schema of ``ivdrem paper --json``).

    t_end, theta_hat (final), theta_err_norm (final ‖θ̃‖), e_max_last20 (max ‖e‖ over
    the last 20 %), tau_d_err_rms_last20 (RMS of ‖τ̃_d‖ there), wall_s (solver wall time).
    """
    t = _time(lawrun)
    last = window(t, t[-1] - LAST_FRACTION * (t[-1] - t[0]))
    th = signal(lawrun, "theta_hat")
    err = norm(np.asarray(theta, dtype=float).reshape(-1, 1) - th)
    stats = getattr(lawrun, "stats", None) or {}
    wall = stats.get("wall_s")
    return {
        "t_end": float(t[-1]),
        "theta_hat": [float(v) for v in th[:, -1]],
        "theta_err_norm": float(err[-1]),
        "e_max_last20": float(np.max(norm(signal(lawrun, "e"))[last])),
        "tau_d_err_rms_last20": rms(t[last], norm(tau_d_error(lawrun))[last]),
        "wall_s": None if wall is None else float(wall),
    }


# --------------------------------------------------------------------------- conclusions
_STATEMENTS = {
    "C1": "Composite learning (eq. 35) keeps the parameter error θ̃ bounded, "
          "but θ̃ does not converge to zero.",
    "C2": "IV-DREM (eqs. 11 + 21) drives the parameter error θ̃ towards zero.",
    "C3": "IV-DREM estimates the external torque τ_d better than composite learning.",
    "C4": "The instrument ζ matters: DREM with the measured regressor φ in its place "
          "(no instrument) converges worse.",
}
_CRITERIA = {
    "C1": "over the last half, max and min of ‖θ̃‖ within 10 % of ‖θ̃(t_mid)‖, "
          "and ‖θ̃(t_end)‖ > 0.1 ‖θ̃(0)‖",
    "C2": "‖θ̃(t_end)‖ ≤ 0.1 ‖θ̃(0)‖, and max ‖θ̃‖ over the last quarter "
          "< max ‖θ̃‖ over the second quarter",
    "C3": "RMS ‖τ̃_d‖ over the last 20 % of the run: IV-DREM ≤ 0.5 × composite learning",
    "C4": "‖θ̃(t_end)‖ of DREM without instrument ≥ 2 × that of IV-DREM",
}


def _missing(cid: str, laws: list[str], runs: Mapping) -> dict:
    absent = [law for law in laws if law not in runs]
    return {
        "id": cid,
        "statement": _STATEMENTS[cid],
        "criterion": _CRITERIA[cid],
        "laws": laws,
        "measured": {},
        "threshold": {},
        "verdict": None,
        "note": "not evaluated: law(s) not run: " + ", ".join(absent),
    }


def _theta_norm(lawrun, theta):
    return _time(lawrun), norm(theta_error(lawrun, theta))


def _c1(lawrun, theta) -> dict:
    t, n = _theta_norm(lawrun, theta)
    t_mid = t[0] + 0.5 * (t[-1] - t[0])
    half = window(t, t_mid)
    i_mid = int(np.argmax(half))  # first sample at or after mid-run
    mid = float(n[i_mid])
    hi, lo = float(np.max(n[half])), float(np.min(n[half]))
    if mid > 0:
        dev = max(hi - mid, mid - lo) / mid
    else:
        dev = 0.0 if hi == 0 else float("inf")
    n0, nend = float(n[0]), float(n[-1])
    ratio = nend / n0 if n0 > 0 else float("inf") if nend > 0 else 0.0
    return {
        "measured": {
            "t_mid": float(t[i_mid]),
            "theta_err_norm_0": n0,
            "theta_err_norm_mid": mid,
            "theta_err_norm_max_last_half": hi,
            "theta_err_norm_min_last_half": lo,
            "max_rel_deviation_last_half": dev,
            "theta_err_norm_end": nend,
            "end_to_initial_ratio": ratio,
        },
        "threshold": {"max_rel_deviation_last_half": C1_REL_DEV, "end_to_initial_ratio_above": C1_END_RATIO},
        "verdict": bool(dev <= C1_REL_DEV and nend > C1_END_RATIO * n0),
    }


def _c2(lawrun, theta) -> dict:
    t, n = _theta_norm(lawrun, theta)
    t0, d = t[0], t[-1] - t[0]
    q2 = window(t, t0 + 0.25 * d, t0 + 0.5 * d)
    q4 = window(t, t0 + 0.75 * d)
    n0, nend = float(n[0]), float(n[-1])
    ratio = nend / n0 if n0 > 0 else float("inf") if nend > 0 else 0.0
    m2, m4 = float(np.max(n[q2])), float(np.max(n[q4]))
    return {
        "measured": {
            "theta_err_norm_0": n0,
            "theta_err_norm_end": nend,
            "end_to_initial_ratio": ratio,
            "theta_err_norm_max_second_quarter": m2,
            "theta_err_norm_max_last_quarter": m4,
        },
        "threshold": {"end_to_initial_ratio_at_most": C2_END_RATIO},
        "verdict": bool(nend <= C2_END_RATIO * n0 and m4 < m2),
    }


def _tau_rms_last(lawrun) -> tuple[float, float]:
    t = _time(lawrun)
    start = t[-1] - LAST_FRACTION * (t[-1] - t[0])
    w = window(t, start)
    return rms(t[w], norm(tau_d_error(lawrun))[w]), float(start)


def _c3(proposed, baseline) -> dict:
    r_iv, start = _tau_rms_last(proposed)
    r_cl, _ = _tau_rms_last(baseline)
    ratio = r_iv / r_cl if r_cl > 0 else (0.0 if r_iv == 0 else float("inf"))
    return {
        "measured": {
            "window_start": start,
            "tau_d_err_rms_last20_iv_drem": r_iv,
            "tau_d_err_rms_last20_composite_learning": r_cl,
            "ratio": ratio,
        },
        "threshold": {"ratio_at_most": C3_RMS_RATIO},
        "verdict": bool(r_iv <= C3_RMS_RATIO * r_cl),
    }


def _c4(proposed, plain, theta) -> dict:
    t_iv, n_iv = _theta_norm(proposed, theta)
    t_dr, n_dr = _theta_norm(plain, theta)
    tq = t_iv[0] + 0.25 * (t_iv[-1] - t_iv[0])
    iq_iv = int(np.searchsorted(t_iv, tq))
    iq_dr = int(np.searchsorted(t_dr, tq))
    end_iv, end_dr = float(n_iv[-1]), float(n_dr[-1])
    ratio = end_dr / end_iv if end_iv > 0 else (1.0 if end_dr == 0 else float("inf"))
    return {
        "measured": {
            "theta_err_norm_end_iv_drem": end_iv,
            "theta_err_norm_end_drem": end_dr,
            "ratio_end": ratio,
            "t_quarter": float(t_iv[min(iq_iv, t_iv.size - 1)]),
            "theta_err_norm_quarter_iv_drem": float(n_iv[min(iq_iv, n_iv.size - 1)]),
            "theta_err_norm_quarter_drem": float(n_dr[min(iq_dr, n_dr.size - 1)]),
        },
        "threshold": {"ratio_end_at_least": C4_RATIO},
        "verdict": bool(ratio >= C4_RATIO),
    }


def short_horizon_note(t_end, T, mixing, *, windowed=True):
    """The note of a run too short to judge the composite term, or "": the window (15a)
    is full at t = T, and the scale-free mixings start the term (21) there
    (:func:`ivdrem.blocks.mixing.start_of_term`), so a run ending by then (by the end of
    the start's ramp for those mixings) cannot show whether the law learns."""
    if not windowed:
        return ""
    from ..blocks.mixing import start_of_term
    t_on, t_ramp = start_of_term(mixing, T) if mixing is not None else (0.0, 0.0)
    if t_on > 0 and t_end <= t_on + t_ramp:
        return (f"not evaluated: the composite term starts at T = {T:g} s"
                f" (the run ends at t = {t_end:g} s)")
    if t_end <= T:
        return (f"not evaluated: the run ends at t = {t_end:g} s, before the window "
                f"T = {T:g} s is full")
    return ""



def gamma_choice_and_mixing(lawrun, iv_drem: Mapping):
    """(γ "auto"'s choice the run recorded, or None; the mixing its Δ came from: the
    choice's variant, else the configuration's [iv_drem] mixing)."""
    stats = getattr(lawrun, "stats", None) or {}
    choice = stats.get("gamma_choice") if isinstance(stats, Mapping) else None
    return choice, (choice or {}).get("variant") or iv_drem.get("mixing", "paper")


def law_horizon_note(lawrun, config) -> str:
    """:func:`short_horizon_note` of one law's run: the law's own window T (its
    configuration section's, as composite learning's (35), else [iv_drem]'s), the mixing its
    Δ came from (γ "auto"'s choice if the run made one), whether the law has a window at
    all.  The diagnostics' horizon checks and conclusions C1-C4 both read it."""
    from ..laws import LAWS as registry

    resp = getattr(lawrun, "response", lawrun)
    spec = registry.get(getattr(lawrun, "law", "?"))
    ivd = (config or {}).get("iv_drem") or {}
    if "T" not in ivd:
        return ""           # runs given without their configuration: no window known
    _, mixing = gamma_choice_and_mixing(lawrun, ivd)
    own = config.get(spec.section, {}) if spec is not None and spec.section else {}
    windowed = spec is not None and "T" in spec.defaults
    t_end = float(np.asarray(resp.time, dtype=float)[-1])
    has_delta = "Delta" in signal_names(resp)
    return short_horizon_note(t_end, float(own.get("T", ivd["T"])),
                              mixing if has_delta else None, windowed=windowed)


def conclusions(run) -> list[dict]:
    """Conclusions C1-C4 of a PaperRun with their numbers and verdicts."""
    runs = run.runs
    theta = np.asarray(run.theta, dtype=float)
    out = []
    for cid, laws, fn in (
        ("C1", [BASELINE], lambda: _c1(runs[BASELINE], theta)),
        ("C2", [PROPOSED], lambda: _c2(runs[PROPOSED], theta)),
        ("C3", [PROPOSED, BASELINE], lambda: _c3(runs[PROPOSED], runs[BASELINE])),
        ("C4", [PROPOSED, NO_INSTRUMENT], lambda: _c4(runs[PROPOSED], runs[NO_INSTRUMENT], theta)),
    ):
        if any(law not in runs for law in laws):
            out.append(_missing(cid, laws, runs))
            continue
        res = fn()
        # a run that ends before the composite term of one of its laws could act judges
        # nothing about learning: the numbers are kept, the verdict is not given
        short = next((note for note in (law_horizon_note(runs[law], run.config) for law in laws)
                      if note), "")
        out.append({
            "id": cid,
            "statement": _STATEMENTS[cid],
            "criterion": _CRITERIA[cid],
            "laws": laws,
            "measured": res["measured"],
            "threshold": res["threshold"],
            "verdict": None if short else res["verdict"],
            "note": short,
        })
    return out


def verdict_text(verdict: Any) -> str:
    """'PASS', 'FAIL' or 'not evaluated'."""
    return "not evaluated" if verdict is None else ("PASS" if verdict else "FAIL")


def key_numbers(c: Mapping) -> str:
    """One line with the decisive measured numbers of a conclusion."""
    m = c["measured"]
    if not m:
        return c.get("note", "")
    if c["id"] == "C1":
        return (f"max rel. deviation of ‖θ̃‖ over last half = {m['max_rel_deviation_last_half']:.3g} "
                f"(≤ {C1_REL_DEV:g}); ‖θ̃(t_end)‖/‖θ̃(0)‖ = {m['end_to_initial_ratio']:.3g} (> {C1_END_RATIO:g})")
    if c["id"] == "C2":
        return (f"‖θ̃(t_end)‖/‖θ̃(0)‖ = {m['end_to_initial_ratio']:.3g} (≤ {C2_END_RATIO:g}); "
                f"max ‖θ̃‖ last quarter = {m['theta_err_norm_max_last_quarter']:.3g} "
                f"vs second quarter = {m['theta_err_norm_max_second_quarter']:.3g}")
    if c["id"] == "C3":
        return (f"RMS ‖τ̃_d‖ last 20 %: IV-DREM {m['tau_d_err_rms_last20_iv_drem']:.3g} N·m, "
                f"composite learning {m['tau_d_err_rms_last20_composite_learning']:.3g} N·m, "
                f"ratio {m['ratio']:.3g} (≤ {C3_RMS_RATIO:g})")
    if c["id"] == "C4":
        return (f"‖θ̃(t_end)‖: DREM without IV {m['theta_err_norm_end_drem']:.3g}, IV-DREM "
                f"{m['theta_err_norm_end_iv_drem']:.3g}, ratio {m['ratio_end']:.3g} (≥ {C4_RATIO:g}); "
                f"at t = {m['t_quarter']:.3g} s: {m['theta_err_norm_quarter_drem']:.3g} vs "
                f"{m['theta_err_norm_quarter_iv_drem']:.3g}")
    return ", ".join(f"{k} = {v:.4g}" for k, v in m.items())


def format_conclusions(concl: list[dict]) -> str:
    """Plain-text table of conclusions, for terminals."""
    lines = []
    for c in concl:
        lines.append(f"{c['id']}  {verdict_text(c['verdict']):<13}  {c['statement']}")
        lines.append(f"    {key_numbers(c)}")
    return "\n".join(lines)
