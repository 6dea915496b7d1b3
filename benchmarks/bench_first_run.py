#!/usr/bin/env python
"""A new user's first Panda run, before and after, side by side (docs/performance.md, "First
run"), and γ "auto" from the reference estimate against the calibration run.

Rows (``--rows``): ``ivdrem paper --config examples/panda.toml --t-end 1 --laws iv-drem`` as a
new user types it, once with an empty compile cache (``IVDREM_CACHE_DIR`` a new directory:
numba's machine code, the models' code, the C libraries, the calibrations all start empty)
and once again warm; wall seconds and peak resident memory of the whole command
(``/usr/bin/time -v``, children included), for this checkout and for ``--commit`` (default
dca66b6, the code before this change) checked out into a temporary git worktree and run with
this checkout's venv.  The two versions alternate.  A version with the prebuilt machine code
(``python -m ivdrem.cli.prebuild``, which ``./run``'s set-up runs) first makes it afresh for
its own tree in a temporary folder (a row "prebuild": the set-up's extra cost), and its first
run loads it (``IVDREM_PREBUILT_DIR``); a version without runs with none.  ``--compile-table``
does the same (untimed).

``--gamma``: per arm, γ "auto" of IV-DREM from the reference estimate (no loop simulated,
the default for the "eigen" and "channel" mixings) and from the calibration run over [0, 2T]
(the rule before this change, ``calibration={"source": "run"}``), with the seconds each took.

Usage::

    ./run python benchmarks/bench_first_run.py --rows              # first run and warm, before/after
    ./run python benchmarks/bench_first_run.py --rows --stages --commit main   # and where it goes
    ./run python benchmarks/bench_first_run.py --rows --t-end 300  # the 300 s run's memory
    ./run python benchmarks/bench_first_run.py --warm 5 --commit main  # warm runs, alternating
    ./run python benchmarks/bench_first_run.py --warm 3 --stages --commit main  # and their stages
    ./run python benchmarks/bench_first_run.py --compile-table --commit main  # numba, per function

``--compile-table``: where numba's compile time goes on a first run, per function, this
checkout and ``--commit`` one after the other: the command from an empty cache in one
process (``IVDREM_COMPILE_CHILD=0``), numba's ``numba:compile`` events timed (CPU, each
function's own time without the functions compiled inside it, and with them), and each
generated module's import (a kernel wrapper's ``cfunc`` compile, less the functions it made
numba compile).

``--warm N``: the warm run alone, this checkout and ``--commit`` alternating N times each
after one untimed run of each (which fills the cache if it is not yet), both with the
usual compile cache (``$IVDREM_CACHE_DIR`` or its default: what each version keeps there is
keyed by its own sources; numba's machine code of equal kernels is shared); the median and
the range of wall, CPU and peak memory per version.
    ./run python benchmarks/bench_first_run.py --gamma --arms two-link,planar-3,planar-4,planar-5,planar-6,ur5,panda
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
try:
    import ivdrem  # noqa: F401
except ImportError:
    sys.path.insert(0, str(REPO))


def _timed(cmd, cwd, env):
    """(wall s, peak RSS MiB, exit status, output tail, CPU s, stderr) of `cmd` under
    /usr/bin/time -v (CPU: user + system, children included)."""
    t0 = time.perf_counter()
    out = subprocess.run(["/usr/bin/time", "-v", *cmd], cwd=cwd, env=env, capture_output=True,
                         text=True)
    wall = time.perf_counter() - t0
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr)
    rss = int(m.group(1)) / 1024 if m else float("nan")
    cpu = sum(float(x) for x in re.findall(r"(?:User|System) time \(seconds\): ([\d.]+)",
                                           out.stderr))
    return wall, rss, out.returncode, (out.stdout + out.stderr)[-1500:], cpu, out.stderr


#: ``--stages``: the command run under a timer of its set-up stages (the functions below,
#: by module and name, wrapped where the version has them), each printed to stderr as
#: "[stage] name: wall W s, cpu C s" (CPU of the main process; a child compiling wrappers
#: is not in it)
STAGES = [("ivdrem.cli.preflight", "check_runs", "preflight (the loop built and priced)"),
          ("ivdrem.experiments.experiment", "Experiment.loop", "the loop built"),
          ("ivdrem.diagrams.gamma_auto", "reference_mean_delta2", "γ reference estimate"),
          ("ivdrem.sim.plan", "DiagramPlan.from_diagram", "the plan (each simulate)"),
          ("ivdrem.sim.compiled", "kernel_modules", "the kernels' sources"),
          ("ivdrem.sim.compiled", "diagram_tables", "the tables (built, or read)"),
          # this version: the engine reads kept tables before it starts any compile
          ("ivdrem.sim.compiled", "kept_tables", "the tables (built, or read)"),
          ("ivdrem.sim.jacobian", "_local_patterns", "sparsity probe"),
          # this version: the robot-model blocks' wrappers imported (compiled) for the probe
          ("ivdrem.sim.jacobian", "_wrapper_kernels", "the probe's wrappers imported"),
          ("ivdrem.sim.jacobian", "JacobianProgram._build", "Jacobian program build"),
          ("ivdrem.sim.sparse_lu", "_grouped_symbolic_lu", "symbolic LU (orderings, search)"),
          ("ivdrem.sim.compiled", "_load_kernels", "kernels compiled and imported"),
          # this version: the child started before the probe, the rest after the tables
          ("ivdrem.sim.compiled", "KernelCompile.finish", "kernels compiled and imported"),
          ("ivdrem.sim.simulator", "Simulator.advance", "the simulation (C stepper)"),
          ("ivdrem.experiments.diagnostics", "diagnose_run", "diagnostics")]
_STAGE_RUNNER = """
import functools, importlib, sys, time
w, c = time.perf_counter(), time.process_time()
import ivdrem.laws
print(f'[stage] imports (python-control, SciPy, numba, ivdrem): '
      f'wall {time.perf_counter() - w:.2f} s, cpu {time.process_time() - c:.2f} s',
      file=sys.stderr, flush=True)
def wrap(mod, name, label):
    mod = importlib.import_module(mod)
    owner, _, attr = name.rpartition('.')
    owner = getattr(mod, owner, None) if owner else mod
    if owner is None or not hasattr(owner, attr):
        return
    f = getattr(owner, attr)
    @functools.wraps(f)
    def g(*a, **k):
        w, c = time.perf_counter(), time.process_time()
        try:
            return f(*a, **k)
        finally:
            print(f'[stage] {label}: wall {time.perf_counter() - w:.2f} s, '
                  f'cpu {time.process_time() - c:.2f} s', file=sys.stderr, flush=True)
    setattr(owner, attr, g)
for m, n, l in %r:
    wrap(m, n, l)
sys.argv = ['ivdrem'] + sys.argv[1:]
from ivdrem.cli import run
run()
"""


_COMPILE_RUNNER = """
import atexit, collections, json, sys, time
from numba.core import event
stack, mods = [], []
funcs = collections.defaultdict(lambda: [0.0, 0.0, 0])   # name: [own, with callees, count]

class Timer(event.Listener):
    def on_start(self, ev):
        stack.append([time.process_time(), 0.0, ev.data.get('dispatcher')])

    def on_end(self, ev):
        t0, inner, disp = stack.pop()
        dt = time.process_time() - t0
        if stack:
            stack[-1][1] += dt
        elif mods and mods[-1][2] is None:
            mods[-1][1] += dt            # compiled inside a generated module's import
        f = getattr(disp, 'py_func', None)
        name = f'{f.__module__}.{f.__qualname__}' if f is not None else str(disp)
        r = funcs[name]
        r[0] += dt - inner
        r[1] += dt
        r[2] += 1

event.register('numba:compile', Timer())
import ivdrem.compile_cache as cc
import ivdrem.sim.compiled as compiled
plain = cc.import_generated

def timed(cdir, name, src):
    if name in sys.modules:
        return plain(cdir, name, src)
    mods.append([src.splitlines()[0][:150], 0.0, None])
    c = time.process_time()
    try:
        return plain(cdir, name, src)
    finally:
        mods[-1][2] = time.process_time() - c

compiled._import = timed
c0 = time.process_time()

@atexit.register          # the command ends by its exit handlers, without a teardown
def report():
    print('[compile-table] ' + json.dumps(dict(
        cpu=time.process_time() - c0, funcs=funcs,
        modules=[(m[0], m[2] - m[1], m[2]) for m in mods if m[2] is not None])),
        file=sys.stderr, flush=True)

sys.argv = ['ivdrem'] + sys.argv[1:]
from ivdrem.cli import run
run()
"""


def make_prebuilt(tree, label, root):
    """The prebuilt machine code of `tree` (``python -m ivdrem.cli.prebuild``, what ``./run``'s
    set-up runs) made afresh in `root`, timed: its row, or None for a version without it."""
    if not (Path(tree) / "ivdrem" / "cli" / "prebuild.py").exists():
        return None
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
    for k in ("NUMBA_CACHE_DIR", "IVDREM_PREBUILT_DIR", "IVDREM_CACHE_DIR"):
        env.pop(k, None)
    cmd = [sys.executable, "-m", "ivdrem.cli.prebuild", "--dir", str(root), "--force",
           "--quiet"]
    wall, rss, rc, tail, cpu, _ = _timed(cmd, tree, env)
    if rc != 0:
        raise RuntimeError(f"{label}: the prebuild failed (exit {rc}):\n{tail}")
    row = dict(version=label, run="prebuild", wall_s=wall, cpu_s=cpu, peak_MiB=rss, theta=None)
    print(json.dumps(row, ensure_ascii=False), flush=True)
    return row


def _first_run_env(tree, cache, prebuilt):
    """The environment of a first run of `tree`: an empty compile cache `cache`, the
    prebuilt machine code in `prebuilt` (None: none at all), nothing else of the caller's."""
    env = dict(os.environ, IVDREM_CACHE_DIR=str(cache), PYTHONPATH=str(tree),
               OPENBLAS_NUM_THREADS="1", IVDREM_PREBUILT_DIR=str(prebuilt or ""))
    for k in ("NUMBA_CACHE_DIR", "IVDREM_PREBUILD_INTO"):
        env.pop(k, None)
    return env


def compile_table(tree, label, cache, top=25, prebuilt=None):
    """numba's compile time on a first run of the Panda command in `tree` (an empty
    `cache`, one process; the prebuilt machine code in `prebuilt` when given): per function
    and per generated module (see the docstring)."""
    env = dict(_first_run_env(tree, cache, prebuilt), IVDREM_COMPILE_CHILD="0")
    cmd = [sys.executable, "-c", _COMPILE_RUNNER, "paper", "--config", "examples/panda.toml",
           "--t-end", "1", "--laws", "iv-drem", "--quiet"]
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    m = re.search(r"\[compile-table\] (.*)", out.stderr)
    if out.returncode != 0 or not m:
        raise RuntimeError(f"{label}: the run failed (exit {out.returncode}):\n"
                           f"{out.stderr[-1500:]}")
    got = json.loads(m.group(1))
    funcs = got["funcs"]
    own = sum(v[0] for v in funcs.values())
    mods = got["modules"]
    print(f"\n{label}: process CPU {got['cpu']:.1f} s; numba compiling functions (njit, "
          f"overloads) {own:.1f} s; generated modules' imports {sum(m[2] for m in mods):.1f} s, "
          f"of which their own cfunc compiles {sum(m[1] for m in mods):.1f} s "
          f"(load {os.getloadavg()[0]:.1f})")
    print(f"{'own s':>7} {'with callees':>12} {'n':>3}  function")
    for name, (o, w, n) in sorted(funcs.items(), key=lambda kv: -kv[1][0])[:top]:
        print(f"{o:7.2f} {w:12.2f} {n:3d}  {name}")
    print(f"{'own s':>7} {'with callees':>12}      generated module")
    for first, o, w in sorted(mods, key=lambda m: -m[2])[:top]:
        what = re.sub(r"^# Generated by ivdrem \S+: ", "", first)
        print(f"{o:7.2f} {w:12.2f}      {what[:110]}")
    return dict(version=label, **got)


def _stages_of(err):
    """{stage: (wall s, CPU s)} summed from a run's "[stage]" lines."""
    got = {}
    for name, w, c in re.findall(r"\[stage\] (.+?): wall ([\d.]+) s, cpu ([\d.]+) s", err):
        a, b = got.get(name, (0.0, 0.0))
        got[name] = (a + float(w), b + float(c))
    return got


def _stage_table(rows):
    """The stages of `rows` per version: median CPU s (median wall s) of each."""
    labels = list(dict.fromkeys(r["version"] + " " + r["run"] for r in rows))
    print(f"\n{'stage (main process): CPU s (wall s)':<46}" + "".join(f" {l[:24]:>24}"
                                                                   for l in labels))
    names = ["imports (python-control, SciPy, numba, ivdrem)"] + list(
        dict.fromkeys(name for _, _, name in STAGES))
    for name in names:
        cells = []
        for l in labels:
            got = [r["stages"][name] for r in rows
                   if r["version"] + " " + r["run"] == l and name in r.get("stages", {})]
            cells.append("-" if not got else
                         f"{_median([g[1] for g in got]):.2f} ({_median([g[0] for g in got]):.2f})")
        print(f"{name:<46}" + "".join(f" {c:>24}" for c in cells))


def first_run_rows(tree, label, t_end, cache, stages=False, prebuilt=None):
    """The first run (empty cache; the prebuilt machine code in `prebuilt` when given) and
    the warm run of the Panda command in `tree`; with `stages`, each run's set-up stages too
    (STAGES: seconds summed per stage)."""
    env = _first_run_env(tree, cache, prebuilt)
    head = ([sys.executable, "-c", _STAGE_RUNNER % (STAGES,)] if stages
            else [sys.executable, "-m", "ivdrem"])
    cmd = head + ["paper", "--config", "examples/panda.toml", "--t-end", f"{t_end:g}",
                  "--laws", "iv-drem", "--quiet"]
    rows = []
    for kind in ("first", "warm"):
        wall, rss, rc, tail, cpu, err = _timed(cmd, tree, env)
        if rc != 0:
            raise RuntimeError(f"{label} {kind} run failed (exit {rc}):\n{tail}")
        theta = re.search(r"theta_err\|\(t_end\)[^\n]*", tail)
        rows.append(dict(version=label, run=kind, wall_s=wall, cpu_s=cpu, peak_MiB=rss,
                         theta=theta.group(0) if theta else None))
        if stages:
            rows[-1]["stages"] = _stages_of(err)
        print(json.dumps(rows[-1], ensure_ascii=False), flush=True)
    return rows


def warm_rows(trees, t_end, n, stages=False):
    """`n` warm runs of the Panda command per (tree, label) of `trees`, alternating, after one
    untimed run each; every run's row (with `stages`, its stages: STAGES), then per version
    the medians."""
    head = ([sys.executable, "-c", _STAGE_RUNNER % (STAGES,)] if stages
            else [sys.executable, "-m", "ivdrem"])
    cmd = head + ["paper", "--config", "examples/panda.toml", "--t-end", f"{t_end:g}",
                  "--laws", "iv-drem", "--quiet"]
    envs = {label: dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
            for tree, label in trees}
    for tree, label in trees:
        if _timed(cmd, tree, envs[label])[2] != 0:
            raise RuntimeError(f"{label}: the untimed first run failed")
    rows = []
    for _ in range(n):
        for tree, label in trees:
            wall, rss, rc, tail, cpu, err = _timed(cmd, tree, envs[label])
            if rc != 0:
                raise RuntimeError(f"{label} warm run failed (exit {rc}):\n{tail}")
            rows.append(dict(version=label, run="warm", wall_s=wall, cpu_s=cpu, peak_MiB=rss,
                             load=os.getloadavg()[0]))
            if stages:
                rows[-1]["stages"] = _stages_of(err)
            print(json.dumps(rows[-1]), flush=True)
    return rows


def _median(v):
    v = sorted(v)
    return 0.5 * (v[(len(v) - 1) // 2] + v[len(v) // 2])


def gamma_rows(arms):
    """γ "auto" of IV-DREM per arm from the reference estimate and from the calibration run."""
    import numpy as np
    from ivdrem.diagrams.gamma_auto import calibrate_gamma
    import importlib
    cl = importlib.import_module("ivdrem.diagrams.closed_loop")
    from ivdrem import laws
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_arms import _experiment, resolve_model

    rows = []
    for spec in arms:
        arm, _, variant = spec.partition(":")
        model = resolve_model(arm)
        variant = variant or ("eigen" if model.name != "two-link" else "paper")
        exp = {} if model.name == "two-link" else _experiment(model)
        law = laws.get_law("iv-drem")
        args = _calibration_args(cl, law, model, variant, exp)
        row = dict(arm=model.name, ntheta=model.ntheta, mixing=variant)
        for source in ("run", "reference"):
            t0 = time.perf_counter()
            out = calibrate_gamma("iv-drem", model, args, method="rodas5p", source=source)
            row[f"gamma_{source}"] = out["gamma"]
            row[f"s_{source}"] = time.perf_counter() - t0
        g_run = np.atleast_1d(row["gamma_run"])
        g_ref = np.atleast_1d(row["gamma_reference"])
        row["max_rel_diff"] = float(np.max(np.abs(g_ref / g_run - 1.0)))
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def _calibration_args(cl, law, model, variant, exp):
    """The arguments closed_loop hands calibrate_gamma for `model` (its experiment designed
    as closed_loop designs it)."""
    kw = dict(trajectory=exp.get("trajectory"), disturbance=exp.get("disturbance"),
              q0=exp.get("q0"), dq0=exp.get("dq0"), K=None, T=exp.get("T"))
    if model.name != "two-link":
        traj, dist, q0, dq0, K, T = cl._arm_experiment(model, law, None, kw["trajectory"],
                                                       kw["disturbance"], kw["q0"], kw["dq0"],
                                                       None, kw["T"])
        kw.update(trajectory=traj, disturbance=dist, q0=q0, dq0=dq0, K=K, T=T)
    else:
        from ivdrem._default_config import paper_experiment
        paper = paper_experiment()
        kw.update(trajectory=paper["trajectory"], disturbance=paper["disturbance"],
                  q0=paper["q0"], K=2.0)
    return dict(alpha=1.0, K=kw["K"], delta_mu=0.8, Gamma=0.01, mu0=1.0, mu1=15.0,
                observer_variant="corrected", l=50.0, T=kw["T"], p=None, F0=None,
                mixing=variant, epsilon=None, sigma=None, theta_star=None, theta_hat0=None,
                q0=kw["q0"], dq0=kw["dq0"], theta=None, trajectory=kw["trajectory"],
                disturbance=kw["disturbance"], replace=None, external_plant=False)


@contextmanager
def _old_tree(commit, prefix):
    """(a temporary folder, `commit` checked out in a git worktree inside it), both removed
    on leaving: the "before" version each comparison runs beside this checkout."""
    tmp = Path(tempfile.mkdtemp(prefix=prefix))
    before = tmp / "before"
    subprocess.run(["git", "worktree", "add", "--detach", str(before), commit], cwd=REPO,
                   check=True, capture_output=True)
    try:
        yield tmp, before
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(before)], cwd=REPO,
                       capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", action="store_true", help="first run and warm run, before/after")
    ap.add_argument("--commit", default="dca66b6")
    ap.add_argument("--stages", action="store_true",
                    help="with --rows or --warm: time the stages of each run (main process)")
    ap.add_argument("--t-end", type=float, default=1.0)
    ap.add_argument("--warm", type=int, default=0, metavar="N",
                    help="N warm runs of each version, alternating (see the docstring)")
    ap.add_argument("--gamma", action="store_true", help="γ auto: reference estimate vs run")
    ap.add_argument("--compile-table", action="store_true",
                    help="numba's compile time per function on a first run, before/after")
    ap.add_argument("--arms", default="two-link,planar-3,planar-4,planar-5,planar-6,ur5,panda")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    out = {"uptime": os.getloadavg()}
    if a.gamma:
        out["gamma"] = gamma_rows([x for x in a.arms.split(",") if x])
    if a.warm:
        with _old_tree(a.commit, "ivdrem-warm-") as (tmp, before):
            out["warm"] = warm_rows([(before, f"before ({a.commit})"), (REPO, "after")],
                                    a.t_end, a.warm, stages=a.stages)
        print(f"\n{'version':<22} {'runs':>4} {'wall s: median (range)':>24} "
              f"{'CPU s: median':>14} {'peak MiB':>9}")
        for label in dict.fromkeys(r["version"] for r in out["warm"]):
            rs = [r for r in out["warm"] if r["version"] == label]
            w = [r["wall_s"] for r in rs]
            print(f"{label:<22} {len(rs):>4} {_median(w):>10.2f} ({min(w):.2f}-{max(w):.2f})"
                  f"{'':>5} {_median([r['cpu_s'] for r in rs]):>14.2f} "
                  f"{_median([r['peak_MiB'] for r in rs]):>9.0f}")
        if a.stages:
            _stage_table(out["warm"])
    if a.compile_table:
        with _old_tree(a.commit, "ivdrem-compile-table-") as (tmp, before):
            out["compile_table"] = []
            for tree, label in ((before, f"before ({a.commit})"), (REPO, "after")):
                pre = tmp / f"prebuilt-{tree.name}"
                made = make_prebuilt(tree, label, pre)
                out["compile_table"].append(compile_table(
                    tree, label, tmp / f"cache-{tree.name}", prebuilt=pre if made else None))
    if a.rows:
        with _old_tree(a.commit, "ivdrem-first-run-") as (tmp, before):
            rows = []
            for tree, label in ((before, f"before ({a.commit})"), (REPO, "after")):
                # the set-up's prebuilt, made for the tree measured (a version without one
                # runs with none)
                pre = tmp / f"prebuilt-{tree.name}"
                made = make_prebuilt(tree, label, pre)
                rows += [made] if made else []
                rows += first_run_rows(tree, label, a.t_end, tmp / f"cache-{tree.name}",
                                       stages=a.stages, prebuilt=pre if made else None)
            out["rows"] = rows
        print(f"\n{'version':<22} {'run':<8} {'wall s':>8} {'CPU s':>7} {'peak MiB':>9}")
        for r in out["rows"]:
            print(f"{r['version']:<22} {r['run']:<8} {r['wall_s']:>8.1f} {r['cpu_s']:>7.1f} "
                  f"{r['peak_MiB']:>9.0f}")
        if a.stages:
            _stage_table(out["rows"])
    if a.gamma:
        print(f"\n{'arm':<10} {'nθ':>3} {'mixing':<7} {'γ run (today)':>14} {'γ reference':>12} "
              f"{'max rel diff':>12} {'run s':>7} {'ref s':>6}")
        for r in out["gamma"]:
            g = lambda v: f"{v:.4g}" if not isinstance(v, list) else f"{min(v):.3g}..{max(v):.3g}"
            print(f"{r['arm']:<10} {r['ntheta']:>3} {r['mixing']:<7} {g(r['gamma_run']):>14} "
                  f"{g(r['gamma_reference']):>12} {r['max_rel_diff']:>12.2%} "
                  f"{r['s_run']:>7.1f} {r['s_reference']:>6.1f}")
    out["uptime_end"] = os.getloadavg()
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
