"""Figures of the paper experiment (matplotlib, no pyplot: safe in any backend).

Each builder takes a PaperRun and returns a :class:`FigureSpec` (or None when the
run has nothing to show for it).  Figures 1-4 are the paper's; the others show the
estimates, the control torque and the auxiliary signals.  Every law keeps one colour
in every figure.
"""
from __future__ import annotations

import io
import math
import re
import textwrap
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from ..experiments import metrics

__all__ = ["FigureSpec", "FIGURES", "LAW_STYLE", "law_label", "law_color", "law_linestyle", "iter_figures",
           "figure_to_svg", "decimate", "RC"]

#: matplotlib settings of every report figure (used with ``rc_context``).
RC = {
    "text.usetex": False,
    "font.family": "DejaVu Sans",
    "mathtext.fontset": "dejavusans",
    "font.size": 9,
    "axes.titlesize": 9,
    "axes.labelsize": 9,
    "legend.fontsize": 8,
    "xtick.labelsize": 8,
    "ytick.labelsize": 8,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "lines.linewidth": 1.0,
    "pdf.fonttype": 42,  # TrueType: text stays selectable and searchable
    "svg.fonttype": "path",  # glyphs as paths: same look in every browser, no font needed
    "svg.hashsalt": "ivdrem",  # deterministic ids
    "figure.dpi": 100,
    "axes.linewidth": 0.6,
    "axes.edgecolor": "#444444",
}

class _LawStyle(dict):
    """colour and legend label of each law, read from the law registry (ivdrem.laws) at
    look-up time, so a law registered later has its own style (Okabe-Ito palette)."""

    def _fill(self):
        from ..laws import LAWS as registry
        for name, law in registry.items():
            dict.__setitem__(self, name, (law.color, law.label))

    def get(self, key, default=None):
        self._fill()
        return dict.get(self, key, default)

    def __getitem__(self, key):
        self._fill()
        return dict.__getitem__(self, key)

    def __iter__(self):
        self._fill()
        return dict.__iter__(self)

    def __len__(self):
        self._fill()
        return dict.__len__(self)


#: colour and legend label of each law (from the registry; colour-blind safe palette).
LAW_STYLE = _LawStyle()
_EXTRA_COLORS = ["#D55E00", "#56B4E9", "#000000", "#F0E442"]

WIDTH = 8.27  # inches: A4 width, so that PDF pages of figures and text line up
PANEL_H = 2.05
DECADES_FOR_LOG = 2.0
#: Most component panels a figure draws one per component; above it (a URDF arm's 36
#: parameters) each law gets one panel with every component, so a page keeps legible panels.
MAX_COMPONENT_PANELS = 8
#: Start-up share of the run left out of a zoomed panel's y range (Figure 2: e starts at
#: 0.8 rad and settles to 1e-3 rad, so the whole range hides the steady state).
ZOOM_SKIP = 0.05


def law_color(law: str, order: int = 0) -> str:
    """The law's colour in every figure (a law outside the registry gets the `order`-th
    spare colour)."""
    return LAW_STYLE.get(law, (_EXTRA_COLORS[order % len(_EXTRA_COLORS)], law))[0]


def law_linestyle(law: str) -> str:
    """The law's line style (ivdrem.laws): with the colour, so that five laws are told apart
    by colour-blind readers and in print."""
    from ..laws import LAWS as registry
    got = registry.get(law)
    return got.linestyle if got is not None else "-"


def law_label(law: str) -> str:
    """The law's label in legends, e.g. "IV-DREM, (11)+(21)"."""
    return LAW_STYLE.get(law, (None, law))[1]


@dataclass
class FigureSpec:
    """A figure of the report: its HTML id, title, caption and matplotlib figure."""
    key: str  # html id, e.g. "fig1"
    title: str  # e.g. "Figure 1. Regressor Δ(t) and disturbance 𝒲(t)"
    caption: str
    figure: Figure


# --------------------------------------------------------------------------- helpers
def decimate(t: np.ndarray, y: np.ndarray, buckets: int = 1200):
    """Min-max decimation: keeps the envelope of fast oscillations with few points."""
    t = np.asarray(t)
    y = np.asarray(y)
    n = t.size
    if n <= 2 * buckets:
        return t, y
    size = int(math.ceil(n / buckets))
    m = (n // size) * size
    yb = y[:m].reshape(-1, size)
    finite = np.isfinite(yb)
    lo = np.where(finite, yb, np.inf).argmin(axis=1)
    hi = np.where(finite, yb, -np.inf).argmax(axis=1)
    base = np.arange(yb.shape[0]) * size
    first = np.minimum(lo, hi) + base
    second = np.maximum(lo, hi) + base
    idx = np.empty(2 * first.size, dtype=int)
    idx[0::2] = first
    idx[1::2] = second
    tail = []
    if m < n:  # the last, shorter bucket
        yt = y[m:]
        ft = np.isfinite(yt)
        if ft.any():
            tail = [m + int(np.where(ft, yt, np.inf).argmin()), m + int(np.where(ft, yt, -np.inf).argmax())]
    idx = np.concatenate([[0], idx, tail, [n - 1]]).astype(int)
    idx = np.unique(idx)
    return t[idx], y[idx]


def _spans_decades(y: np.ndarray, t: np.ndarray) -> bool:
    """True when |y| spans more than DECADES_FOR_LOG decades after the first 2 % of the run."""
    a = np.abs(np.asarray(y, dtype=float))
    late = t >= t[0] + 0.02 * (t[-1] - t[0])
    a = a[late & np.isfinite(a) & (a > 0)]
    if a.size < 2:
        return False
    lo, hi = np.percentile(a, 1), np.max(a)
    return lo > 0 and math.log10(hi / lo) > DECADES_FOR_LOG


def _plot(ax, t, y, law, order, *, log=False, label=None, **kw):
    y = np.asarray(y, dtype=float)
    if log:
        y = np.abs(y)
        y = np.where(y > 0, y, np.nan)
    td, yd = decimate(t, y)
    kw.setdefault("color", law_color(law, order))
    kw.setdefault("ls", law_linestyle(law))
    kw.setdefault("zorder", 2.5 if law == "iv-drem" else 2.0)  # the proposed law on top
    ax.plot(td, yd, label=label, **kw)
    if log:
        ax.set_yscale("log")


# layout in inches (fixed margins: faster and steadier than constrained layout)
_LEFT, _RIGHT, _TOP, _AX_H, _GAP, _WGAP = 0.85, 0.2, 0.78, 1.55, 0.5, 0.95
_CAPTION_LINE = 0.14


def _grid(k: int, *, cols: int | None = None, titles: bool = False, caption_lines: int = 1):
    cols = cols or (2 if k > 3 else 1)
    rows = int(math.ceil(k / cols))
    gap = _GAP + (0.22 if titles else 0.0)
    top = _TOP + (0.22 if titles else 0.0)
    bottom = 0.5 + caption_lines * _CAPTION_LINE + 0.08
    h = top + bottom + rows * _AX_H + (rows - 1) * gap
    fig = Figure(figsize=(WIDTH, h))
    ax_w = (WIDTH - _LEFT - _RIGHT - (cols - 1) * _WGAP) / cols
    fig.subplots_adjust(left=_LEFT / WIDTH, right=1 - _RIGHT / WIDTH, bottom=bottom / h,
                        top=1 - top / h, hspace=gap / _AX_H, wspace=_WGAP / ax_w)
    axes = fig.subplots(rows, cols, sharex=True, squeeze=False)
    flat = list(axes.ravel())
    for ax in flat[k:]:
        ax.remove()
    for ax in flat[:k]:
        ax.xaxis.set_tick_params(labelbottom=True)
        ax.set_xlabel("t (s)", labelpad=1)
    return fig, flat[:k]


def _tidy_log(ax, t_from: float, decades: float = 1.0) -> None:
    """Lower y limit of a log axis from the data after the start-up (first 2 % of the run).

    Magnitudes that start at exactly 0 (Δ, 𝒲, λ_min) would otherwise stretch the axis
    over dozens of empty decades; values below the limit are clipped by the axes.
    """
    vals, peak = [], 0.0
    for line in ax.get_lines():
        x = np.asarray(line.get_xdata(), dtype=float)
        y = np.asarray(line.get_ydata(), dtype=float)
        pos = np.isfinite(y) & (y > 0)
        if pos.any():
            peak = max(peak, float(np.max(y[pos])))
        vals.append(y[pos & (x >= t_from)])
    vals = np.concatenate(vals) if vals else np.array([])
    if vals.size == 0 or peak <= 0:
        return
    low = 10.0 ** (math.floor(math.log10(np.percentile(vals, 0.5))) - decades)
    if low >= peak:
        return
    span = math.log10(peak / low)
    ax.set_ylim(low, peak * 10.0 ** (0.05 * span))


def _caption_lines(caption: str) -> list[str]:
    return textwrap.wrap(caption, 150)


def _finish(fig, axes, title, caption, laws, run, *, extra_handles=()):
    h = fig.get_figheight()
    times = [_t(lr) for lr in run.runs.values()]
    t0, t1 = min(t[0] for t in times), max(t[-1] for t in times)
    if t1 > t0:
        for ax in axes:
            ax.set_xlim(t0, t1)
    for ax in axes:
        if ax.get_yscale() == "log":
            _tidy_log(ax, t0 + 0.02 * (t1 - t0))
    handles = [Line2D([], [], color=law_color(law, i), ls=law_linestyle(law), label=law_label(law))
               for i, law in enumerate(laws)]
    handles += list(extra_handles)
    if handles:
        fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 1 - 0.36 / h),
                   ncols=min(len(handles), 4), frameon=False, borderaxespad=0.0)
    fig.text(0.5, 1 - 0.12 / h, _mathify(title), ha="center", va="top", fontsize=11,
             fontweight="bold")
    fig.text(0.5, 0.08 / h, _mathify("\n".join(_caption_lines(caption))), ha="center",
             va="bottom", fontsize=7.5, color="#333333")


# Unicode with sub/superscripts, and glyphs the DejaVu fonts lack, as mathtext (figures only)
_MATH = [
    ("Πᵀθ̂", r"$\Pi^\top\hat{\theta}$"), ("τ̃_d", r"$\tilde{\tau}_d$"), ("τ̂_d", r"$\hat{\tau}_d$"), ("τ_d", r"$\tau_d$"),
    ("θ̂_j", r"$\hat{\theta}_j$"), ("θ_j", r"$\theta_j$"), ("Δθ_i", r"$\Delta\theta_i$"),
    ("𝒴_i", r"$\mathcal{Y}_i$"), ("𝒲_i", r"$\mathcal{W}_i$"), ("𝒲", r"$\mathcal{W}$"),
    ("𝒴", r"$\mathcal{Y}$"), ("θ̃", r"$\tilde{\theta}$"), ("θ̂", r"$\hat{\theta}$"),
    ("Ψ_b", r"$\Psi_b$"), ("Y_b", r"$Y_b$"),
    ("λ_min", r"$\lambda_{\min}$"), ("t_e", r"$t_e$"), ("δ_μ", r"$\delta_\mu$"),
    ("u_f", r"$u_f$"), ("q_d", r"$q_d$"),
]


def _mathify(s: str) -> str:
    for a, b in _MATH:
        s = s.replace(a, b)
    return s


def _laws(run, need=None):
    out = []
    for law, lr in run.runs.items():
        if need is None or need in metrics.signal_names(lr.response):
            out.append(law)
    return out


def _t(lr):
    return np.asarray(lr.response.time, dtype=float)


def _norm_panel(ax, run, laws, fn, ylabel):
    """‖x‖ per law; log axis when it spans decades."""
    data = [(law, _t(run.runs[law]), metrics.norm(fn(run.runs[law]))) for law in laws]
    log = any(_spans_decades(y, t) for _, t, y in data)
    for i, (law, t, y) in enumerate(data):
        _plot(ax, t, y, law, list(run.runs).index(law), log=log)
    ax.set_ylabel(ylabel + (" (log)" if log else ""))


# --------------------------------------------------------------------------- figures
def fig_delta_W(run):
    laws = _laws(run, "Delta")
    if not laws:
        return None
    theta = np.asarray(run.theta, dtype=float)
    title = "Figure 1. Regressor Δ(t) and disturbance 𝒲(t)"
    caption = ("Log scale of the magnitudes (Ψ is singular at t = 0, so Δ and 𝒲 start from 0; the "
               "start-up below the axis is clipped). 𝒴_i = Δθ_i + 𝒲_i (erratum E4). The paper's "
               "condition for convergence: Δ vanishes slower than 𝒲, i.e. the ratio decreases.")
    fig, axes = _grid(3, cols=1, titles=True, caption_lines=len(_caption_lines(caption)))
    order = list(run.runs)
    for law in laws:
        lr = run.runs[law]
        t = _t(lr)
        Dc = np.atleast_2d(metrics.signal(lr, "Delta"))    # one row, or one per channel
        Wc = metrics.calW(lr, theta)
        D = np.min(np.abs(Dc), axis=0)                      # the weakest channel's |Δ_i|
        W = metrics.norm(Wc)
        k = order.index(law)
        _plot(axes[0], t, D, law, k, log=True)
        _plot(axes[1], t, W, law, k, log=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            # ‖(𝒲_i/Δ_i)_i‖, = ‖𝒲‖/|Δ| for one Δ (docs/mixing.md)
            ratio = np.where(np.all(np.abs(Dc) > 0, axis=0),
                             np.sqrt(np.sum((Wc / Dc) ** 2, axis=0)), np.nan)
        _plot(axes[2], t, ratio, law, k, log=True)
    axes[0].set_ylabel(r"$|\Delta(t)|$")
    axes[1].set_ylabel(r"$\|\mathcal{W}(t)\|$")
    axes[2].set_ylabel(r"$\|\mathcal{W}\| \,/\, |\Delta|$")
    axes[0].set_title("regressor of the mixed regression (17): determinant of the normalized Ψ")
    axes[1].set_title(r"disturbance of the mixed regression, $\mathcal{W} = \mathcal{Y} - \Delta\theta$")
    axes[2].set_title(r"ratio: decreasing when $\Delta$ vanishes slower than $\mathcal{W}$")
    _finish(fig, axes, title, caption, laws, run)
    return FigureSpec("fig1", title, caption, fig)


def _zoom(ax, t_from: float) -> bool:
    """y limits of `ax` from its lines after `t_from` (10 % margin): the steady state
    fills the panel, the start-up beyond it is clipped.  False if nothing to zoom to."""
    lo, hi = math.inf, -math.inf
    for line in ax.get_lines():
        x = np.asarray(line.get_xdata(), dtype=float)
        y = np.asarray(line.get_ydata(), dtype=float)
        keep = (x >= t_from) & np.isfinite(y)
        if keep.any():
            lo, hi = min(lo, float(y[keep].min())), max(hi, float(y[keep].max()))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return False
    span = hi - lo if hi > lo else max(abs(hi), 1e-12)
    ax.set_ylim(lo - 0.1 * span, hi + 0.1 * span)
    return True


def _component_figure(run, key, title, caption, fn, comp_label, norm_label, unit, *, truth=None,
                      zoom=False, layered=False):
    """One panel per component (and ‖x‖ last); above :data:`MAX_COMPONENT_PANELS`
    components one panel per law with all of them.  `zoom`: component panels' y range
    from the run after its first :data:`ZOOM_SKIP`; `layered`: laws whose curves nearly
    coincide drawn wide below and the proposed law narrow on top, so each stays visible."""
    laws = list(run.runs)
    first = run.runs[laws[0]]
    k = fn(first).shape[0]
    if k > MAX_COMPONENT_PANELS:
        return _overlay_figure(run, key, title, caption, fn, comp_label, norm_label, unit,
                               truth=truth)
    panels = k + (1 if norm_label else 0)
    fig, axes = _grid(panels, caption_lines=len(_caption_lines(caption)))
    for i, law in enumerate(laws):
        lr = run.runs[law]
        x = fn(lr)
        t = _t(lr)
        kw = {}
        if layered:
            kw = dict(lw=1.0) if law == "iv-drem" else dict(lw=2.6, alpha=0.75)
        for j in range(k):
            _plot(axes[j], t, x[j], law, i, **kw)
    for j in range(k):
        axes[j].set_ylabel(comp_label(j) + f" ({unit})" if unit else comp_label(j))
        if truth is not None:
            tt = _t(first)
            axes[j].plot([tt[0], tt[-1]], [truth[j], truth[j]], color="black", ls="--", lw=1.0)
    if zoom:
        t0 = min(_t(lr)[0] for lr in run.runs.values())
        t1 = max(_t(lr)[-1] for lr in run.runs.values())
        for j in range(k):
            _zoom(axes[j], t0 + ZOOM_SKIP * (t1 - t0))
    extra = []
    if truth is not None:
        extra.append(Line2D([], [], color="black", ls="--", label="true θ"))
    if norm_label:
        _norm_panel(axes[k], run, laws, fn, norm_label + (f" ({unit})" if unit else ""))
    _finish(fig, axes, title, caption, laws, run, extra_handles=extra)
    return FigureSpec(key, title, caption, fig)


def _overlay_figure(run, key, title, caption, fn, comp_label, norm_label, unit, *, truth=None):
    """Many components (a URDF arm's parameters): one panel per law with every component
    (thin lines), and ‖x‖ of every law last."""
    laws = list(run.runs)
    k = fn(run.runs[laws[0]]).shape[0]
    caption = (f"{caption} All {k} components of each law in one panel (one per law; "
               f"a page of {k} panels would be unreadable).")
    panels = len(laws) + (1 if norm_label else 0)
    fig, axes = _grid(panels, cols=1, titles=True, caption_lines=len(_caption_lines(caption)))
    label = comp_label(0).replace("{1}", "{j}").replace(",1}", ",j}")   # e_j, θ̃_j, τ_d,j
    for i, law in enumerate(laws):
        lr = run.runs[law]
        x, t = fn(lr), _t(lr)
        ax = axes[i]
        for j in range(k):
            _plot(ax, t, x[j], law, i, lw=0.7, alpha=0.8)
        if truth is not None:
            for j in range(k):
                ax.axhline(truth[j], color="black", ls="--", lw=0.5, alpha=0.5)
        ax.set_ylabel(label + (f" ({unit})" if unit else ""))
        ax.set_title(f"{law_label(law)}: {k} components")
    extra = []
    if truth is not None:
        extra.append(Line2D([], [], color="black", ls="--", label="true θ"))
    if norm_label:
        _norm_panel(axes[-1], run, laws, fn, norm_label + (f" ({unit})" if unit else ""))
    _finish(fig, axes, title, caption, laws, run, extra_handles=extra)
    return FigureSpec(key, title, caption, fig)


def fig_tracking_error(run):
    return _component_figure(
        run, "fig2", "Figure 2. Tracking error e(t)",
        "e = q_d − q for each joint, its y range zoomed to the run after the first "
        f"{ZOOM_SKIP:.0%} (the start-up, from q(0) ≠ q_d(0), is clipped there); the last panel "
        "is ‖e‖ over the whole run (log scale when it spans decades).",
        lambda lr: metrics.signal(lr, "e"), lambda j: rf"$e_{{{j + 1}}}$", r"$\|e\|$", "rad",
        zoom=True)


def fig_theta_error(run):
    theta = np.asarray(run.theta, dtype=float)
    return _component_figure(
        run, "fig3", "Figure 3. Parameter error θ̃(t)",
        "θ̃ = θ − θ̂ for each parameter; the last panel is ‖θ̃‖ (log scale when it spans decades).",
        lambda lr: metrics.theta_error(lr, theta), lambda j: rf"$\tilde\theta_{{{j + 1}}}$",
        r"$\|\tilde\theta\|$", "")


def fig_tau_d_error(run):
    return _component_figure(
        run, "fig4", "Figure 4. Disturbance estimation error τ̃_d(t)",
        "τ̃_d = τ_d − τ̂_d, τ̂_d extracted from the control signal (9); the last panel is ‖τ̃_d‖.",
        lambda lr: metrics.tau_d_error(lr), lambda j: rf"$\tilde\tau_{{d,{j + 1}}}$",
        r"$\|\tilde\tau_d\|$", "N·m")


def fig_theta_hat(run):
    theta = np.asarray(run.theta, dtype=float)
    return _component_figure(
        run, "fig5", "Figure 5. Parameter estimates θ̂(t) and true θ",
        "Each estimate θ̂_j against the true value θ_j (dashed).",
        lambda lr: metrics.signal(lr, "theta_hat"), lambda j: rf"$\hat\theta_{{{j + 1}}}$", None, "",
        truth=theta)


def fig_torque(run):
    return _component_figure(
        run, "fig6", "Figure 6. Control torque τ(t)",
        "τ = (K + δ_μ μ) r + Πᵀθ̂ − u_f, eq. (9). The laws' torques nearly coincide: "
        "IV-DREM is drawn narrow on top of the other laws' wide, lighter lines.",
        lambda lr: metrics.signal(lr, "tau"), lambda j: rf"$\tau_{{{j + 1}}}$", None, "N·m",
        layered=True)


def fig_auxiliary(run):
    cl = _laws(run, "lambda_min_held")
    title = "Figure 7. Excitation of composite learning and observer weight μ(t)"
    caption = ("λ_min of Ψ_b at the time t_e held by the max-hold of the baseline (35), which uses "
               "the data (Y_b, Ψ_b) of t_e only; μ(t) of the high-gain torque observer.")
    fig, axes = _grid(2 if cl else 1, cols=1, titles=True, caption_lines=len(_caption_lines(caption)))
    order = list(run.runs)
    ax = axes[0]
    if cl:
        for law in cl:
            lr = run.runs[law]
            t = _t(lr)
            lam = metrics.signal(lr, "lambda_min_held")
            _plot(ax, t, lam, law, order.index(law), log=_spans_decades(lam, t))
        ax.set_ylabel(r"$\lambda_{\min}(\Psi_b(t_e))$")
        ax.set_title(r"smallest eigenvalue of the held $\Psi_b$ of composite learning (35)")
        ax = axes[1]
    lr = run.runs[order[0]]
    ax.plot(*decimate(_t(lr), metrics.signal(lr, "mu")), color="#333333")
    ax.set_ylabel(r"$\mu(t)$")
    ax.set_title(r"weight $\mu(t) = \mu_0 t + \mu_1$ of the torque observer (same for every law)")
    laws = cl
    _finish(fig, axes, title, caption, laws, run)
    return FigureSpec("fig7", title, caption, fig)


def _na(ax, text):
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="#777777")
    ax.set_yticks([])


def fig_diagnostics_law(run, law, diag):
    """Figure D: the signals behind the verdicts of one law (ivdrem.experiments.diagnostics)."""
    from ..experiments import diagnostics
    title = f"Figure D ({law}). Assumptions of Theorem 2 along the run"
    caption = ("(a) ∫Δ² ds (KA1: keeps growing when Δ ∉ L2); (b) ∫‖τ̇_d‖²/μ² ds (KA2: levels "
               "off when λ ∈ L2); (c) running integrals ∫ζ_kj w_j ds of (19) (KA3: bounded); "
               "(d) max_i |𝒲_i| F/Ḟ (Proposition 2, eq. 20: bounded); (e) ‖θ̃‖ and the fit C t^(−a) "
               "over the last half; (f) V of (23) and the bound of the proof.")
    fig, axes = _grid(6, cols=2, titles=True, caption_lines=len(_caption_lines(caption)))
    order = list(run.runs)
    k = order.index(law)
    ser = diag["series"]
    t = ser["t"]
    verdict = {c["id"]: c["verdict"] for c in diag["checks"]}
    color = law_color(law, k)

    def head(ax, text, cid):
        ax.set_title(f"{text}  [{verdict.get(cid, diagnostics.NA)}]")

    ax = axes[0]
    if "int_Delta2" in ser:
        ax.plot(*decimate(t, ser["int_Delta2"]), color=color)
    else:
        _na(ax, "no Δ (17) in this law")
    ax.set_ylabel(r"$\int_0^t \Delta^2 ds$")
    head(ax, "(a) KA1", "KA1")
    ax = axes[1]
    ax.plot(*decimate(t, ser["int_lambda2"]), color=color)
    ax.set_ylabel(r"$\int_0^t \|\dot\tau_d\|^2/\mu^2 ds$")
    head(ax, "(b) KA2", "KA2")
    ax = axes[2]
    if "ka3_integrals" in ser:
        ints = ser["ka3_integrals"]
        for row in ints:
            if np.any(row):
                ax.plot(*decimate(t, row), color=color, lw=0.6, alpha=0.6)
    else:
        _na(ax, "no instrument in this law")
    ax.set_ylabel(r"$\int_0^t \zeta_{kj} w_j ds$")
    head(ax, "(c) KA3, (19)", "KA3")
    ax = axes[3]
    if "prop2_ratio" in ser:
        R = ser["prop2_ratio"]
        _plot(ax, t, R, law, k, log=_spans_decades(np.nan_to_num(R), t))
    else:
        _na(ax, r"no $\mathcal{W}$ in this law")
    ax.set_ylabel(r"$\max_i |\mathcal{W}_i| F/\dot F$")
    head(ax, "(d) Proposition 2", "P2")
    ax = axes[4]
    y = ser["theta_err_norm"]
    _plot(ax, t, y, law, k, log=True)
    a, C = ser["rate_fit"]
    if np.isfinite(a):
        half = t >= t[0] + 0.5 * (t[-1] - t[0])
        ax.plot(t[half], C * t[half] ** (-a), color="black", ls="--", lw=1.0)
    ax.set_ylabel(r"$\|\tilde\theta\|$ (log)")
    head(ax, f"(e) rate, a = {a:.3g}", "RATE")
    ax = axes[5]
    if "V" in ser:
        _plot(ax, t, ser["V"], law, k, log=True)
        if ser.get("V_bound") is not None:
            ax.plot(*decimate(t, ser["V_bound"]), color="black", ls="--", lw=1.0)
    else:
        _na(ax, "model not available")
    ax.set_ylabel("V (23) (log)")
    head(ax, "(f) Lyapunov V, bound dashed", "V")
    _finish(fig, axes, title, caption, [law], run)
    return FigureSpec(f"figD-{law}", title, caption, fig)


def fig_diagnostics(run):
    """One Figure D per law (a list)."""
    from ..experiments.diagnostics import diagnose_run
    diags = diagnose_run(run)
    return [fig_diagnostics_law(run, law, d) for law, d in diags.items()]


#: builders in report order (names, looked up at call time)
FIGURES = ["fig_delta_W", "fig_tracking_error", "fig_theta_error", "fig_tau_d_error",
           "fig_theta_hat", "fig_torque", "fig_auxiliary", "fig_diagnostics"]


def iter_figures(run):
    """Yield the FigureSpecs of a run, built one at a time (a builder may return a list)."""
    import sys
    mod = sys.modules[__name__]
    for name in FIGURES:
        spec = getattr(mod, name)(run)
        if spec is None:
            continue
        for one in (spec if isinstance(spec, list) else [spec]):
            yield one


# --------------------------------------------------------------------------- svg
_ID = re.compile(r'\bid="([^"]+)"')


def figure_to_svg(fig: Figure, prefix: str) -> str:
    """Inline SVG text of a figure: no XML prolog, DOCTYPE or metadata, ids prefixed."""
    buf = io.StringIO()
    fig.savefig(buf, format="svg", metadata={"Date": None})
    svg = buf.getvalue()
    svg = re.sub(r"<\?xml[^>]*\?>\s*", "", svg)
    svg = re.sub(r"<!DOCTYPE[^>]*>\s*", "", svg, flags=re.S)
    svg = re.sub(r"<metadata>.*?</metadata>\s*", "", svg, flags=re.S)
    ids = set(_ID.findall(svg))
    if ids:
        def fix_ref(m):
            ident = m.group(2)
            return m.group(1) + (prefix + ident if ident in ids else ident)
        svg = _ID.sub(lambda m: f'id="{prefix}{m.group(1)}"', svg)
        svg = re.sub(r'((?:xlink:)?href="#)([^"]+)', fix_ref, svg)
        svg = re.sub(r"(url\(#)([^)]+)", fix_ref, svg)
    # scale with the page
    svg = re.sub(r'<svg ([^>]*?)width="[^"]*" height="[^"]*"', r'<svg \1', svg, count=1)
    return svg.strip()
