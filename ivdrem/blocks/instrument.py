"""Instrumental variable, paper eq. (14): zeta^T = l/(s+l) [Phi^T(q_d, dq_d, dq_d, ddq_d)]."""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks


def instrument_update(t, x, u, dx, l):
    # states   x = zeta^T (n*nθ)
    # inputs   u = [q_d, dq_d, ddq_d] (n each)
    # params   l > 0
    n = u.shape[0] // 3
    m = x.shape[0]
    nth = m // n
    A = np.empty((n, nth))
    model.Phi(u[0:n], u[n:2 * n], u[n:2 * n], u[2 * n:3 * n], A)
    for i in range(n):
        for j in range(nth):
            dx[i * nth + j] = l * (A[i, j] - x[i * nth + j])


def instrument_output(t, x, u, y, l):
    # outputs  y = zeta^T (n*nθ, row-major)
    for i in range(x.shape[0]):
        y[i] = x[i]


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
                     output=instrument_output, direct=(), model=model, validate=validate)
    return make_block(spec, {"l": l})
