"""High-gain external torque observer, paper eq. (7), with the regressor Pi of eq. (8).

States are stored in the n x nθ orientation (Phi_f^T, Phi_Mf^T), row-major.

``injection="nominal"`` evaluates the observer's injection mu (Phi_M^T(q,r) - Phi_Mf^T) theta
at the nominal parameters theta_nominal instead of theta_hat (a momentum observer on the
nominal inertia M(q, theta_nominal); docs/controller.md, "The observer on the nominal
inertia"): the block then outputs Pi_X^T = Phi^T - Phi_f^T as Pi (the regressor of
theta_tilde left in the closed loop (10), which the adaptation (11) reads) and the
injection chi = mu (Phi_M^T(q,r) - Phi_Mf^T) theta_nominal for the control law (9).
"""
from __future__ import annotations

import numpy as np

from ._kernels import stack_empty
from ._core import BlockSpec, make_block
from ._core import ParameterError
from . import _validate as checks
from .jacobians import torque_observer_jacobian

_VARIANTS = {"corrected": 1.0, "literal": 0.0}


def torque_observer_update(t, x, u, dx, n, ntheta, literal_e1, nominal, theta_nominal):
    # states   x.Phi_f, x.Phi_Mf (Phi_f^T, Phi_Mf^T: n*nθ row-major), x.u_f (n)
    # inputs   u.q, u.dq, u.r, u.v, u.dv (n), u.mu[0], u.dmu[0], u.tau (n), u.theta_hat (nθ)
    # params   n, ntheta, literal_e1 (0: erratum E1 gain mu + dmu/mu; 1: the paper's mu);
    #          nominal, theta_nominal: the outputs' injection only (the states are the same)
    mu = u.mu[0]
    A = stack_empty((n, ntheta))
    B = stack_empty((n, ntheta))
    C = stack_empty((n, ntheta))
    model.Phi(u.q, u.dq, u.v, u.dv, A)
    model.Phi_C(u.q, u.dq, u.r, B)
    model.Phi_dM(u.q, u.dq, u.r, C)
    # dPhi_f = mu (Phi^T(q,dq,v,dv) - Phi_C^T(q,dq,r) + Phi_dM^T(q,dq,r) - Phi_f)   (7)
    for i in range(n):
        for j in range(ntheta):
            k = i * ntheta + j
            dx.Phi_f[k] = mu * (A[i, j] - B[i, j] + C[i, j] - x.Phi_f[k])
    # dPhi_Mf = (mu + dmu/mu) (Phi_M^T(q,r) - Phi_Mf)   (7) with E1; literal: gain mu
    model.Phi_M(u.q, u.r, A)
    g = mu + (1.0 - literal_e1) * u.dmu[0] / mu
    for i in range(n):
        for j in range(ntheta):
            k = i * ntheta + j
            dx.Phi_Mf[k] = g * (A[i, j] - x.Phi_Mf[k])
    # du_f = mu (u - u_f) with u = -tau   (7)
    for i in range(n):
        dx.u_f[i] = mu * (-u.tau[i] - x.u_f[i])


def torque_observer_output(t, x, u, y, n, ntheta, literal_e1, nominal, theta_nominal):
    # outputs  y.Pi (Pi^T, n*nθ row-major), y.u_f (n), y.tau_d_hat (n)
    #   Pi^T = mu (Phi_M^T(q,r) - Phi_Mf^T) + Phi^T(q,dq,v,dv) - Phi_f^T      (eq. 8)
    #   tau_d_hat = -mu (Phi_M^T(q,r) - Phi_Mf^T - Phi_f^T/mu) theta_hat + u_f (Section 4)
    mu = u.mu[0]
    PM = stack_empty((n, ntheta))
    P = stack_empty((n, ntheta))
    model.Phi_M(u.q, u.r, PM)
    model.Phi(u.q, u.dq, u.v, u.dv, P)
    for i in range(n):
        s = 0.0
        for j in range(ntheta):
            k = i * ntheta + j
            e = mu * (PM[i, j] - x.Phi_Mf[k]) - x.Phi_f[k]
            y.Pi[k] = e + P[i, j]
            s += e * u.theta_hat[j]
        y.u_f[i] = x.u_f[i]
        y.tau_d_hat[i] = -s + x.u_f[i]


def torque_observer_nominal_output(t, x, u, y, n, ntheta, literal_e1, nominal, theta_nominal):
    # outputs  y.Pi (Pi_X^T, n*nθ row-major), y.u_f (n), y.tau_d_hat (n), y.chi (n)
    #   Pi_X^T = Phi^T(q,dq,v,dv) - Phi_f^T   (Pi^T of (8) without the injection)
    #   chi = mu (Phi_M^T(q,r) - Phi_Mf^T) theta_nominal   (the injection, nominal momentum)
    #   tau_d_hat = -(chi - Phi_f^T theta_hat) + u_f   (Section 4, the same observer)
    mu = u.mu[0]
    PM = stack_empty((n, ntheta))
    P = stack_empty((n, ntheta))
    model.Phi_M(u.q, u.r, PM)
    model.Phi(u.q, u.dq, u.v, u.dv, P)
    for i in range(n):
        c = 0.0
        s = 0.0
        for j in range(ntheta):
            k = i * ntheta + j
            y.Pi[k] = P[i, j] - x.Phi_f[k]
            c += mu * (PM[i, j] - x.Phi_Mf[k]) * theta_nominal[j]
            s += x.Phi_f[k] * u.theta_hat[j]
        y.u_f[i] = x.u_f[i]
        y.chi[i] = c
        y.tau_d_hat[i] = -(c - s) + x.u_f[i]


def torque_observer(model, *, variant="corrected", injection="estimate", theta_nominal=None,
                    name="torque_observer"):
    """Torque observer (7) and regressor Pi (8); estimates tau_d from theta_hat.

    ======  ===============================================================
    states  Phi_f[n*nθ], Phi_Mf[n*nθ], u_f[n]        (all zero at t0)
    inputs  q, dq, r, v, dv (n each), mu, dmu, tau[n], theta_hat[nθ]
    output  Pi[n*nθ] (Pi^T row-major), u_f[n], tau_d_hat[n]; "nominal": Pi is Pi_X^T =
            Phi^T - Phi_f^T, and chi[n] (the injection at theta_nominal) follows
    params  variant: "corrected" (erratum E1, gain mu + dmu/mu) or "literal" (mu);
            injection: "estimate" (theta_hat, the paper's (8)) or "nominal"
            (theta_nominal[nθ], default the model's theta_values)
    ======  ===============================================================
    """
    from .control_law import INJECTIONS
    if variant not in _VARIANTS:
        raise ParameterError(f"block '{name}': unknown observer variant {variant!r}; "
                               f"use one of {sorted(_VARIANTS)}")
    if injection not in INJECTIONS:
        raise ParameterError(f"block '{name}': injection = {injection!r} is not an option; "
                             f"choose one of {', '.join(map(repr, INJECTIONS))}")
    n, nth = model.n, model.ntheta
    m = n * nth
    nominal = injection == "nominal"
    constants = {"n": n, "ntheta": nth, "literal_e1": 1.0 - _VARIANTS[variant],
                 "nominal": 1.0 if nominal else 0.0}
    params = {}
    if nominal:
        if theta_nominal is None:
            theta_nominal = model.theta_values
        if theta_nominal is None:
            raise ParameterError(f"block '{name}': injection 'nominal' needs the nominal "
                                 f"parameters theta_nominal (model {model.name!r} has none)")
        params["theta_nominal"] = theta_nominal
    else:
        constants["theta_nominal"] = np.zeros(nth)      # read by the "nominal" kernels only

    def validate(p):
        p = dict(p)
        if nominal:
            p["theta_nominal"] = checks.vector(name, "theta_nominal", p["theta_nominal"], nth)
        return p
    spec = BlockSpec(
        name=name,
        inputs=[("q", n), ("dq", n), ("r", n), ("v", n), ("dv", n), ("mu", 1), ("dmu", 1),
                ("tau", n), ("theta_hat", nth)],
        outputs=[("Pi", m), ("u_f", n), ("tau_d_hat", n)] + ([("chi", n)] if nominal else []),
        states=[("Phi_f", m), ("Phi_Mf", m), ("u_f", n)], x0=np.zeros(2 * m + n),
        param_names=("n", "ntheta", "literal_e1", "nominal", "theta_nominal"),
        update=torque_observer_update,
        output=torque_observer_nominal_output if nominal else torque_observer_output,
        direct=("q", "dq", "r", "v", "dv", "mu", "theta_hat"), model=model, named_ports=True,
        jacobian=torque_observer_jacobian, validate=validate, constants=constants)
    return make_block(spec, params)
