#!/usr/bin/env python
"""Cost of the FMU plant in the compiled closed loop, against the Python (numba) plant.

The same IV-DREM loop, ``closed_loop("iv-drem", model)`` and ``closed_loop("iv-drem", model,
replace={"plant": fmu_plant(path)})``, the FMU exported from the same model with the
Python plant's q(0), is simulated on the compiled engine, alternately, ``--reps`` times
per method; the best ``sim_s`` (integration only, compile and cache load apart) of each is
divided by the horizon: seconds of computing per simulated second.  Printed side by side
with the ratio FMU / Python (target <= 2x), the right-hand-side and Jacobian counts (the
same step sequence: the two loops agree to ~1e-12) and the largest |q_FMU - q_Python|.

Usage::

    PYTHONPATH=. python benchmarks/bench_fmu_plant.py [--t-end 10] [--reps 3]
                                                      [--methods rodas5p,dp45,rk4]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=10.0)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--methods", default="rodas5p,dp45,rk4")
    args = ap.parse_args(argv)

    from ivdrem.diagrams import closed_loop
    from ivdrem.fmu import export_fmu, fmu_plant
    from ivdrem.models import two_link
    from ivdrem.sim import simulate

    model = two_link()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average (1 min) at start: {load:.2f}", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        path = export_fmu(model, Path(tmp) / "TwoLink.fmu", q0=[0.0, 0.3 * np.pi])
        loops = {"python plant": closed_loop("iv-drem", model),
                 "FMU plant": closed_loop("iv-drem", model,
                                          replace={"plant": fmu_plant(path, name="plant")})}
        rows = []
        for method in args.methods.split(","):
            best, stats, q = {}, {}, {}
            for name, d in loops.items():       # warm-up: compile / load every module
                simulate(d, min(0.05, args.t_end), method=method, progress=False)
            for _ in range(args.reps):
                for name, d in loops.items():
                    r = simulate(d, args.t_end, method=method, progress=False,
                                 return_states=False)
                    s = r.stats
                    if name not in best or s["sim_s"] < best[name]:
                        best[name], stats[name] = s["sim_s"], s
                    q[name] = np.asarray(r.outputs[:model.n])
            dq = float(np.max(np.abs(q["FMU plant"] - q["python plant"])))
            ratio = best["FMU plant"] / best["python plant"]
            rows.append((method, best, stats, ratio, dq))
            print(f"{method}: done", file=sys.stderr)

    print(f"\nIV-DREM closed loop, two-link, t_end = {args.t_end:g} s, compiled engine, "
          f"best of {args.reps}")
    head = (f"{'method':<8} {'plant':<13} {'s per sim s':>11} {'steps':>7} {'rhs':>8} "
            f"{'jac':>6} {'us/rhs':>7}")
    print(head)
    print("-" * len(head))
    for method, best, stats, ratio, dq in rows:
        for name in ("python plant", "FMU plant"):
            s = stats[name]
            print(f"{method:<8} {name:<13} {best[name] / args.t_end:>11.4f} {s['steps']:>7} "
                  f"{s['rhs_calls']:>8} {s['jacobians']:>6} "
                  f"{1e6 * best[name] / max(1, s['rhs_calls']):>7.2f}")
        verdict = "OK" if ratio <= 2.0 else "MISSED"
        print(f"{method:<8} ratio FMU / Python = {ratio:.2f}x (target <= 2x: {verdict}); "
              f"max |q_FMU - q_Python| = {dq:.1e}")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average (1 min) at end: {load:.2f}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
