"""Robot plant (paper eq. 1): M(q) q'' + C(q, q') q' + F(q') + G(q) = tau + tau_d."""
from __future__ import annotations

import numpy as np

from ._kernels import stack_empty
from ._core import BlockSpec, make_block
from . import _validate as checks
from .jacobians import plant_jacobian


def plant_update(t, x, u, dx, theta):
    # states   x.q, x.dq (n each)
    # inputs   u.tau (control torque), u.tau_d (external torque), n each
    # params   theta (nθ): the true parameters
    # dq/dt = dq ;  M(q) ddq = tau + tau_d - C(q, dq) dq - F(dq) - G(q)   (eq. 1)
    n = x.q.shape[0]
    tau = stack_empty(n)
    for i in range(n):
        tau[i] = u.tau[i] + u.tau_d[i]
        dx.q[i] = x.dq[i]
    model.forward_dynamics(x.q, x.dq, tau, theta, dx.dq)


def plant_output(t, x, u, y, theta):
    # outputs  y.q, y.dq (positions and velocities are measured)
    for i in range(x.q.shape[0]):
        y.q[i] = x.q[i]
        y.dq[i] = x.dq[i]


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
                     validate=validate, named_ports=True, jacobian=plant_jacobian)
    return make_block(spec, {"theta": theta})
