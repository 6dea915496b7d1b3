"""The ``ivdrem report`` command: run the paper experiment and write the report.

``ivdrem.cli`` wires it as a subcommand::

    p = sub.add_parser("report", help="run the paper experiment and write the PDF/HTML report")
    add_report_arguments(p)
    p.set_defaults(func=run_report_command)
"""
from __future__ import annotations

import argparse
import sys

from ..experiments.config import LAWS, ConfigError, load_config

__all__ = ["add_report_arguments", "run_report_command", "config_from_args"]


def add_report_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the options of ``ivdrem report`` to ``parser``."""
    parser.add_argument("--config", metavar="FILE.toml", default=None,
                        help="experiment configuration merged over the embedded default "
                             "(see examples/paper.toml)")
    parser.add_argument("--out", metavar="DIR", default="reports",
                        help="output directory of ivdrem-paper.html and ivdrem-paper.pdf (default: reports)")
    parser.add_argument("--t-end", metavar="SECONDS", type=float, default=None, dest="t_end",
                        help="simulated horizon, overrides experiment.t_end")
    parser.add_argument("--laws", metavar="NAME", nargs="+", default=None,
                        help="adaptation laws to run, overrides experiment.laws; 'all' or any of: "
                             + ", ".join(LAWS))
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--engine", choices=("compiled", "reference"), default="compiled",
                        help="compiled (numba, default) or reference (python-control) evaluation")
    parser.add_argument("--no-fmu-check", action="store_true", dest="no_fmu_check",
                        help="skip the plant-FMU co-simulation check (needs a C compiler)")
    parser.add_argument("--fmu-check-t-end", type=float, default=10.0, metavar="SECONDS",
                        help="horizon of the FMU co-simulation check (default 10 s)")
    return parser


def fmu_check(config, t_end=10.0, *, engine="compiled", progress=False):
    """Export the plant FMU, co-simulate the IV-DREM controller against it at three
    communication steps, and return (rows for the report table, comparison)."""
    import tempfile
    from pathlib import Path

    from ..experiments.config import closed_loop_kwargs
    from ..experiments.paper import _model
    from ..fmu import export_fmu
    from ..fmu.cosim import compare_to_python

    model = _model(config)
    kw = closed_loop_kwargs(config, "iv-drem")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "Plant.fmu"
        export_fmu(model, path, q0=kw["q0"], dq0=kw["dq0"])
        cmp = compare_to_python(path, t_end, law="iv-drem", model=model, engine=engine,
                                progress=progress, **kw)
    rows = {}
    for sig in cmp.signals:
        for i, H in enumerate(cmp.comm_steps):
            rows[f"{sig}, H = {H:g} s"] = {
                "max |co-sim − Python|": float(cmp.errors[sig][i]),
                "observed order": ("" if i == 0 else f"{cmp.orders[sig][i - 1]:.2f}")}
    rows["verdict"] = {"max |co-sim − Python|": cmp.verdict(), "observed order": ""}
    return rows, cmp


def config_from_args(args) -> dict:
    """The validated configuration of the command line (raises ConfigError)."""
    overrides: dict = {}
    if getattr(args, "t_end", None) is not None:
        overrides["experiment.t_end"] = args.t_end
    if getattr(args, "laws", None):
        overrides["experiment.laws"] = list(args.laws)
    return load_config(getattr(args, "config", None), overrides or None)


def run_report_command(args) -> int:
    """Validate the configuration, run the experiment, write the report; exit status."""
    try:
        config = config_from_args(args)
    except ConfigError as exc:
        print(f"ivdrem report: error: {exc}", file=sys.stderr)
        return 2

    from ..experiments.metrics import conclusions, format_conclusions
    from .report import ReportError, report_paths, write_report

    try:  # refuse an unusable output directory before minutes of simulation
        report_paths(args.out)
    except (ReportError, ValueError) as exc:
        print(f"ivdrem report: error: {exc}", file=sys.stderr)
        return 2

    from ..experiments.paper import run_paper

    run = run_paper(config, progress=not args.quiet, engine=args.engine, log=print)
    check = None
    if not getattr(args, "no_fmu_check", False):
        try:
            check, cmp = fmu_check(config, args.fmu_check_t_end, engine=args.engine,
                                   progress=not args.quiet)
            print(cmp.table())
            print(cmp.verdict())
        except Exception as exc:   # no C compiler, ...: the report still gets written
            print(f"ivdrem report: FMU check skipped: {exc}", file=sys.stderr)
            check = {"FMU check": {"result": f"not run: {exc}"}}
    html_path, pdf_path = write_report(run, args.out, fmu_check=check)
    print(f"HTML report: {html_path}")
    print(f"PDF report:  {pdf_path}")
    print(format_conclusions(conclusions(run)))
    return 0


def main(argv=None) -> int:  # pragma: no cover - convenience for `python -m ivdrem.reports.cli`
    parser = add_report_arguments(argparse.ArgumentParser(prog="ivdrem report"))
    return run_report_command(parser.parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
