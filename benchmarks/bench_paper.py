#!/usr/bin/env python
"""Benchmarks of the paper experiment against the targets of issue 3 (section 6).

Measured side by side in one run:

* reference and compiled engines: microseconds per right-hand side, in the loop (wall time of a
  short RK4 run / RHS calls, so the per-step work of delays and max-holds is included), and
  also isolated (the RHS function alone, called repeatedly at one state);
  simulated seconds per wall second and the compiled / reference speed-up;
* the full paper experiment (both laws, 300 s, default settings: dp45);
* 1000 s of both laws (default settings);
* compile time (a fresh process with an empty cache directory) and cache-load start-up
  (a second process with the same directory).

Usage::

    cd /work/main && PYTHONPATH=. python benchmarks/bench_paper.py [--quick]
        [--skip-compile] [--json FILE]

Progress goes to stderr, the table to stdout.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
try:                            # PYTHONPATH (or an installed ivdrem) wins; else this checkout
    import ivdrem
except ImportError:
    sys.path.insert(0, str(REPO))
    import ivdrem
PKG_ROOT = Path(ivdrem.__file__).resolve().parents[1]   # what the child processes import

LAWS = ("iv-drem", "composite-learning")

# targets of issue 3, section 6
TARGET_PAPER_S = 3.0        # full paper experiment (both laws, 300 s) <= 3 s
TARGET_SPEEDUP = 300.0      # compiled >= 300x faster than reference per simulated second
TARGET_LONG_S = 20.0        # 1000 s of both laws <= 20 s


def log(msg):
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _git_rev():
    try:
        out = subprocess.run(["git", "-C", str(PKG_ROOT), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, timeout=10)
        rev = out.stdout.strip()
        if out.returncode != 0 or not rev:
            return "unknown"
        dirty = subprocess.run(["git", "-C", str(PKG_ROOT), "status", "--porcelain", "ivdrem"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return rev + ("+dirty(ivdrem)" if dirty else "")
    except Exception:           # pragma: no cover - no git
        return "unknown"


def _environment():
    import numba
    import control
    env = {"python": platform.python_version(), "numpy": np.__version__,
           "numba": numba.__version__, "control": control.__version__,
           "machine": platform.machine(), "cpus": os.cpu_count(), "git": _git_rev(),
           "ivdrem": str(PKG_ROOT)}
    try:
        with open("/proc/cpuinfo") as f:
            env["cpu"] = next(ln.split(":", 1)[1].strip() for ln in f
                              if ln.startswith("model name"))
    except (OSError, StopIteration):
        env["cpu"] = platform.processor() or "unknown"
    return env


def _loadavg():
    try:
        return os.getloadavg()[0]
    except OSError:             # pragma: no cover
        return float("nan")


# --------------------------------------------------------------------------- measurements
def warm_up():
    """Compile (or load from the cache) everything that will be timed."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import simulate
    t0 = time.perf_counter()
    for law in LAWS:
        d = closed_loop(law)
        simulate(d, 0.5, method="dp45", progress=False)
        simulate(d, 0.05, method="rk4", progress=False)
    simulate(closed_loop("iv-drem"), 0.005, method="rk4", engine="reference", progress=False)
    return time.perf_counter() - t0


def _rhs_callable(sim, t, x, dx):
    """A no-argument call of the engine's RHS alone, through whichever entry point exists
    (generated module's diagram_eval(RHS, ...) or rhs(...), reference _rhs, engine.rhs)."""
    from ivdrem.sim import _template as T
    eng, P, W = sim.engine, sim.engine.P, sim.W
    mod = getattr(eng, "module", None)
    if mod is not None and hasattr(mod, "diagram_eval") and hasattr(T, "RHS"):
        f, mode = mod.diagram_eval, T.RHS
        return lambda: f(mode, t, x, P, W, dx)
    if mod is not None and hasattr(mod, "rhs"):
        f = mod.rhs
        return lambda: f(t, x, P, W, dx)
    if hasattr(eng, "_rhs"):
        f = eng._rhs
        return lambda: f(t, x, P, W, dx)
    f = eng.rhs
    return lambda: f(t, x, W)


def rhs_speed(engine, t_sim, h=1e-3, n_iso=None):
    """RK4 run of the iv-drem diagram with one engine; in-loop and isolated us per RHS."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import Simulator
    sim = Simulator(closed_loop("iv-drem"), method="rk4", engine=engine, h=h)
    try:
        sim.advance(t_sim)
        st = sim.stats_dict()
        # isolated RHS at the final state (delay history and max-holds in place)
        dx = np.zeros_like(sim.x)
        x = sim.x.copy()
        t = sim.t
        call = _rhs_callable(sim, t, x, dx)
        n = n_iso or (200_000 if engine == "compiled" else 300)
        call()
        t0 = time.perf_counter()
        for _ in range(n):
            call()
        iso_us = (time.perf_counter() - t0) / n * 1e6
    finally:
        sim.close()
    wall = st["wall_s"]
    return {"engine": engine, "method": "rk4", "h": h, "t_sim": t_sim, "steps": st["steps"],
            "rhs_calls": st["rhs_calls"], "wall_s": wall,
            "us_per_rhs_in_loop": wall / st["rhs_calls"] * 1e6,
            "us_per_rhs_isolated": iso_us, "isolated_calls": n,
            "sim_s_per_wall_s": t_sim / wall}


def run_both_laws(t_end):
    """Both laws with the default settings; end-to-end wall (diagram + simulate) per law."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import simulate
    rows = []
    for law in LAWS:
        log(f"  {law}: {t_end:g} s (dp45, compiled) ...")
        t0 = time.perf_counter()
        d = closed_loop(law)
        r = simulate(d, t_end, progress=False)
        wall = time.perf_counter() - t0
        st = r.stats
        rows.append({"law": law, "t_end": t_end, "wall_s": wall,
                     "integration_wall_s": st["wall_s"], "steps": st["steps"],
                     "rejected": st["rejected"], "rhs_calls": st["rhs_calls"],
                     "last_h": st["h"], "method": st["method"], "engine": st["engine"]})
        log(f"    {wall:.2f} s wall, {st['steps']} steps, {st['rejected']} rejected, "
            f"{st['rhs_calls']} RHS calls")
    return {"t_end": t_end, "laws": rows, "wall_s": sum(r["wall_s"] for r in rows),
            "integration_wall_s": sum(r["integration_wall_s"] for r in rows)}


_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
from ivdrem.diagrams import closed_loop
from ivdrem.sim import simulate
t_import = time.perf_counter() - t0
first = {}
for law in %(laws)r:
    t1 = time.perf_counter()
    simulate(closed_loop(law), %(t_sim)r, progress=False)
    first[law] = time.perf_counter() - t1
total = time.perf_counter() - t0
print("BENCH_JSON " + json.dumps({"import_s": t_import, "first_simulate_s": first,
                                  "import_to_done_s": total}))
"""


def _child(cache, t_sim):
    env = dict(os.environ)
    env["IVDREM_CACHE_DIR"] = cache
    env.pop("NUMBA_CACHE_DIR", None)     # numba caches beside the generated module
    env["PYTHONPATH"] = os.pathsep.join([str(PKG_ROOT)] + [p for p in
                                         env.get("PYTHONPATH", "").split(os.pathsep) if p])
    code = _CHILD % {"laws": LAWS, "t_sim": t_sim}
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       cwd=str(PKG_ROOT))
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"benchmark child failed ({p.returncode}):\n{p.stderr[-3000:]}")
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("BENCH_JSON "))
    res = json.loads(line[len("BENCH_JSON "):])
    res["process_wall_s"] = wall
    return res


def compile_times(t_sim=0.1):
    with tempfile.TemporaryDirectory(prefix="ivdrem-bench-cache-") as cache:
        log("  first process, empty cache (compiles both laws' modules) ...")
        cold = _child(cache, t_sim)
        log(f"    import to done {cold['import_to_done_s']:.1f} s")
        log("  second process, same cache (loads) ...")
        warm = _child(cache, t_sim)
        log(f"    import to done {warm['import_to_done_s']:.1f} s")
    return {"t_sim": t_sim, "cold": cold, "cached": warm}


# --------------------------------------------------------------------------- report
def _check(value, target, kind):
    """kind '<=' or '>='; returns (PASS/MISS, value/target)."""
    ok = value <= target if kind == "<=" else value >= target
    return ("PASS" if ok else "MISS"), value / target


def build_report(res):
    L = []
    env = res["environment"]
    L.append(f"ivdrem benchmark ({'quick' if res['quick'] else 'full'}) - ivdrem from "
             f"{env['ivdrem']}, git {env['git']}, "
             f"python {env['python']}, numba {env['numba']}, control {env['control']}")
    L.append(f"CPU: {env['cpu']} x {env['cpus']}; load average at start {res['load_start']:.2f},"
             f" at end {res['load_end']:.2f}; warm-up {res['warmup_s']:.1f} s")
    L.append("")

    ref, cmp_ = res["rhs"]["reference"], res["rhs"]["compiled"]
    L.append("Right-hand side, iv-drem diagram, RK4 h = 1 ms")
    hdr = f"  {'engine':<10} {'sim s':>7} {'RHS calls':>10} {'wall s':>9} " \
          f"{'us/RHS loop':>12} {'us/RHS alone':>13} {'sim s/wall s':>13}"
    L.append(hdr)
    for r in (ref, cmp_):
        L.append(f"  {r['engine']:<10} {r['t_sim']:>7g} {r['rhs_calls']:>10d} "
                 f"{r['wall_s']:>9.3f} {r['us_per_rhs_in_loop']:>12.2f} "
                 f"{r['us_per_rhs_isolated']:>13.2f} {r['sim_s_per_wall_s']:>13.4g}")
    L.append(f"  speed-up compiled/reference: {res['speedup_per_sim_s']:.0f}x per simulated "
             f"second (isolated RHS: {res['speedup_rhs_isolated']:.0f}x)")
    L.append("")

    for key, title in (("paper", "Paper experiment"), ("long", "Long run")):
        b = res[key]
        L.append(f"{title}: both laws, {b['t_end']:g} s, default settings "
                 f"(dp45, compiled, rtol 1e-6, atol 1e-8)")
        L.append(f"  {'law':<20} {'wall s':>8} {'integr. s':>10} {'steps':>9} "
                 f"{'rejected':>9} {'RHS calls':>10} {'us/RHS':>7}")
        for r in b["laws"]:
            L.append(f"  {r['law']:<20} {r['wall_s']:>8.2f} {r['integration_wall_s']:>10.2f} "
                     f"{r['steps']:>9d} {r['rejected']:>9d} {r['rhs_calls']:>10d} "
                     f"{r['integration_wall_s'] / r['rhs_calls'] * 1e6:>7.2f}")
        L.append(f"  {'both':<20} {b['wall_s']:>8.2f} {b['integration_wall_s']:>10.2f}")
        L.append("")

    if res.get("compile"):
        c = res["compile"]
        L.append(f"Start-up in a new process (both laws, first simulate of {c['t_sim']:g} s each)")
        L.append(f"  {'cache':<14} {'import s':>9} " +
                 " ".join(f"{'1st ' + law + ' s':>24}" for law in LAWS) +
                 f" {'import->done s':>15} {'process s':>10}")
        for name, k in (("cold (compile)", "cold"), ("cached (load)", "cached")):
            r = c[k]
            L.append(f"  {name:<14} {r['import_s']:>9.2f} " +
                     " ".join(f"{r['first_simulate_s'][law]:>24.2f}" for law in LAWS) +
                     f" {r['import_to_done_s']:>15.2f} {r['process_wall_s']:>10.2f}")
        L.append("")
    else:
        L.append("Start-up in a new process: skipped (--skip-compile)")
        L.append("")

    L.append("Targets (issue 3, section 6)")
    L.append(f"  {'target':<52} {'measured':>10} {'target':>8} {'meas/tgt':>9}  result")
    for t in res["targets"]:
        L.append(f"  {t['name']:<52} {t['measured']:>10.3g} {t['kind']}{t['target']:<6g} "
                 f"{t['ratio']:>9.3f}  {t['result']}")
    if res["quick"]:
        L.append("  (--quick: shorter horizons than the targets state; the results are indicative)")
    return "\n".join(L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: 30 s / 100 s instead of 300 s / 1000 s, shorter RHS runs")
    ap.add_argument("--skip-compile", action="store_true",
                    help="skip the cold-cache / cache-load subprocess measurement")
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args(argv)

    t_paper, t_long = (30.0, 100.0) if args.quick else (300.0, 1000.0)
    t_ref, t_cmp = (0.2, 5.0) if args.quick else (1.0, 20.0)

    res = {"quick": args.quick, "load_start": _loadavg()}
    log("importing ivdrem ...")
    res["environment"] = _environment()

    log("warm-up (compile or load the modules of both laws, dp45 and rk4) ...")
    res["warmup_s"] = warm_up()
    log(f"  {res['warmup_s']:.1f} s")

    log(f"RHS speed: reference engine, RK4 {t_ref:g} s ...")
    ref = rhs_speed("reference", t_ref)
    log(f"  {ref['us_per_rhs_in_loop']:.1f} us/RHS in the loop")
    log(f"RHS speed: compiled engine, RK4 {t_cmp:g} s ...")
    cmp_ = rhs_speed("compiled", t_cmp)
    log(f"  {cmp_['us_per_rhs_in_loop']:.2f} us/RHS in the loop")
    res["rhs"] = {"reference": ref, "compiled": cmp_}
    res["speedup_per_sim_s"] = cmp_["sim_s_per_wall_s"] / ref["sim_s_per_wall_s"]
    res["speedup_rhs_isolated"] = ref["us_per_rhs_isolated"] / cmp_["us_per_rhs_isolated"]

    log(f"paper experiment, both laws, {t_paper:g} s ...")
    res["paper"] = run_both_laws(t_paper)
    log(f"long run, both laws, {t_long:g} s ...")
    res["long"] = run_both_laws(t_long)

    if args.skip_compile:
        res["compile"] = None
    else:
        log("compile time and cache load in new processes ...")
        res["compile"] = compile_times()
    res["load_end"] = _loadavg()

    targets = []
    for name, value, target, kind in (
            (f"full paper experiment, both laws {t_paper:g} s, wall s", res["paper"]["wall_s"],
             TARGET_PAPER_S, "<="),
            ("compiled/reference speed-up per simulated s", res["speedup_per_sim_s"],
             TARGET_SPEEDUP, ">="),
            (f"both laws {t_long:g} s, wall s", res["long"]["wall_s"], TARGET_LONG_S, "<=")):
        verdict, ratio = _check(value, target, kind)
        targets.append({"name": name, "measured": value, "target": target, "kind": kind,
                        "ratio": ratio, "result": verdict})
    res["targets"] = targets

    print(build_report(res), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
        log(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
