#!/usr/bin/env python
"""Cost of the MuJoCo loop per sample, driven from Python, measured side by side in one run.

For each arm (the paper's 2-link, planar-6, the Panda and the UR5 by default):

* ``mj_step``: MuJoCo's step alone (``mujoco.mj_step`` in a Python loop, implicit, 1 ms);
* ``plant``: :meth:`ivdrem.plants.mujoco.MujocoPlant.step` (the torque set, the divergence
  check) and reading q, q̇;
* ``controller``: one step of the generated C controller (``CController.step``, ctypes;
  URDF arms: the eigen mixing every ``--mix-every`` samples);
* ``loop``: one sample of :func:`ivdrem.plants.mujoco.closed_loop` (everything: plant,
  controller, disturbance, sensors off, recording every 100 samples) over ``--t-end``, as
  the loop measures it (``response.costs["loop_us"]``: the run's set-up left out).

Best of ``--reps`` runs, µs per sample, with the 1-min load average at start and end (the
machine is shared: the ratios within one run are what counts).  The issue's target: a
MuJoCo step plus a controller step, from Python, <= 150 µs for the Panda.

Usage::

    ./run python benchmarks/bench_mujoco.py [--arms two-link,planar-6,panda,ur5]
                                            [--steps 5000] [--t-end 5] [--reps 3]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np


def _best(fn, reps):
    return min(fn() for _ in range(reps))


def bench(name, steps, t_end, reps, mix_every):
    import mujoco
    from ivdrem.plants.mujoco import closed_loop, load
    plant = load(name, states=20)
    n = plant.n
    row = dict(arm=name, n=n)

    def mj_only():
        plant.reset(np.zeros(n))
        m, d = plant.mj, plant.data
        t0 = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(m, d)
        return (time.perf_counter() - t0) / steps * 1e6

    def plant_step():
        plant.reset(np.zeros(n))
        tau = np.zeros(n)
        t0 = time.perf_counter()
        for _ in range(steps):
            plant.q, plant.dq
            plant.step(tau)
        return (time.perf_counter() - t0) / steps * 1e6

    row["mj_step"] = _best(mj_only, reps)
    row["plant"] = _best(plant_step, reps)
    try:
        from ivdrem.controller.clib import CController
        from ivdrem.models.urdf import RigidBodyModel
        gains = dict(mu_max=135.0)
        if isinstance(plant.model, RigidBodyModel):      # eigen mixing of many parameters
            gains["mix_every"] = mix_every
        ctl = CController(plant.model, "iv-drem", **gains)
    except Exception as exc:             # the C library has no URDF arms yet
        row["controller"] = row["loop"] = None
        row["note"] = f"no C controller ({type(exc).__name__})"
        return row

    def ctl_step():
        ctl.reset()
        q, dq = np.full(n, 0.3), np.full(n, 0.1)
        t0 = time.perf_counter()
        for k in range(steps):
            ctl.step(k * ctl.h, q, dq)
        return (time.perf_counter() - t0) / steps * 1e6

    row["controller"] = _best(ctl_step, reps)

    def loop():
        r = closed_loop(plant, t_end, every=100, progress=False, **gains)
        return r.costs["loop_us"]

    row["loop"] = _best(loop, reps)
    row["note"] = ""
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arms", default="two-link,planar-6,panda,ur5")
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--t-end", type=float, default=5.0, dest="t_end")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--mix-every", type=int, default=50, dest="mix_every",
                    help="URDF arms: mix (17) every N samples (default %(default)s)")
    args = ap.parse_args(argv)
    print(f"load average at start: {os.getloadavg()[0]:.1f} (1 min), {os.cpu_count()} cores")
    rows = []
    for name in args.arms.split(","):
        rows.append(bench(name.strip(), args.steps, args.t_end, args.reps, args.mix_every))
        r = rows[-1]
        fmt = lambda v: "    -" if v is None else f"{v:7.1f}"  # noqa: E731
        if len(rows) == 1:
            print(f"{'arm':<10} {'n':>2} {'mj_step':>8} {'plant':>8} {'ctrl':>8} {'loop':>8} "
                  f"{'plant/mj':>8}  (µs per sample, best of {args.reps})")
        print(f"{r['arm']:<10} {r['n']:>2} {fmt(r['mj_step']):>8} {fmt(r['plant']):>8} "
              f"{fmt(r['controller']):>8} {fmt(r['loop']):>8} "
              f"{r['plant'] / r['mj_step']:8.2f}  {r['note']}", flush=True)
    for r in rows:
        if r["controller"] is not None:
            print(f"{r['arm']}: MuJoCo step + controller step from Python "
                  f"{r['plant'] + r['controller']:.1f} µs (loop {r['loop']:.1f} µs; "
                  f"target for the Panda <= 150 µs)")
    print(f"load average at end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
