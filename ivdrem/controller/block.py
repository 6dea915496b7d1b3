"""The sampled controller as a discrete-time block of ivdrem's diagrams.

:func:`controller_block` is a python-control discrete-time system (dt = h) whose update
runs the sampled controller (the generated C library called directly, or the Python
reference); :func:`sampled_closed_loop` closes it around the continuous plant block, with
the paper's disturbance sampled and held as the FMU loops hold it, so that ivdrem's
simulator (sampled blocks, ``ivdrem.sim.sampled``) runs the 1 kHz controller against the
continuous plant (docs/controller.md, "The controller as a block").
"""
from __future__ import annotations

import numpy as np
import control as ct

from ..sim import declare_feedthrough, sampled
from .clib import CController
from .loop import PAPER_DISTURBANCE, default_period, disturbance_at, paper_q0
from .sampled import SampledController

__all__ = ["controller_block", "disturbance_block", "sampled_closed_loop", "auto_gamma"]


#: the controller's arguments that the continuous loop's gain rule (gamma = "auto") reads
_CALIBRATION_ARGS = ("alpha", "K", "delta_mu", "Gamma", "mu0", "mu1", "observer_variant", "l",
                     "T", "p", "F0", "epsilon", "sigma", "theta_star", "theta_hat0",
                     "trajectory")


def auto_gamma(model, law, kwargs, calibration=None):
    """The γ of ``gamma = "auto"`` for the sampled controller: the rule of
    :mod:`ivdrem.diagrams.gamma_auto` (γ = κ / (λ_max(Γ) mean Δ²), Δ measured on ivdrem's
    continuous loop with the same gains over 2T), with the numbers it came from."""
    from ..diagrams.gamma_auto import calibrate_gamma
    if model is None:
        from ..models import two_link
        model = two_link()
    args = {k: v for k, v in kwargs.items() if k in _CALIBRATION_ARGS and v is not None}
    return calibrate_gamma(law, model, args, **(calibration or {}))


def controller_block(model=None, law="iv-drem", *, h=None, backend="c", name="controller",
                     calibration=None, **kwargs):
    """The sampled controller as a discrete-time block (python-control semantics at
    t_k = k h; keyword arguments as :class:`SampledController`).

    ======  ===================================================================
    states  th[nθ]: θ̂(t_k) (the controller's other state, its filters and window, stays
            inside the controller object, ``block.controller``)
    inputs  q[n], dq[n]: the measurements at t_k
    output  tau[n]: τ_k (``delay = 0``, direct feedthrough of q_k, q̇_k) or τ_{k-1}
            (``delay = 1``, no feedthrough); theta_hat[nθ] = θ̂(t_k)
    ======  ===================================================================

    With ``delay = 0`` the controller's step (9)-(11) runs in the output function at t_k
    (τ_k needs q_k); with ``delay = 1`` in the update, and the output holds the previous
    torque.  A run that starts again at t = 0 resets the controller.  ``gamma="auto"``
    chooses γ by :func:`auto_gamma` (``calibration``: its keyword arguments); the choice is
    ``block.gamma_choice``.
    """
    if backend not in ("c", "python"):
        raise ValueError(f"backend must be 'c' (the generated C library) or 'python' (the "
                         f"reference), got {backend!r}")
    choice = None
    if isinstance(kwargs.get("gamma"), str):
        if kwargs["gamma"] != "auto":
            raise ValueError(f"gamma must be a positive number or 'auto', got "
                             f"{kwargs['gamma']!r}")
        choice = auto_gamma(model, law, kwargs, calibration)
        kwargs = {**kwargs, "gamma": choice["gamma"]}
    ctl = (CController if backend == "c" else SampledController)(model, law, h=h, **kwargs)
    n, nth, delay = ctl.n, ctl.ntheta, ctl.delay
    held = {"tau": np.zeros(n), "started": False}

    def begin(t):
        if t == 0.0 and held["started"]:        # a new run of the same block
            ctl.reset()
            held["tau"] = np.zeros(n)
        held["started"] = True

    def update(t, x, u, params):
        # x[k+1] = θ̂(t_{k+1}); delay = 1: the step of t_k runs here, its τ_k is output next
        if delay == 1:
            held["tau"] = ctl.step(t, u[:n], u[n:])
        return np.copy(ctl.theta_hat)

    def output(t, x, u, params):
        begin(t)                                  # the output of t = 0 comes first
        th = np.copy(ctl.theta_hat)               # θ̂(t_k), before the step of t_k
        tau = ctl.step(t, u[:n], u[n:]) if delay == 0 else held["tau"]
        return np.concatenate([tau, th])

    sys = ct.nlsys(update, output, inputs=[f"q[{i}]" for i in range(n)] +
                   [f"dq[{i}]" for i in range(n)],
                   outputs=[f"tau[{i}]" for i in range(n)] +
                   [f"theta_hat[{j}]" for j in range(nth)],
                   states=[f"th[{j}]" for j in range(nth)], dt=ctl.h, name=name)
    declare_feedthrough(sys, ["q", "dq"] if delay == 0 else [])
    sys.controller, sys.gamma_choice = ctl, choice
    return sys


def disturbance_block(n, h, disturbance=PAPER_DISTURBANCE, *, name="disturbance"):
    """The external torque of the experiment, sampled every h and held (as the FMU loops
    hold it): a discrete-time block (dt = h).

    ======  ===================================================================
    states  none
    inputs  none
    output  tau_d[n] = A sin(ω t_k + φ) + offset (``disturbance``'s sinusoids)
    ======  ===================================================================
    """
    return ct.nlsys(None, lambda t, x, u, params: disturbance_at(t, disturbance), inputs=[],
                    outputs=[f"tau_d[{i}]" for i in range(n)], dt=h, name=name)


def sampled_closed_loop(model=None, law="iv-drem", *, h=None, q0=None, dq0=None,
                        disturbance=PAPER_DISTURBANCE, backend="c", **kwargs):
    """The continuous plant (``ivdrem.blocks.plant``) with the sampled controller and the
    sampled disturbance: a mixed diagram for ``ivdrem.sim.simulate`` (outputs q, dq, tau,
    theta_hat).  ``h``: the controller's period (default :func:`~ivdrem.controller.loop.
    default_period`); ``q0``: the plant's q(0) (default the paper's,
    :func:`~ivdrem.controller.loop.paper_q0`).  Returns (diagram, controller block)."""
    from ..blocks.plant import plant
    h = default_period() if h is None else h
    q0 = paper_q0() if q0 is None else q0
    if model is None:
        from ..models import two_link
        model = two_link()
    ctl = controller_block(model, law, h=h, backend=backend, **kwargs)
    n, nth = model.n, model.ntheta
    p = plant(model, q0=q0, dq0=dq0)
    dist = disturbance_block(n, h, disturbance)
    d = ct.interconnect([p, sampled(ctl), sampled(dist)], inputs=[],
                        outputs=[f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]
                        + [f"tau[{i}]" for i in range(n)]
                        + [f"theta_hat[{j}]" for j in range(nth)], name="sampled_loop")
    # the block's state starts at the controller's θ̂(0)
    d.ivdrem_start = {ctl.name: {f"th[{j}]": float(v)
                                 for j, v in enumerate(ctl.controller.theta_hat)}}
    return d, ctl
