"""Tracking errors of Section 3.1: e = q_d - q, r = de + alpha e, v = dq_d + alpha e."""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks


def tracking_error_output(t, x, u, y, alpha):
    # inputs   u = [q, dq, q_d, dq_d, ddq_d] (n each)
    # outputs  y = [e, r, v, dv] (n each); dv = ddq_d + alpha de (no acceleration measured)
    # params   alpha > 0
    n = u.shape[0] // 5
    for i in range(n):
        e = u[2 * n + i] - u[i]
        de = u[3 * n + i] - u[n + i]
        y[i] = e
        y[n + i] = de + alpha * e
        y[2 * n + i] = u[3 * n + i] + alpha * e
        y[3 * n + i] = u[4 * n + i] + alpha * de


def tracking_error(n, alpha=1.0, *, name="tracking_error"):
    """Errors e, r and the auxiliary v, dv of eqs. (3)-(4).

    ======  ====================================================
    states  none
    inputs  q[n], dq[n], q_d[n], dq_d[n], ddq_d[n]
    output  e[n], r[n], v[n], dv[n]
    params  alpha > 0
    ======  ====================================================
    """
    def validate(p):
        return {**p, "alpha": checks.scalar(name, "alpha", p["alpha"], positive=True)}
    spec = BlockSpec(name=name,
                     inputs=[("q", n), ("dq", n), ("q_d", n), ("dq_d", n), ("ddq_d", n)],
                     outputs=[("e", n), ("r", n), ("v", n), ("dv", n)], states=[],
                     x0=np.zeros(0), param_names=("alpha",), output=tracking_error_output,
                     direct=("q", "dq", "q_d", "dq_d", "ddq_d"), validate=validate)
    return make_block(spec, {"alpha": alpha})
