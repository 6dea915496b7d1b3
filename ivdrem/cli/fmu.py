"""``ivdrem fmu ...`` and ``ivdrem cosim ...`` sub-commands (routed here by ivdrem.cli)."""
from __future__ import annotations

import argparse
import sys


def _model_names() -> list[str]:
    """The names ``ivdrem.models.get_model`` accepts, from the models package itself."""
    from ivdrem.models import model_names
    return list(model_names())


def _parser() -> argparse.ArgumentParser:
    from ..fmu import DEFAULT_SUBSTEP
    p = argparse.ArgumentParser(prog="ivdrem fmu", description="Plant FMU (FMI 2.0, ME + CS)")
    sub = p.add_subparsers(dest="command", required=True)
    e = sub.add_parser("export", help="export the robot plant as an FMU (generated C, compiled)",
                       description="Generate C for the plant of a model of ivdrem.models, "
                                   "compile it with the system C compiler and write an FMI 2.0 "
                                   "FMU (model exchange + co-simulation).")
    e.add_argument("--model", default=None,
                   help="model name (default: the configuration's, else two-link), any of "
                        "ivdrem.models: " + ", ".join(_model_names())
                        + "; --controller also takes a URDF file")
    e.add_argument("--config", default=None, metavar="ARM.toml",
                   help="experiment configuration: its robot, and with --controller its "
                        "experiment as the FMU's defaults (reference, gains, window, law)")
    e.add_argument("-o", "--output", required=True, metavar="FILE.fmu",
                   help="output file (an existing one only if ivdrem exported it, or with "
                        "--overwrite)")
    e.add_argument("--overwrite", action="store_true",
                   help="replace an existing output file that ivdrem did not write")
    e.add_argument("--q0", type=float, nargs="+", metavar="Q", help="start values of q")
    e.add_argument("--dq0", type=float, nargs="+", metavar="DQ", help="start values of dq")
    e.add_argument("--substep", type=float, default=DEFAULT_SUBSTEP,
                   help="co-simulation RK4 sub-step bound cs_substep in s (default %(default)g)")
    e.add_argument("--cc", default=None, help="C compiler (default $CC or cc)")
    e.add_argument("--no-compile", action="store_true",
                   help="ship sources only (build later with `fmpy compile`)")
    e.add_argument("--controller", action="store_true",
                   help="export the sampled controller (co-simulation FMU) instead of the plant")
    e.add_argument("--law", default="iv-drem", help="--controller: the law (default iv-drem)")
    e.add_argument("--fmi-version", type=int, choices=(2, 3), default=2, dest="fmi_version",
                   help="--controller: FMI 2.0 or 3.0 co-simulation FMU (default 2)")
    e.add_argument("--mu-max", type=float, default=None, dest="mu_max",
                   help="--controller: saturation of mu (default 135)")
    e.add_argument("--h", type=float, default=None, dest="h", metavar="H",
                   help="--controller: sample period in s (default: the configuration's "
                        "[solver] h, 0.001 s in the default); must divide the window T")
    e.add_argument("--mix-every", default=None, dest="mix_every", metavar="M",
                   help="--controller: the mixing (17), or composite learning's max-hold, "
                        "every M samples, its work spread over them (a whole number from 1 "
                        "to the window's samples; default: 20 for a URDF arm, 1 for the "
                        "paper's arms)")
    e.add_argument("--despite-prediction", action="store_true", dest="despite_prediction",
                   help="--controller: export even a sampled loop predicted unstable (by "
                        "default refused before anything is built)")
    e.add_argument("--quiet", action="store_true",
                   help="no progress bars (--controller: the stability prediction's)")
    return p


def _controller_inputs_refused(args) -> str | None:
    """Why the controller export's input files cannot be read (a missing, unreadable or
    non-TOML ``--config``; a ``--model`` URDF file that is missing or not a regular file),
    or None: asked before the library is imported."""
    from .._config_file import ConfigError, read_toml
    from .._paths import not_a_regular_file, user_path
    if args.config is not None:
        try:
            read_toml(user_path(args.config))
        except ConfigError as exc:
            return str(exc)
    if args.model is not None and str(args.model).lower().endswith(".urdf"):
        path = user_path(args.model)
        kind = not_a_regular_file(path)
        if kind is not None:
            return f"URDF file '{path}' is {kind}, not a regular file"
        if not path.exists():
            return f"URDF file '{path}' not found"
    return None


def main_fmu(argv=None) -> int:
    """Entry point of ``ivdrem fmu``; ``argv`` excludes the leading ``fmu``. Returns exit code."""
    args = _parser().parse_args(argv)
    if args.command == "export" and args.controller:
        refused = _controller_inputs_refused(args)     # before python-control and SciPy
        if refused:
            print(f"ivdrem fmu export: error: {refused}", file=sys.stderr)
            return 2
        from . import import_library
        import_library()
        from ivdrem.controller.fmu_export import main_export_controller
        return main_export_controller(args)
    if args.command == "export":
        from .._config_file import read_toml
        from .._paths import user_path
        try:
            if args.config is not None:      # the file before python-control and SciPy
                read_toml(user_path(args.config))
            from . import import_library
            import_library()
            from ivdrem.models import get_model
            from ..fmu.export import export_fmu
            if args.config is not None:
                from ivdrem.experiments.config import read_config
                from ivdrem.experiments.experiment import Experiment
                over = {} if args.model is None else {"model.name": args.model}
                # the configuration checked whole against its model (built once); the
                # plant needs no law
                model = Experiment.from_config(read_config(user_path(args.config), over),
                                               laws=[]).model
            else:
                model = get_model(args.model or "two-link")
            path = export_fmu(model, user_path(args.output), q0=args.q0, dq0=args.dq0,
                              substep=args.substep, cc=args.cc, compile=not args.no_compile,
                              overwrite=args.overwrite)
        except (ValueError, RuntimeError, NotImplementedError, OSError, ImportError) as exc:
            print(f"ivdrem fmu export: error: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {path} (model {model.name}, n = {model.n}, ntheta = {model.ntheta})")
        return 0
    return 2  # pragma: no cover  (argparse enforces the sub-command)


# ----------------------------------------------------------------------------- cosim
def _cosim_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ivdrem cosim",
        description="Co-simulate the controller (ivdrem simulator) with the plant FMU "
                    "(fmpy, co-simulation interface) at communication steps H, H/2, H/4, "
                    "compare q, theta_hat and tau_d_hat with the all-Python closed loop and "
                    "report the max errors and the observed order of convergence "
                    "(sample-and-hold coupling: first order in H).")
    p.add_argument("--t-end", type=float, default=None,
                   help="horizon in s (default 40; --plant mujoco: the configuration's); a "
                        "multiple of the comm step")
    from . import LawNames
    law = p.add_argument("--law", default="iv-drem", choices=LawNames(), metavar="LAW",
                         help="composite term of the controller, one of: %(law_names)s "
                              "(default %(default)s)")
    law.law_names = LawNames()
    p.add_argument("--comm-step", type=float, default=1e-3, metavar="H",
                   help="largest communication step H in s; also runs H/2 and H/4 "
                        "(default %(default)g)")
    p.add_argument("--fmu", default=None, metavar="FILE",
                   help="plant FMU (default: export the configuration's robot to a temporary "
                        "directory)")
    p.add_argument("--config", default=None, metavar="FILE.toml",
                   help="experiment configuration: robot, gains, reference, disturbance, q(0) "
                        "(default: the paper's 2-link experiment)")
    p.add_argument("--engine", default="compiled", choices=("compiled", "reference"),
                   help="controller / reference simulator engine (default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--allow-long", action="store_true", dest="allow_long",
                   help="run even when the reference run's estimated memory or step count "
                        "exceeds the limits of ivdrem.sim.guards")
    p.add_argument("--despite-prediction", action="store_true", dest="despite_prediction",
                   help="co-simulate even where the coupling at H is predicted to diverge "
                        "(by default that is refused before anything is built)")
    p.add_argument("--controller-fmu", default=None, metavar="FILE", dest="controller_fmu",
                   help="close this controller FMU (ivdrem fmu export --controller) around the "
                        "plant FMU in FMPy and compare with the C reference controller")
    p.add_argument("--plant", default="fmu", choices=("fmu", "mujoco"),
                   help="fmu: compare with the plant FMU (default); mujoco: close the sampled "
                        "controller around the arm in MuJoCo (docs/mujoco.md)")
    from ivdrem.cli.plants import add_arguments
    add_arguments(p)
    return p


def main_cosim(argv=None) -> int:
    """Entry point of ``ivdrem cosim``; ``argv`` excludes the leading ``cosim``.

    Exit codes: 0 the comparison ran and the observed orders are in the expected range;
    1 it ran but the orders are outside it, or a run failed (divergence, FMU error);
    2 bad input (arguments, missing or unsuitable FMU).
    """
    import math
    import tempfile
    import time
    import warnings
    from pathlib import Path

    from . import import_library
    try:        # the arguments before python-control and SciPy are imported
        args = _cosim_parser().parse_args(argv)
    except SystemExit as exc:           # --help (0) or an argparse error (2, already printed)
        return int(exc.code or 0)
    prog = "ivdrem cosim"
    if args.plant == "mujoco":
        import_library()
        from ivdrem.cli.plants import main_cosim_mujoco
        return main_cosim_mujoco(args)
    if args.t_end is None:
        args.t_end = 40.0
    if args.controller_fmu is not None:
        import_library()
        from ivdrem.controller.fmu_loop import main_cosim_controller
        return main_cosim_controller(args)
    H = args.comm_step
    if not (math.isfinite(args.t_end) and args.t_end > 0):
        print(f"{prog}: error: --t-end must be a finite number > 0, got {args.t_end:g}",
              file=sys.stderr)
        return 2
    if not (math.isfinite(H) and 0 < H <= args.t_end):
        print(f"{prog}: error: --comm-step must be in (0, t_end], got {H:g}", file=sys.stderr)
        return 2
    import_library()
    from ivdrem._paths import user_path
    from ivdrem._progress import want_progress
    from ivdrem.sim import SimulationError
    from ..fmu.cosim import CosimError, _steps, compare_to_python
    progress = want_progress(not args.quiet)
    steps = (H, H / 2, H / 4)
    fmu_path = None if args.fmu is None else user_path(args.fmu)
    try:   # every option before exporting or simulating anything
        for h, what in zip(steps, ("--comm-step H", "H/2", "H/4")):
            _steps(args.t_end, h, what)
        from ivdrem.cli.preflight import check_cache_dir
        from ivdrem.experiments.config import read_config
        from ivdrem.experiments.experiment import Experiment
        check_cache_dir(args.engine)
        data = read_config(None if args.config is None else user_path(args.config))
        experiment = Experiment.from_config(data, engine=args.engine, laws=[args.law])
        model = experiment.model
        setup = experiment.law(args.law)
        loop_kw = setup.arguments()
        if not args.despite_prediction:
            # the explicit coupling at H, linearized at t = 0 (docs/fmu.md, "Co-simulation
            # check"): a run predicted to diverge is refused before any build or export
            from ..fmu.cosim import coupling_stability
            predicted = coupling_stability(model, H, args.t_end, **loop_kw)
            if predicted.diverges:
                raise ValueError(
                    f"the co-simulation is predicted to diverge: {predicted.reason()}.  Give "
                    f"--comm-step below {predicted.limit_end * 1e3:.2g} ms, or "
                    "--despite-prediction to run it anyway")
        if fmu_path is not None:  # missing, not an FMU, damaged, no CS, not this robot's plant
            from ..fmu.cosim import _check_interface
            from ..fmu.describe import read_description
            _check_interface(fmu_path, read_description(fmu_path, "co-simulation"), model)
        from ivdrem.sim.guards import check_diagram_cost
        from ivdrem.sim.methods import REFERENCE_METHOD
        reference = experiment.loop(args.law)     # a γ "auto" at a placeholder: priced
        if setup.auto:
            experiment.choose_gamma(args.law)
            loop_kw = setup.arguments()           # one γ "auto" for every run
        # the all-Python reference: RK4 at the finest H, sampled there
        check_diagram_cost(reference, args.t_end, engine=args.engine,
                           method=REFERENCE_METHOD, h=min(steps), dt_out=min(steps),
                           return_states=False, allow_long=args.allow_long,
                           what="the reference run")
        del reference      # compare_to_python builds each loop when it runs, one at a time
        experiment.release(args.law)
    except (ValueError, OSError, ImportError) as exc:   # OSError: missing FMU, cache
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ivdrem_cosim_") as tmp:
        if args.fmu is None:
            from ..fmu.export import export_fmu
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")   # compiler chatter; the FMU is tested
                    fmu = export_fmu(model, Path(tmp) / "plant.fmu", q0=loop_kw.get("q0"),
                                     dq0=loop_kw.get("dq0"))
            except (RuntimeError, NotImplementedError, FileNotFoundError) as exc:
                print(f"{prog}: error: exporting the plant FMU failed: {exc}", file=sys.stderr)
                return 2
            origin = f"{model.name} plant exported to a temporary FMU"
        else:
            fmu = fmu_path
            origin = str(fmu)
        try:
            cmp = compare_to_python(fmu, args.t_end, steps, law=args.law, model=model,
                                    engine=args.engine, progress=progress,
                                    allow_long=args.allow_long, **loop_kw)
        except (FileNotFoundError, ValueError) as exc:
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return 2
        except (SimulationError, CosimError) as exc:
            print(f"{prog}: run failed: {exc}", file=sys.stderr)
            return 1
    wall = time.perf_counter() - t0
    print(f"Co-simulation: controller {args.law!r} (ivdrem simulator, {args.engine}) + plant FMU "
          f"({origin}), t_end = {args.t_end:g} s")
    print("Coupling: explicit (Jacobi) sample-and-hold at communication step H; reference: "
          f"all-Python closed loop, RK4 at h = {min(steps):g} s")
    print()
    print(cmp.table())
    print()
    times = ", ".join(f"{k} {v:.1f} s" for k, v in cmp.wall.items())
    per_step = ", ".join(f"H={r.stats['comm_step']:g}: {r.stats['us_per_step']:.0f} us"
                         for r in cmp.results)
    print(f"wall time {wall:.1f} s ({times}); per communication step {per_step}")
    print(cmp.verdict())
    return 0 if cmp.ok else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main_fmu())
