#!/usr/bin/env python
"""Where a command's peak memory and CPU go, phase by phase (docs/performance.md, "Where a
warm run's memory and time go": the warm Panda run's table).

Runs ``ivdrem paper ...`` (default: ``--config examples/panda.toml --t-end 1 --laws
iv-drem``) in a child process per version, with a sampling thread beside the command: every
10 ms it reads the process's resident memory (``/proc/self/status``, VmRSS) and the main
thread's stack, and charges the sample to the innermost phase on the stack (the functions
listed in ``PHASES``); the main thread's CPU time is read from its clock at each sample.
Sampling changes no result (it only reads); the command's own output is discarded.

Per phase: CPU seconds of the main thread (samples' increments; the kernels a child process
compiles are not in it), the peak resident memory while the phase ran, and how much the
resident memory grew over it (the sum of its samples' increments: a phase that frees
what an earlier one allocated shows a negative growth).  ``--commit REV`` runs the same command in a temporary git
worktree of REV beside this checkout (this checkout's venv), alternating, for a before /
after in one run; ``--reps`` repetitions each.

Usage::

    ./run python benchmarks/bench_memory.py                       # this checkout, warm
    ./run python benchmarks/bench_memory.py --commit main --reps 2
    ./run python benchmarks/bench_memory.py -- --config examples/ur5.toml --t-end 1
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: (file suffix, function name) -> phase, innermost on the stack wins
PHASES = [
    (("experiments/config.py", "read_config"), "configuration"),
    (("experiments/config.py", "resolve_config"), "configuration"),
    (("experiments/config.py", "model_from_config"), "model"),
    (("experiments/experiment.py", "loop"), "the loop (priced, then run)"),
    (("experiments/experiment.py", "check_gamma_auto"), "preflight: γ auto estimate"),
    (("diagrams/gamma_auto.py", "calibrate_gamma"), "γ auto"),
    (("control/nlsys.py", "interconnect"), "python-control interconnect"),
    (("diagrams/closed_loop.py", "assemble"), "wiring by name"),
    (("diagrams/closed_loop.py", "check_connected"), "check_connected"),
    (("sim/plan.py", "check_signal_sizes"), "check_signal_sizes"),
    (("sim/plan.py", "from_diagram"), "plan"),
    (("sim/compiled.py", "__init__"), "engine: kernels, tables"),
    (("sim/compiled.py", "generate_source"), "engine: source and tables"),
    (("sim/jacobian.py", "__init__"), "Jacobian program"),
    (("sim/jacobian.py", "_local_patterns"), "sparsity probe"),
    (("sim/sparse_lu.py", "__init__"), "symbolic LU"),
    (("sim/simulator.py", "advance"), "run (integration, recording)"),
    (("sim/simulator.py", "_response"), "the response"),
    (("experiments/metrics.py", ""), "verdicts and summary"),
]

_CHILD = r"""
import json, os, sys, threading, time
sys.argv = ["ivdrem"] + json.loads(os.environ["BENCH_ARGS"])
PHASES = [tuple(p) for p in json.loads(os.environ["BENCH_PHASES"])]
main_id = threading.get_ident()
clock = time.pthread_getcpuclockid(main_id)
stats = {}          # phase -> [cpu, peak, growth]
stop = threading.Event()

def rss_mib():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return 0.0

def phase_of(frame):
    best = "the rest (imports, reports)"
    names = []
    while frame is not None:
        names.append((frame.f_code.co_filename.replace(os.sep, "/"), frame.f_code.co_name))
        frame = frame.f_back
    for fname, func in reversed(names):        # outermost first: the innermost wins
        for (suffix, name), label in PHASES:
            if fname.endswith(suffix) and (not name or func == name):
                best = label
    return best

def sample():
    last_cpu, last_rss = time.clock_gettime(clock), rss_mib()
    while not stop.wait(0.01):
        frame = sys._current_frames().get(main_id)
        label = phase_of(frame)
        cpu = time.clock_gettime(clock)
        rss = rss_mib()
        s = stats.setdefault(label, [0.0, 0.0, 0.0])
        s[0] += cpu - last_cpu
        s[1] = max(s[1], rss)
        s[2] += rss - last_rss
        last_cpu, last_rss = cpu, rss

th = threading.Thread(target=sample, daemon=True)
th.start()
t0 = time.process_time()
real_stdout = os.fdopen(os.dup(1), "w")
os.dup2(os.open(os.devnull, os.O_WRONLY), 1)      # the command's own output: discarded

def report():
    stop.set(); th.join()
    import resource
    out = dict(cpu=time.process_time() - t0,
               peak=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
               phases=stats)
    real_stdout.write("BENCH_MEMORY " + json.dumps(out) + "\n")
    real_stdout.flush()

import atexit
atexit.register(report)
# the console script itself (its garbage-collector set-up and its exit), as a user runs it
from ivdrem.cli import run
run()
"""


def run_once(tree, args):
    env = dict(os.environ, BENCH_ARGS=json.dumps(args), BENCH_PHASES=json.dumps(PHASES),
               PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", _CHILD], cwd=tree, env=env,
                         capture_output=True, text=True)
    for line in out.stdout.splitlines():
        if line.startswith("BENCH_MEMORY "):
            return json.loads(line[len("BENCH_MEMORY "):])
    raise RuntimeError(f"the command failed in {tree}:\n{out.stderr[-3000:]}")


def table(label, res):
    print(f"\n{label}: CPU {res['cpu']:.1f} s (every thread), "
          f"peak resident {res['peak']:.0f} MiB")
    print("| phase | CPU s | peak resident MiB | resident growth MiB |")
    print("| --- | --- | --- | --- |")
    order = sorted(res["phases"].items(), key=lambda kv: -kv[1][1])
    for name, (cpu, peak, growth) in order:
        print(f"| {name} | {cpu:.2f} | {peak:.0f} | {growth:+.0f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--commit", default=None,
                    help="also run REV (a temporary git worktree), alternating")
    ap.add_argument("--reps", type=int, default=1, help="repetitions of each version")
    ap.add_argument("command", nargs="*", help="ivdrem paper's arguments after --")
    a = ap.parse_args()
    args = ["paper"] + (a.command or ["--config", "examples/panda.toml", "--t-end", "1",
                                       "--laws", "iv-drem"]) + ["--quiet"]
    print(f"load average: {os.getloadavg()}; command: ivdrem {' '.join(args)}")
    trees = [("this checkout", REPO)]
    tmp = None
    if a.commit:
        tmp = Path(tempfile.mkdtemp(prefix="ivdrem-bench-memory-"))
        subprocess.run(["git", "worktree", "add", "--detach", str(tmp / "tree"), a.commit],
                       cwd=REPO, check=True, capture_output=True)
        trees.insert(0, (f"{a.commit}", tmp / "tree"))
    try:
        for rep in range(a.reps):
            for label, tree in trees:
                res = run_once(tree, args)
                table(f"{label} (repetition {rep + 1})", res)
    finally:
        if tmp is not None:
            subprocess.run(["git", "worktree", "remove", "--force", str(tmp / "tree")],
                           cwd=REPO, capture_output=True)
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nload average: {os.getloadavg()}")


if __name__ == "__main__":
    main()
