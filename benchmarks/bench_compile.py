#!/usr/bin/env python
"""First-run cost from empty caches, compile time apart from simulation time.

A fresh child process with empty numba and ivdrem cache directories (NUMBA_CACHE_DIR,
IVDREM_CACHE_DIR) builds and simulates, one after the other,

  1. law 1: closed_loop("iv-drem")            (compiles the model, kernels, the loop)
  2. law 2: closed_loop("composite-learning")  (model and shared kernels now cached)
  3. rewired: closed_loop("iv-drem", observer_variant="literal")  (another diagram module)

for 0.2 s each with the default method, and prints per case: the Python-side code generation
(incl. the Jacobian's sparsity probe and symbolic LU), the numba compile + load time of the
first integrate call (``stats["compile_s"]``), and the simulation time (``sim_s``).  A
second child with the same (now warm) cache directories shows the cache-load cost.

Targets: both default laws from empty caches <= 20 s in all (import included); a second
law or a rewired diagram <= 8 s.  The stepper (stepper.c) is built by the C compiler
inside law 1's compile, on a thread, while numba compiles the kernels.

Usage::

    PYTHONPATH=. python benchmarks/bench_compile.py [--method NAME]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_CHILD = r'''
import json, sys, time
t0 = time.perf_counter()
from ivdrem.diagrams import closed_loop
from ivdrem.sim.simulator import Simulator
from ivdrem.sim import compiled
t_import = time.perf_counter() - t0
method = sys.argv[1]
cases = [("law 1: iv-drem", dict(law="iv-drem")),
         ("law 2: composite-learning", dict(law="composite-learning")),
         ("rewired: iv-drem, literal observer", dict(law="iv-drem", observer_variant="literal"))]
gen = [0.0]
_orig = compiled.generate_source
def timed(*a, **k):
    g0 = time.perf_counter()
    try:
        return _orig(*a, **k)
    finally:
        gen[0] += time.perf_counter() - g0
compiled.generate_source = timed
out = {"import_s": t_import, "cases": []}
for label, kw in cases:
    gen[0] = 0.0
    c0 = time.perf_counter()
    d = closed_loop(**kw)
    sim = Simulator(d, method=method)
    t_ctor = time.perf_counter() - c0
    sim.advance(0.2)
    total = time.perf_counter() - c0
    out["cases"].append(dict(label=label, total_s=total, codegen_s=gen[0],
                             ctor_s=t_ctor, compile_s=sim.compile_s, sim_s=sim.wall))
print(json.dumps(out))
'''


def _child(env, method):
    r = subprocess.run([sys.executable, "-c", _CHILD, method], env=env, capture_output=True,
                       text=True, cwd=str(REPO))
    if r.returncode != 0:
        sys.stderr.write(r.stderr)
        raise SystemExit(f"child failed with status {r.returncode}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", default="rodas5p")
    a = ap.parse_args(argv)
    print(f"# bench_compile: {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, "
          f"method {a.method}")
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, IVDREM_CACHE_DIR=str(Path(tmp) / "ivdrem"),
                   NUMBA_CACHE_DIR=str(Path(tmp) / "numba"))
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
        for title in ("cold caches (empty)", "warm caches (second process)"):
            r = _child(env, a.method)
            print(f"\n{title}: import {r['import_s']:.2f} s")
            print(f"  {'case':38s} {'total s':>8s} {'codegen':>8s} {'compile':>8s} "
                  f"{'sim':>6s}")
            for c in r["cases"]:
                print(f"  {c['label']:38s} {c['total_s']:8.2f} {c['codegen_s']:8.2f} "
                      f"{c['compile_s']:8.2f} {c['sim_s']:6.2f}")
            if title.startswith("cold"):
                both = r["cases"][0]["total_s"] + r["cases"][1]["total_s"]
                everything = r["import_s"] + both
                print(f"  both default laws: {both:.2f} s, with the import {everything:.2f} s "
                      f"(target <= 20 s in all: {'PASS' if everything <= 20 else 'MISS'}); "
                      f"second law "
                      f"{r['cases'][1]['total_s']:.2f} s, rewired "
                      f"{r['cases'][2]['total_s']:.2f} s (target <= 8 s: "
                      f"{'PASS' if max(r['cases'][1]['total_s'], r['cases'][2]['total_s']) <= 8 else 'MISS'})")
    print(f"\n# load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
