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
    seeds = [0, 1]                          # the sensor noise's seed
    mu_max = 135.0
    gamma = 53.2                            # optional: γ of (21) instead of the config's
    mix_every = 50                          # optional: mix (17) every N samples

Every combination is run once per law of ``experiment.laws`` (one MuJoCo loop each,
:func:`ivdrem.plants.mujoco.closed_loop`).  Written to the output folder:
``results.csv`` (one row per run: the varied values, θ̃ at the start and the end and their
ratio, the tracking error and τ̃_d RMS over the last 20 %, costs, wall time, status),
``robustness.png`` (the three against the noise level, one line per law and payload) and
``study.toml`` (the file as given).  A run that fails is a row with its error; the others
go on.

    ivdrem cosim --plant mujoco --study examples/panda-robustness.toml [--workers 2]
        [--out DIR] [--t-end T] [--model NAME]
"""
from __future__ import annotations

import copy
import itertools
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = ["read_robustness", "expand", "run_one", "run_robustness", "plot"]

#: keys of [robustness] and their defaults
DEFAULTS = dict(noise_levels=[0.0, 1.0], payload_mass=[0.0], payload_com=[0.0, 0.0, 0.0],
                omega_scale=[1.0], seeds=[0], mu_max=135.0, gamma=None, mix_every=None)


def read_robustness(path, *, model=None, t_end=None):
    """(base configuration, [robustness] table with defaults) of a study file; ``model``
    and ``t_end`` override the file's."""
    from ..experiments.config import load_config, read_toml
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
    if model is not None:
        raw.setdefault("model", {})["name"] = model
    if t_end is not None:
        raw.setdefault("experiment", {})["t_end"] = float(t_end)
    config = load_config(None, overrides=raw)
    return config, rob, text


def expand(config, rob):
    """The runs: dicts of (law, noise_level, payload_mass, omega_scale, seed)."""
    laws = list(config["experiment"]["laws"])
    return [dict(law=law, noise_level=float(lv), payload_mass=float(pm), omega_scale=float(om),
                 seed=int(sd))
            for lv, pm, om, sd, law in itertools.product(
                rob["noise_levels"], rob["payload_mass"], rob["omega_scale"], rob["seeds"],
                laws)]


def run_one(config, rob, run) -> dict:
    """One MuJoCo loop of the study (on a worker); never raises: a failed run is a row."""
    from .cli import summarize
    from .mujoco import Payload, closed_loop, controller_kwargs, load
    from .sensing import REALISTIC, Imperfections
    from ..experiments.config import model_from_config
    t0 = time.perf_counter()
    row = dict(run, status="ok", error="")
    try:
        model = model_from_config(config)
        kw, start = controller_kwargs(config, run["law"])
        kw["mu_max"] = float(rob["mu_max"])
        if rob["gamma"] is not None:              # instead of the configuration's
            kw["gamma"] = float(rob["gamma"])
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
        level = run["noise_level"]
        imp = (Imperfections(seed=run["seed"]) if level == 0 else
               replace(REALISTIC.scaled(level), seed=run["seed"]))
        t_end = float(config["experiment"]["t_end"])
        resp = closed_loop(plant, t_end, run["law"], imperfections=imp, q0=start["q0"],
                           dq0=start["dq0"], disturbance=dist, every=100, progress=False,
                           **kw)
        s = summarize(resp)
        row.update({k: v for k, v in s.items() if not isinstance(v, list)})
    except Exception as exc:  # noqa: BLE001 - a failed run is a result
        row.update(status="failed", error=f"{type(exc).__name__}: {exc}")
    row["wall_s"] = time.perf_counter() - t0
    return row


def run_robustness(path, out, *, workers=1, model=None, t_end=None, progress=True):
    """Run the study file ``path`` into the folder ``out``; returns the results table
    (pandas) and the wall time.  ``workers`` > 1: a Dask LocalCluster of that many
    single-threaded processes; 1: in this process."""
    import pandas as pd
    from .._atomic import write_text_atomic
    config, rob, text = read_robustness(path, model=model, t_end=t_end)
    runs = expand(config, rob)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "study.toml", text)
    t0 = time.perf_counter()
    rows = []
    if workers > 1:
        from dask.distributed import Client, LocalCluster, as_completed
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            futs = [client.submit(run_one, config, rob, r, pure=False) for r in runs]
            for f in as_completed(futs):
                rows.append(f.result())
                if progress:
                    print(f"  {len(rows)}/{len(runs)} runs", file=sys.stderr, flush=True)
    else:
        for r in runs:
            rows.append(run_one(config, rob, r))
            if progress:
                print(f"  {len(rows)}/{len(runs)} runs", file=sys.stderr, flush=True)
    wall = time.perf_counter() - t0
    key = ["noise_level", "payload_mass", "omega_scale", "seed", "law"]
    df = pd.DataFrame(rows).sort_values(key).reset_index(drop=True)
    write_text_atomic(out / "results.csv", df.to_csv(index=False))
    plot(df, out / "robustness.png", model=config["model"].get("name", "?"))
    return df, wall


def plot(df, path, *, model="?"):
    """‖θ̃(end)‖/‖θ̃(0)‖, RMS tracking error and RMS τ̃_d against the noise level, one line
    per law and payload (mean over seeds and disturbance scales; exact sensing drawn at
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
        for (law, pm), g in ok.groupby(["law", "payload_mass"]):
            m = g.groupby("noise_level")[col].mean()
            ax.plot([xpos[x] for x in m.index], m.values, "o-",
                    label=f"{law}" + (f", payload {pm:g} kg" if pm else ""))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("noise level (1: 2^18 counts/rev, filtered difference, 1 sample delay)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{model} in MuJoCo: robustness to sensing (leftmost points: exact q, q̇)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
