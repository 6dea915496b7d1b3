"""The ``ivdrem report`` command: run the paper experiment and write the report.

``ivdrem.cli`` wires it as a subcommand::

    p = sub.add_parser("report", help="run the paper experiment and write the PDF/HTML report")
    add_report_arguments(p)
    p.set_defaults(func=run_report_command)
"""
from __future__ import annotations

import argparse
import sys

from .._config_file import ConfigError, read_toml
from .._paths import OutputLocationError, check_writable_dir, user_path
from .preflight import (PreflightError, add_run_options, check_cache_dir, check_fmu_check_t_end,
                          check_method, check_runs, config_from_args, horizon_note, timing_text)
from .._progress import want_progress

__all__ = ["add_report_arguments", "run_report_command", "config_from_args", "fmu_check",
           "FmuCheckNotRun"]


def add_report_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the options of ``ivdrem report`` to ``parser``."""
    parser.add_argument("--config", metavar="FILE.toml", default=None,
                        help="experiment configuration merged over the embedded default "
                             "(see examples/paper.toml)")
    parser.add_argument("--out", metavar="DIR", default="reports",
                        help="output directory of ivdrem-paper.html and ivdrem-paper.pdf (default: reports)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace ivdrem-paper.html/.pdf in --out even if ivdrem did not write them")
    parser.add_argument("--t-end", metavar="SECONDS", type=float, default=None, dest="t_end",
                        help="simulated horizon, overrides experiment.t_end (conclusions C1-C3 "
                             "need the default 300 s)")
    from . import LawNames
    laws = parser.add_argument(
        "--laws", metavar="NAME", nargs="+", default=None,
        help="adaptation laws to run, overrides experiment.laws; 'all' or any of: %(law_names)s")
    laws.law_names = LawNames()      # the registry imported only to print the help
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--engine", choices=("compiled", "reference"), default="compiled",
                        help="compiled (default: the C stepper over numba-compiled block "
                        "kernels) or reference (the C stepper calling python-control)")
    add_run_options(parser)
    parser.add_argument("--plant", choices=("ivdrem", "mujoco"), default="ivdrem",
                        help="ivdrem (default: the experiment on ivdrem's own plant) or mujoco "
                             "(the arm in MuJoCo around the sampled C controller, "
                             "docs/mujoco.md; writes ivdrem-mujoco.html/.pdf)")
    parser.add_argument("--no-fmu-check", action="store_true", dest="no_fmu_check",
                        help="skip the plant-FMU co-simulation check (needs a C compiler)")
    parser.add_argument("--fmu-check-t-end", type=float, default=10.0, metavar="SECONDS",
                        help="horizon of the FMU co-simulation check (default 10 s; a whole "
                             "number of milliseconds)")
    return parser


class FmuCheckNotRun(Exception):
    """The FMU check is predicted to diverge and was not run; the message says why, with
    the numbers, and what to do instead."""


def fmu_check(experiment, t_end=10.0, *, engine=None, progress=False, allow_long=False,
              gamma=None):
    """Export the plant FMU, co-simulate the IV-DREM controller against it at three
    communication steps, and return (rows for the report table, comparison).

    `experiment`: the report's :class:`~ivdrem.experiments.experiment.Experiment` (or a
    configuration).  First, before exporting or building anything, the explicit coupling
    at the coarsest step is predicted from the model and the configuration
    (:func:`ivdrem.cli.preflight.fmu_check_prediction`); if it diverges, :class:`FmuCheckNotRun`
    is raised with the reason.  Then :func:`~ivdrem.fmu.cosim.compare_to_python`, which
    co-simulates at the coarsest step before it builds the all-Python loop.

    With ``iv_drem.gamma = "auto"`` the check uses `gamma` if given, else the experiment's
    choice (made once, by the report's IV-DREM run or here).  Calibrating again inside the
    co-simulation took DP45 at 10 ms steps over 2T, a stiff loop on a real arm (the Panda:
    minutes)."""
    import tempfile
    from pathlib import Path

    from .preflight import FMU_CHECK_COMM_STEPS, experiment_of, fmu_check_prediction
    from ..fmu import export_fmu
    from ..fmu.cosim import compare_to_python

    experiment = experiment_of(experiment, engine)
    engine = experiment.engine if engine is None else engine
    predicted = fmu_check_prediction(experiment, t_end)
    if predicted.diverges:
        raise FmuCheckNotRun(
            f"predicted to diverge: {predicted.reason()}.  The check co-simulates at H = "
            + ", ".join(f"{H * 1e3:g}" for H in FMU_CHECK_COMM_STEPS)
            + f" ms; to check the plant FMU on this arm use `ivdrem cosim --config FILE.toml "
            f"--comm-step H --t-end {float(t_end):g}` with H below "
            f"{predicted.limit_end * 1e3:.2g} ms, or leave the check out with --no-fmu-check")
    model = experiment.model
    setup = experiment.law("iv-drem")
    if setup.auto and gamma is None:
        experiment.choose_gamma("iv-drem")
    kw = setup.arguments()
    if setup.auto and gamma is not None:
        kw["gains"]["gamma"] = gamma
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "Plant.fmu"
        export_fmu(model, path, q0=kw["q0"], dq0=kw["dq0"])
        cmp = compare_to_python(path, t_end, law="iv-drem", model=model, engine=engine,
                                progress=progress, allow_long=allow_long, **kw)
    rows = {}
    for sig in cmp.signals:
        for i, H in enumerate(cmp.comm_steps):
            rows[f"{sig}, H = {H:g} s"] = {
                "max |co-sim − Python|": float(cmp.errors[sig][i]),
                "observed order": ("" if i == 0 else f"{cmp.orders[sig][i - 1]:.2f}")}
    rows["verdict"] = {"max |co-sim − Python|": cmp.verdict(), "observed order": ""}
    return rows, cmp


def _preflight(args):
    """Everything checked before the first simulation step: (experiment, html, pdf
    paths)."""
    # the options, the files and the compiler first, before python-control, SciPy and
    # Matplotlib are imported: a typo costs a tenth of a second, not three
    check_method(args.method)
    if args.config is not None:
        read_toml(user_path(args.config))
    if not args.no_fmu_check:
        check_fmu_check_t_end(args.fmu_check_t_end)
    out = check_writable_dir(user_path(args.out), "report directory")
    check_cache_dir(args.engine)
    from . import import_library
    import_library()
    from ..experiments.experiment import Experiment
    from ..reports.report import report_paths

    config = config_from_args(args)
    html_path, pdf_path = report_paths(out, overwrite=args.overwrite)
    experiment = Experiment.from_config(config, engine=args.engine)     # resolved once
    check_runs(experiment, allow_long=args.allow_long,
               fmu_check_t_end=None if args.no_fmu_check else args.fmu_check_t_end)
    return experiment, html_path, pdf_path


def _write_or_keep(run, out, check, overwrite):
    """write_report, and if writing to `out` fails at the end, to a new temporary
    directory instead: (html, pdf, the error or None)."""
    import tempfile

    from .._atomic import os_error_behind
    from ..reports.report import write_report
    try:
        return (*write_report(run, out, fmu_check=check, overwrite=overwrite), None)
    except Exception as exc:
        cause = os_error_behind(exc)
        if cause is None:
            raise
        keep = tempfile.mkdtemp(prefix="ivdrem-report-")
        return (*write_report(run, keep, fmu_check=check), cause)


def _refused(exc) -> bool:
    """Whether `exc` is a refusal of :func:`_preflight` (one line, exit status 2).  Its
    ReportError (a report file ivdrem did not write) can only come once
    ``ivdrem.reports.report`` is imported, which imports Matplotlib: not before."""
    kinds = (ConfigError, PreflightError, OutputLocationError, ValueError, ImportError)
    report = sys.modules.get("ivdrem.reports.report")
    return isinstance(exc, kinds + ((report.ReportError,) if report is not None else ()))


def run_report_command(args) -> int:
    """Check every option and output location, run the experiment, write the report;
    returns the exit status (2: refused before any work, 1: a run or the write failed)."""
    if getattr(args, "plant", "ivdrem") == "mujoco":
        from . import import_library
        import_library()
        from .plants import run_mujoco_report
        return run_mujoco_report(args)
    args.overwrite = getattr(args, "overwrite", False)
    args.allow_long = getattr(args, "allow_long", False)
    try:
        experiment, html_path, pdf_path = _preflight(args)
    except Exception as exc:
        if not _refused(exc):
            raise
        print(f"ivdrem report: error: {exc}", file=sys.stderr)
        return 2
    note = horizon_note(experiment.config)
    if note:
        print(f"ivdrem report: {note}", file=sys.stderr)

    from ..experiments.metrics import conclusions, format_conclusions
    from ..experiments.paper import run_paper
    from ..sim import SimulationError

    progress = want_progress(not args.quiet)
    extra = {"allow_long": True} if args.allow_long else {}
    try:
        run = run_paper(experiment, progress=progress, log=print, **extra)
    except SimulationError as exc:
        print(f"ivdrem report: simulation failed: {exc}", file=sys.stderr)
        return 1
    except ValueError as exc:        # gamma = "auto" refused (diagrams.gamma_auto.GainRuleError)
        print(f"ivdrem report: error: {exc}", file=sys.stderr)
        return 2
    for law, lr in run.runs.items():
        print(f"{law:>20s}: {lr.stats.get('steps', '?')} steps, {timing_text(lr.stats)}")
    check = None
    if not args.no_fmu_check:
        try:
            ivdrem_run = run.runs.get("iv-drem")
            check, cmp = fmu_check(experiment, args.fmu_check_t_end,
                                   progress=progress,
                                   gamma=getattr(ivdrem_run, "gamma", None), **extra)
            print(cmp.table())
            print(cmp.verdict())
        except FmuCheckNotRun as exc:
            print(f"ivdrem report: FMU check not run: {exc}", file=sys.stderr)
            check = {"FMU check": {"result": f"not run: {exc}"}}
        except Exception as exc:   # no C compiler, ...: the report still gets written
            print(f"ivdrem report: FMU check skipped: {exc}", file=sys.stderr)
            check = {"FMU check": {"result": f"not run: {exc}"}}
    html, pdf, failed = _write_or_keep(run, html_path.parent, check, args.overwrite)
    if failed is not None:
        print(f"ivdrem report: error: cannot write the report to {html_path.parent}: "
              f"{failed}; the results were kept in {html.parent}", file=sys.stderr)
    print(f"HTML report: {html}")
    print(f"PDF report:  {pdf}")
    print(format_conclusions(conclusions(run)))
    return 1 if failed is not None else 0


def main(argv=None) -> int:  # pragma: no cover - convenience for `python -m ivdrem.cli.report`
    parser = add_report_arguments(argparse.ArgumentParser(prog="ivdrem report"))
    try:
        return run_report_command(parser.parse_args(argv))
    except KeyboardInterrupt:
        from . import interrupted
        return interrupted("ivdrem report")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
