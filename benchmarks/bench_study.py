"""Throughput of parameter studies: runs per minute with 1 and 2 Dask workers.

A study of 8 paper runs of 60 s (the paper experiment, both laws, at 4 values of
controller.alpha within 3e-4 of the paper's 1.0, so the cost of every run is the paper's),
run side by side:

* in this process, one run after the other (``run_law``): the floor without Dask;
* ``run_study`` on a LocalCluster of 1 and of 2 single-threaded worker processes (cluster
  start-up timed separately; the study's wall time includes the warm-up tasks, result
  transfer and the atomic per-run writes);
* the per-task overhead: worker-side time of a task (``task_s``) against the study's
  wall time x workers, and a round trip of no-op tasks returning a record-sized result.

    .venv/bin/python benchmarks/bench_study.py

With ``--robustness [T]``: instead, the MuJoCo robustness study (ivdrem.plants.study) of
the paper's arm, 8 runs of T seconds (default 60: noise levels 0, 1 × payload 0, 0.5 kg
× IV-DREM, composite learning), on a Dask LocalCluster of 1 and of 2 worker processes,
one after the other, the cluster's start and the workers' imports included as a user
sees them.  Printed per cluster: the wall time, the sum of the runs' CPU time (each
worker's ``process_time``) and its efficiency, CPU / (wall x workers): 1 when the workers
never wait, so a ratio 2-workers/1-worker above 0.5 with an efficiency near 1 is the
machine (other processes holding the cores), not the study.

The machine's load average is printed: wall times on a shared machine are upper bounds.
"""
from __future__ import annotations

import json
import logging
import os
import tempfile
import time
import warnings
from pathlib import Path

T_END = 60.0
ALPHAS = [1.0, 1.0001, 1.0002, 1.0003]


def study(shift=0.0):
    return {"experiment": {"t_end": T_END, "laws": ["iv-drem", "composite-learning"]},
            "study": {"grid": {"controller.alpha": [a + shift for a in ALPHAS]}}}


def _echo(payload):
    return payload


def main():
    from dask.distributed import Client, LocalCluster

    from ivdrem.experiments.config import read_config, resolve_config
    from ivdrem.experiments.paper import run_law
    from ivdrem.experiments.study import run_study

    print(f"load average before: {os.getloadavg()}")
    # warm the disk cache and measure the floor: 8 runs in this process, one after the other
    for law in ("iv-drem", "composite-learning"):
        run_law(resolve_config(read_config(None, {"experiment.t_end": 1.0}))[0], law, progress=False)
    t0 = time.perf_counter()
    serial = []
    for a in ALPHAS:
        cfg = resolve_config(read_config(None, {"experiment.t_end": T_END, "controller.alpha": a}))[0]
        for law in cfg["experiment"]["laws"]:
            serial.append(run_law(cfg, law, progress=False).stats["wall_s"])
    t_serial = time.perf_counter() - t0
    print(f"in-process, serial: 8 runs in {t_serial:.1f} s = {8 / t_serial * 60:.1f} runs/min "
          f"(stepping {sum(serial):.1f} s)")

    rows = {}
    for n in (1, 2):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Port .* is already in use")
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None,
                                   silence_logs=logging.ERROR)
        t_start = time.perf_counter() - t0
        for phase, shift in (("fresh workers", 0.0), ("warm workers", 1e-5)):
            with tempfile.TemporaryDirectory() as out:
                t0 = time.perf_counter()
                df = run_study(study(shift), out, scheduler=cluster.scheduler_address,
                               progress=False, report=False)
                wall = time.perf_counter() - t0
                rec = json.loads(sorted(Path(out, "runs").glob("*.json"))[0].read_text())
            busy = df["task_s"].sum()
            overhead = (wall * n - busy) / len(df)
            rows[(n, phase)] = wall
            print(f"{n} worker(s), {phase}: study of 8 runs {wall:.1f} s = "
                  f"{8 / wall * 60:.1f} runs/min (all ok: {(df['status'] == 'ok').all()}); "
                  f"per task: simulation {df['sim_s'].mean():.2f} s, diagram build + code load "
                  f"{df['compile_s'].mean():.2f} s, worker time {df['task_s'].mean():.2f} s; "
                  f"wall x workers - worker time = {overhead:.2f} s/task (imports and warm-up on "
                  f"fresh workers, idle, scheduling, transfer)")
        client = Client(cluster.scheduler_address, set_as_default=False)
        payload = {k: rec[k] for k in ("summary", "curves", "conclusions")}
        client.submit(_echo, payload, pure=False).result()
        k = 40
        t0 = time.perf_counter()
        futs = [client.submit(_echo, payload, pure=False) for _ in range(k)]
        client.gather(futs)
        rtt = (time.perf_counter() - t0) / k
        client.close()
        cluster.close()
        print(f"{n} worker(s): cluster start {t_start:.1f} s; a no-op task returning a "
              f"run-sized record ({len(json.dumps(payload))} bytes of JSON): {rtt * 1e3:.1f} ms "
              f"per task through the scheduler")
    for phase in ("fresh workers", "warm workers"):
        print(f"speed-up 2 workers vs 1, {phase}: {rows[(1, phase)] / rows[(2, phase)]:.2f}x")
    print(f"load average after: {os.getloadavg()}")


ROBUSTNESS = """
[experiment]
t_end = {t_end}
laws = ["iv-drem", "composite-learning"]
[model]
name = "two-link"
[robustness]
noise_levels = [0.0, 1.0]
payload_mass = [0.0, 0.5]
payload_com = [0.3, 0.0, 0.0]
omega_scale = [1.0]
seeds = [0]
mu_max = 60.0
"""


def robustness(t_end):
    from ivdrem.plants.study import run_robustness
    print(f"load average before: {os.getloadavg()}")
    walls = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp, "robustness.toml")
        path.write_text(ROBUSTNESS.format(t_end=float(t_end)))
        for workers in (1, 2):
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="Port .* is already in use")
                logging.getLogger("distributed").setLevel(logging.ERROR)
                # workers = 1 through Dask too (a LocalCluster of one process): like for like
                import ivdrem.plants.study as study
                t0 = time.perf_counter()
                df = _run_on_dask(study, path, Path(tmp, f"out{workers}"), workers)
                wall = time.perf_counter() - t0
            cpu = df["cpu_s"].sum()
            walls[workers] = wall
            print(f"{workers} worker(s): {len(df)} runs of {t_end:g} s in {wall:.1f} s "
                  f"(all ok: {(df['status'] == 'ok').all()}); runs' CPU {cpu:.1f} s, run wall "
                  f"{df['wall_s'].sum():.1f} s; efficiency CPU/(wall x workers) "
                  f"{cpu / (wall * workers):.2f}; load now {os.getloadavg()[0]:.1f}", flush=True)
    print(f"2 workers / 1 worker wall time: {walls[2] / walls[1]:.2f} (target <= 0.6)")
    print(f"load average after: {os.getloadavg()}")


def _run_on_dask(study, path, out, workers):
    """run_robustness on a LocalCluster of ``workers`` processes (1 included)."""
    from dask.distributed import Client, LocalCluster, as_completed
    import pandas as pd
    config, rob, _ = study.read_robustness(path)
    runs = study.expand(config, rob)
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None, silence_logs=logging.ERROR) as cluster, \
            Client(cluster) as client:
        futs = [client.submit(study.run_one, config, rob, r, pure=False) for r in runs]
        rows = [f.result() for f in as_completed(futs)]
    return pd.DataFrame(rows)


if __name__ == "__main__":
    import sys
    if "--robustness" in sys.argv:
        i = sys.argv.index("--robustness")
        robustness(float(sys.argv[i + 1]) if len(sys.argv) > i + 1 else 60.0)
    else:
        main()
