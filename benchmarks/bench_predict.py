#!/usr/bin/env python
"""The sampled loop's stability prediction (ivdrem.controller.stability, as
``ivdrem fmu export --controller`` calls it: ``fmu_export.predict`` on an arm's
configuration, γ = 500, the default prefix 1.25 T) as it is now (the prefix's loop in one
compiled call around the C library built with -O3) against as it was (the loop stepped
from Python, ``compiled=False``, around the library built with -O2), side by side,
alternating, in one process, both warm (a short prediction of each first; the compile
cache's load is printed apart).  Per run: the wall time, the prefix's share, and whether
every row (t, which θ̂, ρ) is the same as the other path's, bit for bit.

Usage::

    ./run python benchmarks/bench_predict.py [--arms panda ur5] [--rounds 2]
"""
from __future__ import annotations

import argparse
import functools
import os
import time

from ivdrem.controller import stability
from ivdrem.controller.fmu_export import controller_design, predict
from ivdrem.experiments.config import read_config
from ivdrem.experiments.experiment import Experiment

_original = stability.closed_loop_prefix


def _run(model, design, experiment, compiled):
    """One prediction: (result, wall s, prefix s)."""
    spent = [0.0]

    def timed(*a, **k):
        t0 = time.perf_counter()
        try:
            if compiled:
                return _original(*a, **k)
            return _original(*a, compiled=False, flags=("-O2",), **k)
        finally:
            spent[0] += time.perf_counter() - t0
    stability.closed_loop_prefix = timed
    try:
        t0 = time.perf_counter()
        st = predict(model, "iv-drem", design, experiment)
        return st, time.perf_counter() - t0, spent[0]
    finally:
        stability.closed_loop_prefix = _original


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arms", nargs="+", default=["panda", "ur5"])
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args(argv)
    print(f"load at start {os.getloadavg()[0]:.1f}")
    differ = []
    for arm in args.arms:
        experiment = Experiment.from_config(read_config(f"examples/{arm}.toml",
                                                        {"iv_drem.gamma": 500.0}))
        model = experiment.model
        design = controller_design(experiment, "iv-drem", h=experiment.h)
        short = {**design, "T": 0.08}
        for compiled in (True, False):          # warm: the compile cache loaded, built
            _, wall, _ = _run(model, short, experiment, compiled)
            print(f"{arm}: warm-up {'now' if compiled else 'before'} {wall:.2f} s")
        walls = {True: [], False: []}
        rows = {}
        for r in range(args.rounds):
            for compiled in ((True, False) if r % 2 == 0 else (False, True)):
                st, wall, pre = _run(model, design, experiment, compiled)
                walls[compiled].append(wall)
                rows.setdefault(compiled, st.points)
                print(f"{arm}: {'now   ' if compiled else 'before'} {wall:6.1f} s "
                      f"(prefix {pre:5.1f} s), growth {st.growth:.6f}, "
                      f"load {os.getloadavg()[0]:.1f}", flush=True)
        same = rows[True] == rows[False]
        if not same:
            differ.append(arm)
        best = {c: min(w) for c, w in walls.items()}
        print(f"{arm}: before / now = {best[False] / best[True]:.2f} (best of "
              f"{args.rounds} each: {best[False]:.1f} s / {best[True]:.1f} s); rows "
              f"{'identical' if same else 'DIFFER'} ({len(rows[True])} rows)")
    print(f"load at end {os.getloadavg()[0]:.1f}")
    return 1 if differ else 0         # a prediction that moved is a failure


if __name__ == "__main__":
    raise SystemExit(main())
