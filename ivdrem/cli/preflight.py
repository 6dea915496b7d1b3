"""What ``ivdrem paper`` and ``ivdrem report`` check before the first simulation step.

Every option and every output location is checked first, so that a mistake costs a second,
not the minutes of a run: the solver method, the cost of each law's run (output memory and
a lower bound on the step count, :mod:`ivdrem.sim.guards`), a gamma = "auto" whose Δ the
reference estimate puts below the doubles, the FMU check's horizon, and that the compile
cache can be written.  The commands call these in order and print the error (exit status
2) without having simulated anything: γ "auto" is calibrated by its law's run.  They take
the command's :class:`~ivdrem.experiments.experiment.Experiment`: the loops they price are
the ones the runs then simulate.
"""
from __future__ import annotations

import argparse
import math

from .._paths import check_writable_dir

__all__ = ["PreflightError", "config_from_args", "add_run_options", "solver_methods", "check_method",
           "check_runs", "check_inertia", "pricing_diagram",
           "experiment_of", "check_fmu_check_t_end", "fmu_check_prediction",
           "check_cache_dir", "horizon_note",
           "timing_text", "CONCLUSIONS_HORIZON", "FMU_CHECK_COMM_STEPS"]

#: The horizon (s) that conclusions C1-C3 are stated for: the paper's Figures 1-4 and the
#: default experiment.t_end.  Shorter runs are allowed but their verdicts mostly FAIL.
CONCLUSIONS_HORIZON = 300.0
#: Communication steps of the report's FMU co-simulation check (compare_to_python's default).
FMU_CHECK_COMM_STEPS = (1e-3, 5e-4, 2.5e-4)


class PreflightError(ValueError):
    """A command-line option or output location refused before any work."""


def add_run_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options that ``paper`` and ``report`` share: --method, --allow-long."""
    parser.add_argument("--method", default=None, metavar="NAME",
                        help="integration method, overrides solver.method (default from the "
                             f"config: {_config_method()}); one of: {', '.join(solver_methods())}")
    parser.add_argument("--allow-long", action="store_true", dest="allow_long",
                        help="run even when the estimated output memory or step count "
                             "exceeds the limits of ivdrem.sim.guards")
    return parser


def _config_method() -> str:
    """solver.method of the built-in configuration (the --method help names it)."""
    from importlib import resources
    try:
        import tomllib
    except ImportError:  # pragma: no cover - Python < 3.11
        import tomli as tomllib
    text = resources.files("ivdrem.experiments").joinpath("default.toml").read_text()
    return str(tomllib.loads(text)["solver"]["method"])


def solver_methods() -> tuple:
    """The simulator's method names (the method registry, ivdrem.sim.methods)."""
    from ..sim.methods import METHODS
    return tuple(METHODS)


def check_method(name):
    """None, or a method name the simulator knows (raises PreflightError)."""
    if name is None:
        return None
    methods = solver_methods()
    if name not in methods:
        raise PreflightError(f"--method {name!r} is not a method of the simulator; "
                             f"valid: {', '.join(methods)}")
    return name


def method_overrides(name, config_path=None) -> dict:
    """Config overrides for ``--method NAME``: the method, and its default tolerances
    (Rodas5P runs at rtol 2e-4, DP45 needs 1e-6) unless the user's file sets them."""
    if check_method(name) is None:
        return {}
    from ..sim.methods import method_info
    user = {}
    if config_path is not None:
        try:   # a broken file is reported by read_config, with its own message
            from ..experiments.config import read_toml
            user = read_toml(config_path)[0].get("solver", {})   # never a FIFO or a device
        except Exception:
            user = {}
    out = {"solver.method": name}
    info = method_info(name)
    for key, value in zip(("rtol", "atol"), (info.rtol, info.atol)):
        if key not in user:
            out[f"solver.{key}"] = value
    return out


def experiment_of(experiment, engine=None):
    """`experiment` itself (an :class:`ivdrem.experiments.experiment.Experiment`), or the
    Experiment of a configuration (its model built, its laws resolved once)."""
    from ..experiments.experiment import Experiment
    return Experiment.of(experiment, engine=engine)


def check_runs(experiment, *, engine=None, allow_long=False, fmu_check_t_end=None):
    """Price every law's run of `experiment` (an
    :class:`~ivdrem.experiments.experiment.Experiment`, or a configuration) and the FMU
    check's, if a horizon is given, before any of them starts; raises ValueError
    (CostLimitError) with the numbers.  Returns [(law, estimated seconds)] of the runs whose
    time is estimated.

    It prices, it does not simulate: each law's loop is the one its run will simulate
    (``Experiment.loop``, built once; a γ "auto" is a parameter of it, chosen by the
    calibration before the run); then a γ "auto" whose mixing the reference estimate puts
    below the doubles is refused (``Experiment.check_gamma_auto``)."""
    from ..sim.guards import (check_diagram_cost, check_run_time, oscillation_steps,
                             paper_loop_steps, run_seconds)
    from ..sim.methods import REFERENCE_METHOD, method_info

    experiment = experiment_of(experiment, engine)
    engine = experiment.engine
    config, model = experiment.config, experiment.model
    check_inertia(config, model)
    exp = config["experiment"]
    walls, sources, fmu_loop = [], [], None
    for law in experiment.laws:
        solver = experiment.law(law).solver
        d = experiment.loop(law)
        experiment.check_cost(law, d, allow_long=allow_long)
        if law == "iv-drem" and fmu_check_t_end is not None:
            fmu_loop = d                   # the FMU check's loop, priced below
        # the paper's 2-link loop: the measured step count and time per step
        # (ivdrem.sim.guards); another robot's loop keeps the lower bound above
        measured = paper_loop_steps(law, solver["method"], float(exp["t_end"]),
                                    rtol=solver.get("rtol")) \
            if _is_paper_robot(config) else None
        if method_info(solver["method"]).adaptive:
            # any robot: an adaptive method follows the fastest sinusoid (a lower bound)
            bound = oscillation_steps(fastest_omega(config), float(exp["t_end"]))
            if measured is None or sum(bound[0]) > sum(measured[0]):
                measured = bound
        if measured is not None:
            (steps, explicit), source = measured
            wall = run_seconds((steps, explicit), engine)
            check_run_time(wall, f"about {steps + explicit:.3g} steps, {source}",
                           engine=engine, allow_long=allow_long,
                           what=f"the {law} run ({float(exp['t_end']):g} s)")
            walls.append((law, wall))
            sources.append(source)
    if len(walls) > 1:
        tight = [src for src in sources if "rtol =" in src]
        check_run_time(sum(w for _, w in walls),
                       " + ".join(f"{law} {w / 60:.0f} min" for law, w in walls)
                       + (f"; {tight[0].rsplit('; ', 1)[-1]}" if tight else ""),
                       engine=engine, allow_long=allow_long,
                       what=f"the {len(walls)} runs")
    if fmu_check_t_end is not None and \
            not fmu_check_prediction(experiment, fmu_check_t_end).diverges:
        d = fmu_loop or pricing_diagram(experiment, "iv-drem")
        h = min(FMU_CHECK_COMM_STEPS)   # its Python reference: fixed steps, the finest
        check_diagram_cost(d, float(fmu_check_t_end), engine=engine, method=REFERENCE_METHOD, h=h,
                           dt_out=h, return_states=False, allow_long=allow_long,
                           what=f"the FMU check (--fmu-check-t-end {float(fmu_check_t_end):g} s)")
    for law in experiment.laws:     # every run priced: the refusals of γ "auto" that need no run
        experiment.check_gamma_auto(law)
    return walls


#: A command whose runs are estimated above this many seconds says so before they start.
LONG_RUN_NOTE_S = 60.0


def long_run_note(walls) -> str | None:
    """One line announcing runs estimated above :data:`LONG_RUN_NOTE_S` (the list
    :func:`check_runs` returns), or None."""
    total = sum(w for _, w in walls or ())
    if total <= LONG_RUN_NOTE_S:
        return None
    parts = ", ".join(f"{law} {w / 60:.1f} min" for law, w in walls)
    return (f"note: the runs are estimated at about {total / 60:.0f} min ({parts}; measured "
            "step counts and times per step, ivdrem.sim.guards)")


def fastest_omega(config) -> float:
    """The highest frequency (rad/s) in the loop's exogenous signals: the disturbance's
    sinusoids and the reference's (a Fourier reference's highest harmonic)."""
    tr = config["trajectory"]
    if tr.get("kind", "sinusoid") == "fourier":
        ref = float(tr["omega_f"]) * len(tr["a"][0])
    else:
        ref = max(abs(float(w)) for w in tr["omega"])
    return max([ref] + [abs(float(w)) for w in config["disturbance"]["omega"]])


def check_inertia(config, model) -> None:
    """model.theta must give a positive definite inertia matrix M(q(0)) (Property 2 of the
    paper: M is bounded and positive definite): a zero or negative mass parameter would
    otherwise stop the first step with "singular inertia", blaming the plant block."""
    import numpy as np
    n = model.n
    q0 = np.asarray(config["initial"]["q0"], float)
    theta = np.asarray(config["model"]["theta"], float)
    M = np.empty((n, n))
    model.functions.M(q0, theta, M)
    smallest = float(np.linalg.eigvalsh(0.5 * (M + M.T))[0]) if np.all(np.isfinite(M)) \
        else float("nan")
    if not smallest > 0.0:
        raise PreflightError(
            f"config key 'model.theta' = {np.round(theta, 6).tolist()}: the inertia matrix "
            f"M(q) of model {model.name!r} at q(0) = {np.round(q0, 6).tolist()} is not "
            f"positive definite (smallest eigenvalue {smallest:.3g}); the mass and inertia "
            "parameters must be physical (positive masses and inertias)")


def pricing_diagram(experiment, law):
    """The loop whose cost `law`'s run of `experiment` (an Experiment, or a configuration)
    has: the run's own (``Experiment.loop``, a γ "auto" at a placeholder: the cost does not
    depend on γ's value, so nothing is calibrated)."""
    return experiment_of(experiment).loop(law)


def _is_paper_robot(config) -> bool:
    """True if the configuration's plant is the paper's 2-link arm (the loop the cost
    table of ivdrem.sim.guards was measured on)."""
    m = config.get("model", {})
    return m.get("urdf") is None and m.get("name") in ("two-link", "planar-2")


def fmu_check_prediction(experiment, t_end):
    """The FMU check's explicit coupling at its coarsest communication step, predicted
    from the model and the experiment (an Experiment, or a configuration) alone
    (:func:`ivdrem.fmu.cosim.coupling_stability`: ``.diverges``, ``.reason()``); a check
    predicted to diverge is not run, nor priced."""
    from ..fmu.cosim import coupling_stability
    experiment = experiment_of(experiment)
    return coupling_stability(experiment.model, max(FMU_CHECK_COMM_STEPS), float(t_end),
                              **experiment.law("iv-drem").loop)


def check_fmu_check_t_end(t_end) -> float:
    """--fmu-check-t-end: finite, > 0 and a whole number of every communication step."""
    t = float(t_end)
    H = max(FMU_CHECK_COMM_STEPS)
    if not (math.isfinite(t) and t > 0):
        raise PreflightError(f"--fmu-check-t-end must be a finite number of seconds > 0, "
                             f"got {t_end:g}")
    n = round(t / H)
    if n < 1 or abs(n * H - t) > 1e-9 * max(1.0, t):
        raise PreflightError(f"--fmu-check-t-end = {t:g} s must be a whole number of the "
                             f"check's largest communication step {H:g} s")
    return t


def check_cache_dir(engine) -> None:
    """The compiled engine writes generated modules to the cache: refuse an unwritable one
    now rather than when the first (or a later) diagram compiles; and a C compiler that
    does not run (:func:`check_c_compiler`)."""
    check_c_compiler()          # both engines step in C (ivdrem/sim/stepper.c)
    if engine != "compiled":
        return
    from ..sim.compiled import cache_dir
    check_writable_dir(cache_dir(), "compile cache directory (IVDREM_CACHE_DIR)")


def check_c_compiler() -> None:
    """$CC (or cc) must run (``--version``) before any work: CC=/bin/false or a missing
    compiler is one line naming it and what to install, not a traceback at the first run."""
    from ..sim import _cstepper
    from ..sim.compiled import C_COMPILER_HINT
    try:
        _cstepper._compiler()
    except _cstepper.CStepperUnavailable as e:
        raise PreflightError(f"{e}; {C_COMPILER_HINT}") from None


def horizon_note(config) -> str | None:
    """A one-line note when t_end is shorter than the horizon C1-C3 are stated for."""
    t_end = float(config["experiment"]["t_end"])
    if t_end >= CONCLUSIONS_HORIZON:
        return None
    return (f"note: t_end = {t_end:g} s is shorter than the {CONCLUSIONS_HORIZON:g} s horizon "
            f"that conclusions C1-C3 are stated for; expect FAIL verdicts, or none where "
            f"the run ends before the composite term can act")


def timing_text(stats) -> str:
    """'compile X s + simulation Y s' when the stats split them, else the wall time."""
    comp, sim = stats.get("compile_s"), stats.get("sim_s")
    if comp is not None and sim is not None:
        return f"compile {comp:.2f} s + simulation {sim:.2f} s"
    return f"{stats.get('wall_s', float('nan')):.2f} s"


def config_from_args(args) -> dict:
    """The configuration data of the command line (``--config``, ``--t-end``, ``--laws``,
    ``--method``), checked key by key and nothing built (:func:`read_config`; raises
    ConfigError, PreflightError): ``Experiment.from_config`` of it builds the model."""
    from .._paths import user_path
    from ..experiments.config import read_config
    overrides: dict = {}
    if getattr(args, "t_end", None) is not None:
        overrides["experiment.t_end"] = args.t_end
    if getattr(args, "laws", None):
        overrides["experiment.laws"] = list(args.laws)
    config = getattr(args, "config", None)
    overrides.update(method_overrides(getattr(args, "method", None),
                                      None if config is None else user_path(config)))
    return read_config(None if config is None else user_path(config), overrides or None)
