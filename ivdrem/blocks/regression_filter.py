"""Acceleration-free filtered regression, paper eq. (13): z = phi^T theta + w.

Every filter is H(s) = l/(s + l) (erratum E2), so phi^T = l(Phi_M^T(q,dq) - xi) + eta.
"""
from __future__ import annotations

import numpy as np

from ._kernels import stack_empty
from ._core import BlockSpec, make_block
from . import _validate as checks
from .jacobians import regression_filter_jacobian


def regression_filter_update(t, x, u, dx, l, ntheta):
    # states   x.z (n), x.xi (n*nθ), x.eta (n*nθ)   (xi, eta: n x nθ row-major)
    # inputs   u.tau, u.q, u.dq (n each)
    # params   l > 0, ntheta
    n = u.q.shape[0]
    for i in range(n):
        dx.z[i] = l * (u.tau[i] - x.z[i])                 # dz = l (tau - z)
    A = stack_empty((n, ntheta))
    B = stack_empty((n, ntheta))
    C = stack_empty((n, ntheta))
    D = stack_empty((n, ntheta))
    model.Phi_M(u.q, u.dq, A)
    for i in range(n):
        for j in range(ntheta):
            k = i * ntheta + j
            dx.xi[k] = l * (A[i, j] - x.xi[k])            # dxi = l (Phi_M^T(q,dq) - xi)
    # deta = l (-Phi_dM^T(q,dq,dq) + Phi_C^T(q,dq,dq) + Phi_F^T + Phi_G^T - eta)   (13)
    model.Phi_C(u.q, u.dq, u.dq, A)
    model.Phi_dM(u.q, u.dq, u.dq, B)
    model.Phi_F(u.dq, C)
    model.Phi_G(u.q, D)
    for i in range(n):
        for j in range(ntheta):
            k = i * ntheta + j
            dx.eta[k] = l * (A[i, j] - B[i, j] + C[i, j] + D[i, j] - x.eta[k])


def regression_filter_output(t, x, u, y, l, ntheta):
    # outputs  y.z (n), y.phi (phi^T, n*nθ row-major),
    #          phi^T = l (Phi_M^T(q,dq) - xi) + eta                               (13)
    n = u.q.shape[0]
    A = stack_empty((n, ntheta))
    model.Phi_M(u.q, u.dq, A)
    for i in range(n):
        y.z[i] = x.z[i]
        for j in range(ntheta):
            k = i * ntheta + j
            y.phi[k] = l * (A[i, j] - x.xi[k]) + x.eta[k]


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
                     direct=("q", "dq"), model=model, validate=validate, named_ports=True,
                     constants={"ntheta": nth}, jacobian=regression_filter_jacobian)
    return make_block(spec, {"l": l})
