"""Robot plant (paper eq. 1): M(q) q'' + C(q, q') q' + F(q') + G(q) = tau + tau_d."""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks


def plant_update(t, x, u, dx, theta):
    # states   x = [q (n), dq (n)]
    # inputs   u = [tau (n), tau_d (n)]
    # params   theta (nθ): the true parameters
    n = x.shape[0] // 2
    tau = np.empty(n)
    for i in range(n):
        tau[i] = u[i] + u[n + i]
        dx[i] = x[n + i]
    model.forward_dynamics(x[:n], x[n:], tau, theta, dx[n:])


def plant_output(t, x, u, y, theta):
    # outputs  y = [q (n), dq (n)] (positions and velocities are measured)
    for i in range(x.shape[0]):
        y[i] = x[i]


def plant(model, *, theta=None, q0=None, dq0=None, name="plant"):
    """The robot of `model` as a block.

    ======  =================================================================
    states  q[n], dq[n]
    inputs  tau[n] (control torque), tau_d[n] (external torque)
    output  q[n], dq[n]
    params  theta[nθ] (true parameters; default model.theta_values)
    ======  =================================================================
    """
    n, nth = model.n, model.ntheta
    q0 = np.zeros(n) if q0 is None else checks.vector(name, "q0", q0, n)
    dq0 = np.zeros(n) if dq0 is None else checks.vector(name, "dq0", dq0, n)
    theta = model.theta_values if theta is None else theta

    def validate(p):
        p = dict(p)
        p["theta"] = checks.vector(name, "theta", p["theta"], nth)
        return p

    spec = BlockSpec(name=name, inputs=[("tau", n), ("tau_d", n)],
                     outputs=[("q", n), ("dq", n)], states=[("q", n), ("dq", n)],
                     x0=np.concatenate([q0, dq0]), param_names=("theta",),
                     update=plant_update, output=plant_output, direct=(), model=model,
                     validate=validate)
    return make_block(spec, {"theta": theta})
