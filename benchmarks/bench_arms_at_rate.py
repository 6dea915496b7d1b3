"""The sampled controller (C library) at the robot's rate around each arm's own dynamics.

The real-arm experiment of docs/experiment.md (Fourier reference, q(0) = q_d(0), the
designed disturbance, window T) with IV-DREM, "eigen" mixing every ``--mix-every`` samples,
the "inertia-scaled" design (K_i = design_gains_i / M_ii(q0), floored and capped for the
delay: ivdrem.controller.sampled.inertia_scaled_gains), closed around the model's forward
dynamics (RK4, ``--substeps`` per sample, 1 by default as the plant FMU at 1 ms; torque and
disturbance held; ivdrem.controller.loop.ModelPlant), the torque applied ``--delay``
samples late (1 by default, as around the controller FMU).  Prints per arm: ‖θ̃(0)‖ → ‖θ̃(t_end)‖ and their ratio,
the largest tracking error over the last 10 s, the largest torque, the wall time.

    OPENBLAS_NUM_THREADS=1 nice -n 10 ./run python benchmarks/bench_arms_at_rate.py --t-end 300
    ./run python benchmarks/bench_arms_at_rate.py --arms ur5 --h 2e-3 --t-end 300
    ./run python benchmarks/bench_arms_at_rate.py --arms panda --design paper --t-end 0.2
"""
from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402


def run(name, *, h, t_end, design, gamma, mix_every, law="iv-drem", backend="c", mu_max=135.0,
        K=None, delay=1, substeps=1, Gamma=0.01, injection=None):
    from ivdrem.controller.clib import CController
    from ivdrem.controller.loop import ModelPlant, sampled_loop
    from ivdrem.controller.sampled import SampledController, inertia_scaled_gains
    from ivdrem.diagrams import arm_reference as arm
    from ivdrem.models import get_model
    m = get_model(name)
    traj = arm.design_trajectory(m)
    q0, dq0 = arm.initial_state(traj)
    dist = arm.design_disturbance(m, traj)
    T = arm.design_window(traj, dist) or 20.0
    if K is not None:                       # the same K (1/s or N m s) on every joint
        K = np.full(m.n, float(K))
    else:
        K = np.array(arm.design_gains(m, q0))
        if design == "inertia-scaled":
            K = inertia_scaled_gains(m, K, q0, h, mu_max=mu_max, delay=delay)
    cls = CController if backend == "c" else SampledController
    ctl = cls(m, law, h=h, K=K, T=T, trajectory=traj, design=design, gamma=gamma,
              mixing="eigen", mix_every=mix_every, mu_max=mu_max, delay=delay, Gamma=Gamma,
              injection=injection)
    plant = ModelPlant(m, q0, dq0, substeps=substeps)
    th = np.asarray(m.theta_values)
    t0 = time.perf_counter()
    try:
        rec = sampled_loop(ctl, plant, t_end, disturbance=dist, every=int(round(0.1 / h)))
    except (FloatingPointError, ValueError, RuntimeError) as exc:
        return dict(arm=name, h=h, design=design, injection=injection,
                    diverged=f"{type(exc).__name__}: {exc}"[:300],
                    wall=time.perf_counter() - t0)
    wall = time.perf_counter() - t0
    ref = SampledController(m, "none", trajectory=traj, h=h)
    t = rec["t"]
    qd = np.array([ref.reference(tk)[0] for tk in t])
    last = t >= t[-1] - 10.0
    e0, e1 = np.linalg.norm(th - rec["theta_hat"][0]), np.linalg.norm(th - rec["theta_hat"][-1])
    return dict(arm=name, h=h, delay=delay, design=design, injection=ctl.injection,
                K=np.round(K, 1).tolist(), T=T,
                theta0=e0, theta_end=e1, ratio=e1 / e0,
                e_last=float(np.abs(rec["q"][last] - qd[last]).max()),
                tau_max=float(np.abs(rec["tau"]).max()), wall=wall,
                window_MiB=getattr(ctl, "window_bytes", 0) / 2 ** 20)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arms", default="panda,ur5,iiwa,xarm7")
    ap.add_argument("--h", type=float, default=1e-3)
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--design", default="inertia-scaled")
    ap.add_argument("--gamma", type=float, default=None,
                    help="gamma of (21); default 0.5 / Gamma: 'eigen' keeps Delta near 1, so "
                         "that is what gamma 'auto' (0.5 / (lambda_max(Gamma) mean Delta^2)) "
                         "gives")
    ap.add_argument("--mix-every", type=int, default=10)
    ap.add_argument("--mu-max", type=float, default=135.0)
    ap.add_argument("--K", type=float, default=None,
                    help="one K for every joint (default: inertia_scaled_gains of design_gains)")
    ap.add_argument("--backend", default="c", choices=("c", "python"))
    ap.add_argument("--delay", type=int, default=1, choices=(0, 1),
                    help="samples between the measurement and the torque (controller FMU: 1)")
    ap.add_argument("--substeps", type=int, default=1,
                    help="RK4 sub-steps of the plant per sample (plant FMU at 1 ms: 1)")
    ap.add_argument("--Gamma", type=float, default=None,
                    help="Γ of (11) (scalar; default the design's GRADIENT_GAIN, 1e-3)")
    ap.add_argument("--injection", default=None, choices=("estimate", "nominal"),
                    help="the observer's injection of (8) at theta_hat or theta_nominal "
                         "(default: the design's, 'nominal' for 'inertia-scaled')")
    a = ap.parse_args(argv)
    from ivdrem.controller.sampled import GRADIENT_GAIN
    a.Gamma = GRADIENT_GAIN if a.Gamma is None else a.Gamma
    a.gamma = 0.5 / a.Gamma if a.gamma is None else a.gamma
    print(f"load {os.getloadavg()}", flush=True)
    for name in a.arms.split(","):
        r = run(name, h=a.h, t_end=a.t_end, design=a.design, gamma=a.gamma,
                mix_every=a.mix_every, backend=a.backend, mu_max=a.mu_max, K=a.K,
                delay=a.delay, substeps=a.substeps, Gamma=a.Gamma, injection=a.injection)
        print(r, flush=True)
    print(f"load {os.getloadavg()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
