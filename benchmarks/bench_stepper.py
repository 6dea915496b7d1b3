#!/usr/bin/env python
"""The compiled engine's two stepper builds side by side: C (stepper.c, the default) and
numba (stepper.py), on the paper's loops, both methods, integration time only (sim_s).

Both builds give the same numbers bit for bit (tests/test_cstepper.py); this measures
their speed, alternating the builds run by run in one process, and the DP45 / Rodas5P
ratio each gives (both laws summed, the fastest of the repetitions).

Usage::

    PYTHONPATH=. python benchmarks/bench_stepper.py [--t-end 300] [--reps 2]
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
from ivdrem.sim import simulate  # noqa: E402

LAWS = ("iv-drem", "composite-learning")
STEPPERS = ("c", "numba")
METHODS = ("dp45", "rodas5p")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--reps", type=int, default=2)
    a = ap.parse_args(argv)
    print(f"# bench_stepper: {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, "
          f"t_end {a.t_end:g} s, outputs every 10 ms, {a.reps} repetitions")
    loops = {law: closed_loop(law) for law in LAWS}
    for st in STEPPERS:                       # build / compile / load both first
        os.environ["IVDREM_STEPPER"] = st
        for d in loops.values():
            simulate(d, 0.01, progress=False)
    best = {}
    for rep in range(a.reps):
        for law, d in loops.items():
            for st in STEPPERS:
                os.environ["IVDREM_STEPPER"] = st
                for m in METHODS:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")    # DP45's stiffness warning
                        r = simulate(d, a.t_end, method=m, dt_out=0.01, progress=False,
                                     return_states=False)
                    assert r.stats["stepper"] == st
                    k = (law, st, m)
                    best[k] = min(best.get(k, float("inf")), r.stats["sim_s"])
                    print(f"  rep {rep + 1} {law:20s} {st:6s} {m:8s} sim_s {r.stats['sim_s']:7.3f}"
                          f"  steps {r.stats['steps']}", flush=True)
    print(f"\n  {'':28s} " + " ".join(f"{st + ' ' + m:>14s}" for st in STEPPERS for m in METHODS))
    for law in LAWS:
        print(f"  {law:28s} " + " ".join(f"{best[(law, st, m)]:14.3f}" for st in STEPPERS
                                          for m in METHODS))
    for m in METHODS:
        c, nb = (sum(best[(law, st, m)] for law in LAWS) for st in STEPPERS)
        print(f"  {m}: both laws, numba / C = {nb / c:.2f}x")
    for st in STEPPERS:
        dp, ro = (sum(best[(law, st, m)] for law in LAWS) for m in METHODS)
        print(f"  stepper {st}: DP45 / Rodas5P, both laws = {dp / ro:.2f}x")
    print(f"# load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
