"""write_report: the PDF and HTML report of a paper run, written atomically."""
from __future__ import annotations

import os
from pathlib import Path

import matplotlib as mpl
from matplotlib.backends.backend_pdf import PdfPages

from .._atomic import written_together
from . import figures as report_figures
from .content import build_content
from .html import GENERATOR, render_html
from .pdf import write_text_pages

__all__ = ["write_report", "report_paths", "ReportError"]


class ReportError(FileExistsError):
    """The report would overwrite a file that ivdrem did not write."""


def _is_ours(path: Path, kind: str, generator: str = GENERATOR) -> bool:
    """Whether `path` is an HTML or PDF file that `generator` wrote (so it may be replaced)."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return False
    if kind == "html":
        return f'<meta name="generator" content="{generator}">'.encode() in data[:4096]
    return data.startswith(b"%PDF") and generator.encode() in data


def _check_target(path: Path, kind: str, overwrite: bool) -> None:
    if not os.path.lexists(path):
        return
    if path.is_dir():
        raise ReportError(f"cannot write the report to {path}: it is a directory")
    if not overwrite and not _is_ours(path, kind):
        raise ReportError(
            f"refusing to overwrite {path}: it was not written by ivdrem's report; "
            "move it, choose another output directory or basename, or pass overwrite=True "
            "(command line: ivdrem report --overwrite)"
        )


def report_paths(outdir, basename="ivdrem-paper", *, overwrite=False) -> tuple[Path, Path]:
    """The two report paths; raises before any work if writing them would be refused.

    ValueError for a basename that is not a plain file name, :class:`ReportError` when a
    target exists and is a directory or a file that ivdrem's report did not write.
    """
    if not basename or any(sep in basename for sep in ("/", "\\", os.sep)) or basename in (".", ".."):
        raise ValueError(f"basename must be a plain file name without extension, got {basename!r}")
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise ReportError(f"cannot write the report into {outdir}: it is not a directory")
    html_path = outdir / f"{basename}.html"
    pdf_path = outdir / f"{basename}.pdf"
    _check_target(html_path, "html", overwrite)
    _check_target(pdf_path, "pdf", overwrite)
    return html_path, pdf_path


def write_report(run, outdir, *, fmu_check=None, basename="ivdrem-paper", overwrite=False):
    """Write ``outdir/basename.html`` and ``outdir/basename.pdf``; return their paths.

    ``run`` is a PaperRun (``ivdrem.experiments.paper``): figures 1-4 of the paper plus
    estimates, torque and auxiliary signals, the conclusions C1-C3 with their numbers,
    the parameters, the errata (docs/conventions.md, "Errata and choices"), solver statistics, versions and the
    git commit.  ``fmu_check`` (optional) is a dict of numbers (or of rows) rendered as
    a table.

    Both files are first written to temporary files in ``outdir`` and then moved into
    place with ``os.replace``: an exception leaves any previous report untouched and no
    partial file.  Only the two target names are ever replaced, and only when they are
    previous ivdrem reports (or ``overwrite=True``): an unrelated user file of the same
    name raises :class:`ReportError` before anything is computed.
    """
    html_path, pdf_path = report_paths(outdir, basename, overwrite=overwrite)
    outdir = html_path.parent
    outdir.mkdir(parents=True, exist_ok=True)

    with written_together(html_path, pdf_path) as (html_tmp, pdf_tmp):
        with mpl.rc_context(report_figures.RC):
            content = build_content(run, fmu_check=fmu_check)
            specs = []
            for spec in report_figures.iter_figures(run):
                specs.append(spec)
            svgs = [(s.key, s.title, report_figures.figure_to_svg(s.figure, f"{s.key}-")) for s in specs]
            meta = {
                "Title": content.title,
                "Subject": content.subtitle,
                "Creator": f"{GENERATOR} (ivdrem {_version()})",
                "Keywords": "ivdrem, IV-DREM, composite adaptive control",
            }
            with PdfPages(pdf_tmp, metadata=meta) as pdf:
                write_text_pages(pdf, content, [s.title for s in specs])
                for s in specs:
                    pdf.savefig(s.figure)
            html_tmp.write_text(render_html(content, svgs), encoding="utf-8")
    return html_path, pdf_path


def _version() -> str:
    from .. import __version__

    return __version__
