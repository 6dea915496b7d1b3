#!/usr/bin/env python
"""The one stepper (stepper.c) on the paper's loops: every method on the compiled engine,
integration time only (sim_s), and the reference engine (python-control's evaluation
called back from the same stepper) over a short horizon, side by side.

Usage::

    PYTHONPATH=. python benchmarks/bench_stepper.py [--t-end 300] [--t-ref 2] [--reps 2]
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
try:
    import ivdrem  # noqa: F401
except ImportError:
    sys.path.insert(0, str(REPO))

from ivdrem.diagrams import closed_loop  # noqa: E402
from ivdrem.sim import METHODS, simulate  # noqa: E402

LAWS = ("iv-drem", "composite-learning")


def _run(d, t_end, method, engine):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")    # DP45's stiffness warning
        return simulate(d, t_end, method=method, engine=engine, dt_out=0.01, progress=False,
                        return_states=False)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--t-ref", type=float, default=2.0)
    ap.add_argument("--reps", type=int, default=2)
    a = ap.parse_args(argv)
    print(f"# bench_stepper: {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, "
          f"t_end {a.t_end:g} s (reference engine {a.t_ref:g} s), outputs every 10 ms, "
          f"{a.reps} repetitions")
    loops = {law: closed_loop(law) for law in LAWS}
    for d in loops.values():                  # build / compile / load first
        simulate(d, 0.01, progress=False)
    best = {}
    for rep in range(a.reps):
        for law, d in loops.items():
            for m in METHODS:
                for engine, t in (("compiled", a.t_end), ("reference", a.t_ref)):
                    if engine == "reference" and rep > 0:
                        continue
                    r = _run(d, t, m, engine)
                    k = (law, m, engine)
                    best[k] = min(best.get(k, float("inf")), r.stats["sim_s"])
                    print(f"  rep {rep + 1} {law:20s} {m:8s} {engine:9s} {t:6g} s  sim_s "
                          f"{r.stats['sim_s']:8.3f}  steps {r.stats['steps']}", flush=True)
    print(f"\n  sim_s of the compiled engine, and the reference engine's time per simulated "
          f"second over the compiled one's")
    print(f"  {'':22s}" + "".join(f"{m + ' ' + a_:>24s}" for m in METHODS
                                  for a_ in ("compiled s", "ref/compiled")))
    for law in LAWS:
        row = ""
        for m in METHODS:
            row += f"{best[(law, m, 'compiled')]:24.3f}"
            # per simulated second: reference / compiled (other step counts: the loop's
            # evaluations differ, not the stepper)
            ratio = (best[(law, m, 'reference')] / a.t_ref) / \
                (best[(law, m, 'compiled')] / a.t_end)
            row += f"{ratio:24.0f}"
        print(f"  {law:22s}{row}")
    print(f"# load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
