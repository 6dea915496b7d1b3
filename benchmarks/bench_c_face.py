#!/usr/bin/env python
"""The models' C face (model.c_source, docs/models.md) against their numba-compiled Python.

Per model, in one process and one run: the C face compiled with -O2 (ivdrem._cc) and a
small timing loop compiled beside it (the loop in C: no ctypes call in the measure), and
the model's numba functions (``jit_functions``) timed by a numba loop, on the same state;
printed per function: C ns/call, numba ns/call (each the best of 15 alternating short
runs) and their ratio, plus the C build time.

Usage::

    ./run python benchmarks/bench_c_face.py [--models two-link panda ...] [--iters N]
"""
from __future__ import annotations

import argparse
import ctypes
import os
import tempfile
import time
from pathlib import Path

import numpy as np

#: short runs per measure, the best kept
REPEATS = 15

_LOOP = r"""
#include <time.h>
static double now_(void) {
    struct timespec ts; clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}
double bench_phi(const double *q, const double *dq, const double *v, const double *dv,
                 double *out, long iters) {
    double t0 = now_();
    for (long i = 0; i < iters; i++) bf_Phi(q, dq, v, dv, out);
    return (now_() - t0) / iters;
}
double bench_fd(const double *q, const double *dq, const double *tau, const double *th,
                double *out, long iters) {
    double t0 = now_();
    for (long i = 0; i < iters; i++) bf_forward_dynamics(q, dq, tau, th, out);
    return (now_() - t0) / iters;
}
"""


def _numba_loops():
    import numba

    @numba.njit
    def loop_phi(f, q, dq, v, dv, out, iters):
        for _ in range(iters):
            f(q, dq, v, dv, out)

    @numba.njit
    def loop_fd(f, q, dq, tau, th, out, iters):
        for _ in range(iters):
            f(q, dq, tau, th, out)
    return loop_phi, loop_fd


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=["two-link", "planar-3", "panda", "ur5"])
    ap.add_argument("--iters", type=int, default=20000)
    args = ap.parse_args(argv)
    from ivdrem import _cc
    from ivdrem.models import get_model
    loop_phi, loop_fd = _numba_loops()
    print(f"load average {os.getloadavg()[0]:.1f} (2 cores shared)")
    print(f"{'model':<10} {'function':<18} {'C ns':>9} {'numba ns':>9} {'numba/C':>8}"
          f"  C build s")
    for name in args.models:
        model = get_model(name)
        n, nt = model.n, model.ntheta
        with tempfile.TemporaryDirectory() as tmp:
            src = Path(tmp) / "bf.c"
            src.write_text("#define _POSIX_C_SOURCE 199309L\n" + model.c_source("bf_") + _LOOP)
            t0 = time.perf_counter()
            _cc.compile_shared([src], Path(tmp) / "libbf.so", what="the benchmark")
            build = time.perf_counter() - t0
            lib = ctypes.CDLL(str(Path(tmp) / "libbf.so"))
        P = ctypes.POINTER(ctypes.c_double)
        for f in (lib.bench_phi, lib.bench_fd):
            f.argtypes = [P] * 5 + [ctypes.c_long]
            f.restype = ctypes.c_double
        rng = np.random.default_rng(0)
        q, dq, v, dv = (rng.uniform(-1, 1, n) for _ in range(4))
        th = np.asarray(model.theta_values, float)
        out_phi, out_fd = np.empty((n, nt)), np.empty(n)
        p = lambda a: a.ctypes.data_as(P)  # noqa: E731
        jf = model.jit_functions
        loop_phi(jf.Phi, q, dq, v, dv, out_phi, 10)          # compile
        loop_fd(jf.forward_dynamics, q, dq, dv, th, out_fd, 10)
        it = max(1, args.iters // REPEATS)

        def numba_time(loop, *a):
            t0 = time.perf_counter()
            loop(*a, it)
            return (time.perf_counter() - t0) / it
        # the best of REPEATS alternating short runs: a shared machine's preemptions only
        # ever add time
        c_phi = c_fd = nb_phi = nb_fd = float("inf")
        for _ in range(REPEATS):
            c_phi = min(c_phi, lib.bench_phi(p(q), p(dq), p(v), p(dv), p(out_phi), it))
            nb_phi = min(nb_phi, numba_time(loop_phi, jf.Phi, q, dq, v, dv, out_phi))
            c_fd = min(c_fd, lib.bench_fd(p(q), p(dq), p(dv), p(th), p(out_fd), it))
            nb_fd = min(nb_fd, numba_time(loop_fd, jf.forward_dynamics, q, dq, dv, th, out_fd))
        for fn, c, nb in (("Phi", c_phi, nb_phi), ("forward_dynamics", c_fd, nb_fd)):
            print(f"{name:<10} {fn:<18} {c * 1e9:9.0f} {nb * 1e9:9.0f} {nb / c:8.2f}"
                  f"  {build:.2f}")


if __name__ == "__main__":
    main()
