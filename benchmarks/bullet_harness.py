#!/usr/bin/env python
"""A URDF arm the project does not name, its controller FMU closed by an outside harness
around an independent physics engine (PyBullet) at 1 kHz.

The harness knows nothing of ivdrem but the FMU: it loads the URDF in PyBullet (inertias as
written, ``URDF_USE_INERTIA_FROM_FILE``; fixed base; the default velocity motors disabled;
joint and link damping 0, as ivdrem's model has no friction unless asked), steps at 1 ms
with torque control (``setJointMotorControlArray(TORQUE_CONTROL)``), and exchanges q, q̇ and
τ with the controller FMU (FMPy, Jacobi: τ read at t_k is held over [t_k, t_k+1], the FMU
has delay 1).  The arm starts on the FMU's reference q_d(0), q̇_d(0).  Printed: the
predicted growth per step, whether the loop diverged, ‖θ̂ − θ‖ against its start (θ: the
URDF's base parameters), the tracking error, the wall time per step.

Usage::

    ./run python benchmarks/bullet_harness.py [--urdf PATH] [--t-end 120] [--gamma 50]
                                              [--mix-every 20]
"""
from __future__ import annotations

import argparse
import os
import sysconfig
import tempfile
import time
from pathlib import Path

import numpy as np

#: example-robot-data's UR3 (not one of ivdrem's named arms)
UR3 = "ur_description/urdf/ur3_robot.urdf"


def default_urdf():
    return (Path(sysconfig.get_paths()["purelib"])
            / "cmeel.prefix/share/example-robot-data/robots" / UR3)


def export(urdf, directory, *, h=1e-3, gamma=None, mix_every=None, law="iv-drem"):
    """The controller FMU of the URDF's default experiment (ivdrem's side of the harness),
    with the inertia-scaled design's Γ (GRADIENT_GAIN) and γ = 0.5/Γ unless given
    (docs/controller.md, "Sampled designs"): (FMU path, the model, the configuration, the
    prediction)."""
    from ivdrem.controller.fmu_export import controller_design, export_controller_fmu, predict
    from ivdrem.controller.sampled import GRADIENT_GAIN
    from ivdrem.experiments.config import read_config
    from ivdrem.experiments.experiment import Experiment
    gamma = 0.5 / GRADIENT_GAIN if gamma is None else gamma
    experiment = Experiment.from_config(read_config(
        None, {"model.urdf": str(urdf), "iv_drem.gamma": float(gamma),
               "controller.Gamma": GRADIENT_GAIN}), laws=[law])
    config, model = experiment.config, experiment.model
    design = controller_design(experiment, law, h=h)
    if mix_every is not None:
        design["mix_every"] = int(mix_every)
    st = predict(model, law, design, experiment)
    if not st.stable:
        raise SystemExit(st.reason())
    path = export_controller_fmu(model, Path(directory) / "Controller.fmu", law=law, **design)
    return path, model, config, st


def bullet_arm(urdf, joint_names, h):
    """PyBullet, direct mode, the arm loaded with its inertias as written: (client, body,
    the joint indices in the model's order)."""
    import pybullet as p
    cid = p.connect(p.DIRECT)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setTimeStep(h, physicsClientId=cid)
    body = p.loadURDF(str(urdf), useFixedBase=True, flags=p.URDF_USE_INERTIA_FROM_FILE,
                      physicsClientId=cid)
    index = {p.getJointInfo(body, j, physicsClientId=cid)[1].decode(): j
             for j in range(p.getNumJoints(body, physicsClientId=cid))}
    joints = [index[name] for name in joint_names]
    for j in range(-1, p.getNumJoints(body, physicsClientId=cid)):
        p.changeDynamics(body, j, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                         physicsClientId=cid)
    # torque control needs the default velocity motors off (zero force)
    p.setJointMotorControlArray(body, joints, p.VELOCITY_CONTROL, forces=[0.0] * len(joints),
                                physicsClientId=cid)
    return cid, body, joints


def run(urdf, t_end, *, h=1e-3, gamma=None, mix_every=None, every=1000):
    import pybullet as p
    from ivdrem.controller.fmu_loop import _Slave
    from ivdrem.experiments.config import closed_loop_kwargs
    from ivdrem.diagrams.arm_reference import joint_names
    from ivdrem.controller.loop import disturbance_at
    with tempfile.TemporaryDirectory(prefix="ivdrem_bullet_") as tmp:
        fmu, model, config, st = export(urdf, tmp, h=h, gamma=gamma, mix_every=mix_every)
        kw = closed_loop_kwargs(config, "iv-drem")
        theta, dist = np.asarray(kw["theta"], float), kw["disturbance"]
        n = model.n
        cid, body, joints = bullet_arm(urdf, joint_names(model), h)
        ctl = _Slave(fmu, "controller", {})
        try:
            nth = sum(1 for k in ctl.vr if k.startswith("theta_hat["))
            vr = {k: ctl.refs([f"{k}[{i}]" for i in range(m)])
                  for k, m in (("q", n), ("dq", n), ("tau", n), ("theta_hat", nth),
                               ("q_d", n), ("dq_d", n))}
            q0, dq0 = np.array(ctl.get(vr["q_d"])), np.array(ctl.get(vr["dq_d"]))
            for j, qi, vi in zip(joints, q0, dq0):
                p.resetJointState(body, j, qi, vi, physicsClientId=cid)
            th0 = np.array(ctl.get(vr["theta_hat"]))
            N = int(round(t_end / h))
            rows, diverged = [], None
            t0 = time.perf_counter()
            for k in range(N + 1):
                t = k * h
                s = p.getJointStates(body, joints, physicsClientId=cid)
                q = np.array([x[0] for x in s])
                dq = np.array([x[1] for x in s])
                if not (np.all(np.isfinite(q)) and np.abs(q).max() < 1e3):
                    diverged = t
                    break
                tau = np.array(ctl.get(vr["tau"]))            # held over [t_k, t_k+1]
                ctl.set(vr["q"] + vr["dq"], [*q, *dq])
                ctl.step(t, h)
                if k % every == 0 or k == N:
                    qd = np.array(ctl.get(vr["q_d"]))          # the reference at t_k
                    rows.append((t, np.abs(q - qd).max(),
                                 np.linalg.norm(np.array(ctl.get(vr["theta_hat"])) - theta)))
                if k == N:
                    break
                p.setJointMotorControlArray(body, joints, p.TORQUE_CONTROL,
                                            forces=list(tau + disturbance_at(t, dist)),
                                            physicsClientId=cid)
                p.stepSimulation(physicsClientId=cid)
            wall = time.perf_counter() - t0
        finally:
            ctl.close()
            p.disconnect(physicsClientId=cid)
    e0 = np.linalg.norm(th0 - theta)
    return dict(model=model.name, n=n, ntheta=model.ntheta, growth=st.growth,
                diverged=diverged, rows=rows, theta_err0=e0,
                ratio=rows[-1][2] / e0 if rows else float("nan"),
                us_per_step=1e6 * wall / max(1, len(rows) and N))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--urdf", default=None, help="URDF file (default: example-robot-data's UR3)")
    ap.add_argument("--t-end", type=float, default=120.0, dest="t_end")
    ap.add_argument("--gamma", type=float, default=None, help="γ of (21) (default 0.5 / Γ)")
    ap.add_argument("--mix-every", type=int, default=None, dest="mix_every")
    args = ap.parse_args(argv)
    urdf = Path(args.urdf) if args.urdf else default_urdf()
    print(f"PyBullet harness, {urdf.name}, h = 1 ms, {args.t_end:g} s (1-min load "
          f"{os.getloadavg()[0]:.2f})", flush=True)
    r = run(urdf, args.t_end, gamma=args.gamma, mix_every=args.mix_every)
    print(f"model {r['model']} (n = {r['n']}, ntheta = {r['ntheta']}): predicted growth "
          f"{r['growth']:.6f} per step; diverged: {r['diverged'] or 'no'}")
    for t, e, th in r["rows"]:
        print(f"  t = {t:7.1f} s  max |q - q_d| = {e:.3e}  ||theta_hat - theta|| = {th:.4f}")
    print(f"||theta~(end)|| / ||theta~(0)|| = {r['ratio']:.4f}; {r['us_per_step']:.0f} us per "
          "step (PyBullet + FMU + Python)")


if __name__ == "__main__":
    main()
