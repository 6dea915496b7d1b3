#!/usr/bin/env python
"""Microseconds per Jacobian, per factorisation of c I - J and per solve, on the paper's
closed loops: the generated structured Jacobian + static-pattern sparse LU against the
whole-system forward-difference Jacobian + dense partial-pivoting LU (the template's
fallbacks) and against LAPACK (scipy.linalg.lu_factor / lu_solve, from Python).

Each compiled function is timed inside a numba loop (so numba's per-call dispatch from
Python is not counted), at a state reached by a 2 s run, c = 1/(gamma h) for h = 1 ms.
The functions are the numba stepper's (``IVDREM_STEPPER=numba``, set here: numba loops
can call them); the C stepper runs the same algorithms line for line.

Usage::

    PYTHONPATH=. python benchmarks/bench_jacobian.py [--reps N]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
os.environ["IVDREM_STEPPER"] = "numba"      # numba-compiled functions, callable from numba loops
try:
    import ivdrem  # noqa: F401
except ImportError:
    sys.path.insert(0, str(REPO))

from numba import njit  # noqa: E402
import scipy.linalg as sla  # noqa: E402

from ivdrem.diagrams import closed_loop  # noqa: E402
from ivdrem.sim.simulator import Simulator  # noqa: E402
from ivdrem.sim.jacobian import JacobianProgram  # noqa: E402
from ivdrem.sim.sparse_lu import symbolic_lu  # noqa: E402

_LOOPS = '''
def loop_jac(k, t, x, P, W, J):
    for i in range(k):
        JAC(t, x, P, W, J)


def loop_factor(k, W, J, c, LU, piv):
    for i in range(k):
        FACTOR(W, J, c, LU, piv)


def loop_solve(k, W, LU, piv, b0, b):
    for i in range(k):
        for j in range(b.shape[0]):
            b[j] = b0[j]
        SOLVE(W, LU, piv, b)


def loop_rhs(k, t, x, P, W, out):
    for i in range(k):
        EVAL(0, t, x, P, W, out)
'''


def _loops(jac, factor, solve, ev):
    ns = {"JAC": jac, "FACTOR": factor, "SOLVE": solve, "EVAL": ev, "np": np}
    exec(_LOOPS, ns)
    return {k: njit(ns[k]) for k in ("loop_jac", "loop_factor", "loop_solve", "loop_rhs")}


def _time(fn, args, reps):
    fn(1, *args)                        # compile
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        fn(reps, *args)
        best = min(best, time.perf_counter() - t0)
    return 1e6 * best / reps


def _py_time(fn, reps):
    fn()
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        best = min(best, time.perf_counter() - t0)
    return 1e6 * best / reps


def bench(law, reps):
    sim = Simulator(closed_loop(law))
    sim.advance(2.0)
    eng, mod = sim.engine, sim.engine.module
    t, x, P, W = sim.t, sim.x.copy(), eng.P, sim.W
    n = x.size
    c = 1.0 / (0.21193756319429014 * 1e-3)          # Rodas5P gamma, h = 1 ms
    prog = JacobianProgram(sim.plan)
    slu = symbolic_lu(prog.pattern)
    J = np.zeros((n, n))
    LU = np.zeros((n + 2, n))       # the template's layout: two spare rows for the sparse LU
    piv = np.zeros(n, dtype=np.int64)
    b0 = np.random.default_rng(0).standard_normal(n)
    b = b0.copy()
    fast = _loops(mod.diagram_jacobian, mod.newton_factor, mod.newton_solve, mod.diagram_eval)
    dense_factor, dense_solve = mod.dense_factor, mod.dense_solve
    dense = _loops(mod.fd_jacobian,
                   njit(lambda W, J, c, LU, piv: dense_factor(J, c, LU, piv)),
                   njit(lambda W, LU, piv, b: dense_solve(LU, piv, b)), mod.diagram_eval)
    rows = {}
    for name, L in (("structured + sparse LU", fast), ("dense FD + dense LU", dense)):
        r = {"jac": _time(L["loop_jac"], (t, x, P, W, J), reps)}
        Jc = J.copy()
        r["factor"] = _time(L["loop_factor"], (W, Jc, c, LU, piv), reps)
        r["solve"] = _time(L["loop_solve"], (W, LU, piv, b0, b), reps)
        rows[name] = r
    A = c * np.eye(n) - J
    lu = sla.lu_factor(A)
    rows["LAPACK (from Python)"] = {"jac": np.nan,
                                   "factor": _py_time(lambda: sla.lu_factor(A), reps),
                                   "solve": _py_time(lambda: sla.lu_solve(lu, b0), reps)}
    rhs = _time(fast["loop_rhs"], (t, x, P, W, np.zeros(n)), reps)
    return dict(law=law, n=n, nnz=prog.nnz, nnz_lu=slu.nnz_lu, fill=slu.fill,
                ordering=slu.ordering, groups=int(prog.gc_ptr.size - 1),
                fd_cols=int(prog.col.size), rhs=rhs, rows=rows)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=2000)
    a = ap.parse_args(argv)
    print(f"# bench_jacobian: {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}")
    for law in ("iv-drem", "composite-learning"):
        r = bench(law, a.reps)
        print(f"\n{law}: n = {r['n']}, nnz(J) = {r['nnz']} (structural), nnz(L+U) = "
              f"{r['nnz_lu']} ({r['ordering']} ordering, fill {r['fill']}), block FD: "
              f"{r['fd_cols']} columns in {r['groups']} groups; one RHS = {r['rhs']:.2f} µs")
        print(f"  {'':24s} {'µs/Jacobian':>12s} {'µs/factor':>10s} {'µs/solve':>9s}")
        for name, v in r["rows"].items():
            print(f"  {name:24s} {v['jac']:12.2f} {v['factor']:10.2f} {v['solve']:9.2f}")
        f, d = r["rows"]["structured + sparse LU"], r["rows"]["dense FD + dense LU"]
        print(f"  speed-up                 {d['jac'] / f['jac']:11.1f}x {d['factor'] / f['factor']:9.1f}x"
              f" {d['solve'] / f['solve']:8.1f}x")
    print(f"\n# load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
