#!/usr/bin/env python
"""CPU of a command that refuses bad input: this checkout against an earlier commit, side
by side in one run.

Each refusal (a missing or FIFO --config, a bad option value, an output location that
cannot be written, a missing study file, ...) runs as ``python -X importtime -m ivdrem
...`` in a child process, the two versions alternating; the table gives each one's median
CPU (user + system, of the child), the ratio, and whether python-control was imported
before the refusal.  The commit's tree is exported (``git archive``) into a temporary
directory and put first on PYTHONPATH, the children start there (this checkout's venv:
the same numpy, scipy and python-control)::

    ./run python benchmarks/bench_refusals.py                 # against main, 3 runs each
    ./run python benchmarks/bench_refusals.py --commit HEAD~3 --repeat 5
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def cases(d: Path) -> dict:
    fifo = d / "pipe"
    if not fifo.exists():
        os.mkfifo(fifo)
    plain = d / "plain.toml"
    plain.write_text("[experiment]\nt_end = 1.0\n")
    missing = str(d / "missing.toml")
    return {
        "paper --config missing": ["paper", "--config", missing],
        "paper --config FIFO": ["paper", "--config", str(fifo)],
        "paper --config /dev/zero": ["paper", "--config", "/dev/zero"],
        "paper --json FIFO": ["paper", "--json", str(fifo)],
        "paper --json under a file": ["paper", "--json", str(plain / "x.json")],
        "paper --engine bogus": ["paper", "--engine", "bogus"],
        "paper --method bogus": ["paper", "--method", "bogus"],
        "paper --t-end -1": ["paper", "--t-end", "-1"],
        "report --config missing": ["report", "--config", missing],
        "report --out under a file": ["report", "--out", str(plain / "r")],
        "study missing file": ["study", missing],
        "fmu export --config missing": ["fmu", "export", "--config", missing, "-o",
                                        str(d / "x.fmu")],
    }


def run_once(tree, argv, cwd):
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([sys.executable, "-X", "importtime", "-m", "ivdrem", *argv], env=env,
                       cwd=cwd, capture_output=True, text=True, stdin=subprocess.DEVNULL,
                       timeout=600)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    imported = {ln.rsplit("|", 1)[-1].strip() for ln in p.stderr.splitlines()
                if ln.startswith("import time:")}
    said = [ln for ln in p.stderr.splitlines() if not ln.startswith("import time:")]
    return cpu, "control" in imported, p.returncode, (said[-1] if said else "")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--commit", default="main")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ivdrem-bench-refusals-") as tmp:
        before = Path(tmp) / "before"
        before.mkdir()
        archive = subprocess.run(["git", "archive", a.commit], cwd=REPO, check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(before)], input=archive, check=True)
        work = Path(tmp) / "work"
        work.mkdir()
        print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (1, 5 min)")
        print(f"{'refusal':30s} {'before s':>9s} {'after s':>8s} {'ratio':>6s}  "
              f"python-control before/after, exit before/after")
        for name, args in cases(work).items():
            cpu = {"before": [], "after": []}
            ctl, code = {}, {}
            for i in range(a.repeat):
                order = ("before", "after") if i % 2 == 0 else ("after", "before")
                for which in order:
                    c, imp, rc, _ = run_once(before if which == "before" else None, args, work)
                    cpu[which].append(c)
                    ctl[which], code[which] = imp, rc
            b, af = statistics.median(cpu["before"]), statistics.median(cpu["after"])
            print(f"{name:30s} {b:9.2f} {af:8.2f} {b / af:6.1f}  "
                  f"{'yes' if ctl['before'] else 'no'}/{'yes' if ctl['after'] else 'no'}, "
                  f"{code['before']}/{code['after']}", flush=True)


if __name__ == "__main__":
    main()
