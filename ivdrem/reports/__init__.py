"""Figures and the PDF/HTML report of the paper experiment.

``write_report(run, outdir)`` writes ``ivdrem-paper.html`` (self-contained, inline SVG)
and ``ivdrem-paper.pdf``; ``ivdrem.reports.cli`` holds the ``ivdrem report`` command.
"""
from .report import ReportError, report_paths, write_report

__all__ = ["write_report", "report_paths", "ReportError"]
