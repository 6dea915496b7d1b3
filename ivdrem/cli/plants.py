"""``ivdrem cosim --plant mujoco``: the sampled controller closed around the arm in MuJoCo
(docs/mujoco.md).  Prints and writes (``--json``) per law θ̃ (absolute and relative to
θ̃(0)), the tracking error, τ̃_d and the per-sample costs.  Also the robustness study's
command (``ivdrem study FILE`` with a [robustness] table) and ``ivdrem report --plant
mujoco`` (the report builder on :func:`ivdrem.plants.study.mujoco_paper_run`'s runs)."""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path


PROG = "ivdrem cosim --plant mujoco"


def add_arguments(p):
    """The options of the MuJoCo plant and the robot's imperfections (on ``cosim``)."""
    g = p.add_argument_group("--plant mujoco", "the arm in MuJoCo, a robot's sensors and limits")
    g.add_argument("--laws", nargs="+", default=None, metavar="LAW",
                   help="laws to run (default: the configuration's [experiment] laws)")
    g.add_argument("--json", default=None, metavar="FILE",
                   help="write the numbers (and the plant's report) to FILE")
    g.add_argument("--mu-max", type=float, default=135.0, dest="mu_max",
                   help="saturation of mu of the sampled controller (default %(default)g)")
    g.add_argument("--gamma", type=float, default=None,
                   help="γ of (21) instead of the configuration's (its \"auto\" calibrates on "
                        "the continuous loop first: for the Panda it picks 53.2)")
    g.add_argument("--mix-every", type=int, default=None, dest="mix_every",
                   help="mix (17) every N samples, holding Δ between (the controller's "
                        "default 1; the Panda's eigen mixing costs ~9 ms a sample)")
    g.add_argument("--integrator", default="implicit",
                   choices=("implicit", "implicitfast", "euler", "rk4"),
                   help="MuJoCo's integrator (default %(default)s)")
    g.add_argument("--substeps", type=int, default=1,
                   help="MuJoCo steps per controller sample (default %(default)s)")
    g.add_argument("--joint-friction", action="store_true", dest="joint_friction",
                   help="keep the URDF's joint damping and dry friction in the plant")
    g.add_argument("--realistic", action="store_true",
                   help="2^18 counts/rev, velocity by a filtered difference at 200 Hz, one "
                        "sample of measurement delay (the options below change it)")
    g.add_argument("--noise-level", type=float, default=1.0, dest="noise_level",
                   help="multiply the encoder's quantum and the velocity noise (default 1)")
    g.add_argument("--encoder-counts", type=float, default=None, dest="encoder_counts",
                   help="encoder counts per revolution (default: exact positions)")
    g.add_argument("--encoder-noise", type=float, default=None, dest="encoder_noise",
                   help="white noise on the angles before the encoder, sigma in counts "
                        "(needs encoder counts; seeded by --seed)")
    g.add_argument("--velocity", default=None, choices=("exact", "difference", "noise"),
                   help="how q' is measured (default exact)")
    g.add_argument("--velocity-cutoff", type=float, default=None, dest="velocity_cutoff",
                   help="cut-off of the filtered difference in Hz (default 200)")
    g.add_argument("--velocity-noise", type=float, default=None, dest="velocity_noise",
                   help="sigma of the velocity noise in rad/s (--velocity noise)")
    g.add_argument("--measurement-delay", type=int, default=None, choices=(0, 1),
                   dest="measurement_delay", help="samples of measurement delay")
    g.add_argument("--tau-limit", type=float, nargs="+", default=None, dest="tau_limit",
                   help="torque saturation in N m (one or per joint)")
    g.add_argument("--tau-rate-limit", type=float, nargs="+", default=None,
                   dest="tau_rate_limit", help="torque rate limit in N m/s")
    g.add_argument("--payload-mass", type=float, default=None, dest="payload_mass",
                   help="a payload on the last link (kg), unknown to the controller")
    g.add_argument("--payload-com", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   dest="payload_com", metavar=("X", "Y", "Z"),
                   help="its centre of mass in the last link's frame (m)")
    g.add_argument("--payload-inertia", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   dest="payload_inertia", metavar=("IXX", "IYY", "IZZ"),
                   help="its principal inertias about the centre of mass (kg m^2)")
    g.add_argument("--payload-at", type=float, default=0.0, dest="payload_at",
                   help="when it is grasped (s, default 0)")
    g.add_argument("--seed", type=int, default=0, help="seed of the sensor noise")
    g.add_argument("--model", default=None,
                   help="run on this model instead of the configuration's (e.g. two-link)")
    g.add_argument("--study", default=None, metavar="FILE.toml",
                   help="run a robustness study (configuration + [robustness], "
                        "ivdrem.plants.study; the same as `ivdrem study FILE`, with --t-end "
                        "and --model overriding the file's) instead of one run per law")
    g.add_argument("--workers", type=int, default=1,
                   help="--study: Dask worker processes (default 1: in this process)")
    g.add_argument("--out", default=None, metavar="DIR",
                   help="--study: output folder (default studies/<file name>)")


def imperfections_from_args(args):
    from dataclasses import replace
    from ..plants.sensing import REALISTIC, Imperfections
    base = REALISTIC if args.realistic else Imperfections()
    given = {k: getattr(args, k) for k in ("encoder_counts", "encoder_noise", "velocity",
                                           "velocity_cutoff", "velocity_noise",
                                           "measurement_delay", "tau_limit", "tau_rate_limit")
             if getattr(args, k) is not None}
    imp = replace(base, seed=args.seed, **given)
    return imp.scaled(args.noise_level) if args.noise_level != 1.0 else imp


def main_cosim_mujoco(args) -> int:
    """``ivdrem cosim --plant mujoco``: exit 0 when every run finished, 1 when one
    diverged, 2 on bad input (before anything runs)."""
    from .._paths import user_path
    from .._progress import want_progress
    from ..experiments.config import read_config
    from ..experiments.experiment import Experiment
    from ..plants.mujoco import MujocoError, Payload, closed_loop, controller_kwargs, load
    from ..plants.study import summarize
    if args.study is not None:
        return _main_study(args)
    try:
        data = read_config(None if args.config is None else user_path(args.config),
                           overrides=None if args.model is None
                           else {"model": {"name": args.model}})
        t_end = float(args.t_end if args.t_end is not None else data["experiment"]["t_end"])
        if not (math.isfinite(t_end) and t_end > 0):
            raise ValueError(f"--t-end must be a finite number > 0, got {t_end:g}")
        laws = args.laws or list(data["experiment"]["laws"])
        from ..controller.sampled import SAMPLED_LAWS
        bad = [law for law in laws if law not in SAMPLED_LAWS]
        if bad:
            raise ValueError(f"law(s) {bad} have no sampled form; choose from "
                             f"{', '.join(SAMPLED_LAWS)}")
        imp = imperfections_from_args(args)
        payload = None if args.payload_mass is None else Payload(
            args.payload_mass, tuple(args.payload_com), tuple(args.payload_inertia),
            args.payload_at)
        if not (math.isfinite(args.comm_step) and args.comm_step > 0):
            raise ValueError(f"--comm-step (the controller's h) must be > 0, got "
                             f"{args.comm_step:g}")
        # the model built once, the reference designed once, each law resolved once
        experiment = Experiment.from_config(data, laws=laws)
        runs = [(law, *controller_kwargs(experiment, law)) for law in laws]
        model = experiment.model
        plant = load(model, h=args.comm_step, integrator=args.integrator, substeps=args.substeps,
                     joint_friction=args.joint_friction, payload=payload)
    except (ValueError, OSError, ImportError) as exc:     # MujocoError is a ValueError
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    r = plant.report
    print(f"MuJoCo plant: {model.name} (n = {model.n}, {model.ntheta} parameters), "
          f"{args.integrator} at {plant.mj.opt.timestep:g} s, controller h = {args.comm_step:g} s")
    print(f"  load check ({plant.check['states']} states): M {plant.check['M']:.2g}, bias "
          f"forces {plant.check['bias']:.2g} (relative)")
    if r["locked_joints"]:
        print(f"  locked joints: {', '.join(r['locked_joints'])}")
    print(f"  joint damping {r['damping']}, dry friction {r['frictionloss']} "
          f"({'left in the plant' if r['joint_friction_in_plant'] else 'removed'}), "
          f"armature {r['armature']}")
    print(f"  sensing: {'; '.join(imp.active) or 'exact'}"
          + (f"; payload {payload.mass:g} kg at t = {payload.at:g} s" if payload else ""))
    results, status = [], 0
    progress = want_progress(not getattr(args, "quiet", False))
    for law, kw, run in runs:
        kw["mu_max"] = args.mu_max
        if args.gamma is not None:
            kw["gamma"] = args.gamma
        if args.mix_every is not None:
            kw["mix_every"] = args.mix_every
        if kw.get("gamma") == "auto":
            from ..controller.block import auto_gamma
            kw["gamma"] = auto_gamma(model, law, kw)["gamma"]
        t0 = time.perf_counter()
        try:
            resp = closed_loop(plant, t_end, law, imperfections=imp, progress=progress,
                               every=max(1, int(round(0.01 / args.comm_step))), **run, **kw)
        except (FloatingPointError, RuntimeError) as exc:
            print(f"{PROG}: {law}: run failed: {exc}", file=sys.stderr)
            status = 1
            continue
        except (ValueError, MujocoError) as exc:
            print(f"{PROG}: error: {law}: {exc}", file=sys.stderr)
            return 2
        s = summarize(resp)
        s["wall_s"] = time.perf_counter() - t0
        results.append(s)
    print()
    print(f"{'law':<20} {'|θ̃(0)|':>9} {'|θ̃(end)|':>10} {'ratio':>9} {'RMS e':>9} "
          f"{'RMS τ̃_d':>9} {'plant µs':>9} {'ctrl µs':>8} {'wall s':>7}")
    for s in results:
        print(f"{s['law']:<20} {s['theta_error_0']:9.4g} {s['theta_error_end']:10.4g} "
              f"{s['theta_error_ratio']:9.3g} {s['tracking_rms_last']:9.3g} "
              f"{s['tau_d_error_rms_last']:9.3g} {s['plant_us']:9.1f} "
              f"{s['controller_us']:8.1f} {s['wall_s']:7.1f}")
    print(f"(t_end = {t_end:g} s; RMS over the last 20 %; costs per sample, wall clock)")
    if args.json:
        from .._atomic import write_text_atomic
        out = dict(model=model.name, t_end=t_end, h=args.comm_step, integrator=args.integrator,
                   substeps=args.substeps, imperfections=imp.as_dict(),
                   payload=None if payload is None else payload.__dict__,
                   load_check={k: float(v) for k, v in plant.check.items()},
                   plant_report=r, runs=results)
        try:
            path = write_text_atomic(user_path(args.json), json.dumps(out, indent=1))
        except OSError as exc:
            print(f"{PROG}: error: cannot write {args.json}: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {path}")
    return status


def _main_study(args) -> int:
    return run_robustness_command(args, prog=f"{PROG} --study")


def run_robustness_command(args, *, prog="ivdrem study") -> int:
    """A robustness study (``ivdrem study FILE`` with a [robustness] table, or ``ivdrem
    cosim --plant mujoco --study FILE``): prints the runs and writes the results and the
    report; 0 when every run finished, 1 when one failed, 2 on bad input."""
    from .._paths import user_path
    from ..plants.study import conclusions, run_robustness
    for opt, what in (("scheduler", "--scheduler"), ("resume", "--resume")):
        if getattr(args, opt, None):
            print(f"{prog}: error: {what} is not available for a robustness study (a "
                  "[robustness] table); run it again with --workers N", file=sys.stderr)
            return 2
    path = user_path(args.study)
    out = user_path(args.out) if args.out else user_path(Path("studies") / path.stem)
    import os
    cores = os.cpu_count() or 1
    workers = cores if args.workers is None else args.workers
    if not 1 <= workers <= cores:
        # as `ivdrem study`: one MuJoCo loop per process, more than one per core is no faster
        print(f"{prog}: error: --workers must be between 1 and the {cores} cores of this "
              f"machine, got {workers}", file=sys.stderr)
        return 2
    try:
        df, wall = run_robustness(path, out, workers=workers, model=getattr(args, "model", None),
                                  t_end=getattr(args, "t_end", None),
                                  progress=not getattr(args, "quiet", False),
                                  report=not getattr(args, "no_report", False))
    except (ValueError, OSError, ImportError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    show = ["noise_level", "payload_mass", "omega_scale", "seed", "law", "theta_error_end",
            "theta_error_ratio", "tracking_rms_last", "tau_d_error_rms_last", "status"]
    import pandas as pd
    with pd.option_context("display.width", 200):
        print(df[[c for c in show if c in df]].to_string(index=False))
    for line in conclusions(df):
        print(line)
    print(f"{len(df)} runs, {workers} worker(s), {wall:.1f} s; wrote {out}")
    return 0 if (df["status"] == "ok").all() else 1


def run_mujoco_report(args) -> int:
    """``ivdrem report --plant mujoco``: the report's figures and C1-C3 for the experiment
    of ``--config`` with the arm in MuJoCo, written as ``ivdrem-mujoco.html`` / ``.pdf`` in
    ``--out``; 0 when written, 1 when a run or the write failed, 2 on bad input."""
    from ..experiments.metrics import conclusions, format_conclusions
    from ..plants.study import mujoco_paper_run
    from ..reports.report import report_paths, write_report
    from ..experiments.experiment import Experiment
    from .preflight import config_from_args
    from .._paths import check_writable_dir, user_path
    prog = "ivdrem report --plant mujoco"
    try:
        from ..plants.mujoco import _mujoco
        _mujoco()
        data = config_from_args(args)
        out = check_writable_dir(user_path(args.out), "report directory")
        report_paths(out, "ivdrem-mujoco", overwrite=getattr(args, "overwrite", False))
        from ..controller.sampled import SAMPLED_LAWS
        bad = [law for law in data["experiment"]["laws"] if law not in SAMPLED_LAWS]
        if bad:
            raise ValueError(f"law(s) {bad} have no sampled form; choose from "
                             f"{', '.join(SAMPLED_LAWS)}")
        experiment = Experiment.from_config(data)          # resolved once
        run = mujoco_paper_run(experiment, progress=not getattr(args, "quiet", False),
                               log=print)
    except (FloatingPointError, RuntimeError) as exc:
        print(f"{prog}: run failed: {exc}", file=sys.stderr)
        return 1
    except (ValueError, OSError, ImportError) as exc:      # ConfigError, ReportError too
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    try:
        html, pdf = write_report(run, out, basename="ivdrem-mujoco",
                                 overwrite=getattr(args, "overwrite", False))
    except OSError as exc:
        print(f"{prog}: error: cannot write the report to {out}: {exc}", file=sys.stderr)
        return 1
    print(f"HTML report: {html}")
    print(f"PDF report:  {pdf}")
    print(format_conclusions(conclusions(run)))
    return 0
