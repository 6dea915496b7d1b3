"""Acceleration-free filtered regression, paper eq. (13): z = phi^T theta + w.

Every filter is H(s) = l/(s + l) (erratum E2), so phi^T = l(Phi_M^T(q,dq) - xi) + eta.
"""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks


def regression_filter_update(t, x, u, dx, l, ntheta):
    # states   x = [z (n), xi (n*nθ), eta (n*nθ)]
    # inputs   u = [tau, q, dq] (n each)
    # params   l > 0, ntheta
    n = u.shape[0] // 3
    m = n * ntheta
    q = u[n:2 * n]
    dq = u[2 * n:3 * n]
    for i in range(n):
        dx[i] = l * (u[i] - x[i])                         # dz = l (tau - z)
    A = np.empty((n, ntheta))
    B = np.empty((n, ntheta))
    C = np.empty((n, ntheta))
    D = np.empty((n, ntheta))
    model.Phi_M(q, dq, A)
    for i in range(n):
        for j in range(ntheta):
            k = n + i * ntheta + j
            dx[k] = l * (A[i, j] - x[k])                  # dxi = l (Phi_M^T(q,dq) - xi)
    # deta = l (-Phi_dM^T(q,dq,dq) + Phi_C^T(q,dq,dq) + Phi_F^T + Phi_G^T - eta)
    model.Phi_C(q, dq, dq, A)
    model.Phi_dM(q, dq, dq, B)
    model.Phi_F(dq, C)
    model.Phi_G(q, D)
    for i in range(n):
        for j in range(ntheta):
            k = n + m + i * ntheta + j
            dx[k] = l * (A[i, j] - B[i, j] + C[i, j] + D[i, j] - x[k])


def regression_filter_output(t, x, u, y, l, ntheta):
    # outputs  y = [z (n), phi^T (n*nθ)],  phi^T = l (Phi_M^T(q,dq) - xi) + eta
    n = u.shape[0] // 3
    m = n * ntheta
    A = np.empty((n, ntheta))
    model.Phi_M(u[n:2 * n], u[2 * n:3 * n], A)
    for i in range(n):
        y[i] = x[i]
        for j in range(ntheta):
            k = i * ntheta + j
            y[n + k] = l * (A[i, j] - x[n + k]) + x[n + m + k]


def regression_filter(model, l=50.0, *, name="regression_filter"):
    """Filtered regression z = phi^T theta + w of eq. (13), without accelerations.

    ======  ==========================================================
    states  z[n], xi[n*nθ], eta[n*nθ]        (all zero at t0)
    inputs  tau[n], q[n], dq[n]
    output  z[n], phi[n*nθ] (phi^T row-major)
    params  l > 0 (filter l/(s+l))
    ======  ==========================================================
    """
    n, nth = model.n, model.ntheta

    def validate(p):
        return {**p, "l": checks.scalar(name, "l", p["l"], positive=True)}
    spec = BlockSpec(name=name, inputs=[("tau", n), ("q", n), ("dq", n)],
                     outputs=[("z", n), ("phi", n * nth)],
                     states=[("z", n), ("xi", n * nth), ("eta", n * nth)],
                     x0=np.zeros(n + 2 * n * nth), param_names=("l", "ntheta"),
                     update=regression_filter_update, output=regression_filter_output,
                     direct=("q", "dq"), model=model, validate=validate,
                     constants={"ntheta": nth})
    return make_block(spec, {"l": l})
