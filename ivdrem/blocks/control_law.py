"""Disturbance-rejection control law, paper eq. (9)."""
from __future__ import annotations

import numpy as np

from .jacobians import control_law_jacobian
from ._core import BlockSpec, make_block
from . import _validate as checks


def control_law_output(t, x, u, y, K, delta_mu, ntheta):
    # inputs   u.r (n), u.mu[0], u.Pi (Pi^T, n*nθ row-major), u.theta_hat (nθ), u.u_f (n)
    # outputs  y.tau = (K + delta_mu mu) r + Pi^T theta_hat - u_f                  (eq. 9)
    # params   K (n x n, positive definite), delta_mu in (0, 1), ntheta
    n = K.shape[0]
    r = u.r
    Pi = u.Pi.reshape((n, ntheta))
    for i in range(n):
        s = delta_mu * u.mu[0] * r[i] - u.u_f[i]
        for j in range(n):
            s += K[i, j] * r[j]
        for j in range(ntheta):
            s += Pi[i, j] * u.theta_hat[j]
        y.tau[i] = s


def control_law(n, ntheta, K=2.0, delta_mu=0.8, *, name="control_law"):
    """tau = (K + delta_mu mu(t)) r + Pi^T theta_hat - u_f   (eq. 9).

    ======  ==========================================================
    states  none
    inputs  r[n], mu, Pi[n*nθ], theta_hat[nθ], u_f[n]
    output  tau[n]
    params  K (n x n positive definite; scalar or diagonal accepted), delta_mu in (0, 1)
    ======  ==========================================================
    """
    def validate(p):
        p = dict(p)
        p["K"] = checks.square(name, "K", p["K"], n, pd=True)
        p["delta_mu"] = checks.scalar(name, "delta_mu", p["delta_mu"], lo=0.0, hi=1.0)
        return p
    spec = BlockSpec(name=name, inputs=[("r", n), ("mu", 1), ("Pi", n * ntheta),
                                        ("theta_hat", ntheta), ("u_f", n)],
                     outputs=[("tau", n)], states=[], x0=np.zeros(0),
                     param_names=("K", "delta_mu", "ntheta"), output=control_law_output,
                     direct=("r", "mu", "Pi", "theta_hat", "u_f"), validate=validate,
                     named_ports=True, jacobian=control_law_jacobian,
                     constants={"ntheta": ntheta})
    return make_block(spec, {"K": K, "delta_mu": delta_mu})
