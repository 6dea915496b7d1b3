#!/usr/bin/env python
"""Cost of a block ivdrem did not write, in the paper's IV-DREM loop on the 2-link arm.

Three loops, side by side in one run, same method (Rodas5P) and tolerances, same initial
state, simulated for ``--t-end`` seconds (after a warm-up run of each, so compile time is
apart):

  1. all compiled: the ivdrem plant block;
  2. numba: the user's plant written as a plain ``ct.nlsys`` (its own numpy M, C, g),
     compiled by numba from its source (ivdrem.sim.foreign);
  3. one block in Python: the same plant reading a Python dict, which numba cannot
     compile, so that block alone is called back into Python from the compiled loop.

Prints seconds of integration per simulated second, the ratio of each to loop 1 (target:
loop 3 at most 10x loop 1), right-hand-side calls, integration microseconds per
right-hand side (Jacobians included), and the largest |q| difference to loop 1 (q1) as a
check that all three compute the same thing.

Usage::

    PYTHONPATH=. python benchmarks/bench_open_engine.py [--t-end 10] [--reference]

``--reference`` adds the python-control reference engine on loop 1 (slow: about 1 s per
simulated second or more).
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))

from ivdrem.diagrams import closed_loop  # noqa: E402
from ivdrem.models import two_link  # noqa: E402
from ivdrem.sim import DiagramPlan, simulate  # noqa: E402
from ivdrem.sim.foreign import PythonBlockNotice  # noqa: E402

from test_open_engine import _user_plant, user_arm_update, dict_arm_update, _q  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--t-end", type=float, default=10.0)
    ap.add_argument("--reference", action="store_true")
    a = ap.parse_args(argv)
    model = two_link()
    base = closed_loop("iv-drem", model)
    x0 = DiagramPlan.from_diagram(base).x0
    loops = [("all compiled (ivdrem plant)", base, "compiled"),
             ("user nlsys plant, numba", closed_loop(
                 "iv-drem", model, replace={"plant": _user_plant(user_arm_update)}), "compiled"),
             ("user nlsys plant, in Python", closed_loop(
                 "iv-drem", model, replace={"plant": _user_plant(dict_arm_update)}), "compiled")]
    if a.reference:
        loops.append(("all ivdrem blocks, reference engine", base, "reference"))
    print(f"IV-DREM loop, 2-link arm, rodas5p defaults, {a.t_end:g} s simulated; "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"{'loop':40s} {'s/sim-s':>10s} {'ratio':>7s} {'rhs':>8s} {'us/rhs':>8s} "
          f"{'max|q-q1|':>9s}")
    ref_q, ref_cost = None, None
    for name, d, engine in loops:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PythonBlockNotice)
            if engine == "compiled":
                simulate(d, 0.05, x0=x0, progress=False)           # compile / cache load
            r = simulate(d, a.t_end, x0=x0, progress=False, engine=engine)
        cost = r.stats["sim_s"] / a.t_end
        q = _q(r)
        if ref_q is None:
            ref_q, ref_cost = q, cost
        print(f"{name:40s} {cost:10.4f} {cost / ref_cost:7.2f} {r.stats['rhs_calls']:8d} "
              f"{1e6 * r.stats['sim_s'] / max(r.stats['rhs_calls'], 1):8.1f} "
              f"{np.max(np.abs(q - ref_q)):9.2e}")
    print(f"load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
