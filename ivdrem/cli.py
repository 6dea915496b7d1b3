"""Command line: ``ivdrem paper | report | fmu export | cosim``."""
from __future__ import annotations

import argparse
import json
import sys

from ._atomic import write_text_atomic

__all__ = ["main"]


def _cmd_paper(args):
    from .experiments.config import ConfigError, load_config
    from .experiments.metrics import conclusions, format_conclusions, summary
    from .experiments.paper import run_paper
    from .sim import SimulationError
    overrides = {}
    if args.t_end is not None:
        overrides["experiment.t_end"] = args.t_end
    if args.law:
        overrides["experiment.laws"] = list(args.law)
    try:
        config = load_config(args.config, overrides or None)
    except ConfigError as e:
        print(f"ivdrem paper: error: {e}", file=sys.stderr)
        return 2
    try:
        run = run_paper(config, progress=not args.quiet, engine=args.engine, log=print)
    except SimulationError as e:
        print(f"ivdrem paper: simulation failed: {e}", file=sys.stderr)
        return 1
    out = {law: summary(lr, run.theta) for law, lr in run.runs.items()}
    for law, s in out.items():
        st = run.runs[law].stats
        print(f"{law:>20s}: |theta_err|(t_end) = {s['theta_err_norm']:.4g}, "
              f"max|e| last 20% = {s['e_max_last20']:.3g} rad, "
              f"RMS tau_d err last 20% = {s['tau_d_err_rms_last20']:.4g} N m  "
              f"({st['steps']} steps, {st['wall_s']:.2f} s)")
    if set(run.runs) >= {"iv-drem", "composite-learning"}:
        print(format_conclusions(conclusions(run)))
    from .experiments.diagnostics import diagnose_run, format_diagnostics, to_json
    for law, d in diagnose_run(run).items():   # the assumptions of Theorem 2 on this run
        print(format_diagnostics(d))
        out[law]["diagnostics"] = to_json(d)
        gamma = getattr(run.runs[law], "gamma", None)
        if isinstance(gamma, (int, float)):
            out[law]["gamma"] = float(gamma)
    if args.json:
        write_text_atomic(args.json, json.dumps(out, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def _cmd_report(args):
    from .reports.cli import run_report_command
    return run_report_command(args)


def build_parser():
    from .reports.cli import add_report_arguments
    p = argparse.ArgumentParser(prog="ivdrem", description=(
        "Composite adaptive disturbance rejection via IV-based DREM "
        "(Glushchenko & Lastochkin): paper experiment, report, plant FMU."))
    sub = p.add_subparsers(dest="command", required=True)

    pp = sub.add_parser("paper", help="run the paper experiment and print/write its numbers")
    pp.add_argument("--t-end", type=float, default=None, metavar="SECONDS",
                    help="horizon (default from the config: 300 s)")
    pp.add_argument("--law", nargs="+", default=None, metavar="NAME",
                    help="laws to run, or 'all' (default: iv-drem composite-learning)")
    pp.add_argument("--json", default=None, metavar="FILE", help="write per-law numbers as JSON")
    pp.add_argument("--config", default=None, metavar="FILE.toml",
                    help="experiment configuration (see examples/paper.toml)")
    pp.add_argument("--engine", choices=("compiled", "reference"), default="compiled")
    pp.add_argument("--quiet", action="store_true", help="no progress bars")
    pp.set_defaults(func=_cmd_paper)

    rp = sub.add_parser("report", help="run the paper experiment and write the PDF/HTML report")
    add_report_arguments(rp)
    rp.set_defaults(func=_cmd_report)

    fp = sub.add_parser("fmu", help="plant FMU tools (ivdrem fmu export -o FILE.fmu)",
                        add_help=False)
    fp.set_defaults(func=None, passthrough="fmu")
    cp = sub.add_parser("cosim", help="co-simulate the controller with the plant FMU",
                        add_help=False)
    cp.set_defaults(func=None, passthrough="cosim")
    return p


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    # sub-commands owned by ivdrem.fmu parse their own arguments
    if argv and argv[0] in ("fmu", "cosim"):
        from .fmu import cli as fcli
        fn = fcli.main_fmu if argv[0] == "fmu" else getattr(fcli, "main_cosim", None)
        if fn is None:
            print("ivdrem cosim: not available in this version", file=sys.stderr)
            return 2
        return fn(argv[1:])
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
