"""The continuous-time loop with the sampled controller's saturated mu, for comparison.

:func:`saturated_mu_schedule` is the mu block of :func:`ivdrem.diagrams.closed_loop` with
mu(t) = min(mu0 t + mu1, mu_max) (dmu = 0 once saturated), so that ivdrem's continuous
closed loop and the sampled controller (ivdrem.controller.sampled) use the same mu(t)
(docs/controller.md, "Saturating mu").

:func:`sampled_against_continuous` runs the sampled loop at several steps h against the
continuous loop with the same gains (the "inertia-scaled" design of (9) in both,
docs/controller.md "The inertia-scaled design in continuous time"): the differences shrink
like O(h) (tests/test_sampled_vs_continuous.py, benchmarks/bench_sampled_vs_continuous.py).
"""
from __future__ import annotations

import numpy as np

from ..blocks._core import BlockSpec, make_block

__all__ = ["saturated_mu_schedule", "continuous_closed_loop", "sampled_against_continuous"]


def saturated_mu_output(t, x, u, y, mu0, mu1, mu_max):
    # outputs  y.mu[0] = min(mu0 t + mu1, mu_max), y.dmu[0] = mu0 (0 once saturated)
    m = mu0 * t + mu1
    if m >= mu_max:
        y.mu[0] = mu_max
        y.dmu[0] = 0.0
    else:
        y.mu[0] = m
        y.dmu[0] = mu0


def saturated_mu_schedule(mu0=1.0, mu1=15.0, mu_max=135.0, *, name="mu_schedule"):
    """mu(t) = min(mu0 t + mu1, mu_max), its derivative dmu (a drop-in for mu_schedule)."""
    if not (mu0 >= 0 and mu1 > 0 and mu_max >= mu1):
        raise ValueError(f"need mu0 >= 0, mu1 > 0, mu_max >= mu1; got {mu0}, {mu1}, {mu_max}")
    spec = BlockSpec(name=name, inputs=[], outputs=[("mu", 1), ("dmu", 1)], states=[],
                     x0=np.zeros(0), param_names=("mu0", "mu1", "mu_max"),
                     output=saturated_mu_output,
                     named_ports=True,
                     constants={"mu0": float(mu0), "mu1": float(mu1), "mu_max": float(mu_max)})
    return make_block(spec, {})


def continuous_closed_loop(law="iv-drem", model=None, *, mu0=1.0, mu1=15.0, mu_max=135.0,
                           **kwargs):
    """ivdrem.diagrams.closed_loop with mu saturated at mu_max (γ "auto" chosen first,
    ivdrem.diagrams.calibrated_loop)."""
    from ..diagrams import calibrated_loop
    return calibrated_loop(law, model, mu0=mu0, mu1=mu1,
                           replace={"mu_schedule": saturated_mu_schedule(mu0, mu1, mu_max)},
                           **kwargs)


def sampled_against_continuous(model, law="iv-drem", *, hs=(4e-3, 2e-3, 1e-3), t_end=0.5,
                               K, theta_hat0=None, mu_max=135.0, T=None, gamma=None,
                               mixing=None, backend="python", substeps=2, n_out=5,
                               rtol=1e-9, atol=1e-11):
    """The sampled loop at each step h in `hs` against the continuous loop with the same
    gains, both with the inertia-scaled feedback M̂(q)(K + δ_μ μ) r of (9), K in 1/s.

    Both take the real-arm experiment of docs/experiment.md (the Fourier reference, q(0) =
    q_d(0), the designed disturbance) and the same K, μ (saturated at mu_max), observer,
    window T, γ and mixing; the sampled controller
    (:class:`~ivdrem.controller.sampled.SampledController`, or the C library with
    ``backend="c"``) runs around the model's own dynamics (RK4, `substeps` per sample,
    torque and disturbance held; :class:`~ivdrem.controller.loop.ModelPlant`), the
    continuous loop in ivdrem's simulator at tolerances (rtol, atol).

    Returns {"h", "theta", "e", "wall"} (per h: max |θ̂_h − θ̂_c| and max |e_h − e_c| over
    the n_out + 1 output times 0, t_end/n_out, ..., t_end, and the sampled run's seconds) and
    "continuous" (the response), "theta_moved" (max |θ̂_c − θ̂(0)|)."""
    import time
    from ..diagrams import arm_reference as arm
    from ..sim import simulate
    from .clib import CController
    from .loop import ModelPlant, sampled_loop
    from .sampled import SampledController
    traj = arm.design_trajectory(model)
    q0, dq0 = arm.initial_state(traj)
    dist = arm.design_disturbance(model, traj)
    th0 = (np.zeros(model.ntheta) if theta_hat0 is None
           else np.asarray(theta_hat0, dtype=float))
    given = {k: v for k, v in dict(T=T, gamma=gamma, mixing=mixing).items() if v is not None}
    gains = dict(K=np.asarray(K, dtype=float), theta_hat0=th0)
    loop = continuous_closed_loop(law, model, mu_max=mu_max, design="inertia-scaled",
                                  gains=given, **gains)
    dt_out = t_end / n_out
    r = simulate(loop, t_end, rtol=rtol, atol=atol, h_max=min(0.01, dt_out),
                 dt_out=dt_out, progress=False)
    lab = list(r.output_labels)

    def rows(name, k):
        return r.outputs[[lab.index(f"{name}[{j}]") for j in range(k)]].T
    th_c, e_c, qd_c = rows("theta_hat", model.ntheta), rows("e", model.n), rows("q_d", model.n)
    cls = CController if backend == "c" else SampledController
    out = dict(h=[float(h) for h in hs], theta=[], e=[], wall=[], continuous=r,
               theta_moved=float(np.abs(th_c - th0).max()))
    for h in hs:
        every = int(round(dt_out / h))
        if abs(every * h - dt_out) > 1e-9 * dt_out:
            raise ValueError(f"h = {h} must divide t_end / n_out = {dt_out}")
        t0 = time.perf_counter()
        ctl = cls(model, law, h=h, mu_max=mu_max, trajectory=traj, design="inertia-scaled",
                  **gains, **given)
        plant = ModelPlant(model, q0, dq0, substeps=substeps)
        rec = sampled_loop(ctl, plant, t_end, disturbance=dist, every=every)
        out["wall"].append(time.perf_counter() - t0)
        if rec["t"].shape != r.time.shape or np.abs(rec["t"] - r.time).max() > 1e-9:
            raise RuntimeError(f"the sampled loop's times {rec['t']} are not the continuous "
                               f"loop's {r.time}")
        out["theta"].append(float(np.abs(rec["theta_hat"] - th_c).max()))
        # e_h = q_d - q_h with the one reference both loops follow (the continuous loop's
        # q_d output at the same times)
        out["e"].append(float(np.abs((qd_c - rec["q"]) - e_c).max()))
    return out
