#!/usr/bin/env python
"""The C library against its Python reference over 10 s, every law with a sampled form, on
the Panda (nθ = 43) and the UR5 (nθ = 36).

Both controllers (``ivdrem.controller.clib.CController`` and
``ivdrem.controller.sampled.SampledController``, the same arguments) take the same measured
motion, sample by sample: the real-arm experiment's reference (docs/experiment.md) plus a
smooth offset, no plant (a plant would feed each controller's own torque back, and the
comparison would measure the plant's sensitivity, not the controller's arithmetic).  The
options are the real arm's (inertia-scaled design, the Fourier reference, γ = 50) with the
window T = 2 s (it wraps four times in 10 s, the scale-free mixings' composite term is on
from t = 2 s), the mixing every 20 samples (the multi-rate schedule: a mixing applied one
period after its sample) and, per law, one of the robot's contract options.  Printed per
(arm, law): the largest relative difference of τ over the steps
(``|τ_py - τ_c| / max(1, |τ_py|)``) and of θ̂ (same, over the steps), Δ at the end, and
the CPU seconds each side took.  Target: 1e-10.  tests/test_controller_arms.py runs one law
per arm of it over 10 s.

    ./run python benchmarks/check_c_equals_python.py [--arms panda,ur5] [--laws ...] [--t-end 10]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

#: per law, the options beside the real arm's defaults (each law exercises one more option)
LAW_OPTIONS = {
    "iv-drem": dict(mixing="eigen", gravity="robot"),
    "drem": dict(mixing="channel", delay=1),
    "composite-learning": dict(tau_rate_max=1000.0, first_zero=True),
    "sigma-modification": dict(gravity="robot", tau_max=80.0),
    "none": dict(delay=1),
}
TARGET = 1e-10


def compare(name, law, *, t_end=10.0, T=2.0, mix_every=20, **extra):
    """Step the C library and the Python reference side by side over t_end seconds;
    returns a dict of the worst relative differences and the times."""
    from ivdrem._threads import one_blas_thread
    from ivdrem.controller.clib import CController
    from ivdrem.controller.sampled import SampledController
    from ivdrem.diagrams import arm_reference as arm
    from ivdrem.models import get_model
    model = get_model(name)
    kw = dict(T=T, gamma=50.0, trajectory=arm.design_trajectory(model), mix_every=mix_every,
              **LAW_OPTIONS[law])
    kw.update(extra)
    py, c = SampledController(model, law, **kw), CController(model, law, **kw)
    worst_tau = worst_th = 0.0
    t_py = t_c = 0.0
    steps = int(round(t_end / py.h))
    with one_blas_thread():         # the reference's SVD of Psi: 20 ms with 2 BLAS threads
        for k in range(steps):
            t = k * py.h
            qd, dqd, _ = py.reference(t)
            q, dq = qd + 0.05 * np.sin(3 * t) + 0.02, dqd + 0.15 * np.cos(3 * t)
            t0 = time.process_time()
            a = py.step(t, q, dq)
            t1 = time.process_time()
            b = c.step(t, q, dq)
            t_c += time.process_time() - t1
            t_py += t1 - t0
            worst_tau = max(worst_tau, np.abs(a - b).max() / max(1.0, np.abs(a).max()))
            th = py.theta_hat
            worst_th = max(worst_th,
                           np.abs(th - c.theta_hat).max() / max(1.0, np.abs(th).max()))
    return dict(arm=name, law=law, steps=steps, tau=worst_tau, theta_hat=worst_th,
                Delta_py=float(py.Delta), Delta_c=float(c.Delta),
                moved=float(np.abs(py.theta_hat - py.theta_hat0).max()), py_s=t_py, c_s=t_c)


def main(argv=None):
    from ivdrem.controller.sampled import SAMPLED_LAWS
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arms", default="panda,ur5")
    ap.add_argument("--laws", default=",".join(SAMPLED_LAWS))
    ap.add_argument("--t-end", type=float, default=10.0, dest="t_end")
    a = ap.parse_args(argv)
    print(f"C library = Python reference over {a.t_end:g} s (load {os.getloadavg()[0]:.1f})")
    print(f"{'arm':<6} {'law':<19} {'steps':>6} {'max rel τ':>10} {'max rel θ̂':>10} "
          f"{'Δ(end)':>10} {'|θ̂-θ̂0|':>9} {'py cpu s':>8} {'C cpu s':>7}  options")
    bad = 0
    for name in a.arms.split(","):
        for law in a.laws.split(","):
            r = compare(name, law, t_end=a.t_end)
            ok = r["tau"] <= TARGET and r["theta_hat"] <= TARGET
            bad += not ok
            print(f"{name:<6} {law:<19} {r['steps']:>6} {r['tau']:10.2e} {r['theta_hat']:10.2e} "
                  f"{r['Delta_c']:10.3g} {r['moved']:9.3g} {r['py_s']:8.1f} {r['c_s']:7.2f}  "
                  f"{LAW_OPTIONS[law]}{'' if ok else '  ABOVE 1e-10'}", flush=True)
    print(f"target {TARGET:g} (relative); {bad} above (load {os.getloadavg()[0]:.1f})")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
