"""A robustness study in MuJoCo: noise level × payload × disturbance frequencies × seed, each
law, on Dask (docs/mujoco.md, "Robustness study").

A study file is an experiment configuration (as ``examples/paper.toml``) with a
``[robustness]`` table::

    [robustness]
    noise_levels = [0.0, 1.0, 10.0, 100.0]  # 0: exact q, q̇; 1: the realistic robot
                                            # (ivdrem.plants.sensing.REALISTIC); x: its
                                            # encoder quantum x times larger
    payload_mass = [0.0, 1.0]               # kg on the last link, unknown to the controller
    payload_com = [0.0, 0.0, 0.05]          # m, in the last link's frame
    omega_scale = [1.0, 1.37]               # the disturbance's frequencies times this: the
                                            # window T was chosen from the unscaled ones
    encoder_noise = 1.0                     # optional: white noise on the angles before
                                            # the encoder, σ in counts (of the level's
                                            # encoder), at every level > 0
    seeds = [0, 1]                          # the sensor noise's seed: runs without noise
                                            # (level 0, or encoder_noise = 0) take the first
    mu_max = 135.0
    gamma = 53.2                            # optional: γ of (21) instead of the config's
                                            # (IV-DREM, DREM); or a table {law = γ}
    mix_every = 50                          # optional: mix (17) every N samples

Every combination is run once per law of ``experiment.laws`` (one MuJoCo loop each,
:func:`ivdrem.plants.mujoco.closed_loop`).  Written to the output folder:
``results.csv`` (one row per run: the varied values, θ̃ at the start and the end and their
ratio, the tracking error and τ̃_d RMS over the last 20 %, costs, wall time, status),
``runs.jsonl`` (the same rows as they finish), ``robustness.png`` (the three against the
noise level, one line per law, payload and disturbance scale), ``robustness.html`` (the
figure, the conclusions per noise level, payload and disturbance scale, the table of means
over the seeds, the failed runs) and
``study.toml`` (the file as given).  A run that fails is a row with its error; the others
go on. From the command line::

    ivdrem study examples/panda-robustness.toml [--workers 2] [--out DIR] [--no-report]
    ivdrem cosim --plant mujoco --study FILE [--workers 2] [--out DIR] [--t-end T]
        [--model NAME]          (the same, with the horizon and the arm overridden)
"""
from __future__ import annotations

import copy
import itertools
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = ["read_robustness", "sensing", "expand", "run_one", "run_robustness", "plot", "summary_table",
           "conclusions", "write_report", "rebuild_report", "is_robustness_file"]

#: keys of [robustness] and their defaults
DEFAULTS = dict(noise_levels=[0.0, 1.0], payload_mass=[0.0], payload_com=[0.0, 0.0, 0.0],
                omega_scale=[1.0], seeds=[0], encoder_noise=0.0, mu_max=135.0, gamma=None,
                mix_every=None)


def is_robustness_file(path) -> bool:
    """Whether the TOML file at ``path`` is a robustness study (has a [robustness] table);
    False for a file that cannot be read (the study command then says why)."""
    from .._config_file import read_toml
    try:
        raw, _ = read_toml(Path(path), "study file")
    except Exception:  # noqa: BLE001 - reported by the command that reads it
        return False
    return isinstance(raw, dict) and "robustness" in raw


def read_robustness(path, *, model=None, t_end=None):
    """(the base :class:`~ivdrem.experiments.experiment.Experiment`, [robustness] table
    with defaults, the file's text) of a study file; ``model`` and ``t_end`` override the
    file's.  The experiment's model is built once, its laws resolved once."""
    from ..experiments.config import read_config, read_toml
    from ..experiments.experiment import Experiment
    raw, text = read_toml(Path(path), "study file")
    table = raw.pop("robustness", None)
    if not isinstance(table, dict):
        raise ValueError(f"{path}: no [robustness] table")
    unknown = set(table) - set(DEFAULTS)
    if unknown:
        raise ValueError(f"{path}: unknown [robustness] keys {sorted(unknown)}; valid: "
                         f"{', '.join(DEFAULTS)}")
    rob = {**copy.deepcopy(DEFAULTS), **table}
    for key in ("noise_levels", "payload_mass", "omega_scale", "seeds"):
        v = rob[key]
        if not isinstance(v, list) or not v:
            raise ValueError(f"[robustness] {key} must be a non-empty list, got {v!r}")
    if any(not (isinstance(x, (int, float)) and x >= 0) for x in rob["noise_levels"]):
        raise ValueError(f"[robustness] noise_levels must be numbers >= 0, got "
                         f"{rob['noise_levels']}")
    e = rob["encoder_noise"]
    if not (isinstance(e, (int, float)) and math.isfinite(e) and e >= 0):
        raise ValueError(f"[robustness] encoder_noise must be a standard deviation >= 0 in "
                         f"counts, got {e!r}")
    g = rob["gamma"]
    if not (g is None or isinstance(g, (int, float)) or (isinstance(g, dict) and all(
            isinstance(v, (int, float)) and v > 0 for v in g.values()))) or (
            isinstance(g, (int, float)) and not g > 0):
        raise ValueError(f"[robustness] gamma must be a number > 0 (for the laws with the "
                         f"mixing (21): {', '.join(_MIXING_LAWS)}) or a table of numbers by "
                         f"law, got {g!r}")
    if model is not None:
        raw.setdefault("model", {})["name"] = model
    if t_end is not None:
        raw.setdefault("experiment", {})["t_end"] = float(t_end)
    return Experiment.from_config(read_config(None, overrides=raw)), rob, text


#: the laws whose γ scales Δ² of the mixing (21); composite learning's γ of (35) multiplies
#: Ψ_b itself, so a number given for the first must not reach it
_MIXING_LAWS = ("iv-drem", "drem")


def _law_gamma(gamma, law):
    """γ for ``law`` from [robustness] gamma: a number (the laws with the mixing (21)
    only) or a table by law; None: the configuration's."""
    if isinstance(gamma, dict):
        return None if gamma.get(law) is None else float(gamma[law])
    if gamma is not None and law in _MIXING_LAWS:
        return float(gamma)
    return None


def sensing(rob, level, seed):
    """The robot's sensing at a noise level (:class:`~ivdrem.plants.sensing.Imperfections`):
    0 exact; x > 0 ``REALISTIC`` with its encoder's quantum x times larger and the study's
    encoder noise (σ in counts of that encoder)."""
    from .sensing import REALISTIC, Imperfections
    if level == 0:
        return Imperfections(seed=int(seed))
    return replace(REALISTIC.scaled(level), seed=int(seed),
                   encoder_noise=float(rob["encoder_noise"]))


def expand(experiment, rob):
    """The runs of `experiment` (an Experiment, or its configuration): dicts of (law,
    noise_level, payload_mass, omega_scale, seed); a noise level whose sensing draws no
    noise runs with the first seed only (the others would repeat it)."""
    config = getattr(experiment, "config", experiment)
    laws = list(config["experiment"]["laws"])
    first = rob["seeds"][0]
    return [dict(law=law, noise_level=float(lv), payload_mass=float(pm), omega_scale=float(om),
                 seed=int(sd))
            for lv, pm, om, sd, law in itertools.product(
                rob["noise_levels"], rob["payload_mass"], rob["omega_scale"], rob["seeds"],
                laws)
            if sd == first or sensing(rob, lv, sd).random]


def run_one(experiment, rob, run) -> dict:
    """One MuJoCo loop of the study's `experiment` (an Experiment; on a worker, its
    configuration, resolved there once); never raises: a failed run is a row."""
    from .mujoco import Payload, closed_loop, controller_kwargs, load
    from ..experiments.experiment import Experiment
    t0, cpu0 = time.perf_counter(), time.process_time()
    row = dict(run, status="ok", error="")
    try:
        if not isinstance(experiment, Experiment):
            experiment = Experiment.from_config(experiment, laws=[run["law"]])
        model = experiment.model
        kw, start = controller_kwargs(experiment, run["law"])
        kw["mu_max"] = float(rob["mu_max"])
        gamma = _law_gamma(rob["gamma"], run["law"])
        if gamma is not None:                     # instead of the configuration's
            kw["gamma"] = gamma
        if rob["mix_every"] is not None:
            kw["mix_every"] = int(rob["mix_every"])
        if kw.get("gamma") == "auto":
            from ..controller.block import auto_gamma
            kw["gamma"] = auto_gamma(model, run["law"], kw)["gamma"]
        dist = dict(start["disturbance"])
        dist["omega"] = np.asarray(dist["omega"], float) * run["omega_scale"]
        payload = None if run["payload_mass"] == 0 else Payload(
            run["payload_mass"], tuple(rob["payload_com"]))
        plant = load(model, payload=payload, states=20)
        imp = sensing(rob, run["noise_level"], run["seed"])
        resp = closed_loop(plant, experiment.t_end, run["law"], imperfections=imp, q0=start["q0"],
                           dq0=start["dq0"], disturbance=dist, every=100, progress=False,
                           **kw)
        s = summarize(resp)
        row.update({k: v for k, v in s.items() if not isinstance(v, list)})
    except Exception as exc:  # noqa: BLE001 - a failed run is a result
        row.update(status="failed", error=f"{type(exc).__name__}: {exc}")
    row["wall_s"] = time.perf_counter() - t0
    row["cpu_s"] = time.process_time() - cpu0     # the worker's CPU: wall_s less the waiting
    return row


def run_robustness(path, out, *, workers=1, model=None, t_end=None, progress=True,
                   report=True):
    """Run the study file ``path`` into the folder ``out``; returns the results table
    (pandas) and the wall time.  ``workers`` > 1: a Dask LocalCluster of that many
    single-threaded processes; 1: in this process.  ``report``: write robustness.png and
    robustness.html (:func:`write_report`)."""
    import pandas as pd
    from .._atomic import write_text_atomic
    experiment, rob, text = read_robustness(path, model=model, t_end=t_end)
    runs = expand(experiment, rob)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "study.toml", text)
    t0 = time.perf_counter()
    rows = []
    log = out / "runs.jsonl"          # each run as it finishes: a long study can be followed
    log.write_text("")

    def done(row):
        rows.append(row)
        with log.open("a") as fh:
            fh.write(json.dumps(row) + "\n")
        if progress:
            print(f"  {len(rows)}/{len(runs)} runs ({row['law']}, noise {row['noise_level']:g}, "
                  f"payload {row['payload_mass']:g} kg, ω x {row['omega_scale']:g}, seed "
                  f"{row['seed']}: {row['status']}"
                  + (f", ratio {row['theta_error_ratio']:.3g}" if row["status"] == "ok" else "")
                  + f", {row['wall_s']:.0f} s)", file=sys.stderr, flush=True)
    if workers > 1:
        import logging
        import warnings
        from dask.distributed import Client, LocalCluster, as_completed
        with warnings.catch_warnings():
            # the scheduler's HTTP server (no dashboard) moves to a free port when another
            # cluster holds 8787, and says so: nothing for the user to do
            warnings.filterwarnings("ignore", message="Port .* is already in use")
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR)
        with cluster, Client(cluster) as client:
            # the longest runs first (the laws with the window (15a) cost the most per
            # sample), so that no worker is left with a long run at the end
            order = sorted(runs, key=lambda r: r["law"] not in _MIXING_LAWS + (
                "composite-learning",))
            # a worker gets the resolved configuration and makes its Experiment once per run
            futs = [client.submit(run_one, experiment.config, rob, r, pure=False)
                    for r in order]
            for f in as_completed(futs):
                done(f.result())
    else:
        for r in runs:
            done(run_one(experiment, rob, r))
    wall = time.perf_counter() - t0
    key = ["noise_level", "payload_mass", "omega_scale", "seed", "law"]
    df = pd.DataFrame(rows).sort_values(key).reset_index(drop=True)
    write_text_atomic(out / "results.csv", df.to_csv(index=False))
    df.attrs.update(wall_s=wall, workers=workers)
    if report:
        write_report(df, out, model=experiment.config["model"].get("name", "?"), study_text=text,
                     wall_s=wall, workers=workers)
    return df, wall


#: what a row of the summary is the mean over the seeds of
SUMMARY_KEY = ["noise_level", "payload_mass", "omega_scale", "law"]


def summary_table(df):
    """Per law, noise level, payload and disturbance scale: the mean over the seeds of
    ‖θ̃(end)‖/‖θ̃(0)‖, the RMS tracking error and RMS τ̃_d over the last 20 %, with the
    runs that finished and that failed.  Disturbance scales stay apart: a law that
    diverges at one scale is not averaged with its runs at another."""
    import pandas as pd
    key = SUMMARY_KEY
    ok = df[df["status"] == "ok"]
    cols = ["theta_error_ratio", "tracking_rms_last", "tau_d_error_rms_last"]
    mean = (ok.groupby(key)[cols].mean() if len(ok) else
            pd.DataFrame(columns=cols, index=pd.MultiIndex.from_tuples([], names=key)))
    counts = df.groupby(key)["status"].agg(ok=lambda s: int((s == "ok").sum()),
                                           failed=lambda s: int((s != "ok").sum()))
    return counts.join(mean).reset_index()


def conclusions(df) -> list[str]:
    """One sentence per noise level, payload and disturbance scale: each law's
    ‖θ̃(end)‖/‖θ̃(0)‖ and RMS τ̃_d (mean over the seeds), IV-DREM's against the best other
    law's, or which runs diverged."""
    lines = []
    tab = summary_table(df)
    for (lv, pm, om), g in tab.groupby(["noise_level", "payload_mass", "omega_scale"]):
        where = (f"noise level {lv:g}" + (" (exact q, q̇)" if lv == 0 else "")
                 + f", payload {pm:g} kg, disturbance frequencies x {om:g}")
        parts, ratio = [], {}
        for _, row in g.iterrows():
            if row["ok"] == 0:
                parts.append(f"{row['law']} diverged in every run")
                continue
            ratio[row["law"]] = row["theta_error_ratio"]
            parts.append(f"{row['law']} ‖θ̃(end)‖/‖θ̃(0)‖ = {row['theta_error_ratio']:.3g}, "
                         f"RMS τ̃_d {row['tau_d_error_rms_last']:.3g} N·m"
                         + (f" ({int(row['failed'])} run(s) failed)" if row["failed"] else ""))
        others = {k: v for k, v in ratio.items() if k != "iv-drem"}
        verdict = ""
        if "iv-drem" in ratio and others:
            best = min(others, key=others.get)
            f = others[best] / ratio["iv-drem"]
            verdict = (f": IV-DREM's ratio is {f:.3g} times smaller than {best}'s" if f >= 1
                       else f": IV-DREM's ratio is {1 / f:.3g} times larger than {best}'s")
        lines.append(f"{where}: " + "; ".join(parts) + verdict + ".")
    return lines


def write_report(df, out, *, model="?", study_text="", wall_s=None, workers=1):
    """``out/robustness.png`` and ``out/robustness.html`` (self-contained: the figure as
    inline SVG, the conclusions, the summary table, the failed runs, the study file), each
    written atomically."""
    import io
    from html import escape
    from .._atomic import write_text_atomic
    from ..reports.content import Table, fmt
    from ..reports.study_report import _CSS, _html_table
    fig = plot(df, out / "robustness.png", model=model, keep=True)
    buf = io.StringIO()
    fig.savefig(buf, format="svg")
    svg = buf.getvalue()
    svg = svg[svg.index("<svg"):]
    import matplotlib.pyplot as plt
    plt.close(fig)
    tab = summary_table(df)
    summary = Table("summary", "Mean over the seeds",
                    ["noise level", "payload (kg)", "ω scale", "law", "runs ok", "failed",
                     "‖θ̃(end)‖/‖θ̃(0)‖", "RMS ‖e‖ last 20 % (rad)",
                     "RMS ‖τ̃_d‖ last 20 % (N·m)"],
                    [[fmt(r["noise_level"]), fmt(r["payload_mass"]), fmt(r["omega_scale"]),
                      r["law"], str(r["ok"]), str(r["failed"])]
                     + [fmt(r[c]) if r["ok"] else "–" for c in
                        ("theta_error_ratio", "tracking_rms_last", "tau_d_error_rms_last")]
                     for _, r in tab.iterrows()], [1] * 9,
                    note="noise level 1: 2^18 counts per revolution, velocity by a filtered "
                         "difference at 200 Hz, one sample of measurement delay (and the "
                         "study's encoder noise in counts, if any: the study file); x: the "
                         "encoder's quantum x times larger; 0: exact q, q̇.")
    bad = df[df["status"] != "ok"]
    failed = Table("failed", "Runs that failed", ["law", "noise level", "payload (kg)",
                                                    "ω scale", "seed", "error"],
                   [[r["law"], fmt(r["noise_level"]), fmt(r["payload_mass"]),
                     fmt(r["omega_scale"]), str(r["seed"]), str(r["error"])]
                    for _, r in bad.iterrows()], [1] * 6)
    title = f"ivdrem robustness study: {model} in MuJoCo"
    meta = [("plant", f"{model} in MuJoCo (ivdrem.plants.mujoco), the sampled C controller"),
            ("runs", f"{len(df)} ({int((df['status'] == 'ok').sum())} ok)"),
            ("workers", str(workers))]
    if wall_s is not None:
        meta.append(("wall time", f"{wall_s:.1f} s"))
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             '<meta name="generator" content="ivdrem robustness study">',
             f"<title>{escape(title)}</title>", f"<style>{_CSS}</style>", "</head><body>",
             f"<h1>{escape(title)}</h1>", '<table class="meta">']
    parts += [f"<tr><th>{escape(a)}</th><td>{escape(b)}</td></tr>" for a, b in meta]
    parts += ["</table>", '<section id="sec-conclusions"><h2>Conclusions</h2><ul>']
    parts += [f"<li>{escape(line)}</li>" for line in conclusions(df)]
    parts += ["</ul></section>", f'<figure id="robustness">{svg}</figure>',
              _html_table(summary), _html_table(failed),
              f"<section><h2>Study file</h2><pre>{escape(study_text)}</pre></section>",
              "</body></html>\n"]
    write_text_atomic(out / "robustness.html", "\n".join(parts))


def rebuild_report(out):
    """The report of a finished study in ``out`` again, from its results.csv and
    study.toml (nothing is simulated)."""
    import pandas as pd
    out = Path(out)
    df = pd.read_csv(out / "results.csv", keep_default_na=False,
                     na_values={c: [""] for c in ("theta_error_ratio", "tracking_rms_last",
                                                  "tau_d_error_rms_last")})
    text = (out / "study.toml").read_text(encoding="utf-8")
    from ..experiments.config import read_toml
    raw, _ = read_toml(out / "study.toml", "study file")
    write_report(df, out, model=raw.get("model", {}).get("name", "two-link"), study_text=text)
    return df


def plot(df, path, *, model="?", keep=False):
    """‖θ̃(end)‖/‖θ̃(0)‖, RMS tracking error and RMS τ̃_d against the noise level, one line
    per law, payload and disturbance scale (mean over the seeds; exact sensing drawn at
    the left edge, level 0)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ok = df[df["status"] == "ok"]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    cols = [("theta_error_ratio", "‖θ̃(end)‖ / ‖θ̃(0)‖"),
            ("tracking_rms_last", "RMS ‖e‖, last 20 % (rad)"),
            ("tau_d_error_rms_last", "RMS ‖τ̃_d‖, last 20 % (N·m)")]
    levels = sorted(ok["noise_level"].unique()) if len(ok) else []
    xpos = {lv: (lv if lv > 0 else (min([x for x in levels if x > 0], default=1.0) / 10))
            for lv in levels}
    for ax, (col, label) in zip(axes, cols):
        for (law, pm, om), g in ok.groupby(["law", "payload_mass", "omega_scale"]):
            m = g.groupby("noise_level")[col].mean()
            ax.plot([xpos[x] for x in m.index], m.values,
                    "o-" if law == "iv-drem" else "s--",
                    label=f"{law}" + (f", payload {pm:g} kg" if pm else "")
                    + (f", ω x {om:g}" if om != 1 else ""))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("noise level")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    if len(ok):
        axes[0].legend(fontsize=8)
    fig.suptitle(f"{model} in MuJoCo: robustness to sensing (noise level 1: 2^18 counts/rev, "
                 "filtered difference, 1 sample delay; x: quantum x times; leftmost points: "
                 "exact q, q̇)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    if keep:
        return fig
    plt.close(fig)


# ----------------------------------------------------------------------------- results
def summarize(resp, *, last_fraction=0.2) -> dict:
    """θ̃ at the start and the end (absolute, relative), tracking error and τ̃_d (RMS over
    the last ``last_fraction`` of the run, max |e| there), the costs."""
    from ..experiments.metrics import norm, rms, signal, window
    t = np.asarray(resp.time)
    e_th = norm(signal(resp, "theta_hat") - signal(resp, "theta"))
    e_q = signal(resp, "q_d") - signal(resp, "q")
    e_d = signal(resp, "tau_d_hat") - signal(resp, "tau_d")
    last = window(t, t[-1] * (1 - last_fraction))
    return dict(
        law=resp.law, t_end=float(t[-1]), theta_error_0=float(e_th[0]),
        theta_error_end=float(e_th[-1]), theta_error_ratio=float(e_th[-1] / e_th[0]),
        tracking_rms_last=rms(t[last], norm(e_q)[last]),
        tracking_max_last=float(np.abs(e_q[:, last]).max()),
        tau_d_error_rms_last=rms(t[last], norm(e_d)[last]),
        theta_hat_end=signal(resp, "theta_hat")[:, -1].tolist(),
        theta_end=signal(resp, "theta")[:, -1].tolist(), **resp.costs)


def mujoco_paper_run(experiment, *, mu_max=135.0, every=None, progress=False, log=None):
    """``experiment`` (an :class:`~ivdrem.experiments.experiment.Experiment`, or a
    configuration: its model, laws, t_end, reference, disturbance, gains, and the sampled
    controller's h) with MuJoCo as the plant: a :class:`~ivdrem.experiments.paper.PaperRun`
    whose law runs are :func:`ivdrem.plants.mujoco.closed_loop` responses (recorded every
    10 ms), for the report builder (``ivdrem report --plant mujoco``).  ``run.engine``
    names the plant."""
    import mujoco
    from ..experiments.experiment import Experiment
    from ..experiments.paper import LawRun, PaperRun
    from ..plants.mujoco import closed_loop, controller_kwargs, load
    experiment = Experiment.of(experiment)
    config, model, t_end, h = experiment.config, experiment.model, experiment.t_end, experiment.h
    plant = load(model, h=h)
    every = every or max(1, int(round(float(config["experiment"]["dt_out"]) / h)))
    run = PaperRun(config=config, theta=np.asarray(plant.theta, float), model=model)
    run.engine = (f"MuJoCo {mujoco.__version__} plant ({plant.integrator} integrator, step "
                  f"{plant.mj.opt.timestep:g} s; ivdrem.plants.mujoco), the sampled C "
                  f"controller at h = {h:g} s, μ saturated at {mu_max:g}")
    for law in experiment.laws:
        kw, start = controller_kwargs(experiment, law)
        kw["mu_max"] = float(mu_max)
        if kw.get("gamma") == "auto":
            from ..controller.block import auto_gamma
            kw["gamma"] = auto_gamma(model, law, kw)["gamma"]
        t0 = time.perf_counter()
        resp = closed_loop(plant, t_end, law, every=every, progress=progress, **start, **kw)
        wall = time.perf_counter() - t0
        stats = dict(method=f"MuJoCo {plant.integrator}", h=h, steps=resp.costs["samples"],
                     wall_s=wall, engine="MuJoCo plant, sampled C controller",
                     plant_us=resp.costs["plant_us"], controller_us=resp.costs["controller_us"])
        run.runs[law] = LawRun(law=law, response=resp, stats=stats, gamma=kw.get("gamma"))
        if log is not None:
            log(f"{law:>20s}: {resp.costs['samples']} samples in MuJoCo, {wall:.1f} s")
    return run
