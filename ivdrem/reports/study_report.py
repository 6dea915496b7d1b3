"""The study report: ``DIR/study.html`` (self-contained: inline CSS and SVG) and ``DIR/study.pdf``.

Contents (docs/studies.md): the study's definition, the conclusions C1-C3 counted over the
study's points, a table of the runs, each metric against each varied key (a line per law:
the median over the other varied keys, every run as a dot), a heatmap of ‖θ̃(t_end)‖ over
the first two numeric grid keys, the envelope of ‖θ̃(t)‖ over the runs per law, and the
runs that failed with their messages.  Built from the result tables only (results.parquet,
curves.parquet), so it can be rebuilt without simulating: :func:`rebuild_study_report`.
``ivdrem study`` writes it from the results :func:`ivdrem.experiments.study.run_study`
returns (:func:`write_study_report_of`); the study itself writes no report.

Written like the paper report: matplotlib figures without pyplot, temporary files next to
the targets and ``os.replace``, and a file that ivdrem did not write is never replaced.
"""
from __future__ import annotations

import datetime as _dt
import math
import os
from html import escape
from pathlib import Path

import matplotlib as mpl
import numpy as np
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from .._atomic import written_together
from .report import _is_ours as is_report_of
from . import figures as report_figures
from .content import Table, fmt, git_commit
from .pdf import TextPages

__all__ = ["write_study_report", "write_study_report_of", "rebuild_study_report", "report_paths",
           "GENERATOR"]

#: marker of files written by this report (checked before overwriting)
GENERATOR = "ivdrem study report"

METRIC_LABELS = {
    "theta_err_norm": r"$\|\tilde\theta(t_{end})\|$",
    "e_max_last20": r"max $\|e\|$, last 20 % (rad)",
    "tau_d_err_rms_last20": r"RMS $\|\tilde\tau_d\|$, last 20 % (N·m)",
}
_METRIC_TEXT = {
    "theta_err_norm": "‖θ̃(t_end)‖",
    "e_max_last20": "max ‖e‖ last 20 % (rad)",
    "tau_d_err_rms_last20": "RMS ‖τ̃_d‖ last 20 % (N·m)",
}


# --------------------------------------------------------------------------- targets
def _is_ours(path: Path, kind: str) -> bool:
    return is_report_of(path, kind, GENERATOR)


def report_paths(outdir) -> tuple[Path, Path]:
    """(study.html, study.pdf) in outdir; FileExistsError if one is a file ivdrem did not write."""
    outdir = Path(outdir)
    paths = (outdir / "study.html", outdir / "study.pdf")
    for p, kind in zip(paths, ("html", "pdf")):
        if os.path.lexists(p) and (p.is_dir() or not _is_ours(p, kind)):
            raise FileExistsError(f"refusing to overwrite {p}: it was not written by ivdrem's "
                                  "study report; move it or choose another --out")
    return paths


# --------------------------------------------------------------------------- helpers
def _laws(df) -> list[str]:
    return list(dict.fromkeys(df["law"])) if not df.empty else []


def _numeric(series) -> bool:
    vals = [v for v in series if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return bool(vals) and all(isinstance(v, (int, float, np.integer, np.floating))
                              and not isinstance(v, bool) for v in vals)


def _log_axis(values) -> bool:
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=float)
    return v.size > 1 and bool(np.all(v > 0)) and np.max(v) / np.min(v) > 30.0


def _figure(rows: int, cols: int, title: str, caption: str, height: float = 2.2):
    h = 0.9 + rows * height + 0.45
    fig = Figure(figsize=(report_figures.WIDTH, h))
    fig.subplots_adjust(left=0.9 / report_figures.WIDTH, right=1 - 0.25 / report_figures.WIDTH, top=1 - 0.75 / h,
                        bottom=0.6 / h, hspace=0.45, wspace=0.35)
    axes = fig.subplots(rows, cols, squeeze=False)
    fig.text(0.5, 1 - 0.12 / h, title, ha="center", va="top", fontsize=11, fontweight="bold")
    fig.text(0.5, 0.06 / h, caption, ha="center", va="bottom", fontsize=7.5, color="#333333",
             wrap=True)
    return fig, axes


def _legend(fig, laws):
    handles = [Line2D([], [], color=report_figures.law_color(law, i), marker="o", ms=3, label=report_figures.law_label(law))
               for i, law in enumerate(laws)]
    h = fig.get_figheight()
    fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 1 - 0.36 / h),
               ncols=min(len(handles), 4), frameon=False, borderaxespad=0.0)


# --------------------------------------------------------------------------- figures
def fig_metrics_vs_key(df, key: str, grid_keys: list[str], number: int):
    """Each metric against one varied key; a line per law through the medians."""
    ok = df[df["status"] == "ok"]
    if ok.empty or key not in ok:
        return None
    laws = _laws(ok)
    metrics = list(METRIC_LABELS)
    fig, axes = _figure(1, len(metrics), f"Figure {number}. Metrics against {key}",
                        "Dots: every run; line: median over the other varied keys"
                        + (" (grid key)" if key in grid_keys else " (random key: dots only)") + ".")
    numeric = _numeric(ok[key])
    cats = None if numeric else list(dict.fromkeys(str(v) for v in ok[key]))
    for ax, m in zip(axes[0], metrics):
        for i, law in enumerate(laws):
            sub = ok[ok["law"] == law]
            x = sub[key].astype(float).to_numpy() if numeric else \
                np.array([cats.index(str(v)) for v in sub[key]], dtype=float)
            y = sub[m].astype(float).to_numpy()
            color = report_figures.law_color(law, i)
            ax.plot(x, y, "o", ms=2.5, alpha=0.45, color=color, mec="none")
            if key in grid_keys or not numeric:
                xs = np.unique(x)
                med = [np.nanmedian(y[x == v]) for v in xs]
                ax.plot(xs, med, "-", color=color, lw=1.3)
        ax.set_xlabel(key)
        ax.set_ylabel(METRIC_LABELS[m], fontsize=8)
        if _log_axis(ok[m].astype(float)):
            ax.set_yscale("log")
        if numeric and _log_axis(ok[key].astype(float)):
            ax.set_xscale("log")
        if cats is not None:
            ax.set_xticks(range(len(cats)), cats, rotation=20, fontsize=7)
    _legend(fig, laws)
    return f"fig-metric-{number}", f"Figure {number}. Metrics against {key}", fig


def fig_heatmap(df, kx: str, ky: str, number: int):
    """‖θ̃(t_end)‖ over two grid keys, one panel per law (median over other keys)."""
    ok = df[df["status"] == "ok"]
    if ok.empty:
        return None
    laws = _laws(ok)
    xs = sorted(set(ok[kx].astype(float)))
    ys = sorted(set(ok[ky].astype(float)))
    title = f"Figure {number}. ‖θ̃(t_end)‖ over {kx} and {ky}"
    fig, axes = _figure(1, len(laws), title.replace("‖θ̃(t_end)‖", r"$\|\tilde\theta(t_{end})\|$"),
                        "Colour (log scale) and number: median of ‖θ̃(t_end)‖ over the other varied "
                        "keys at each grid point; blank: no finished run.".replace(
                            "‖θ̃(t_end)‖", r"$\|\tilde\theta(t_{end})\|$"), height=2.6)
    vals = ok["theta_err_norm"].astype(float)
    pos = vals[(vals > 0) & np.isfinite(vals)]
    norm = LogNorm(vmin=float(pos.min()), vmax=float(pos.max())) if len(pos) and pos.max() > pos.min() else None
    for ax, law in zip(axes[0], laws):
        sub = ok[ok["law"] == law]
        z = np.full((len(ys), len(xs)), np.nan)
        for i, yv in enumerate(ys):
            for j, xv in enumerate(xs):
                cell = sub[(sub[kx].astype(float) == xv) & (sub[ky].astype(float) == yv)]
                if len(cell):
                    z[i, j] = float(np.nanmedian(cell["theta_err_norm"].astype(float)))
        im = ax.imshow(z, origin="lower", aspect="auto", cmap="viridis", norm=norm)
        for i in range(len(ys)):
            for j in range(len(xs)):
                if np.isfinite(z[i, j]):
                    ax.text(j, i, f"{z[i, j]:.2g}", ha="center", va="center", fontsize=7,
                            color="white" if norm is None or norm(z[i, j]) < 0.6 else "black")
        ax.set_xticks(range(len(xs)), [f"{v:g}" for v in xs])
        ax.set_yticks(range(len(ys)), [f"{v:g}" for v in ys])
        ax.set_xlabel(kx)
        ax.set_ylabel(ky)
        ax.set_title(report_figures.law_label(law))
        ax.grid(False)
        fig.colorbar(im, ax=ax, shrink=0.9)
    return f"fig-heatmap-{number}", title, fig


def fig_envelope(df, curves, number: int, random: bool):
    """min-max band and median of ‖θ̃(t)‖ over the runs, per law."""
    if curves is None or curves.empty:
        return None
    ok_runs = set(df.loc[df["status"] == "ok", "run"])
    if random:
        ok_runs &= set(df.loc[df["sample"].notna(), "run"])
    cv = curves[curves["run"].isin(ok_runs)]
    if cv.empty:
        return None
    laws = list(dict.fromkeys(cv["law"]))
    what = "random runs" if random else "runs"
    title = f"Figure {number}. Envelope of ‖θ̃(t)‖ over the {what}, per law"
    fig, axes = _figure(1, 1, title.replace("‖θ̃(t)‖", r"$\|\tilde\theta(t)\|$"),
                        f"Band: min to max over the {what} at each time (1 s grid); line: median; "
                        "runs of different horizons end where they end.", height=3.0)
    ax = axes[0][0]
    for i, law in enumerate(laws):
        sub = cv[cv["law"] == law]
        g = sub.groupby("t")["theta_err_norm"]
        t = np.asarray(g.median().index, dtype=float)
        color = report_figures.law_color(law, i)
        ax.fill_between(t, g.min().to_numpy(), g.max().to_numpy(), color=color, alpha=0.22, lw=0)
        ax.plot(t, g.median().to_numpy(), color=color, lw=1.3)
    if _log_axis(cv["theta_err_norm"].astype(float)):
        ax.set_yscale("log")
    ax.set_xlabel("t (s)")
    ax.set_ylabel(r"$\|\tilde\theta(t)\|$")
    _legend(fig, laws)
    return f"fig-envelope-{number}", title, fig


# --------------------------------------------------------------------------- tables
def _definition(spec, runs, df, wall_s, lost) -> list[tuple[str, str]]:
    laws = list(dict.fromkeys(r.law for r in runs))
    points = len({r.point for r in runs})
    meta = [("generated", _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")),
            ("git commit", git_commit()),
            ("study", spec.source),
            ("runs", f"{len(runs)} = {points} point(s) × {len(laws)} law(s) ({', '.join(laws)})")]
    if spec.grid:
        meta.append(("grid", "; ".join(f"{k} ∈ {fmt(v)}" for k, v in spec.grid.items())))
    if spec.random:
        parts = []
        for k, d in spec.random.items():
            if isinstance(d, list):
                parts.append(f"{k} = [" + ", ".join(x.text() if hasattr(x, "text") else fmt(x)
                                                     for x in d) + "]")
            else:
                parts.append(f"{k} ~ {d.text()}")
        meta.append(("random", "; ".join(parts) + f"; samples = {spec.samples}, seed = {spec.seed}"))
    meta.append(("horizon", ", ".join(sorted({f"{fmt(r.config['experiment']['t_end'])} s" for r in runs}))))
    n_ok = int((df["status"] == "ok").sum()) if not df.empty else 0
    n_failed = int((df["status"] != "ok").sum()) if not df.empty else 0
    meta.append(("finished", f"{n_ok} ok, {n_failed} failed, {len(runs) - len(df)} missing"
                 + (f" ({len(lost)} lost to the cluster: run again with --resume)" if lost else "")))
    if wall_s is not None:
        meta.append(("wall time of this session", f"{wall_s:.1f} s"))
    return meta


def _verdict_counts(df) -> Table:
    rows = []
    if not df.empty:
        points = df.drop_duplicates("point")
        for cid, text in (("C1", "composite learning: θ̃ bounded, not converging"),
                          ("C2", "IV-DREM: θ̃ → 0"),
                          ("C3", "IV-DREM estimates τ_d at least 2× better")):
            v = points[cid].dropna()
            rows.append([cid, text, str(int(v.sum())), str(int((~v.astype(bool)).sum())),
                         str(int(len(points) - len(v)))])
    return Table("verdicts", "Conclusions C1-C3 over the study's points",
                 ["", "conclusion", "PASS", "FAIL", "not evaluated"], rows,
                 [0.06, 0.58, 0.12, 0.12, 0.12],
                 note="One verdict per point (grid point × random sample), computed from its "
                      "runs with the criteria of the paper report; C3 needs both laws.")


def _runs_table(df, varied) -> Table:
    import pandas as pd

    head = ["run", *varied, "law", "status", "‖θ̃(t_end)‖", "max ‖e‖ l.20 %", "RMS ‖τ̃_d‖ l.20 %",
            "C1", "C2", "C3", "steps", "sim (s)"]
    rows = []
    for _, r in df.iterrows():
        def v(c):
            x = r.get(c)
            if x is None or x is pd.NA or (isinstance(x, float) and math.isnan(x)):
                return "–"
            if isinstance(x, (bool, np.bool_)):
                return "PASS" if x else "FAIL"
            if isinstance(x, (float, np.floating)):
                return f"{float(x):.4g}"  # the full precision is in results.parquet
            return fmt(x)
        rows.append([v("run"), *[v(k) for k in varied], r["law"], r["status"],
                     v("theta_err_norm"), v("e_max_last20"), v("tau_d_err_rms_last20"),
                     v("C1"), v("C2"), v("C3"), v("steps"), v("sim_s")])
    w = [0.05] + [0.09] * len(varied) + [0.13, 0.06, 0.09, 0.09, 0.09, 0.05, 0.05, 0.05, 0.06, 0.06]
    return Table("runs", "Runs", head, rows, w,
                 note="C1 and C2 are verdicts of the point's composite-learning and IV-DREM run; "
                      "C3 compares the two.")


def _failed_table(df, lost) -> Table:
    rows = []
    if not df.empty:
        for _, r in df[df["status"] != "ok"].iterrows():
            rows.append([str(r["run"]), r["law"], str(r["error"])])
    for h, msg in lost.items():
        rows.append([f"(hash {h})", "", "lost: " + msg])
    return Table("failed", "Failed runs", ["run", "law", "message"], rows, [0.08, 0.17, 0.75])


# --------------------------------------------------------------------------- html
_CSS = """
body { font-family: "DejaVu Sans", Arial, sans-serif; color: #222; max-width: 66rem;
       margin: 1.5rem auto; padding: 0 1rem; line-height: 1.45; }
h1 { font-size: 1.6rem; } h2 { font-size: 1.2rem; border-bottom: 1px solid #ccc; margin-top: 2rem; }
table { border-collapse: collapse; margin: 0.6rem 0; font-size: 0.8rem; }
th, td { border: 1px solid #d0d0d0; padding: 0.2rem 0.4rem; text-align: left; vertical-align: top; }
th { background: #f2f2f2; } table.meta th { text-align: right; }
td.PASS { background: #dff3e0; color: #1b5e20; } td.FAIL { background: #fde0dc; color: #b71c1c; }
figure { margin: 1.2rem 0; } figure svg { width: 100%; height: auto; display: block; }
p.note { color: #555; font-size: 0.85rem; }
pre { background: #f7f7f7; border: 1px solid #ddd; padding: 0.6rem; overflow-x: auto; font-size: 0.8rem; }
"""


def _html_table(t: Table) -> str:
    out = [f'<section id="sec-{t.key}"><h2>{escape(t.title)}</h2>']
    if not t.rows:
        out.append("<p>(none)</p></section>")
        return "".join(out)
    out.append("<table><thead><tr>" + "".join(f"<th>{escape(h)}</th>" for h in t.header)
               + "</tr></thead><tbody>")
    for row in t.rows:
        cells = []
        for c in row:
            cls = f' class="{c}"' if c in ("PASS", "FAIL") else ""
            cells.append(f"<td{cls}>{escape(c)}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    if t.note:
        out.append(f'<p class="note">{escape(t.note)}</p>')
    out.append("</section>")
    return "".join(out)


def _render_html(title, meta, tables, figures, study_text) -> str:
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             f'<meta name="generator" content="{GENERATOR}">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             f"<title>{escape(title)}</title>", f"<style>{_CSS}</style>", "</head><body>",
             f"<h1>{escape(title)}</h1>", '<section id="sec-definition"><h2>Definition</h2>',
             '<table class="meta">']
    parts += [f"<tr><th>{escape(a)}</th><td>{escape(b)}</td></tr>" for a, b in meta]
    parts.append("</table>")
    if study_text:
        parts.append(f"<pre>{escape(study_text)}</pre>")
    parts.append("</section>")
    by_key = {t.key: t for t in tables}
    parts.append(_html_table(by_key["verdicts"]))
    parts.append('<section id="sec-figures"><h2>Figures</h2>')
    for key, ftitle, svg in figures:
        parts.append(f'<figure id="{key}" aria-label="{escape(ftitle)}">{svg}</figure>')
    parts.append("</section>")
    parts.append(_html_table(by_key["failed"]))
    parts.append(_html_table(by_key["runs"]))
    parts.append("</body></html>\n")
    return "\n".join(parts)


# --------------------------------------------------------------------------- writing
def build_figures(spec, df, curves):
    """The report's figures, as (key, title, matplotlib Figure)."""
    figs = []
    varied = _varied(df)
    grid_cols = [c for c in varied if _grid_key(c, spec)]
    n = 1
    for key in varied:
        f = fig_metrics_vs_key(df, key, grid_cols, n)
        if f is not None:
            figs.append(f)
            n += 1
    num_grid = [c for c in grid_cols if _numeric(df[c])]
    if len(num_grid) >= 2:
        f = fig_heatmap(df, num_grid[0], num_grid[1], n)
        if f is not None:
            figs.append(f)
            n += 1
    f = fig_envelope(df, curves, n, random=bool(spec.random))
    if f is not None:
        figs.append(f)
    return figs


def _grid_key(col: str, spec) -> bool:
    return col in spec.grid or col.split("[", 1)[0] in spec.grid


_FIXED = {"run", "point", "law", "sample", "seed", "t_end", "status", "error", "theta_err_norm",
          "e_max_last20", "tau_d_err_rms_last20", "C1_max_rel_deviation", "C1_end_ratio", "C1",
          "C2_end_ratio", "C2_quarter_ratio", "C2", "C3_ratio", "C3", "steps", "sim_s",
          "compile_s", "task_s", "hash"}


def _varied(df) -> list[str]:
    return [c for c in df.columns if c not in _FIXED and not c.startswith("theta_hat[")]


def write_study_report(outdir, *, spec, runs, results, curves, lost=None, wall_s=None):
    """Write ``outdir/study.html`` and ``outdir/study.pdf`` atomically; return their paths."""
    html_path, pdf_path = report_paths(outdir)
    lost = dict(lost or {})
    outdir = html_path.parent
    title = f"ivdrem study: {Path(spec.source).name if spec.source != '<dict>' else 'study'}"
    meta = _definition(spec, runs, results, wall_s, lost)
    varied = _varied(results)
    tables = [_verdict_counts(results), _failed_table(results, lost), _runs_table(results, varied)]
    with written_together(html_path, pdf_path) as (html_tmp, pdf_tmp):
        with mpl.rc_context(report_figures.RC):
            figs = build_figures(spec, results, curves)
            svgs = [(k, t, report_figures.figure_to_svg(fig, f"{k}-")) for k, t, fig in figs]
            pdf_meta = {"Title": title, "Creator": GENERATOR, "Keywords": "ivdrem, parameter study"}
            with PdfPages(pdf_tmp, metadata=pdf_meta) as pdf:
                tp = TextPages(pdf, footer=f"{title}  ·  {meta[0][1]}")
                tp.new_page()
                tp._text(0.7, tp.y, title, 18, fontweight="bold")
                tp.y -= tp._lh(18) + 0.1
                for label, value in meta:
                    tp.paragraph(f"{label}: {value}", 9)
                tp.space(0.1)
                for t in tables[:2]:
                    tp.table(t)
                tp.heading("Study file", 11)
                tp.paragraph(spec.text, 7)
                tp.new_page()
                tp.table(tables[2], size=6.5)
                tp.flush()
                for _, _, fig in figs:
                    pdf.savefig(fig)
            html_tmp.write_text(_render_html(title, meta, tables, svgs, spec.text), encoding="utf-8")
    return html_path, pdf_path


def write_study_report_of(result):
    """The report of what :func:`ivdrem.experiments.study.run_study` returned (its
    ``StudyResult``), in the study's directory, as ``ivdrem study`` writes it."""
    return write_study_report(result.out, spec=result.spec, runs=result.runs,
                              results=result.results, curves=result.curves, lost=result.lost,
                              wall_s=result.wall_s)


def rebuild_study_report(outdir, study):
    """Rewrite the report of a finished study from its tables (no simulation)."""
    import pandas as pd

    from ..experiments.study_spec import expand_study, read_study
    spec = read_study(study)
    runs = expand_study(spec)
    df = pd.read_parquet(Path(outdir) / "results.parquet")
    cf = pd.read_parquet(Path(outdir) / "curves.parquet")
    return write_study_report(outdir, spec=spec, runs=runs, results=df, curves=cf)
