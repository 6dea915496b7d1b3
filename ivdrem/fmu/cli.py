"""``ivdrem fmu ...`` sub-commands (routed here by ivdrem.cli)."""
from __future__ import annotations

import argparse
import sys

from .export import DEFAULT_SUBSTEP


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ivdrem fmu", description="Plant FMU (FMI 2.0, ME + CS)")
    sub = p.add_subparsers(dest="command", required=True)
    e = sub.add_parser("export", help="export the robot plant as an FMU (generated C, compiled)",
                       description="Generate C for the plant of a model of ivdrem.models, "
                                   "compile it with the system C compiler and write an FMI 2.0 "
                                   "FMU (model exchange + co-simulation).")
    e.add_argument("--model", default="two-link",
                   help="model name: two-link (default) or planar-N, e.g. planar-3")
    e.add_argument("-o", "--output", required=True, metavar="FILE.fmu", help="output file")
    e.add_argument("--q0", type=float, nargs="+", metavar="Q", help="start values of q")
    e.add_argument("--dq0", type=float, nargs="+", metavar="DQ", help="start values of dq")
    e.add_argument("--substep", type=float, default=DEFAULT_SUBSTEP,
                   help="co-simulation RK4 sub-step bound cs_substep in s (default %(default)g)")
    e.add_argument("--cc", default=None, help="C compiler (default $CC or cc)")
    e.add_argument("--no-compile", action="store_true",
                   help="ship sources only (build later with `fmpy compile`)")
    return p


def main_fmu(argv=None) -> int:
    """Entry point of ``ivdrem fmu``; ``argv`` excludes the leading ``fmu``. Returns exit code."""
    args = _parser().parse_args(argv)
    if args.command == "export":
        from ivdrem.models import get_model
        from .export import export_fmu
        try:
            model = get_model(args.model)
            path = export_fmu(model, args.output, q0=args.q0, dq0=args.dq0,
                              substep=args.substep, cc=args.cc, compile=not args.no_compile)
        except (ValueError, RuntimeError, NotImplementedError, FileNotFoundError) as exc:
            print(f"ivdrem fmu export: error: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {path} (model {model.name}, n = {model.n}, ntheta = {model.ntheta})")
        return 0
    return 2  # pragma: no cover  (argparse enforces the sub-command)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main_fmu())
