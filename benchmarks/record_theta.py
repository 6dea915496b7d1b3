#!/usr/bin/env python
"""theta_hat(t_end) of both default laws with every method on the compiled engine, written
as JSON (the reference values a change of the stepper must reproduce to 1e-12 relative).

Usage::

    PYTHONPATH=. python benchmarks/record_theta.py OUT.json [--t-end 300]
    PYTHONPATH=. python benchmarks/record_theta.py NEW.json --compare OLD.json
    PYTHONPATH=. python benchmarks/record_theta.py OUT.json --methods rodas5p
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
try:
    import ivdrem  # noqa: F401
except ImportError:
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from ivdrem.diagrams import closed_loop  # noqa: E402
from ivdrem.sim import METHODS, simulate  # noqa: E402

LAWS = ("iv-drem", "composite-learning")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--compare", default=None)
    ap.add_argument("--methods", default=",".join(METHODS),
                    help="comma-separated methods (default: all)")
    a = ap.parse_args(argv)
    methods = [m for m in a.methods.split(",") if m]
    for m in methods:
        if m not in METHODS:
            ap.error(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    res = {}
    for law in LAWS:
        d = closed_loop(law)
        for m in methods:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = simulate(d, a.t_end, method=m, t_eval=[0.0, a.t_end], progress=False,
                             return_states=False)
            labels = list(r.output_labels)
            rows = [i for i, s in enumerate(labels) if s.startswith("theta_hat")]
            th = np.asarray(r.outputs)[rows, -1]
            res[f"{law}/{m}"] = {"theta_hat": th.tolist(), "steps": int(r.stats["steps"]),
                                 "hold_times": [float(v) for v in r.hold_times]
                                 if r.hold_times is not None else None}
            print(f"{law:20s} {m:8s} steps {r.stats['steps']:8d} sim_s "
                  f"{r.stats['sim_s']:7.2f} theta_hat {th}", flush=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    if a.compare:
        old = json.loads(Path(a.compare).read_text())
        worst = 0.0
        for k, v in res.items():
            if k not in old:
                continue
            o = np.array(old[k]["theta_hat"])
            rel = float(np.max(np.abs(np.array(v["theta_hat"]) - o)) / np.max(np.abs(o)))
            worst = max(worst, rel)
            print(f"{k:30s} relative change {rel:.3e}  steps {old[k]['steps']} -> {v['steps']}")
        print(f"worst relative change {worst:.3e}")


if __name__ == "__main__":
    main()
