"""High-gain external torque observer, paper eq. (7), with the regressor Pi of eq. (8).

States are stored in the n x nθ orientation (Phi_f^T, Phi_Mf^T), row-major.
"""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from ._core import ParameterError

_VARIANTS = {"corrected": 1.0, "literal": 0.0}


def torque_observer_update(t, x, u, dx, n, ntheta, literal_e1):
    # states   x = [Phi_f^T (n*nθ), Phi_Mf^T (n*nθ), u_f (n)]
    # inputs   u = [q, dq, r, v, dv (n each), mu, dmu, tau (n), theta_hat (nθ)]
    # params   n, ntheta, literal_e1 (0: erratum E1 gain mu + dmu/mu; 1: the paper's mu)
    m = n * ntheta
    q = u[0:n]
    dq = u[n:2 * n]
    r = u[2 * n:3 * n]
    v = u[3 * n:4 * n]
    dv = u[4 * n:5 * n]
    mu = u[5 * n]
    dmu = u[5 * n + 1]
    A = np.empty((n, ntheta))
    B = np.empty((n, ntheta))
    C = np.empty((n, ntheta))
    model.Phi(q, dq, v, dv, A)
    model.Phi_C(q, dq, r, B)
    model.Phi_dM(q, dq, r, C)
    # dPhi_f = mu (Phi^T(q,dq,v,dv) - Phi_C^T(q,dq,r) + Phi_dM^T(q,dq,r) - Phi_f)
    for i in range(n):
        for j in range(ntheta):
            k = i * ntheta + j
            dx[k] = mu * (A[i, j] - B[i, j] + C[i, j] - x[k])
    # dPhi_Mf = (mu + dmu/mu) (Phi_M^T(q,r) - Phi_Mf)   (E1; literal: gain mu)
    model.Phi_M(q, r, A)
    g = mu + (1.0 - literal_e1) * dmu / mu
    for i in range(n):
        for j in range(ntheta):
            k = i * ntheta + j
            dx[m + k] = g * (A[i, j] - x[m + k])
    # du_f = mu (u - u_f), u = -tau
    for i in range(n):
        dx[2 * m + i] = mu * (-u[5 * n + 2 + i] - x[2 * m + i])


def torque_observer_output(t, x, u, y, n, ntheta, literal_e1):
    # outputs  y = [Pi^T (n*nθ), u_f (n), tau_d_hat (n)]
    #   Pi^T = mu (Phi_M^T(q,r) - Phi_Mf^T) + Phi^T(q,dq,v,dv) - Phi_f^T      (eq. 8)
    #   tau_d_hat = -mu (Phi_M^T(q,r) - Phi_Mf^T - Phi_f^T/mu) theta_hat + u_f (Section 4)
    m = n * ntheta
    q = u[0:n]
    dq = u[n:2 * n]
    r = u[2 * n:3 * n]
    v = u[3 * n:4 * n]
    dv = u[4 * n:5 * n]
    mu = u[5 * n]
    th0 = 6 * n + 2
    PM = np.empty((n, ntheta))
    P = np.empty((n, ntheta))
    model.Phi_M(q, r, PM)
    model.Phi(q, dq, v, dv, P)
    for i in range(n):
        s = 0.0
        for j in range(ntheta):
            k = i * ntheta + j
            e = mu * (PM[i, j] - x[m + k]) - x[k]
            y[k] = e + P[i, j]
            s += e * u[th0 + j]
        y[m + i] = x[2 * m + i]
        y[m + n + i] = -s + x[2 * m + i]


def torque_observer(model, *, variant="corrected", name="torque_observer"):
    """Torque observer (7) and regressor Pi (8); estimates tau_d from theta_hat.

    ======  ===============================================================
    states  Phi_f[n*nθ], Phi_Mf[n*nθ], u_f[n]        (all zero at t0)
    inputs  q, dq, r, v, dv (n each), mu, dmu, tau[n], theta_hat[nθ]
    output  Pi[n*nθ] (Pi^T row-major), u_f[n], tau_d_hat[n]
    params  variant: "corrected" (erratum E1, gain mu + dmu/mu) or "literal" (mu)
    ======  ===============================================================
    """
    if variant not in _VARIANTS:
        raise ParameterError(f"block '{name}': unknown observer variant {variant!r}; "
                               f"use one of {sorted(_VARIANTS)}")
    n, nth = model.n, model.ntheta
    m = n * nth
    spec = BlockSpec(
        name=name,
        inputs=[("q", n), ("dq", n), ("r", n), ("v", n), ("dv", n), ("mu", 1), ("dmu", 1),
                ("tau", n), ("theta_hat", nth)],
        outputs=[("Pi", m), ("u_f", n), ("tau_d_hat", n)],
        states=[("Phi_f", m), ("Phi_Mf", m), ("u_f", n)], x0=np.zeros(2 * m + n),
        param_names=("n", "ntheta", "literal_e1"),
        update=torque_observer_update, output=torque_observer_output,
        direct=("q", "dq", "r", "v", "dv", "mu", "theta_hat"), model=model,
        constants={"n": n, "ntheta": nth, "literal_e1": 1.0 - _VARIANTS[variant]})
    return make_block(spec, {})
