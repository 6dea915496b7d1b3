"""The ``ivdrem study`` command (a grid or Monte Carlo study of the experiment on a Dask
cluster, :func:`ivdrem.experiments.study.run_study`; a MuJoCo robustness study goes to
:mod:`ivdrem.cli.plants`): its options, the run, the report written from its results
(:func:`ivdrem.reports.study_report.write_study_report_of`), the lines it prints."""
from __future__ import annotations

import sys
from pathlib import Path

from .._paths import user_path

__all__ = ["add_study_arguments", "run_study_command", "summary_text"]


def add_study_arguments(parser):
    """Options of ``ivdrem study``."""
    parser.add_argument("study", metavar="FILE.toml",
                        help="study file: a configuration plus [study.grid] / [study.random] "
                             "(see examples/study-window.toml, docs/studies.md)")
    parser.add_argument("--out", metavar="DIR", default=None,
                        help="output directory (default: studies/<name of FILE>)")
    parser.add_argument("--workers", metavar="N", type=int, default=None,
                        help="worker processes of the local Dask cluster (default: one per core)")
    parser.add_argument("--scheduler", metavar="ADDRESS", default=None,
                        help="submit to a running Dask scheduler, e.g. tcp://HOST:8786, whose "
                             "workers have ivdrem installed")
    parser.add_argument("--resume", action="store_true",
                        help="continue a study in DIR: skip the runs already finished there")
    parser.add_argument("--no-report", action="store_true", dest="no_report",
                        help="write the tables only, not study.html / study.pdf")
    parser.add_argument("--quiet", action="store_true", help="no progress bar, no notes on long preparation")
    return parser


def run_study_command(args) -> int:
    """``ivdrem study``: 0 when every run has a record, 1 when runs were lost, 2 for bad input."""
    # Paths on the command line are the caller's (see ivdrem._paths), as for every command.
    study = user_path(args.study)
    out = user_path(args.out if args.out is not None else Path("studies") / study.stem)
    report = not args.no_report
    from .._config_file import ConfigError, read_toml
    try:      # the file before python-control, SciPy and Dask are imported
        read_toml(study, "study file")
    except ConfigError as exc:
        print(f"ivdrem study: error: {exc}", file=sys.stderr)
        return 2
    from . import import_library
    import_library()
    from ..experiments.study import RunStore, StudyError, run_study
    try:
        if report:    # a foreign study.html / study.pdf is refused before any work
            from ..reports.study_report import report_paths
            try:
                report_paths(out)
            except FileExistsError as exc:
                raise StudyError(str(exc)) from None
        result = run_study(study, out, workers=args.workers, scheduler=args.scheduler,
                           resume=args.resume, progress=False if args.quiet else None)
    except StudyError as exc:
        print(f"ivdrem study: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:      # Ctrl-C, or SIGTERM (ivdrem.cli.Terminated)
        done = len(RunStore(Path(out)).load())
        how = getattr(exc, "label", "Ctrl-C")
        print(f"\nivdrem study: interrupted ({how}); {done} finished run(s) are saved in "
              f"{out}/runs; continue with --resume", file=sys.stderr)
        from . import EXIT_INTERRUPTED
        return 128 + exc.signum if hasattr(exc, "signum") else EXIT_INTERRUPTED
    if report:
        from .._atomic import os_error_behind
        from ..reports.study_report import write_study_report_of
        try:
            write_study_report_of(result)
        except Exception as exc:
            cause = os_error_behind(exc)
            if cause is None:
                raise
            # the runs and the tables are written: only the report is missing
            print(f"ivdrem study: error: cannot write the report in {out}: "
                  f"{cause.strerror or cause}; the {len(result.results)} run(s) and the tables "
                  f"are saved there (the report can be rebuilt from them: "
                  f"ivdrem.reports.study_report.rebuild_study_report)", file=sys.stderr)
            return 2
    print(summary_text(result))
    return 1 if result.lost else 0


def summary_text(result) -> str:
    """A few lines for the terminal from a study's results
    (:class:`~ivdrem.experiments.study.StudyResult`): counts, medians per law, verdicts,
    lost runs, files."""
    df, out = result.results, result.out
    lines = []
    n_ok = int((df["status"] == "ok").sum()) if not df.empty else 0
    n_bad = len(df) - n_ok
    wall = result.wall_s
    lines.append(f"{len(df)} runs: {n_ok} ok, {n_bad} failed"
                 + (f"; {wall:.1f} s in this session" if wall is not None else ""))
    if n_ok:
        ok = df[df["status"] == "ok"]
        for law, sub in ok.groupby("law", sort=False):
            lines.append(f"{law:>20s}: median |theta_err|(t_end) = {sub['theta_err_norm'].median():.4g} "
                         f"(min {sub['theta_err_norm'].min():.4g}, max {sub['theta_err_norm'].max():.4g}), "
                         f"median RMS tau_d err last 20% = {sub['tau_d_err_rms_last20'].median():.4g} N m")
        pts = df.drop_duplicates("point")
        for c in ("C1", "C2", "C3"):
            v = pts[c].dropna()
            if len(v):
                lines.append(f"{c}: PASS at {int(v.sum())} of {len(v)} points")
    for h, msg in result.lost.items():
        lines.append(f"lost run {h}: {msg} (run again with --resume)")
    lines.append(f"wrote {out}/results.parquet, results.csv, curves.parquet"
                 + ("" if not (Path(out) / "study.html").exists() else ", study.html, study.pdf"))
    return "\n".join(lines)
