#!/usr/bin/env python
"""Cost of the MuJoCo loop per sample, driven from Python: before and after, side by side.

For each arm (the paper's 2-link and the Panda by default), in one run, alternating:

* ``mj_step``: MuJoCo's step alone (``mujoco.mj_step`` in a Python loop, implicit, 1 ms);
* ``before``: one sample as the loop first did it: q, q̇ copied out of MuJoCo's data,
  ``CController.step`` (ctypes; the copy of q, q̇ in, of τ out) of the library built
  with its default ``-O2``, ``disturbance_at`` (new arrays), ``MujocoPlant.step(τ + τ_d)``;
* ``after``: one sample of :func:`ivdrem.plants.mujoco.closed_loop` as it is now (the C
  library called in place on MuJoCo's q, q̇, the torque in preallocated buffers, τ_d in a
  buffer, τ + τ_d summed into ``qfrc_applied``; the library built with
  ``CONTROLLER_FLAGS``, -O3), sensors off, recording every 100 samples, as the loop
  measures itself (``response.costs``: its set-up left out).

Each figure is the CPU time of the thread per sample (``time.thread_time``), best of
``--reps``: on a shared machine the wall time includes the time the process waited for a
core (printed too, with the load average). URDF arms: the eigen mixing (and composite
learning's max-hold) every ``--mix-every`` samples; ``--law`` the controller's law
(default IV-DREM).  The issue's target: a MuJoCo step plus a controller step, from
Python, <= 150 µs for the Panda.

Usage::

    ./run python benchmarks/bench_mujoco.py [--arms two-link,panda] [--t-end 3] [--reps 3]
        [--law composite-learning]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np


def _best(fn, reps):
    """min over reps of fn() -> (cpu µs, wall µs) per sample, by CPU time."""
    return min((fn() for _ in range(reps)), key=lambda x: x[0])


def bench(name, t_end, reps, mix_every, law="iv-drem"):
    import mujoco
    from ivdrem.controller.clib import CController
    from ivdrem.controller.loop import disturbance_at
    from ivdrem.models.urdf import RigidBodyModel
    from ivdrem.plants.mujoco import CONTROLLER_FLAGS, closed_loop, load
    plant = load(name, states=20)
    n = plant.n
    gains = dict(mu_max=135.0)
    if isinstance(plant.model, RigidBodyModel):          # eigen mixing of many parameters
        gains["mix_every"] = mix_every
    N = int(round(t_end / plant.h))
    dist = dict(amplitude=np.full(n, 0.5), omega=np.linspace(0.5, 2.0, n),
                phase=np.zeros(n), offset=np.zeros(n))
    row = dict(arm=name, n=n)

    def mj_only():
        plant.reset(np.zeros(n))
        m, d = plant.mj, plant.data
        c0, w0 = time.thread_time(), time.perf_counter()
        for _ in range(N):
            mujoco.mj_step(m, d)
        return ((time.thread_time() - c0) / N * 1e6, (time.perf_counter() - w0) / N * 1e6)

    ctl_before = CController(plant.model, law, **gains)                  # -O2
    ctl_after = CController(plant.model, law, flags=CONTROLLER_FLAGS, **gains)

    def before():
        """The earlier loop's per-sample work (its recording every 100 samples left out)."""
        ctl_before.reset()
        plant.reset(np.zeros(n))
        h = plant.h
        c0, w0 = time.thread_time(), time.perf_counter()
        for k in range(N):
            t = k * h
            q, dq = plant.q, plant.dq
            tau = ctl_before.step(t, q, dq)
            tau_d = disturbance_at(t, dist)
            plant.step(tau + tau_d)
        return ((time.thread_time() - c0) / N * 1e6, (time.perf_counter() - w0) / N * 1e6)

    def after():
        r = closed_loop(plant, t_end, law, controller=ctl_after, q0=np.zeros(n),
                        disturbance=dist, every=100, progress=False)
        ctl_after.reset()
        return r.costs["loop_cpu_us"], r.costs["loop_us"]

    row["mj_step"], row["before"], row["after"] = [], [], []
    for _ in range(reps):                      # alternating, so that load changes hit both
        row["mj_step"].append(mj_only())
        row["before"].append(before())
        row["after"].append(after())
    for k in ("mj_step", "before", "after"):
        row[k] = min(row[k], key=lambda x: x[0])
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arms", default="two-link,panda")
    ap.add_argument("--t-end", type=float, default=3.0, dest="t_end")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--mix-every", type=int, default=50, dest="mix_every",
                    help="URDF arms: mix (17) every N samples (default %(default)s)")
    ap.add_argument("--law", default="iv-drem",
                    help="the controller's law (default %(default)s)")
    args = ap.parse_args(argv)
    print(f"load average at start: {os.getloadavg()[0]:.1f} (1 min), {os.cpu_count()} cores; "
          f"law {args.law}")
    print(f"{'arm':<10} {'n':>2} {'mj_step':>8} {'before':>8} {'after':>8} {'after/before':>12}"
          f"   (CPU µs per sample, best of {args.reps}; wall µs in brackets)")
    for name in args.arms.split(","):
        r = bench(name.strip(), args.t_end, args.reps, args.mix_every, args.law)
        print(f"{r['arm']:<10} {r['n']:>2} {r['mj_step'][0]:8.1f} {r['before'][0]:8.1f} "
              f"{r['after'][0]:8.1f} {r['after'][0] / r['before'][0]:12.2f}   "
              f"[{r['mj_step'][1]:.0f}, {r['before'][1]:.0f}, {r['after'][1]:.0f}]",
              flush=True)
    print("target: a MuJoCo step plus a controller step from Python <= 150 µs for the Panda "
          "('after' is the whole sample of the loop)")
    print(f"load average at end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
