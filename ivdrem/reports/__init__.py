"""Figures and the PDF/HTML report of the paper experiment.

``write_report(run, outdir)`` writes ``ivdrem-paper.html`` (self-contained, inline SVG)
and ``ivdrem-paper.pdf``; ``ivdrem.cli.report`` holds the ``ivdrem report`` command.
The report's modules (matplotlib's PDF backend among them) load on first use: every
command line builds the ``report`` subcommand's parser from ``ivdrem.cli.report``.
"""
__all__ = ["write_report", "report_paths", "ReportError"]


def __getattr__(name):
    if name in __all__:
        from . import report
        return getattr(report, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
