"""The continuous-time loop with the sampled controller's saturated mu, for comparison.

:func:`saturated_mu_schedule` is the mu block of :func:`ivdrem.diagrams.closed_loop` with
mu(t) = min(mu0 t + mu1, mu_max) (dmu = 0 once saturated), so that ivdrem's continuous
closed loop and the sampled controller (ivdrem.controller.sampled) use the same mu(t)
(docs/controller.md, "Saturating mu").
"""
from __future__ import annotations

import numpy as np

from ..blocks._core import BlockSpec, make_block

__all__ = ["saturated_mu_schedule", "continuous_closed_loop"]


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
    """ivdrem.diagrams.closed_loop with mu saturated at mu_max."""
    from ..diagrams import closed_loop
    return closed_loop(law, model, mu0=mu0, mu1=mu1,
                       replace={"mu_schedule": saturated_mu_schedule(mu0, mu1, mu_max)},
                       **kwargs)
