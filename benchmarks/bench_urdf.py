#!/usr/bin/env python
"""URDF arms: build time, cache load, kernel compile time and one regressor evaluation.

Per named arm, a fresh child process with empty ivdrem and numba cache directories
(IVDREM_CACHE_DIR, NUMBA_CACHE_DIR) measures

  build        ivdrem.models.arm(name) from an empty cache (Pinocchio's parse, the pivoted
               QR of the stacked regressor, the generated source)          target <= 60 s
  compile      numba compiling every generated function (first call each); the rigid-body
               kernels are compiled once for all arms, so the first arm pays for them
and a second child with the same (now warm) directories measures
  build        arm(name) from the cache                                  target <= 2 s
  load         loading every compiled function from numba's cache
  imports      importing ivdrem.models and ivdrem.sim.compiled (python-control, numba)
  process      the child's whole time: imports, build, load
  Phi          one compiled Phi(q, dq, v, dv) call (median of 20,000)     target <= 20 us (Panda)
  Phi_jac      one compiled Phi_jac call (median of 500)

and for comparison the sympy models' build times (two_link(), planar_arm(3); their source
generated) in a child of their own.

Usage::

    PYTHONPATH=. python benchmarks/bench_urdf.py [--arms panda ur5 ...]
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
import numpy as np
from ivdrem.models import arm
from ivdrem.models.base import FUNCTION_NAMES, REGRESSOR_ARGS
import ivdrem.sim.compiled   # imported by any simulation (python-control, numba): apart
imports = time.perf_counter() - t0
name = sys.argv[1]
t = time.perf_counter()
m = arm(name)
build = time.perf_counter() - t
n, nt = m.n, m.ntheta
rng = np.random.default_rng(0)
vec = {k: rng.uniform(-1, 1, n) for k in ("q", "dq", "v", "dv", "a", "tau")}
th = np.asarray(m.theta_values)
calls = {}
for f in FUNCTION_NAMES:
    base = f[:-4] if f.endswith("_jac") else f
    if base in REGRESSOR_ARGS:
        args = [vec[a] for a in REGRESSOR_ARGS[base]]
        shape = (n, nt, len(args) * n) if f.endswith("_jac") else (n, nt)
    else:
        args = {"M": ["q", th], "C": ["q", "dq", th], "G": ["q", th], "F": ["dq", th],
                "forward_dynamics": ["q", "dq", "tau", th]}[f]
        args = [vec[a] if isinstance(a, str) else a for a in args]
        shape = (n, n) if f in ("M", "C") else (n,)
    calls[f] = (args, np.empty(shape))
t = time.perf_counter()
J = m.jit_functions
for f, (args, out) in calls.items():
    getattr(J, f)(*args, out)
compile_s = time.perf_counter() - t
res = dict(name=name, n=n, ntheta=nt, build=build, compile=compile_s, imports=imports,
           total=time.perf_counter() - t0)
if len(sys.argv) > 2:
    def per_call(f, N):
        args, out = calls[f]
        fn = getattr(J, f)
        ts = []
        for _ in range(5):
            t = time.perf_counter()
            for _ in range(N // 5):
                fn(*args, out)
            ts.append((time.perf_counter() - t) / (N // 5))
        return float(np.median(ts))
    res["Phi_us"] = per_call("Phi", 20000) * 1e6
    res["Phi_jac_us"] = per_call("Phi_jac", 500) * 1e6
    res["forward_dynamics_us"] = per_call("forward_dynamics", 20000) * 1e6
print("RESULT " + json.dumps(res))
'''

_SYMPY = r'''
import json, time
from ivdrem.models import two_link, planar_arm
out = {}
for name, make in (("two-link", two_link), ("planar-3", lambda: planar_arm(3))):
    t = time.perf_counter()
    m = make()
    m.source("")
    out[name] = time.perf_counter() - t
print("RESULT " + json.dumps(out))
'''


def _run(code, args, env):
    p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                       env=env, cwd=REPO, timeout=1800)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"child failed:\n{p.stdout}\n{p.stderr}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arms", nargs="*", default=["panda", "ur5", "iiwa", "xarm7"])
    a = ap.parse_args()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    print(f"{'':<17}|  empty caches      | warm caches")
    print(f"{'arm':<7} {'n':>2} {'ntheta':>6} | {'build s':>7} {'compile s':>9} | "
          f"{'build s':>7} {'load s':>6} {'imports s':>9} {'process s':>9} | {'Phi us':>7} {'Phi_jac us':>10} "
          f"{'fwd dyn us':>10}")
    with tempfile.TemporaryDirectory(prefix="ivdrem_bench_urdf_") as tmp:
        for k, name in enumerate(a.arms):
            # every arm from empty caches; kernels compiled afresh for each
            ivc, nbc = Path(tmp) / f"ivdrem{k}", Path(tmp) / f"numba{k}"
            e = dict(env, IVDREM_CACHE_DIR=str(ivc), NUMBA_CACHE_DIR=str(nbc))
            cold = _run(_CHILD, [name], e)
            warm = _run(_CHILD, [name, "time"], e)
            print(f"{name:<7} {cold['n']:>2} {cold['ntheta']:>6} | {cold['build']:>7.2f} "
                  f"{cold['compile']:>9.1f} | {warm['build']:>7.3f} {warm['compile']:>6.2f} "
                  f"{warm['imports']:>9.2f} {warm['total']:>9.2f} | {warm['Phi_us']:>7.2f} {warm['Phi_jac_us']:>10.1f} "
                  f"{warm['forward_dynamics_us']:>10.2f}")
        sym = _run(_SYMPY, [], env)
    print("targets: build <= 60 s (Panda) from empty caches, <= 2 s from the cache, "
          "Phi <= 20 us (Panda)")
    print("sympy models (build + source): " + ", ".join(f"{k} {v:.2f} s" for k, v in sym.items()))


if __name__ == "__main__":
    main()
