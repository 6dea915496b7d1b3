"""Tracking errors of Section 3.1: e = q_d - q, r = de + alpha e, v = dq_d + alpha e."""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks
from .jacobians import tracking_error_jacobian


def tracking_error_output(t, x, u, y, alpha):
    # inputs   u.q, u.dq, u.q_d, u.dq_d, u.ddq_d (n each)
    # outputs  y.e, y.r, y.v, y.dv (n each): e = q_d - q, r = de + alpha e, v = dq_d + alpha e,
    #          dv = ddq_d + alpha de (no acceleration measured)                  (3)-(4)
    # params   alpha > 0
    for i in range(u.q.shape[0]):
        e = u.q_d[i] - u.q[i]
        de = u.dq_d[i] - u.dq[i]
        y.e[i] = e
        y.r[i] = de + alpha * e
        y.v[i] = u.dq_d[i] + alpha * e
        y.dv[i] = u.ddq_d[i] + alpha * de


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
                     direct=("q", "dq", "q_d", "dq_d", "ddq_d"), validate=validate,
                     named_ports=True, jacobian=tracking_error_jacobian)
    return make_block(spec, {"alpha": alpha})
