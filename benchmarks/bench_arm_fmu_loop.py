#!/usr/bin/env python
"""Each arm's controller FMU closed around its own plant FMU at 1 kHz (FMPy, Jacobi).

For each arm: the controller of its experiment (the configuration's defaults,
``ivdrem.controller.fmu_export.controller_design``; γ given by ``--gamma`` or "auto" from
the calibration cache), the stability prediction of the sampled loop
(``ivdrem.controller.stability``: the growth per step, its margin 1 - growth), the
controller FMU and the arm's plant FMU exported, then ``fmpy_closed_loop`` over ``--t-end``
seconds with the configuration's disturbance, the arm started on the reference (the FMU's
q_d, dq_d).  Printed per arm: the predicted growth, whether the loop diverged, the
estimation error ratio ‖θ̂(t_end) − θ‖ / ‖θ̂(0) − θ‖, the tracking error at the end, and
the wall time per 1 ms step of the whole loop (both FMUs and FMPy) and of the controller's C
step alone (p50 of ``bench_controller.py``'s driver is the figure for the step).

Usage::

    ./run python benchmarks/bench_arm_fmu_loop.py [--arms panda,ur5,iiwa,xarm7] [--t-end 300]
                                                  [--h 0.001] [--gamma 500] [--Gamma 0.001]
                                                  [--mix-every 10]
                                                  [--injection estimate|nominal]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def run_arm(name, t_end, h=1e-3, gamma=None, mix_every=None, every=1000, law="iv-drem",
            Gamma=None, injection=None):
    from ivdrem.controller.fmu_export import (controller_design, export_controller_fmu,
                                              predict, resolve_gamma)
    from ivdrem.controller.fmu_loop import fmpy_closed_loop
    from ivdrem.experiments.config import closed_loop_kwargs, read_config, resolve_config, model_from_config
    from ivdrem.fmu import export_fmu
    config = resolve_config(read_config(None, {"model.name": name,
                                **({} if Gamma is None else {"controller.Gamma": Gamma})}))[0]
    model = model_from_config(config)
    design = controller_design(config, law, h=h)
    if gamma is not None:
        design["gamma"] = float(gamma)
    if mix_every is not None:
        design["mix_every"] = int(mix_every)
    if injection is not None:
        design["injection"] = injection
    design, _ = resolve_gamma(model, law, design, config)
    st = predict(model, law, design, config)
    kw = closed_loop_kwargs(config, law)
    theta = np.asarray(kw["theta"], dtype=float)
    out = dict(arm=name, n=model.n, ntheta=model.ntheta, h=h, growth=st.growth,
               injection=st.injection,
               gamma=design["gamma"], stable=st.stable, reason=st.reason(),
               K=np.round(np.diag(design["K"]), 1).tolist())
    with tempfile.TemporaryDirectory(prefix="ivdrem_arm_loop_") as tmp:
        ctl = export_controller_fmu(model, Path(tmp) / "C.fmu", law=law, **design)
        plant = export_fmu(model, Path(tmp) / "P.fmu")
        t0 = time.perf_counter()
        try:
            rec = fmpy_closed_loop(ctl, plant, t_end, every=every,
                                   disturbance=kw["disturbance"], outputs=("q_d",))
            out["diverged"] = None
        except (ValueError, RuntimeError, Exception) as exc:    # noqa: B014
            out["diverged"] = str(exc).splitlines()[0][:120]
            rec = None
        wall = time.perf_counter() - t0
    out["us_per_step"] = 1e6 * wall / round(t_end / h)
    if rec is not None:
        e0 = np.linalg.norm(rec["theta_hat"][0] - theta)
        out["theta_ratio"] = float(np.linalg.norm(rec["theta_hat"][-1] - theta) / e0)
        out["theta_err_end"] = float(np.linalg.norm(rec["theta_hat"][-1] - theta))
        out["track_end"] = float(np.abs(rec["q"][-1] - rec["q_d"][-1]).max())
        out["record"] = rec
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arms", default="panda,ur5,iiwa,xarm7")
    ap.add_argument("--t-end", type=float, default=300.0, dest="t_end")
    ap.add_argument("--h", type=float, default=1e-3)
    ap.add_argument("--gamma", type=float, default=None,
                    help="gamma of (21) (default: the configuration's, 'auto' calibrated)")
    ap.add_argument("--Gamma", type=float, default=None,
                    help="Γ of (11) (default: the inertia-scaled design's GRADIENT_GAIN, 1e-3, "
                         "with gamma 0.5 / Γ unless --gamma is given)")
    ap.add_argument("--mix-every", type=int, default=None, dest="mix_every",
                    help="the mixing (17) every m samples (default: the controller's)")
    ap.add_argument("--injection", default=None, choices=("estimate", "nominal"),
                    help="the observer's injection of (8) at theta_hat or theta_nominal "
                         "(default: the design's, 'nominal' for 'inertia-scaled')")
    args = ap.parse_args(argv)
    if args.Gamma is None:
        from ivdrem.controller.sampled import GRADIENT_GAIN
        args.Gamma = GRADIENT_GAIN
        args.gamma = 0.5 / GRADIENT_GAIN if args.gamma is None else args.gamma
    print(f"controller FMU + plant FMU in FMPy, h = {args.h * 1e3:g} ms, {args.t_end:g} s "
          f"(1-min load {os.getloadavg()[0]:.2f})", flush=True)
    print(f"{'arm':<7} {'n':>2} {'nθ':>3} {'gamma':>8} {'growth/step':>12} {'margin':>8} "
          f"{'diverged':>9} {'θ̃ ratio':>9} {'‖θ̃‖ end':>9} {'|e| end':>9} {'µs/step':>8}",
          flush=True)
    for arm in args.arms.split(","):
        r = run_arm(arm, args.t_end, h=args.h, gamma=args.gamma, mix_every=args.mix_every,
                    Gamma=args.Gamma, injection=args.injection)
        print(f"        K = {r['K']} 1/s, injection {r['injection']}; {r['reason']}",
              flush=True)
        div = "no" if r["diverged"] is None else "YES"
        ratio = f"{r['theta_ratio']:9.4f}" if "theta_ratio" in r else "        -"
        err = f"{r['theta_err_end']:9.4f}" if "theta_err_end" in r else "        -"
        trk = f"{r['track_end']:9.2e}" if "track_end" in r else "        -"
        print(f"{arm:<7} {r['n']:>2} {r['ntheta']:>3} {r['gamma']:8.3g} {r['growth']:12.6f} "
              f"{1 - r['growth']:8.2e} {div:>9} {ratio} {err} {trk} {r['us_per_step']:8.0f}",
              flush=True)
        if r["diverged"]:
            print(f"        {r['diverged']}", flush=True)


if __name__ == "__main__":
    main()
