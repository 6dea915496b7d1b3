"""Instrumental variable, paper eq. (14): zeta^T = l/(s+l) [Phi^T(q_d, dq_d, dq_d, ddq_d)]."""
from __future__ import annotations

import numpy as np

from ._kernels import stack_empty
from ._core import BlockSpec, make_block
from . import _validate as checks
from .jacobians import instrument_jacobian


def instrument_update(t, x, u, dx, l):
    # states   x.zeta (zeta^T, n*nθ row-major)
    # inputs   u.q_d, u.dq_d, u.ddq_d (n each)
    # params   l > 0
    # dzeta^T = l (Phi^T(q_d, dq_d, dq_d, ddq_d) - zeta^T)                       (14)
    n = u.q_d.shape[0]
    nth = x.zeta.shape[0] // n
    A = stack_empty((n, nth))
    model.Phi(u.q_d, u.dq_d, u.dq_d, u.ddq_d, A)
    for i in range(n):
        for j in range(nth):
            k = i * nth + j
            dx.zeta[k] = l * (A[i, j] - x.zeta[k])


def instrument_output(t, x, u, y, l):
    # outputs  y.zeta = x.zeta (zeta^T, n*nθ row-major)
    for i in range(x.zeta.shape[0]):
        y.zeta[i] = x.zeta[i]


def instrument(model, l=50.0, *, name="instrument"):
    """The instrument zeta: the regressor along the reference trajectory, filtered (14).

    ======  ==========================================================
    states  zeta[n*nθ] (zeta^T row-major, zero at t0)
    inputs  q_d[n], dq_d[n], ddq_d[n]
    output  zeta[n*nθ]
    params  l > 0
    ======  ==========================================================
    """
    n, nth = model.n, model.ntheta

    def validate(p):
        return {**p, "l": checks.scalar(name, "l", p["l"], positive=True)}
    spec = BlockSpec(name=name, inputs=[("q_d", n), ("dq_d", n), ("ddq_d", n)],
                     outputs=[("zeta", n * nth)], states=[("zeta", n * nth)],
                     x0=np.zeros(n * nth), param_names=("l",), update=instrument_update,
                     output=instrument_output, direct=(), model=model, validate=validate,
                     named_ports=True, jacobian=instrument_jacobian)
    return make_block(spec, {"l": l})
