#!/usr/bin/env python
"""This checkout against an earlier commit, side by side in one run: the paper's loops (and
optionally planar arms) simulated by each version's own package.

The commit is checked out into a temporary git worktree (removed at the end); each run is a
child process started with that tree as its working directory and first on PYTHONPATH, so
it imports that version of ivdrem (this checkout's venv, the same numba, scipy and
python-control).  The two versions alternate (which goes first alternates between
repetitions), best of ``--reps``.

* paper's loops (``--laws``): each child builds ``closed_loop(law)``, simulates 1 s (warm:
  kernels loaded from the compile caches) and then times ``simulate(d, t_end)`` as a user
  calls it (Rodas5P defaults, outputs every 10 ms, states recorded): wall and CPU seconds
  of the whole call, steps, theta_hat(t_end);
* arms (``--arms planar-3:paper,planar-4:eigen``): ``benchmarks/bench_arms.py --one`` of each
  tree (gamma "auto", its sim_s: integration only).

Usage::

    ./run python benchmarks/bench_before.py                         # against 5d4339a
    ./run python benchmarks/bench_before.py --commit main --laws iv-drem --reps 5
    ./run python benchmarks/bench_before.py --commit main --laws "" \\
        --arms planar-3:paper,planar-3:eigen,planar-4:paper --t-end-arms 60
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time, warnings
import numpy as np
from ivdrem.diagrams import closed_loop
from ivdrem.sim import simulate
law, t_end = sys.argv[1], float(sys.argv[2])
d = closed_loop(law)
simulate(d, 1.0, progress=False)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    w0, c0 = time.perf_counter(), time.process_time()
    r = simulate(d, t_end, progress=False)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
rows = [i for i, s in enumerate(r.output_labels) if s.startswith("theta_hat")]
print(json.dumps(dict(wall=wall, cpu=cpu, sim_s=float(r.stats["sim_s"]),
                      steps=int(r.stats["steps"]),
                      theta_hat=np.asarray(r.outputs)[rows, -1].tolist())))
"""


def _run(tree, args, timeout=3600):
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, *args], cwd=tree, env=env, capture_output=True,
                         text=True, timeout=timeout)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"child in {tree} failed: {out.stderr.strip()[-2000:]}")
    return json.loads(lines[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--commit", default="5d4339a")
    ap.add_argument("--laws", default="iv-drem,composite-learning")
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--arms", default="", help="arm:variant,... (bench_arms.py --one)")
    ap.add_argument("--t-end-arms", type=float, default=60.0)
    ap.add_argument("--reps", type=int, default=3)
    a = ap.parse_args(argv)
    laws = [x for x in a.laws.split(",") if x]
    arms = [tuple(x.split(":")) for x in a.arms.split(",") if x]
    rev = subprocess.run(["git", "rev-parse", "--short", a.commit], cwd=REPO, text=True,
                         capture_output=True, check=True).stdout.strip()
    here = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, text=True,
                          capture_output=True, check=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                           text=True, capture_output=True).stdout.strip()
    print(f"# bench_before: this checkout ({here}{' + changes' if dirty else ''}) against "
          f"{rev}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, best of {a.reps}, "
          f"alternating", flush=True)
    tmp = Path(tempfile.mkdtemp(prefix="ivdrem-before-"))
    old = tmp / "tree"
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(old), rev], cwd=REPO,
                   check=True)
    trees = {"before": old, "now": REPO}
    best = {}
    try:
        for rep in range(a.reps):
            # the order within a rep alternates too (a load that drifts favours neither)
            order = list(trees.items()) if rep % 2 == 0 else list(trees.items())[::-1]
            for law in laws:
                for name, tree in order:
                    r = _run(tree, ["-c", CHILD, law, str(a.t_end)])
                    k = (law, name)
                    b = best.get(k)
                    if b is None or r["wall"] < b["wall"]:
                        r["cpu_best"] = min(r["cpu"], b["cpu_best"]) if b else r["cpu"]
                        best[k] = r
                    else:
                        b["cpu_best"] = min(b["cpu_best"], r["cpu"])
                    print(f"  rep {rep + 1} {law:20s} {name:6s} wall {r['wall']:7.3f} s  cpu "
                          f"{r['cpu']:7.3f} s  steps {r['steps']}", flush=True)
            for arm, variant in arms:
                for name, tree in order:
                    r = _run(tree, ["benchmarks/bench_arms.py", "--one", arm, variant,
                                    str(a.t_end_arms)])
                    k = (f"{arm} {variant}", name)
                    if k not in best or r["sim_s"] < best[k]["sim_s"]:
                        best[k] = r
                    print(f"  rep {rep + 1} {arm} {variant:8s} {name:6s} sim_s "
                          f"{r['sim_s']:7.3f}  steps {r['steps']}", flush=True)
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=REPO)
        try:
            tmp.rmdir()
        except OSError:
            pass
    print(f"\n  {'loop':26s} {'before s':>9s} {'now s':>9s} {'before/now':>11s} "
          f"{'cpu before':>11s} {'cpu now':>9s} {'steps':>13s} {'theta_hat rel. change':>22s}")
    for law in laws:
        b, n = best[(law, "before")], best[(law, "now")]
        tb, tn = (b["theta_hat"], n["theta_hat"])
        rel = max(abs(x - y) for x, y in zip(tb, tn)) / max(abs(x) for x in tb)
        print(f"  {law + ' %gs' % a.t_end:26s} {b['wall']:9.3f} {n['wall']:9.3f} "
              f"{b['wall'] / n['wall']:11.2f} {b['cpu_best']:11.3f} {n['cpu_best']:9.3f} "
              f"{'%d/%d' % (b['steps'], n['steps']):>13s} {rel:22.2e}")
    for arm, variant in arms:
        k = f"{arm} {variant}"
        b, n = best[(k, "before")], best[(k, "now")]
        print(f"  {k + ' %gs sim_s' % a.t_end_arms:26s} {b['sim_s']:9.3f} {n['sim_s']:9.3f} "
              f"{b['sim_s'] / n['sim_s']:11.2f} {'':11s} {'':9s} "
              f"{'%d/%d' % (b['steps'], n['steps']):>13s} "
              f"{abs(b['err_end'] - n['err_end']) / b['err_end']:22.2e}")
    print(f"# load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
