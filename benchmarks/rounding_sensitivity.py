#!/usr/bin/env python
"""How far theta_hat(t_end) of the paper's loops moves under changes of one ulp that change
nothing of the method: q(0), a true parameter, the adaptation gain Gamma or the solver's
rtol moved to the next double.  A reproducibility criterion on theta_hat (a change of the
code "within rounding") is only meaningful above this floor.

Usage::

    PYTHONPATH=. python benchmarks/rounding_sensitivity.py [--t-end 300] [--method rodas5p]

Prints, per law and perturbation, the steps and the relative change of theta_hat(t_end)
(max abs / max |theta_hat|) from the unperturbed run.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
try:
    import ivdrem  # noqa: F401
except ImportError:
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from ivdrem.experiments.config import default_config  # noqa: E402
from ivdrem.diagrams import closed_loop  # noqa: E402
from ivdrem.sim import simulate  # noqa: E402


def _up(v):
    return float(np.nextafter(v, np.inf))


def cases():
    """(name, closed_loop keywords, simulate keywords): the unperturbed run first."""
    cfg = default_config()
    q0 = [float(v) for v in cfg["initial"]["q0"]]
    theta = [float(v) for v in cfg["model"]["theta"]]
    gamma = float(cfg["controller"]["Gamma"])
    rtol = float(cfg["solver"]["rtol"])
    k = max(range(len(q0)), key=lambda i: abs(q0[i]))        # a nonzero entry: its ulp
    return [("none", {}, {}),
            (f"q0[{k}] + 1 ulp", {"q0": q0[:k] + [_up(q0[k])] + q0[k + 1:]}, {}),
            (f"q0[{k}] - 1 ulp", {"q0": q0[:k] + [float(np.nextafter(q0[k], -np.inf))]
                                  + q0[k + 1:]}, {}),
            ("theta[0] + 1 ulp", {"theta": [_up(theta[0])] + theta[1:]}, {}),
            ("Gamma + 1 ulp", {"Gamma": _up(gamma)}, {}),
            ("rtol + 1 ulp", {}, {"rtol": _up(rtol)})]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--method", default="rodas5p")
    ap.add_argument("--laws", default="iv-drem,composite-learning")
    a = ap.parse_args(argv)
    for law in [s for s in a.laws.split(",") if s]:
        base = None
        for name, loop, sim in cases():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = simulate(closed_loop(law, **loop), a.t_end, method=a.method,
                             t_eval=[0.0, a.t_end], progress=False, return_states=False,
                             **sim)
            rows = [i for i, s in enumerate(r.output_labels) if s.startswith("theta_hat")]
            th = np.asarray(r.outputs)[rows, -1]
            base = th if base is None else base
            rel = float(np.max(np.abs(th - base)) / np.max(np.abs(base)))
            print(f"{law:20s} {name:18s} steps {r.stats['steps']:7d}  theta_hat relative "
                  f"change {rel:.3e}", flush=True)


if __name__ == "__main__":
    main()
