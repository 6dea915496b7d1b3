"""The text content of a report (tables), shared by the HTML and PDF writers."""
from __future__ import annotations

import datetime as _dt
import math
import platform
import re
import subprocess
import sys
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..experiments import metrics
from ..experiments.diagnostics import measured_label

__all__ = ["Table", "ReportContent", "build_content", "versions", "git_commit", "fmt", "pow10"]


def pow10(exponent: float, digits: int = 2) -> str:
    """10**exponent written as a number, "5.0e-09", for any exponent (a decimal logarithm
    far below the doubles' range too: "5.0e-400"); never a fractional exponent ("1e-8.3"
    is no number)."""
    e = math.floor(exponent)
    mantissa = 10.0 ** (exponent - e)
    if round(mantissa, digits - 1) >= 10.0:
        mantissa, e = mantissa / 10.0, e + 1
    return f"{mantissa:.{digits - 1}f}e{e:+03d}"


@dataclass
class Table:
    """A table of the report (HTML and PDF): its id, title, header, rows, relative column
    widths, a note under it and the column holding PASS / FAIL verdicts, if any."""
    key: str  # html id
    title: str
    header: list[str]
    rows: list[list[str]]
    widths: list[float]  # relative column widths (PDF)
    note: str = ""
    verdict_col: int | None = None  # column holding PASS/FAIL (coloured)


@dataclass
class ReportContent:
    """Everything a report shows except its figures: title page, conclusions, tables and
    the configuration as TOML; written by both the HTML and the PDF writer."""
    title: str
    subtitle: str
    meta: list[tuple[str, str]]  # (label, value) lines of the title page
    conclusions: list[dict]
    tables: list[Table] = field(default_factory=list)
    config_toml: str = ""
    synthetic: bool = False


# --------------------------------------------------------------------------- formatting
def fmt(v: Any) -> str:
    """Compact text of a number, vector or string."""
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        x = float(v)
        if x == 0:
            return "0"
        if not np.isfinite(x):
            return str(x)
        a = abs(x)
        if 1e-3 <= a < 1e5:
            s = f"{x:.6g}"
        else:
            s = f"{x:.4g}"
        return s
    if isinstance(v, str):
        return v
    if isinstance(v, Mapping):
        return ", ".join(f"{k} = {fmt(x)}" for k, x in v.items())
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(fmt(x) for x in v) + "]"
    return str(v)


# --------------------------------------------------------------------------- environment
_PACKAGES = ["numpy", "scipy", "control", "numba", "sympy", "matplotlib"]


def versions() -> list[tuple[str, str]]:
    """(name, version) of python, the libraries the results depend on, and ivdrem."""
    from .. import __version__

    out = [("python", platform.python_version())]
    for name in _PACKAGES:
        try:
            out.append((name, metadata.version(name)))
        except metadata.PackageNotFoundError:
            mod = sys.modules.get(name)
            out.append((name, getattr(mod, "__version__", "not installed")))
    out.append(("ivdrem", __version__))
    return out


def git_commit() -> str:
    """``git rev-parse HEAD`` of the checkout holding this ivdrem, else "unknown".

    " (modified)" is appended when tracked files differ from that commit.
    """
    pkg = Path(__file__).resolve().parents[1]
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=pkg, capture_output=True,
                             text=True, timeout=10)
        if top.returncode != 0 or not (Path(top.stdout.strip()) / "ivdrem" / "__init__.py").exists():
            return "unknown"
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=pkg, capture_output=True, text=True,
                              timeout=10)
        if head.returncode != 0:
            return "unknown"
        commit = head.stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=pkg,
                               capture_output=True, text=True, timeout=10)
        if dirty.returncode == 0 and dirty.stdout.strip():
            commit += " (modified)"
        return commit
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# --------------------------------------------------------------------------- tables
def _errata(cfg: Mapping, laws: list[str]) -> Table:
    ctl, ivd = cfg["controller"], cfg["iv_drem"]
    uses_iv = any(law in laws for law in ("iv-drem", "drem", "sigma-modification", "none"))
    sm = cfg["sigma_modification"]
    obs = ctl["observer_variant"]
    rows = [
        ["E1", "The paper filters Φ_Mf with gain μ, but its proof needs ẋ_f = (μ + μ̇/μ)(x − x_f).",
         f"observer_variant = \"{obs}\": "
         + ("gain μ + μ̇/μ (corrected)." if obs == "corrected" else "gain μ (literal paper).")],
        ["E2", "Section 4 writes the filters as 1/(ls + 1); with l = 50 that breaks z = φᵀθ + w.",
         f"Read as H(s) = l/(s + l), the filter of eq. (13), with l = {fmt(cfg['filters']['l'])}."],
        ["E3", "F₀ ≥ t₀ᵖ with t₀ = 0 allows F₀ = 0, which makes Ḟ/F singular at t₀.",
         f"F₀ > 0 required; F₀ = {fmt(ivd['F0'])}, p = {fmt(ivd['p'])}"
         + ("." if uses_iv else " (no law of this run uses it).")],
        ["E4", "Multiplying (16) by adj(Ψ_n) yields Δθ only if Y is divided by the same 1 + ‖Ψ‖.",
         "Ψ_n = Ψ/s, 𝒴 = adj(Ψ_n) Y/s with s = 1 + ‖Ψ‖_F; adjugate, never an inverse."],
        ["E5", "The σ-modification example ϑ_c = σ(θ̂ − θ*) drives θ̂ away from θ*.",
         f"Leakage form ϑ_c = σ(θ* − θ̂), σ = {fmt(sm['sigma'])}, θ* = {fmt(sm['theta_star'])}"
         + ("." if "sigma-modification" in laws else " (law not run).")],
        ["–", "Unstated in the paper.",
         f"θ̂(0) = {fmt(cfg['initial']['theta_hat0'])}, q̇(0) = {fmt(cfg['initial']['dq0'])}, "
         f"Frobenius norm in the mixing, horizon t_end = {fmt(cfg['experiment']['t_end'])} s."],
        ["–", "The paper's Πᵀr in eqs. (11) and (35) is a typo.", "Π r (an nθ-vector) is used."],
    ]
    return Table("errata", "Errata and choices (docs/conventions.md)", ["", "issue in the paper", "what this run uses"],
                 rows, [0.06, 0.47, 0.47])


def _parameters(cfg: Mapping) -> Table:
    rows = []
    for section, table in cfg.items():
        for key, value in table.items():
            rows.append([f"[{section}]", key, fmt(value)])
    return Table("parameters", "Parameters of this run (configuration)", ["section", "key", "value"],
                 rows, [0.25, 0.2, 0.55],
                 note="Vectors are per joint (n entries) or per parameter (nθ entries). "
                      "The full TOML is in the HTML report.")


def _where_it_enters(model) -> list[str]:
    """For each parameter θ_j, the entries of M, G and F it enters (∂/∂θ_j ≠ 0), from the
    model's symbolic matrices: what a parameter groups when the model has no table."""
    out = []
    mats = [("M", getattr(model, "M", None)), ("G", getattr(model, "G", None)),
            ("F", getattr(model, "F", None))]
    if not hasattr(model, "theta") or not all(hasattr(m, "has") for _, m in mats if m is not None):
        return ["–"] * model.ntheta           # no symbolic matrices to read
    for th in model.theta:
        where = []
        for label, mat in mats:
            if mat is None:
                continue
            for i in range(mat.rows):
                for j in range(mat.cols):
                    if label == "M" and j < i:
                        continue                     # symmetric
                    if mat[i, j].has(th):
                        where.append(f"{label}{i + 1}{j + 1}" if label == "M" else f"{label}{i + 1}")
        out.append(", ".join(where) or "–")
    return out


def _terms(terms) -> str:
    """A group as text: names, or (coefficient, name) pairs, as a signed sum
    ("Izz1 + Ixx2 − Izz2", "mx3 + 0.0825 m4"); coefficients ±1 to 1e-9 are left out."""
    out = []
    for t in terms:
        if isinstance(t, (tuple, list)) and len(t) == 2 and not isinstance(t[0], str):
            c, name = float(t[0]), str(t[1])
            sign, c = ("−" if c < 0 else "+"), abs(c)
            text = name if abs(c - 1.0) < 1e-9 else f"{c:.4g} {name}"
        else:
            sign, text = "+", str(t)
        out.append((sign, text))
    if not out:
        return "–"
    first = ("−" if out[0][0] == "−" else "") + out[0][1]
    return " ".join([first] + [f"{sg} {tx}" for sg, tx in out[1:]])


def _groups(model, count, max_terms=6) -> list[str] | None:
    """What each parameter groups, from the model's ``parameter_table()`` (rows whose first
    entry is the name and last the standard parameters: a text, or a list of names or of
    (coefficient, name)); None if the model has none.  Long groups are cut after
    `max_terms` terms (the table stays small)."""
    table = getattr(model, "parameter_table", None)
    table = table() if callable(table) else table
    if table is None:
        return None
    out = []
    for row in (table.items() if isinstance(table, Mapping) else table):
        g = row[-1]
        if isinstance(g, str):
            out.append(g)
            continue
        g = list(g)
        more = len(g) - max_terms
        out.append(_terms(g[:max_terms]) + (f" + … ({more} more)" if more > 0 else ""))
    return out if len(out) == count else None


def _model_table(run) -> Table | None:
    """The model's parameters: name, what it groups, true value (small: one row each)."""
    from ..experiments.config import model_label
    model = getattr(run, "model", None)
    if model is None:
        try:
            from ..experiments.config import model_from_config
            model = model_from_config(run.config)
        except Exception:        # a synthetic run's made-up model: no table
            return None
    names = list(getattr(model, "parameter_names", None) or getattr(model, "theta_names", None)
                 or [f"theta{j + 1}" for j in range(model.ntheta)])
    groups = _groups(model, len(names))
    what = "standard parameters it groups"
    if groups is None:
        groups = _where_it_enters(model)
        what = "entries of M, G, F it enters"
    theta = np.asarray(run.theta, dtype=float)
    names = [re.sub(r"^theta(\d+)$", r"θ\1", n) for n in names]    # the paper's θ1 ... θ5
    rows = [[str(j + 1), names[j], groups[j], fmt(float(theta[j])) if j < theta.size else "–"]
            for j in range(len(names))]
    return Table("model", f"Model {model_label(run.config)}: n = {model.n}, nθ = {model.ntheta}",
                 ["", "parameter", what, "true value"], rows, [0.06, 0.18, 0.58, 0.18],
                 note="θ of the paper's Property 1: M(q)v̇ + C(q, q̇)v + F(q̇) + G(q) = "
                      "Φᵀ(q, q̇, v, v̇)θ.")


#: (stats key, column header) of the solver table; integration and compile/load apart
_STATS = [("method", "method"), ("steps", "steps"), ("rejected", "rejected"),
          ("rhs_calls", "rhs calls"), ("sim_s", "integration (s)"),
          ("compile_s", "compile + load (s)"), ("rtol", "rtol"), ("atol", "atol"), ("h", "h")]


def _solver(run) -> Table:
    rows = []
    for law, lr in run.runs.items():
        st = dict(getattr(lr, "stats", None) or {})
        if "sim_s" not in st:          # a run that reports only its wall time
            st["sim_s"] = st.get("wall_s")
        rows.append([law] + [fmt(st.get(k)) for k, _ in _STATS])
    return Table("solver", "Solver statistics per law", ["law"] + [h for _, h in _STATS],
                 rows, [0.18, 0.08, 0.08, 0.09, 0.09, 0.11, 0.11, 0.09, 0.09, 0.08],
                 note="integration: the time the stepper ran; compile + load: generating, "
                      "compiling (first run only, then cached) and loading the engine.")


def _summary(run) -> Table:
    theta = np.asarray(run.theta, dtype=float)
    rows = []
    for law, lr in run.runs.items():
        s = metrics.summary(lr, theta)
        rows.append([law, fmt(s["t_end"]), fmt(s["theta_err_norm"]), fmt(s["e_max_last20"]),
                     fmt(s["tau_d_err_rms_last20"]), fmt(s["theta_hat"])])
    return Table("summary", "Final values per law",
                 ["law", "t_end (s)", "‖θ̃(t_end)‖", "max ‖e‖, last 20 % (rad)", "RMS ‖τ̃_d‖, last 20 % (N·m)", "θ̂(t_end)"],
                 rows, [0.19, 0.07, 0.13, 0.14, 0.16, 0.31],
                 note=f"True θ = {fmt(list(theta))}.")


def _fmu(fmu_check: Any) -> Table:
    """A table from a dict of numbers, a dict of dicts (rows), or a list of dicts."""
    if isinstance(fmu_check, Mapping) and fmu_check and all(isinstance(v, Mapping) for v in fmu_check.values()):
        cols: list[str] = []
        for row in fmu_check.values():
            cols += [c for c in row if c not in cols]
        rows = [[str(name)] + [fmt(row.get(c)) for c in cols] for name, row in fmu_check.items()]
        header = [""] + cols
    elif isinstance(fmu_check, Mapping):
        header = ["quantity", "value"]
        rows = [[str(k), fmt(v)] for k, v in fmu_check.items()]
    else:
        items = list(fmu_check)
        cols = []
        for row in items:
            cols += [c for c in row if c not in cols]
        header = cols
        rows = [[fmt(row.get(c)) for c in cols] for row in items]
    ncol = max(len(header), 1)
    return Table("fmu", "FMU check", header, rows, [1.0 / ncol] * ncol)


_DIAG_VERDICT = {"holds": "HOLDS", "fails": "FAILS", "not decided": "NOT DECIDED",
                 "not applicable": "n/a"}


def _key(measured: Mapping, limit: int = 4) -> str:
    items = [(k, v) for k, v in measured.items() if not isinstance(v, (list, dict))][:limit]
    return "; ".join(f"{measured_label(k)} = {fmt(v)}" for k, v in items)


def _diagnostics_tables(run, diags: Mapping) -> list[Table]:
    """One verdict table per law (the assumptions of Theorem 2, docs/diagnostics.md)."""
    out = []
    for law, d in diags.items():
        rows = []
        for c in d["checks"]:
            rows.append([c["id"], f"{c['name']} ({c['condition']})\nCriterion: {c['criterion']}",
                         _key(c["measured"]), _DIAG_VERDICT.get(c["verdict"], c["verdict"])])
        note = " ".join("WARNING: " + w for w in d["warnings"])
        out.append(Table(f"diag-{law}", f"Assumptions of Theorem 2 on this run: {law}",
                         ["", "condition and criterion", "measured", "verdict"], rows,
                         [0.07, 0.45, 0.34, 0.14], note=note, verdict_col=3))
    return out


def _tau_d_table(run) -> Table | None:
    from ..experiments.diagnostics import tau_d_decomposition
    model = getattr(run, "model", None)
    rows = []
    for law, lr in run.runs.items():
        dec = tau_d_decomposition(lr, model, run.theta)
        if dec is None:
            continue
        rows.append([law, fmt(dec["tau_d_err_rms"]), fmt(dec["observer_error_true_theta_rms"]),
                     fmt(dec["theta_err_part_rms"]), fmt(dec["theta_err_norm_end"])])
    if not rows:
        return None
    return Table("tau-d", "Why τ̃_d is large when θ̂ does not converge",
                 ["law", "RMS ‖τ̃_d‖, last 20 % (N·m)", "with the true θ in (7)",
                  "part carried by θ̃", "‖θ̃(t_end)‖"], rows, [0.22, 0.2, 0.2, 0.2, 0.18],
                 note="τ̂_d is built from θ̂ in (7): τ̃_d = [τ_d − τ̂_d(θ)] + (Πᵀ − Φᵀ(q, q̇, v, v̇))θ̃. "
                      "The first part (the observer's own error, small for every law) and the "
                      "second (θ̃ seen through Π, which μ(t) = μ₀t + μ₁ amplifies) are computed "
                      "from the recorded Π, v, v̇; a law whose θ̂ stays biased carries its θ̃ "
                      "into τ̂_d with a gain that grows with μ.")


def _instrument_table(run, diags: Mapping) -> Table | None:
    """C4 in detail: IV-DREM (ζ from q_d) against DREM (φ from the measured motion)."""
    if not {"iv-drem", "drem"} <= set(diags):
        return None
    rows = []
    for law in ("iv-drem", "drem"):
        c = {x["id"]: x for x in diags[law]["checks"]}
        ka3, rate = c["KA3"]["measured"], c["RATE"]["measured"]
        rows.append([law, "ζ (reference, (14))" if law == "iv-drem" else "φ (measured motion)",
                     fmt(ka3.get("normalised_mean_max")), fmt(ka3.get("shared_frequency")),
                     fmt(rate.get("calW_over_Delta_last_window")), fmt(rate.get("theta_err_norm_end")),
                     c["KA3"]["verdict"]])
    return Table("instrument", "The instrument's effect (C4): KA3 for ζ against φ",
                 ["law", "instrument", "KA3 normalised mean", "shared frequency with τ_d",
                  "‖𝒲‖/|Δ|, last window", "‖θ̃(t_end)‖", "KA3"], rows,
                 [0.12, 0.19, 0.15, 0.16, 0.15, 0.12, 0.11],
                 note="DREM uses the measured regressor φ as its own instrument; when the motion "
                      "carries the disturbance's frequencies (weak disturbance rejection: small K, "
                      "δ_μ, constant μ), φ and w share a frequency, (19) fails and θ̃ stalls at "
                      "the bias ‖𝒲‖/|Δ| of (17). With the paper's strong rejection the motion "
                      "hardly carries τ_d, so ζ and φ give nearly the same result. "
                      "examples/instrument.toml is such a weak-rejection setting.")


def _mixing_table(run, diags: Mapping) -> Table | None:
    """Which mixing of (17) converges on this arm and which learns nothing, with numbers:
    each variant's mean Δ² over [T, 2T] estimated along the reference (no loop simulated,
    ``gamma_auto.reference_mean_delta2``), the γ the gain rule would give, and for the
    variant that ran its ‖θ̃(0)‖ → ‖θ̃(t_end)‖ and LEARN verdict."""
    import math

    from ..diagrams.closed_loop import PAPER_TRAJECTORY
    from ..diagrams.gamma_auto import (DEFAULT_RATE, DELTA2_MIN, GAMMA_MAX, _lambda_max,
                                       reference_mean_delta2)
    from ..experiments.config import closed_loop_kwargs
    from ..laws import MIXING_VARIANTS
    laws = [law for law in run.runs if getattr(registry_law(law), "uses_delta", False)]
    model = getattr(run, "model", None)
    if not laws or model is None or getattr(run, "synthetic", False):
        return None
    cfg = run.config
    ivd = cfg["iv_drem"]
    experiment = getattr(run, "experiment", None)
    # the law's arguments as its Experiment resolved them (a run made without one: again)
    kw = (experiment.law(laws[0]).configured if experiment is not None
          else closed_loop_kwargs(cfg, laws[0], model))
    trajectory = kw.get("trajectory") or PAPER_TRAJECTORY
    lam = _lambda_max(kw.get("Gamma", 0.01), model.ntheta)
    ran = {}
    for law in laws:
        choice = (run.runs[law].stats or {}).get("gamma_choice") or {}
        ran[choice.get("variant") or ivd.get("mixing", "paper")] = law
    rows = []
    for v in MIXING_VARIANTS:
        try:
            est = reference_mean_delta2(model, trajectory, T=float(ivd["T"]), p=float(ivd["p"]),
                                        F0=float(ivd["F0"]), l=float(cfg["filters"]["l"]),
                                        variant=v)
        except Exception as exc:         # a trajectory block the estimate cannot sample
            rows.append([v, f"not estimated: {exc}", "", ""])
            continue
        worst = min(est)
        log_gamma = math.log10(DEFAULT_RATE) - math.log10(lam) - worst
        if worst < math.log10(DELTA2_MIN):
            rule = "refused: Δ² below the smallest double, γΔ² = 0 in doubles"
        elif log_gamma > math.log10(GAMMA_MAX):
            rule = f"refused: γ = {pow10(log_gamma)} above {GAMMA_MAX:.0e}"
        else:
            rule = f"γ ≈ {pow10(log_gamma)}"
        if v in ran:
            c = {c["id"]: c for c in diags[ran[v]]["checks"]}.get("LEARN", {})
            m = c.get("measured", {})
            e0, e1 = m.get("theta_err_0"), m.get("theta_err_end")
            result = (f"{ran[v]}: ‖θ̃‖ {fmt(e0)} → {fmt(e1)} (ratio {fmt(e1 / e0)}); "
                      f"LEARN {c.get('verdict', '?')}" if e0 else ran[v])
        elif worst < math.log10(DELTA2_MIN) or log_gamma > math.log10(GAMMA_MAX):
            result = "learns nothing from (21): the term cannot be formed (not run)"
        else:
            result = "not run here"
        span = (pow10(worst) if len(est) == 1 else f"{pow10(min(est))} … {pow10(max(est))}")
        rows.append([v, span, rule, result])
    return Table("mixing", f"Mixing variants of (17) on this arm (nθ = {model.ntheta})",
                 ["mixing", "mean Δ² over [T, 2T] (reference estimate)", "gain rule",
                  "result of this run"], rows, [0.1, 0.25, 0.3, 0.35],
                 note="mean Δ² estimated from Ψ built along the reference trajectory with "
                      "φ ≈ ζ (no loop simulated; 0.2 decades from the calibration run "
                      "on the 3-link arm and the UR5, 1.6 on the Panda, docs/mixing.md); "
                      "γ = 0.5/(λ_max(Γ) "
                      "mean Δ²) as gamma = \"auto\" would choose it.")


def _conclusions_table(concl: list[dict]) -> Table:
    rows = []
    for c in concl:
        rows.append([c["id"], c["statement"] + "\nCriterion: " + c["criterion"], metrics.key_numbers(c),
                     metrics.verdict_text(c["verdict"])])
    return Table("conclusions", "Conclusions C1-C3 of the paper and ivdrem's C4, measured",
                 ["", "statement and criterion",
                 "measured", "verdict"], rows, [0.05, 0.43, 0.4, 0.12], verdict_col=3)


def _engine(run) -> str:
    engine = getattr(run, "engine", None)
    if engine:
        return str(engine)
    seen = {str((getattr(lr, "stats", None) or {}).get("engine")) for lr in run.runs.values()}
    seen.discard("None")
    return ", ".join(sorted(seen)) or "–"


def registry_law(name):
    from ..laws import LAWS
    return LAWS.get(name)


def build_content(run, *, fmu_check=None, generated=None) -> ReportContent:
    """The :class:`ReportContent` of a :class:`~ivdrem.experiments.paper.PaperRun`: its
    conclusions, diagnostics, errata, parameters and solver statistics, with the FMU
    check's results (`fmu_check`) and the time stamp `generated` (default: now, UTC)."""
    from ..experiments.config import dump_toml, model_label

    cfg = run.config
    laws = list(run.runs)
    concl = metrics.conclusions(run)
    when = generated or _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    t_end = max(float(np.asarray(lr.response.time)[-1]) for lr in run.runs.values())
    synthetic = bool(getattr(run, "synthetic", False))
    commit = git_commit()
    meta = [
        ("generated", when),
        ("git commit", commit),
        ("model", f"{model_label(cfg)}, θ = {fmt(cfg['model']['theta'])}"),
        ("laws", ", ".join(laws)),
        ("simulated horizon", f"{fmt(t_end)} s"),
        ("engine", _engine(run)),
    ]
    if synthetic:
        meta.append(("DATA", "SYNTHETIC (made-up curves for testing the report, not a simulation)"))
    from ..experiments.diagnostics import diagnose_run
    diags = diagnose_run(run)
    gammas = [f"{law}: γ = {fmt(lr.gamma)}" + (" (auto)" if "gamma_choice" in (lr.stats or {}) else "")
              for law, lr in run.runs.items()
              if isinstance(getattr(lr, "gamma", None), (int, float, list, tuple))]
    if gammas:
        meta.append(("composite gain", "; ".join(gammas)))
    if "mixing" in cfg.get("iv_drem", {}) and any(getattr(registry_law(law), "uses_delta", False)
                                                 for law in laws):
        meta.append(("mixing of (17)", f"{cfg['iv_drem']['mixing']} (docs/mixing.md)"))
    from ..experiments.diagnostics import learning_warnings
    for law, d in diags.items():   # a run that does not learn says so on the first page
        for w in learning_warnings(d):
            meta.append((f"WARNING ({law})", w))
    tables = [
        _conclusions_table(concl),
        _summary(run),
        *_diagnostics_tables(run, diags),
        _parameters(cfg),
        *([t] if (t := _model_table(run)) is not None else []),
        _errata(cfg, laws),
        _solver(run),
        Table("versions", "Software versions", ["package", "version"],
              [[a, b] for a, b in versions()] + [["git commit", commit]], [0.3, 0.7]),
    ]
    tau = _tau_d_table(run)
    if tau is not None:
        tables.insert(2, tau)
    inst = _instrument_table(run, diags)
    if inst is not None:
        tables.insert(2, inst)
    mix = _mixing_table(run, diags)
    if mix is not None:
        tables.insert(2, mix)
    if fmu_check is not None:
        tables.append(_fmu(fmu_check))
    return ReportContent(
        title="ivdrem: the paper experiment",
        subtitle="Composite Adaptive Disturbance Rejection in Robotics via Instrumental Variables based DREM",
        meta=meta,
        conclusions=concl,
        tables=tables,
        config_toml=dump_toml(cfg),
        synthetic=synthetic,
    )
