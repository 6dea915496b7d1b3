"""gamma = "auto": the gain γ of the composite term (21) from the loop's own Δ.

The composite term (21) contracts the parameter error at the rate γΔ²(t)Γ: with
ϑ_c = γΔ(𝒴 − Δθ̂) = γΔ²θ̃ + γΔ𝒲 (17), the adaptation law (11) gives
dθ̃/dt = −ΓΠᵀr − γΔ²Γθ̃ − γΔΓ𝒲.  The size of Δ = det(Ψ/(1 + ‖Ψ‖)) depends on the robot,
its trajectory and nθ (a determinant of an nθ×nθ matrix of small entries): about 8e-5
for the paper's arm and 2.5e-9 for a 3-link arm, so one fixed γ cannot suit every robot.

Rule (documented in docs/diagnostics.md and docs/mixing.md): take the mean of Δ² over
[T, t_cal] (default t_cal = 2T: one window to fill the sliding window (15a), one to
measure), either estimated along the reference without simulating the loop
(:func:`reference_mean_delta2`; the default for the scale-free mixings) or measured by a
calibration run of the loop over [0, t_cal] with the composite term off (γ tiny; the
default for the paper's mixing), and choose

    γ = κ / (λ_max(Γ) · mean Δ²),       κ = 0.5 s⁻¹ (``rate``),

so that the composite term's contraction rate γΔ²λ_max(Γ) is κ at the calibration level
of Δ: a time constant of 2 s, slow against the loop (λ_min(K) + δ_μ μ) and the filters
(l = 50), fast against the horizon.  γ is then one constant for the whole run, so the law
is exactly (21) and Theorem 2 applies unchanged.  For the paper's arm the rule gives γ of
the order of the paper's 1e10.
"""
from __future__ import annotations

import hashlib
import json
import math

import numpy as np

__all__ = ["calibrate_gamma", "calibrated_loop", "gamma_from_delta", "GainRuleError",
           "DEFAULT_RATE", "GAMMA_MAX", "DELTA2_MIN", "reference_mean_delta2", "check_reference_delta",
           "ESTIMATE_MARGIN", "REFERENCE_MIXINGS"]

#: target contraction rate κ = γ Δ² λ_max(Γ) of the composite term, 1/s
DEFAULT_RATE = 0.5
#: γ of the calibration run: the composite term is off
_GAMMA_OFF = 1e-300
#: mixings whose γ "auto" comes from the reference estimate by default, without a
#: calibration run (scale-free: Δ near 1, measured within 0.02 decades of the run's)
REFERENCE_MIXINGS = ("eigen", "channel")
#: largest γ the rule hands out: γΔ(𝒴 − Δθ̂) must stay a finite double (docs/mixing.md)
GAMMA_MAX = 1e300
#: smallest mean Δ² the rule scales by: below it Δ² is subnormal (fewer than 53 bits), so
#: γΔ² is no longer the rate the rule aims at
DELTA2_MIN = float(np.finfo(float).tiny)
#: decades by which the reference estimate of mean Δ² must fall below DELTA2_MIN for the
#: rule to refuse before the calibration run (the estimate's error, measured on the planar
#: arms and the real arms, is far smaller: docs/mixing.md)
ESTIMATE_MARGIN = 20.0


class GainRuleError(ValueError):
    """gamma = "auto" refuses a mixing whose Δ underflows or a γ that would overflow."""


def _lambda_max(Gamma, ntheta):
    G = np.asarray(Gamma, dtype=float)
    if G.ndim == 0:
        return float(G)
    if G.ndim == 1:
        return float(np.max(G))
    return float(np.max(np.linalg.eigvalsh(0.5 * (G + G.T))))


def _remedy(variant):
    """The mixing to use instead of one the rule refuses (docs/mixing.md)."""
    if variant == "eigen":
        return ("use mixing = \"channel\" (one Δ_i per parameter, docs/mixing.md) or a "
                "larger f_rel")
    return "use mixing = \"eigen\" (Δ = ∏ σ_j/(σ_j + f₀), near 1 at any size; docs/mixing.md)"


def _log10_mean_square(t, log10_abs):
    """log10 of the time mean of 10^(2 L) (trapezoid), finite where 10^(2 L) underflows."""
    a = 2.0 * np.asarray(log10_abs, dtype=float)
    top = float(np.max(a))
    if not np.isfinite(top):
        return -math.inf
    mean = float(np.trapezoid(10.0 ** (a - top), t) / (t[-1] - t[0]))
    return top + math.log10(mean) if mean > 0 else -math.inf


def gamma_from_delta(t, delta, T, Gamma, *, rate=DEFAULT_RATE, ntheta=None,
                     delta_log10=None, variant="paper", model_name=None):
    """γ = rate / (λ_max(Γ) · mean Δ² over [T, t_end]) of a recorded Δ(t); with the numbers.

    ``delta`` is one row (Δ of the "paper" and "eigen" mixings) or one row per channel
    ("channel": then γ is a vector, γ_i from the mean of Δ_i²).  ``delta_log10``
    (log10 |Δ|, the mixing's output Delta_log10) lets the rule measure a Δ² below the
    smallest double.  Raises :class:`GainRuleError`, naming the variant, the model and the
    number, when mean Δ² is subnormal or γ would exceed GAMMA_MAX, and ValueError when Δ is
    identically zero (no excitation to scale by).
    """
    t = np.asarray(t, dtype=float)
    d = np.atleast_2d(np.asarray(delta, dtype=float))
    logd = None if delta_log10 is None else np.atleast_2d(np.asarray(delta_log10, dtype=float))
    t_from = T if t[-1] > T else 0.5 * t[-1]
    sel = t >= t_from
    if np.count_nonzero(sel) < 2:
        raise ValueError("gamma='auto': calibration run too short to measure Δ")
    lam = _lambda_max(Gamma, ntheta)
    means, logs = [], []
    for k in range(d.shape[0]):
        d2 = d[k, sel] ** 2
        mean_d2 = float(np.trapezoid(d2, t[sel]) / (t[sel][-1] - t[sel][0]))
        if logd is not None and np.all(np.isfinite(logd[k, sel])):
            log_mean = _log10_mean_square(t[sel], logd[k, sel])
        else:
            log_mean = math.log10(mean_d2) if mean_d2 > 0 else -math.inf
        means.append(mean_d2)
        logs.append(log_mean)
    return _gain_rule(means, logs, lam, rate=rate, variant=variant, model_name=model_name,
                      window=[float(t[sel][0]), float(t[sel][-1])], measured="calibration run")


def _gain_rule(means, logs, lam, *, rate, variant, model_name, window, measured):
    """γ_i = rate / (lam · mean Δ_i²) of the mean Δ_i² (`means`, and their log10 `logs`,
    finite where the mean underflows), with the rule's refusals; the choice as a dict.
    `measured` names where the means come from, in an error."""
    where = f"mixing {variant!r}" + (f" on model {model_name!r}" if model_name else "")
    per_channel = len(means) > 1
    gammas = []
    for k, (mean_d2, log_mean) in enumerate(zip(means, logs)):
        chan = f"Δ_{k + 1}" if per_channel else "Δ"
        if not np.isfinite(mean_d2) or (mean_d2 <= 0.0 and log_mean == -math.inf) \
                or log_mean < -600.0:
            raise ValueError(
                f"gamma='auto' ({where}): {chan} is zero over the {measured} (the regressor "
                "of (17) is not excited by this trajectory); choose another trajectory or a "
                "numeric gamma")
        if mean_d2 < DELTA2_MIN:
            raise GainRuleError(
                f"gamma='auto' refused for {where}: mean {chan}² over the {measured} is "
                f"1e{log_mean:.1f}, below the smallest double ({DELTA2_MIN:.3g}), so the "
                f"composite term (21) cannot be formed; {_remedy(variant)}")
        log_gamma = math.log10(rate) - math.log10(lam) - log_mean
        if log_gamma > math.log10(GAMMA_MAX):
            raise GainRuleError(
                f"gamma='auto' refused for {where}: the rule would give γ = 1e{log_gamma:.1f}"
                f" (mean {chan}² = 1e{log_mean:.1f}), above {GAMMA_MAX:.0e}; {_remedy(variant)}")
        gammas.append(rate / (lam * mean_d2))
    out = {"gamma": [float(g) for g in gammas] if per_channel else float(gammas[0]),
           "rule": (f"gamma_i = {rate:g} / (lambda_max(Gamma) * mean Delta_i^2)" if per_channel
                    else f"gamma = {rate:g} / (lambda_max(Gamma) * mean Delta^2)"),
           "rate": float(rate),
           "mean_Delta2": [float(m) for m in means] if per_channel else float(means[0]),
           "log10_mean_Delta2": [float(v) for v in logs] if per_channel else float(logs[0]),
           "lambda_max_Gamma": lam, "variant": variant, "window": window}
    return out


def _reference_samples(trajectory, n, t):
    """(q_d, dq_d, ddq_d) of the loop's reference at the times t, each (len(t), n), from
    the trajectory block's own output (built from the sinusoid's parameters if given so)."""
    if isinstance(trajectory, dict):
        from ..blocks import trajectory as trajectory_block
        trajectory = trajectory_block(n, **trajectory)
    spec = getattr(trajectory, "ivdrem", None)
    y = np.empty((t.size, 3 * n))
    if spec is not None and spec.nstates == 0 and spec.ninputs == 0:
        from ..blocks._core import flat_kernel, kernel_args
        out = flat_kernel(spec, "output")        # the block's own kernel, without
        args = kernel_args(spec, trajectory.params)  # python-control's per-call overhead
        for k, tk in enumerate(t):
            out(float(tk), np.zeros(0), np.zeros(0), y[k], *args)
    else:
        for k, tk in enumerate(t):
            y[k] = np.asarray(trajectory.output(tk, np.zeros(trajectory.nstates),
                                                np.zeros(trajectory.ninputs)), float)
    return y[:, :n], y[:, n:2 * n], y[:, 2 * n:3 * n]


def reference_mean_delta2(model, trajectory, *, T, p, F0, l, variant, t_cal=None):
    """log10 of mean Δ_i² over [T, t_cal] (default 2T), one per channel for "channel",
    estimated without simulating the loop: Ψ of (15a)-(15b) built from the instrument ζ of
    (14) alone, with φ ≈ ζ (the loop tracks the reference, and φ is the same filter (13)
    of the regressor along the measured motion), then the mixing (17) of that Ψ.

    ζ is filtered exactly for a regressor held over each sample (dt ≤ 1/(4l)); the window
    and the averaging are integrated by the trapezoid rule on a 0.1 s grid.  A few thousand
    regressor evaluations and a few hundred SVDs: seconds at nθ = 43, against minutes for
    the calibration run.
    """
    from ..blocks._kernels import MIXING_VARIANTS, mixing_values
    from ..blocks.mixing import DEFAULT_F_REL, DEFAULT_GUARD, delta_size

    n, nth = model.n, model.ntheta
    t_cal = 2.0 * T if t_cal is None else float(t_cal)
    dt_c = min(0.1, T / 20.0)                  # grid of the window and the averaging
    sub = max(1, int(math.ceil(dt_c * 4.0 * l)))
    dt = dt_c / sub
    nc = int(round(t_cal / dt_c))
    t = np.arange(nc * sub + 1) * dt
    qd, dqd, ddqd = _reference_samples(trajectory, n, t)
    a = math.exp(-l * dt)
    zeta = np.zeros((n, nth))                 # ζᵀ of (14), zero at t = 0
    phi = np.empty((n, nth))
    G_prev = np.zeros((nth, nth))
    C = np.zeros((nc + 1, nth, nth))          # ∫_0^t ζ ζᵀ ds on the coarse grid
    acc = np.zeros((nth, nth))
    for k in range(1, t.size):
        model.functions.Phi(qd[k - 1], dqd[k - 1], dqd[k - 1], ddqd[k - 1], phi)
        zeta = a * zeta + (1.0 - a) * phi
        G = zeta.T @ zeta
        acc += 0.5 * dt * (G + G_prev)
        G_prev = G
        if k % sub == 0:
            C[k // sub] = acc
    tc = np.arange(nc + 1) * dt_c
    lag = int(round(T / dt_c))
    W = C.copy()
    W[lag:] -= C[:nc + 1 - lag]                # window (15a): ∫_{t-T}^t
    F = tc ** p + F0
    dF = p * tc ** (p - 1.0)
    I = np.zeros_like(W)                       # (15b): Ψ(t) = (1/F) ∫_0^t Ḟ W ds
    I[1:] = np.cumsum(0.5 * dt_c * (dF[1:, None, None] * W[1:] + dF[:-1, None, None] * W[:-1]),
                      axis=0)
    code = MIXING_VARIANTS.index(variant)
    k_out = delta_size(nth, variant)
    Delta, calY, logD = np.empty(k_out), np.empty(nth), np.empty(k_out)
    sel = np.nonzero(tc >= T)[0]
    logs = np.empty((k_out, sel.size))
    for j, c in enumerate(sel):
        Psi = I[c] / F[c]
        mixing_values(code, np.zeros(nth), Psi.ravel(), DEFAULT_F_REL, DEFAULT_GUARD,
                      Delta, calY, logD)
        logs[:, j] = logD
    return [_log10_mean_square(tc[sel], logs[i]) for i in range(k_out)]


def check_reference_delta(law, model, args, *, variant, margin=ESTIMATE_MARGIN, t_cal=None):
    """Refuse, before any simulation, a mixing whose Δ² the reference estimate
    (:func:`reference_mean_delta2`) puts more than `margin` decades below the smallest
    double; returns the estimate (log10 mean Δ_i², a list) otherwise."""
    from .. import laws as law_registry

    spec = law_registry.get_law(law)
    args = _flat(args)
    par = law_registry.resolve_params(spec, {k: args.get(k) for k in ("T", "p", "F0")})
    trajectory = args.get("trajectory")
    if trajectory is None:
        from .._default_config import paper_experiment
        trajectory = paper_experiment()["trajectory"]     # the paper's arm
    # t_cal keyed as the horizon it stands for (2T when not given): the preflight's check
    # (no t_cal) and calibrate_gamma's (t_cal = 2T) are the same estimate, computed once
    T = float(par["T"])
    numbers = dict(T=T, p=float(par["p"]), F0=float(par["F0"]),
                   l=float(args.get("l") or 50.0), variant=variant,
                   t_cal=2.0 * T if t_cal is None else float(t_cal))
    path = _estimate_path(model, trajectory, numbers)
    est = _read_estimate(path)
    if est is None:
        # the run this estimate is for needs the mixing's derivatives (its Jacobian kernel):
        # a child compiles them meanwhile (about 8 s of numba on a first run, docs/
        # performance.md), while this process compiles the mixing step the estimate calls
        from ..blocks._kernels import MIXING_VARIANTS
        from ..sim._compile_child import start_helpers
        start_helpers([("mixing_derivatives", MIXING_VARIANTS.index(variant))])
        est = [float(v) for v in reference_mean_delta2(model, trajectory, **numbers)]
        _write_estimate(path, est)
    worst = min(est)
    if worst < math.log10(DELTA2_MIN) - margin:
        where = f"mixing {variant!r}" + (f" on model {getattr(model, 'name', '?')!r}")
        raise GainRuleError(
            f"gamma='auto' refused for {where} (nθ = {model.ntheta}) before its calibration "
            f"run: mean Δ² over [T, 2T] estimated along the reference trajectory is "
            f"1e{worst:.1f}, below the smallest double ({DELTA2_MIN:.3g}), so the composite "
            f"term (21) cannot be formed; {_remedy(variant)}")
    return est


#: reference estimates made in this process, by their key (the preflight's check and the
#: run's γ "auto" ask for the same one)
_ESTIMATES: dict = {}


def _trajectory_key(trajectory):
    """What the estimate reads of the reference, as text: the sinusoid's parameters, or an
    ivdrem source block's output kernel and the arguments it is called with; None for any
    other block (its estimate is not kept)."""
    if isinstance(trajectory, dict):
        return json.dumps({k: np.asarray(v, float).tolist() for k, v in trajectory.items()},
                          sort_keys=True)
    spec = getattr(trajectory, "ivdrem", None)
    if spec is None or spec.nstates != 0 or spec.ninputs != 0 or spec.output is None:
        return None
    from ..blocks._core import kernel_args
    h = hashlib.sha256(f"{spec.output.__module__}.{spec.output.__qualname__}".encode())
    for a in kernel_args(spec, trajectory.params):
        a = np.asarray(a)
        h.update(f"{a.dtype} {a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _estimate_path(model, trajectory, numbers):
    """Where the reference estimate of (`model`, `trajectory`, `numbers`) is kept across
    processes (a repeat of a command, the run after its preflight), named by ivdrem's
    source, the model's code, the reference and the numbers; None when one of them has no
    stable name (the estimate is then computed each time)."""
    from ..compile_cache import cache_dir, package_digest
    key = getattr(model, "key", None)
    key = key() if callable(key) else key
    traj = _trajectory_key(trajectory)
    digest = package_digest()
    if not isinstance(key, str) or traj is None or digest is None:
        return None
    text = f"{digest} {key} {model.n} {model.ntheta} {traj} {json.dumps(numbers, sort_keys=True)}"
    name = hashlib.sha256(text.encode()).hexdigest()[:40]
    return cache_dir() / "estimates" / f"{name}.json"


def _read_estimate(path):
    if path is None:
        return None
    if path in _ESTIMATES:
        return list(_ESTIMATES[path])
    try:
        out = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not (isinstance(out, list) and out and all(isinstance(v, float) for v in out)):
        return None
    _ESTIMATES[path] = out
    return list(out)


def _write_estimate(path, est):
    if path is None:
        return
    _ESTIMATES[path] = [float(v) for v in est]
    from .._atomic import write_text_atomic
    try:
        write_text_atomic(path, json.dumps(_ESTIMATES[path], allow_nan=True))
    except (OSError, TypeError, ValueError):
        pass


def _flat(args):
    """The loop's arguments and the law's gains in one mapping by name (a ``gains`` entry,
    as :func:`ivdrem.diagrams.closed_loop` takes them, merged in)."""
    args = dict(args)
    args.update(args.pop("gains", None) or {})
    return args


def _calibration_loop(law, model, args):
    """The loop of the calibration run: `law`'s closed loop with γ a placeholder (the run
    sets it to _GAMMA_OFF) and ivdrem's own plant of the model, also for a controller built
    for an external plant (an FMU of the same model)."""
    from ..laws import LAWS, get_law
    from .closed_loop import closed_loop
    declared = get_law(law).defaults
    # a gain of another law (a sampled controller's epsilon given to iv-drem) does not
    # apply here; None is the default
    others = {k for spec in LAWS.values() for k in spec.defaults} - set(declared)
    args = {k: v for k, v in args.items() if v is not None and k not in others}
    gains = {k: v for k, v in args.items() if k in declared}
    gains["gamma"] = 1.0
    loop = {k: v for k, v in args.items() if k not in declared}
    return closed_loop(law, model, gains=gains, **{**loop, "external_plant": False})


def calibrated_loop(law="iv-drem", model=None, *, gains=None, calibration=None, **loop):
    """:func:`ivdrem.diagrams.closed_loop` with a γ "auto" chosen first: the gains and the
    loop resolved as closed_loop resolves them (the real-arm experiment designed, the arm's
    gain rule applied), γ from :func:`calibrate_gamma` on them (``calibration``: its keyword
    arguments), then the loop built with that number; the choice is
    ``diagram.gamma_choice``.  A γ that is a number builds the plain closed_loop."""
    from .closed_loop import build_resolved, resolve_loop
    spec, model, gains, loop = resolve_loop(law, model, gains=gains, **loop)
    choice = None
    if gains.get("gamma") == "auto":
        choice = calibrate_gamma(law, model, {**loop, **gains}, **(calibration or {}))
        gains["gamma"] = choice["gamma"]
    diagram = build_resolved(spec, model, gains, **loop)
    if choice is not None:
        diagram.gamma_choice = choice
    return diagram


def _scalar_output(resp, name):
    """The scalar output `name` of a calibration run over time (by its label)."""
    y = np.asarray(resp.outputs, dtype=float).reshape(-1, np.asarray(resp.time).size)
    return y[list(resp.output_labels).index(name)].copy()


def calibrate_gamma(law, model, args, *, t_cal=None, rate=DEFAULT_RATE, passes=1,
                    engine="compiled", method="dp45", rtol=None, atol=None, h=1e-3,
                    h_max=0.01, dt_out=0.01, source=None):
    """The γ of the rule above for ``law`` on ``model``, with the numbers it came from
    (``args``: the loop's arguments and the law's gains, as :func:`calibrated_loop` resolves
    them);
    mean Δ² over [T, t_cal] (default 2T) from ``source``:

    * ``"reference"``: the estimate along the reference (:func:`reference_mean_delta2`), no
      loop built or simulated (seconds at nθ = 43);
    * ``"run"``: a calibration run of the closed loop over [0, t_cal] (kept on disk).

    The default is ``"reference"`` for the scale-free mixings (REFERENCE_MIXINGS: "eigen",
    "channel"), whose estimate is within 0.02 decades of the calibration run's mean Δ² on
    planar-3 … 6, the UR5 and the Panda (γ within 5 %; docs/mixing.md), and ``"run"`` for
    the paper's mixing (17), whose Δ is a product of nθ singular values and moves by up to
    1.6 decades between φ = ζ and the loop's φ.

    The calibration run is with the composite term off.  Δ depends on the motion (φ is
    built from the measured q), and the motion on θ̂, so the Δ of the real run can differ:
    on the 3-link arm of examples/planar3.toml RMS Δ over [T, 2T] was 3.3e-10 with the
    term off and 4.9e-8 with it on, which makes that run stiff early on.  ``passes=2``
    reruns the calibration at pass 1's γ and rescales by the Δ it measures; measured on the
    same arm it removes the stiffness but the smaller γ then learns too little
    (‖θ̃(120 s)‖ = 2.91 against 0.295 with one pass), so one pass is the default.
    """
    from ..sim import simulate

    args = _flat(args)
    T = float(args.get("T") or 20.0)
    t_cal = 2.0 * T if t_cal is None else float(t_cal)
    if not t_cal > 0:
        raise ValueError(f"gamma='auto': calibration horizon must be > 0, got {t_cal}")
    if passes not in (1, 2):
        raise ValueError(f"gamma='auto': passes must be 1 or 2, got {passes!r}")
    variant = args.get("mixing") or "paper"
    if source is None:
        source = "reference" if variant in REFERENCE_MIXINGS else "run"
    if source not in ("reference", "run"):
        raise ValueError(f"gamma='auto': source must be 'reference' or 'run', got {source!r}")
    estimate = check_reference_delta(law, model, args, variant=variant,
                                     t_cal=t_cal if source == "reference" else None)
    if source == "reference":
        out = _gain_rule([10.0 ** v for v in estimate], list(estimate),
                         _lambda_max(args.get("Gamma", 0.01), model.ntheta), rate=rate,
                         variant=variant, model_name=getattr(model, "name", None),
                         window=[T, t_cal], measured="reference estimate")
        out.update(source="reference", t_cal=t_cal, passes=[],
                   reference_log10_mean_Delta2=estimate if len(estimate) > 1 else estimate[0])
        return out
    # the calibration needs the motion: the whole loop with ivdrem's own plant of the model,
    # also for a controller built for an external plant (an FMU of the same model)
    diagram = _calibration_loop(law, model, args)
    settings = dict(law=law, t_cal=t_cal, rate=float(rate), passes=passes, engine=engine,
                    method=method, rtol=rtol, atol=atol, h=h, h_max=h_max, dt_out=dt_out,
                    T=T, Gamma=np.asarray(args.get("Gamma", 0.01), dtype=float).tolist(),
                    variant=variant, model=getattr(model, "name", None))
    path = _calibration_path(diagram, settings)
    kept = _read_calibration(path)
    if kept is not None:
        return kept
    gamma, history = _GAMMA_OFF, []
    for k in range(passes):
        resp = simulate(diagram, t_cal, engine=engine, method=method, rtol=rtol, atol=atol,
                        h=h, h_max=h_max, dt_out=dt_out, params={"gamma": gamma},
                        progress=False, return_states=False)
        out = gamma_from_delta(resp.time, _scalar_output(resp, "Delta"), T,
                               args.get("Gamma", 0.01), rate=rate,
                               delta_log10=_scalar_output(resp, "Delta_log10"),
                               variant=variant, model_name=getattr(model, "name", None))
        history.append({"gamma_run": gamma if isinstance(gamma, float) else list(gamma),
                        "mean_Delta2": out["mean_Delta2"], "gamma": out["gamma"]})
        gamma = out["gamma"]
    out["source"] = "run"
    out["t_cal"] = t_cal
    out["passes"] = history
    out["reference_log10_mean_Delta2"] = estimate if len(estimate) > 1 else estimate[0]
    _write_calibration(path, out)
    return out


def _calibration_path(diagram, settings):
    """Where the calibration of `diagram` with `settings` is kept across processes (a
    repeated run, the report after the run, a study point that does not change the loop),
    named by the run digest of its plan (ivdrem's source, kernels, model, parameter values,
    initial state) and the settings; None for a loop with blocks ivdrem did not write."""
    from ..compile_cache import cache_dir
    from ..sim.jacobian import run_digest
    from ..sim.plan import DiagramPlan
    digest = run_digest(DiagramPlan.from_diagram(diagram, params={"gamma": _GAMMA_OFF}))
    if digest is None:
        return None
    key = hashlib.sha256(f"{digest} {json.dumps(settings, sort_keys=True)}".encode())
    return cache_dir() / "calibrations" / f"{key.hexdigest()[:40]}.json"


def _read_calibration(path):
    if path is None:
        return None
    try:
        out = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return out if isinstance(out, dict) and "gamma" in out else None


def _write_calibration(path, out):
    from .._atomic import write_text_atomic
    if path is None:
        return
    try:
        write_text_atomic(path, json.dumps(out, allow_nan=True))
    except (OSError, TypeError, ValueError):
        pass
