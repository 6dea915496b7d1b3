"""What a user waits for: whole ``ivdrem`` processes, side by side, warm caches.

Each row is a child process started the way a user starts it (``python -m ivdrem ...`` or
``python -c ...`` with this interpreter), timed from outside (wall clock, fork to exit).
The rows run alternately, ``--reps`` times (default 3), after one warm-up round that fills
the caches; the median and the fastest are printed, and for ``ivdrem paper`` the
integration time measured inside (``sim_s`` of each law, from ``--json``) beside it.

| row | target (2-core machine, warm caches) |
|---|---|
| ``ivdrem paper`` (300 s, both laws) | <= 2.5 s |
| ``ivdrem paper --method dp45`` | whole-process ratio dp45 / default >= 3x |
| ``ivdrem paper --t-end 1`` | <= 2.0 s |
| ``import ivdrem.diagrams`` against ``import control`` | <= 0.3 s more |
| ``closed_loop`` of a cached planar-6 model (in its process) | <= 1 s |
| peak RSS of ``ivdrem paper --laws iv-drem`` at two horizons | MB per simulated second |
| a study of 8 runs of 30 s: 1 and 2 workers, and one process one run after another | 2 workers <= 0.6x 1 worker; 1 worker <= 1.3x serial |

    ./run python benchmarks/bench_process.py                 # everything (~10 min under load)
    ./run python benchmarks/bench_process.py --skip-study --reps 3
    ./run python benchmarks/bench_process.py --only startup  # the --t-end 1 and import rows

The 1-min load average is printed before and after every row: on a shared machine the
times are upper bounds; compare rows of the same run only.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PY = sys.executable
ROWS = ("paper", "dp45", "startup", "import", "planar6", "memory", "study")

#: a child that runs ivdrem's command line and prints its own peak RSS (KiB, Linux)
_RSS_CHILD = ("import resource, sys; from ivdrem.cli import main; rc = main(sys.argv[1:]); "
              "print('MAXRSS', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "
              "file=sys.stderr); sys.exit(rc)")
#: a child timing closed_loop of a cached model inside its own process (after the imports)
_CLOSED_LOOP_CHILD = """
import sys, time
import ivdrem.sim, ivdrem.diagrams
from ivdrem.experiments.config import closed_loop_kwargs, read_config, resolve_config, model_from_config
t0 = time.perf_counter()
config = resolve_config(read_config(overrides={"model.name": sys.argv[1]}))[0]
model = model_from_config(config)
t1 = time.perf_counter()
from ivdrem.diagrams import closed_loop
closed_loop("composite-learning", model, **closed_loop_kwargs(config, "composite-learning"))
t2 = time.perf_counter()
print("TIMES", t1 - t0, t2 - t1)
"""
_SERIAL_STUDY_CHILD = """
import sys, time
from ivdrem.experiments.config import read_config, resolve_config
from ivdrem.experiments.paper import run_law
t0 = time.perf_counter()
for alpha in [float(a) for a in sys.argv[2].split(",")]:
    config = resolve_config(read_config(overrides={"experiment.t_end": float(sys.argv[1]),
                                    "controller.alpha": alpha}))[0]
    for law in ("iv-drem", "composite-learning"):
        run_law(config, law, progress=False)
print("TIMES", time.perf_counter() - t0)
"""
STUDY_ALPHAS = (1.0, 1.0001, 1.0002, 1.0003)   # 4 points x 2 laws = 8 runs, each the paper's cost


def load() -> str:
    return "load %.2f" % os.getloadavg()[0]


def run(cmd, env=None):
    """(wall seconds, stdout, stderr) of one child process; raises on a failed child."""
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} exited {p.returncode}:\n{p.stderr[-2000:]}")
    return wall, p.stdout, p.stderr


def ivdrem(*args):
    return [PY, "-m", "ivdrem", *args]


def paper_with_stats(extra):
    """Wall and the summed ``sim_s`` of an ``ivdrem paper`` child (read from its output:
    'compile X s + simulation Y s' per law)."""
    wall, stdout, _ = run(ivdrem("paper", "--quiet", *extra))
    sims = [float(line.split("simulation ")[1].split(" s")[0])
            for line in stdout.splitlines() if "simulation " in line and "steps," in line]
    return wall, sum(sims)


def median_row(name, samples, target=None):
    walls = [s[0] for s in samples]
    inside = [s[1] for s in samples if s[1] is not None]
    txt = (f"{name:<44s} median {statistics.median(walls):6.2f} s  fastest {min(walls):6.2f} s"
           f"  (n = {len(walls)})")
    if inside:
        txt += f"  integration inside {statistics.median(inside):.2f} s"
    if target:
        txt += f"  [target {target}]"
    print(txt + f"  {load()}", flush=True)
    return statistics.median(walls)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--only", nargs="+", choices=ROWS, default=None)
    ap.add_argument("--skip-study", action="store_true")
    ap.add_argument("--study-t-end", type=float, default=30.0)
    ap.add_argument("--memory-horizons", type=float, nargs=2, default=(300.0, 1200.0))
    ap.add_argument("--json", default=None, help="write the medians here")
    args = ap.parse_args(argv)
    rows = set(args.only or ROWS) - ({"study"} if args.skip_study else set())
    results = {}
    print(f"bench_process: python {PY}, {load()}, reps {args.reps}", flush=True)

    # ---------------------------------------------------------------- alternating rows
    alternating = {
        "paper": ("ivdrem paper (300 s, both laws)", lambda: paper_with_stats([]), "<= 2.5 s"),
        "dp45": ("ivdrem paper --method dp45", lambda: paper_with_stats(["--method", "dp45"]),
                 None),
        "startup": ("ivdrem paper --t-end 1", lambda: paper_with_stats(["--t-end", "1"]),
                    "<= 2.0 s"),
        "import": None,
    }
    chosen = [r for r in ("paper", "dp45", "startup", "import") if r in rows]
    samples = {r: [] for r in chosen}
    imports = {"import control": [], "import ivdrem.diagrams": []}
    for rep in range(args.reps + 1):          # round 0 warms the caches and is not counted
        for r in chosen:
            if r == "import":
                for what in imports:
                    w, _, _ = run([PY, "-c", what])
                    if rep:
                        imports[what].append((w, None))
                continue
            s = alternating[r][1]()
            if rep:
                samples[r].append(s)
        print(f"  round {rep}{' (warm-up)' if rep == 0 else ''} done, {load()}", file=sys.stderr,
              flush=True)
    for r in chosen:
        if r == "import":
            a = median_row("python -c 'import control'", imports["import control"])
            b = median_row("python -c 'import ivdrem.diagrams'", imports["import ivdrem.diagrams"])
            print(f"{'  import ivdrem.diagrams - import control':<44s} {b - a:+.2f} s  "
                  f"[target <= +0.3 s]", flush=True)
            results["import_control"], results["import_diagrams"] = a, b
            continue
        name, _, target = alternating[r]
        results[r] = median_row(name, samples[r], target)
    if "paper" in results and "dp45" in results:
        ratio = results["dp45"] / results["paper"]
        inside = (statistics.median(s[1] for s in samples["dp45"])
                  / statistics.median(s[1] for s in samples["paper"]))
        print(f"{'  whole-process ratio dp45 / default':<44s} {ratio:.2f}x  (integration "
              f"inside {inside:.2f}x)  [target >= 3x]", flush=True)
        results["dp45_ratio"] = ratio

    # ---------------------------------------------------------------- closed loop, planar-6
    if "planar6" in rows:
        run([PY, "-c", _CLOSED_LOOP_CHILD, "planar-6"])     # fills the caches if empty
        got = []
        for _ in range(args.reps):
            _, out, _ = run([PY, "-c", _CLOSED_LOOP_CHILD, "planar-6"])
            got.append([float(v) for v in out.split("TIMES")[1].split()])
        cfg = statistics.median(g[0] for g in got)
        cl = statistics.median(g[1] for g in got)
        print(f"{'closed_loop of a cached planar-6 model':<44s} median {cl:6.2f} s  "
              f"(configuration resolved + model {cfg:.2f} s)  [target <= 1 s]  {load()}", flush=True)
        results["planar6_closed_loop"], results["planar6_config"] = cl, cfg

    # ---------------------------------------------------------------- memory
    if "memory" in rows:
        rss = []
        for t_end in args.memory_horizons:
            _, _, err = run([PY, "-c", _RSS_CHILD, "paper", "--quiet", "--laws", "iv-drem",
                             "--t-end", f"{t_end:g}", "--allow-long"])
            kib = int(err.split("MAXRSS")[1].split()[0])
            rss.append(kib / 1024)
            print(f"{'peak RSS, paper --laws iv-drem --t-end %g' % t_end:<44s} {kib / 1024:8.1f} MB"
                  f"  {load()}", flush=True)
        (t1, t2), (m1, m2) = args.memory_horizons, rss
        print(f"{'  growth':<44s} {(m2 - m1) / (t2 - t1):.3f} MB per simulated second",
              flush=True)
        results["rss_mb_per_s"] = (m2 - m1) / (t2 - t1)

    # ---------------------------------------------------------------- study
    if "study" in rows:
        with tempfile.TemporaryDirectory() as tmp:
            spec = Path(tmp) / "bench-study.toml"
            spec.write_text(
                f"[experiment]\nt_end = {args.study_t_end:g}\n"
                "laws = [\"iv-drem\", \"composite-learning\"]\n\n[study.grid]\n"
                f"\"controller.alpha\" = [{', '.join(map(repr, STUDY_ALPHAS))}]\n")
            alphas = ",".join(map(repr, STUDY_ALPHAS))
            walls = {"serial": [], 1: [], 2: []}
            for rep in range(args.reps):
                w, out, _ = run([PY, "-c", _SERIAL_STUDY_CHILD, f"{args.study_t_end:g}", alphas])
                walls["serial"].append((w, float(out.split("TIMES")[1].split()[0])))
                for workers in (1, 2):
                    w, _, _ = run(ivdrem("study", str(spec), "--out", str(Path(tmp) / f"s{rep}{workers}"),
                                         "--workers", str(workers), "--quiet", "--no-report"))
                    walls[workers].append((w, None))
            s = median_row("8 runs of %g s, one process, one after another" % args.study_t_end,
                           walls["serial"])
            w1 = median_row("ivdrem study --workers 1", walls[1])
            w2 = median_row("ivdrem study --workers 2", walls[2])
            print(f"{'  2 workers / 1 worker':<44s} {w2 / w1:.2f}  [target <= 0.6]", flush=True)
            print(f"{'  1 worker / serial':<44s} {w1 / s:.2f}  [target <= 1.3]", flush=True)
            results.update(study_serial=s, study_w1=w1, study_w2=w2)
    print(f"bench_process: done, {load()}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
