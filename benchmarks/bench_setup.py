#!/usr/bin/env python
"""The first simulate of a closed loop in a fresh process, split into its phases, per arm
side by side: import, model load, closed_loop, then inside simulate the block sparsity
probe, the rest of the Jacobian program, the symbolic LU, the tables, loading (or
compiling) the kernel modules, the rest of the engine's construction, and the rest of
simulate (plan and the t_end = 0.01 s run itself).

Usage::

    ./run python benchmarks/bench_setup.py                        # planar-4 and the UR5
    ./run python benchmarks/bench_setup.py --arms planar-4 --repo /path/to/another/tree
    ./run python benchmarks/bench_setup.py --arms two-link,panda --calls 20   # per-call set-up

Each arm runs in a child process (nothing cached in memory: the patterns and symbolic LUs
are cached per process).  The loop is IV-DREM as ``ivdrem paper`` builds it (the arm's
configuration: examples/ur5.toml for the UR5, the defaults with ``model.name`` for the
planar arms) except that γ is a number (``--gamma``): with ``gamma = "auto"`` closed_loop
runs a calibration simulate, which would pay the setup measured here inside closed_loop.
The numba and ivdrem caches are whatever ``$IVDREM_CACHE_DIR`` and numba hold (warm them
with a first run; a cold cache adds the compile to "kernel modules").  ``--repo`` times
another source tree of ivdrem (e.g. ``git archive`` of an older commit) with the same
script, for a before/after in one table.  Timings depend on the load, printed with them.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ARM_CONFIG = {"ur5": "examples/ur5.toml", "panda": "examples/panda.toml"}
PHASES = ["import", "model", "closed_loop", "probe", "jacobian_rest", "symbolic_lu",
          "tables", "kernel_modules", "engine_rest", "simulate_rest", "simulate", "total"]


def child(arm, gamma, repo, calls=0):
    t_start = time.perf_counter()
    sys.path.insert(0, str(repo))
    import ivdrem
    from ivdrem.diagrams import closed_loop
    from ivdrem.experiments.config import (closed_loop_kwargs, read_config, resolve_config,
                                           model_from_config, solver_kwargs)
    from ivdrem.sim import compiled, jacobian, simulate
    import numpy as np
    out = {"import": time.perf_counter() - t_start, "ivdrem": ivdrem.__file__}
    acc = dict.fromkeys(["probe", "jacobian", "symbolic_lu", "tables", "kernel_modules",
                         "engine"], 0.0)

    def timed(key, fn):
        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                acc[key] += time.perf_counter() - t
        return wrapper

    jacobian.cached_block_pattern = timed("probe", jacobian.cached_block_pattern)
    compiled.JacobianProgram = timed("jacobian", compiled.JacobianProgram)
    compiled.symbolic_lu = timed("symbolic_lu", compiled.symbolic_lu)
    compiled.build_tables = timed("tables", compiled.build_tables)
    compiled._load_kernels = timed("kernel_modules", compiled._load_kernels)
    compiled.CompiledEngine.__init__ = timed("engine", compiled.CompiledEngine.__init__)

    path = ARM_CONFIG.get(arm)
    over = {"iv_drem.gamma": gamma}
    if path is None:
        over["model.name"] = arm
    cfg = resolve_config(read_config(None if path is None else repo / path, overrides=over))[0]
    t = time.perf_counter()
    model = model_from_config(cfg)
    out["model"] = time.perf_counter() - t
    t = time.perf_counter()
    loop = closed_loop("iv-drem", model, **closed_loop_kwargs(cfg, "iv-drem"))
    out["closed_loop"] = time.perf_counter() - t
    t = time.perf_counter()
    resp = simulate(loop, 0.01, dt_out=0.01, progress=False, **solver_kwargs(cfg, "iv-drem"))
    out["simulate"] = time.perf_counter() - t
    out["probe"] = acc["probe"]
    out["jacobian_rest"] = acc["jacobian"] - acc["probe"]
    out["symbolic_lu"] = acc["symbolic_lu"]
    out["tables"] = acc["tables"]
    out["kernel_modules"] = acc["kernel_modules"]
    out["engine_rest"] = acc["engine"] - (acc["jacobian"] + acc["symbolic_lu"] + acc["tables"]
                                          + acc["kernel_modules"])
    out["simulate_rest"] = out["simulate"] - acc["engine"]
    out["total"] = time.perf_counter() - t_start
    # the same simulate again, as a study or a benchmark calls it: the per-call set-up
    walls, sets = [], []
    for _ in range(calls):
        t = time.perf_counter()
        again = simulate(loop, 0.01, dt_out=0.01, progress=False, **solver_kwargs(cfg, "iv-drem"))
        walls.append(time.perf_counter() - t)
        sets.append(again.stats["compile_s"])
    out["call_ms"] = 1e3 * float(np.median(walls)) if calls else float("nan")
    out["call_setup_ms"] = 1e3 * float(np.median(sets)) if calls else float("nan")
    out["n_states"] = int(resp.states.shape[0])
    out["steps"] = int(resp.stats["steps"])
    out["load_end"] = round(os.getloadavg()[0], 2)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arms", default="planar-4,ur5")
    ap.add_argument("--gamma", type=float, default=50.7,
                    help="γ of the composite term (a number: no calibration run)")
    ap.add_argument("--repo", default=str(REPO), help="the ivdrem source tree to time")
    ap.add_argument("--calls", type=int, default=0, metavar="N",
                    help="then N more simulate calls of the same loop: median wall and set-up "
                         "(compile_s) per call")
    ap.add_argument("--json", help="write the measurements here")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    repo = Path(a.repo).resolve()
    if not (repo / "ivdrem" / "__init__.py").is_file():
        ap.error(f"--repo {repo}: no ivdrem package there")
    if a.child:
        print(json.dumps(child(a.child, a.gamma, repo, a.calls)))
        return 0
    arms = [s for s in a.arms.split(",") if s]
    print(f"repo {repo}; load average at start {os.getloadavg()[0]:.2f}", flush=True)
    env = dict(os.environ, PYTHONPATH=str(repo))
    results = {}
    for arm in arms:
        r = subprocess.run([sys.executable, __file__, "--child", arm, "--gamma", str(a.gamma),
                            "--repo", str(repo), "--calls", str(a.calls)], env=env,
                           capture_output=True, text=True)
        if r.returncode != 0:
            print(f"{arm}: child failed\n{r.stderr[-3000:]}", file=sys.stderr)
            return 1
        results[arm] = json.loads(r.stdout.strip().splitlines()[-1])
        print(f"  {arm}: {results[arm]['total']:.1f} s", file=sys.stderr, flush=True)
    w = 12
    print(f"{'phase (s)':<16}" + "".join(f"{arm:>{w}}" for arm in arms))
    for p in PHASES:
        print(f"{p:<16}" + "".join(f"{results[arm][p]:>{w}.2f}" for arm in arms))
    rows = ("call_ms", "call_setup_ms") if a.calls else ()
    for p in rows:
        print(f"{p:<16}" + "".join(f"{results[arm][p]:>{w}.2f}" for arm in arms))
    for p in ("n_states", "steps", "load_end"):
        print(f"{p:<16}" + "".join(f"{results[arm][p]:>{w}}" for arm in arms))
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
