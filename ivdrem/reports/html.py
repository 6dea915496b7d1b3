"""Self-contained HTML report: inline CSS and SVG, no external reference."""
from __future__ import annotations

from html import escape

from .content import ReportContent, Table

__all__ = ["render_html", "GENERATOR"]

#: marker of files written by ivdrem (checked before overwriting)
GENERATOR = "ivdrem report"

_CSS = """
body { font-family: "DejaVu Sans", "Helvetica Neue", Arial, sans-serif; color: #222;
       max-width: 62rem; margin: 1.5rem auto; padding: 0 1rem; line-height: 1.45; }
h1 { font-size: 1.6rem; margin-bottom: 0.2rem; }
h1 + p.subtitle { margin-top: 0; color: #555; font-style: italic; }
h2 { font-size: 1.25rem; border-bottom: 1px solid #ccc; padding-bottom: 0.2rem; margin-top: 2rem; }
table { border-collapse: collapse; margin: 0.6rem 0; font-size: 0.85rem; width: 100%; }
th, td { border: 1px solid #d0d0d0; padding: 0.25rem 0.45rem; text-align: left; vertical-align: top; }
th { background: #f2f2f2; }
td.num { font-variant-numeric: tabular-nums; }
table.meta { width: auto; } table.meta th { text-align: right; }
.PASS { background: #dff3e0; color: #1b5e20; font-weight: bold; }
.UNDECIDED { background: #fff4d6; color: #7a5300; font-weight: bold; }
.FAIL { background: #fde0dc; color: #b71c1c; font-weight: bold; }
.NA { background: #eeeeee; color: #555; font-weight: bold; }
.banner { background: #fff3cd; border: 1px solid #e0c36c; padding: 0.5rem 0.8rem; font-weight: bold; }
figure { margin: 1.2rem 0; page-break-inside: avoid; }
figure svg { width: 100%; height: auto; display: block; }
p.note { color: #555; font-size: 0.85rem; margin-top: 0; }
pre { background: #f7f7f7; border: 1px solid #ddd; padding: 0.6rem; overflow-x: auto; font-size: 0.8rem; }
nav ul { columns: 2; }
"""


def _cell(text: str) -> str:
    return "<br>".join(escape(line) for line in text.split("\n"))


def _table(t: Table) -> str:
    out = [f'<table id="tab-{t.key}">', "<thead><tr>"]
    out += [f"<th>{escape(h)}</th>" for h in t.header]
    out.append("</tr></thead><tbody>")
    for row in t.rows:
        out.append("<tr>")
        for j, cell in enumerate(row):
            cls = ""
            if t.verdict_col == j:
                cls = {"PASS": "PASS", "FAIL": "FAIL", "HOLDS": "PASS", "FAILS": "FAIL",
                       "NOT DECIDED": "UNDECIDED"}.get(cell, "NA")
            out.append(f'<td class="{cls}">{_cell(cell)}</td>' if cls else f"<td>{_cell(cell)}</td>")
        out.append("</tr>")
    out.append("</tbody></table>")
    if t.note:
        out.append(f'<p class="note">{escape(t.note)}</p>')
    return "".join(out)


def render_html(content: ReportContent, figures: list[tuple[str, str, str]]) -> str:
    """The HTML text; ``figures`` holds (key, title, inline svg) in order."""
    c = content
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f'<meta name="generator" content="{GENERATOR}">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{escape(c.title)}</title>",
        f"<style>{_CSS}</style>",
        "</head><body>",
        f"<h1>{escape(c.title)}</h1>",
        f'<p class="subtitle">{escape(c.subtitle)}</p>',
    ]
    if c.synthetic:
        parts.append('<p class="banner">Synthetic data: the curves below are made up to test the '
                     "report layout; they are not simulation results.</p>")
    parts.append('<table class="meta">')
    for label, value in c.meta:
        if label == "DATA":
            continue  # shown as the banner above
        parts.append(f"<tr><th>{escape(label)}</th><td>{escape(value)}</td></tr>")
    parts.append("</table>")
    # contents
    parts.append("<nav><h2>Contents</h2><ul>")
    for t in c.tables:
        parts.append(f'<li><a href="#sec-{t.key}">{escape(t.title)}</a></li>')
    for key, title, _ in figures:
        parts.append(f'<li><a href="#{key}">{escape(title)}</a></li>')
    parts.append('<li><a href="#sec-config">Configuration file (TOML)</a></li></ul></nav>')
    tables = {t.key: t for t in c.tables}
    # conclusions and summary first, then the figures, then the rest
    first = [k for k in ("conclusions", "summary") if k in tables]
    for key in first:
        t = tables[key]
        parts.append(f'<section id="sec-{t.key}"><h2>{escape(t.title)}</h2>{_table(t)}</section>')
    parts.append('<section id="sec-figures"><h2>Figures</h2>')
    for key, title, svg in figures:
        parts.append(f'<figure id="{key}" aria-label="{escape(title)}">{svg}</figure>')
    parts.append("</section>")
    for t in c.tables:
        if t.key in first:
            continue
        parts.append(f'<section id="sec-{t.key}"><h2>{escape(t.title)}</h2>{_table(t)}</section>')
    parts.append('<section id="sec-config"><h2>Configuration file (TOML)</h2>'
                 '<p class="note">Save as a file and pass it with <code>--config</code> to repeat this run.</p>'
                 f"<pre>{escape(c.config_toml)}</pre></section>")
    parts.append("</body></html>\n")
    return "\n".join(parts)
