"""Composite adaptation law, paper eq. (11): dtheta_hat = Gamma (Pi r + vartheta_c)."""
from __future__ import annotations

import numpy as np

from .jacobians import adaptation_law_jacobian
from ._core import BlockSpec, make_block
from . import _validate as checks
from ._kernels import as_matrix, matT_vec, stack_empty


def adaptation_law_update(t, x, u, dx, Gamma):
    # states   x.theta_hat (nθ)
    # inputs   u.Pi (Pi^T, n*nθ row-major), u.r (n), u.theta_c (nθ, the composite term)
    # params   Gamma (nθ x nθ, positive definite)
    # dtheta_hat = Gamma (Pi r + vartheta_c)                                     (eq. 11)
    nth = x.theta_hat.shape[0]
    n = u.r.shape[0]
    g = stack_empty(nth)
    matT_vec(as_matrix(u.Pi, n, nth), u.r, g)   # Pi r, Pi = (Pi^T)^T (the paper's "Pi^T r" is a typo)
    for i in range(nth):
        g[i] += u.theta_c[i]
    for i in range(nth):
        s = 0.0
        for j in range(nth):
            s += Gamma[i, j] * g[j]
        dx.theta_hat[i] = s


def adaptation_law_output(t, x, u, y, Gamma):
    # outputs  y.theta_hat = x.theta_hat
    for i in range(x.theta_hat.shape[0]):
        y.theta_hat[i] = x.theta_hat[i]


def adaptation_law(n, ntheta, Gamma=0.01, theta_hat0=None, *, name="adaptation_law"):
    """theta_hat' = Gamma (Pi r + vartheta_c), theta_hat(t0) = theta_hat0   (eq. 11).

    ======  ==========================================================
    states  theta_hat[nθ]
    inputs  Pi[n*nθ], r[n], theta_c[nθ] (the composite term vartheta_c)
    output  theta_hat[nθ]
    params  Gamma (nθ x nθ, symmetric positive definite; scalar or diagonal accepted)
    ======  ==========================================================
    """
    th0 = np.zeros(ntheta) if theta_hat0 is None else checks.vector(name, "theta_hat0",
                                                               theta_hat0, ntheta)

    def validate(p):
        return {**p, "Gamma": checks.square(name, "Gamma", p["Gamma"], ntheta, pd=True)}
    spec = BlockSpec(name=name, inputs=[("Pi", n * ntheta), ("r", n), ("theta_c", ntheta)],
                     outputs=[("theta_hat", ntheta)], states=[("theta_hat", ntheta)], x0=th0,
                     param_names=("Gamma",), update=adaptation_law_update,
                     output=adaptation_law_output, direct=(), validate=validate,
                     named_ports=True, jacobian=adaptation_law_jacobian)
    return make_block(spec, {"Gamma": Gamma})
