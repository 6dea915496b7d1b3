"""Disturbance-rejection control law, paper eq. (9), in two designs of its feedback.

``design="paper"`` is (9) as printed: tau = (K + delta_mu mu) r + Pi^T theta_hat - u_f.
``design="inertia-scaled"`` scales the feedback by the nominal inertia
M̂(q) = M(q, theta_nominal) (Property 1: M̂(q) x = Phi_M^T(q, x) theta_nominal), K then in
1/s: tau = M̂(q)(K + delta_mu mu) r + Pi^T theta_hat - u_f.  It is the sampled controller's
design for real arms (ivdrem.controller.sampled, docs/controller.md "Sampled designs")
in continuous time, so that the sampled loop has a continuous loop with the same gains
(docs/controller.md, "The inertia-scaled design in continuous time").
"""
from __future__ import annotations

import numpy as np

from .jacobians import control_law_jacobian, inertia_scaled_control_law_jacobian
from ._kernels import as_matrix, stack_empty
from ._core import BlockSpec, make_block, ParameterError
from . import _validate as checks

__all__ = ["control_law", "DESIGNS", "INJECTIONS", "default_injection", "inertia_scaled_gain"]

#: designs of the feedback of (9): the one enumeration the continuous block, the sampled
#: controller and the configuration read (docs/controller.md, "Sampled designs")
DESIGNS = ("paper", "inertia-scaled")

#: the parameters the observer's injection mu (Phi_M^T(q, r) - Phi_Mf^T) theta of (7)-(8) is
#: evaluated at: "estimate" (theta_hat, the paper's: the loop's inertia below the observer's
#: bandwidth is then M(q, theta_hat), indefinite where theta_hat is far from theta) or
#: "nominal" (theta_nominal: a momentum observer on the nominal model M(q, theta_nominal),
#: positive definite; the adaptation (11) then reads Pi_X^T = Phi^T - Phi_f^T, the regressor
#: of theta_tilde that is left in (10)); docs/controller.md, "The observer on the nominal
#: inertia"
INJECTIONS = ("estimate", "nominal")


def default_injection(design):
    """"estimate" for the paper's design (bit for bit the paper's (8)-(9)), "nominal" for
    the inertia-scaled design (the URDF arms' default)."""
    return "nominal" if design == "inertia-scaled" else "estimate"


def inertia_scaled_gain(model, K, q0, theta_nominal=None):
    """Joint gains K (N m s/rad) as the inertia-scaled design's gains (1/s):
    K_i / M̂_ii(q0), so that M̂(q0) K r has the paper's K r on the diagonal at q0."""
    th = np.asarray(model.theta_values if theta_nominal is None else theta_nominal, float)
    M = np.empty((model.n, model.n))
    model.functions.M(np.asarray(q0, dtype=float), th, M)
    return np.asarray(K, dtype=float) / np.diag(M)


def control_law_output(t, x, u, y, K, delta_mu, ntheta):
    # inputs   u.r (n), u.mu[0], u.Pi (Pi^T, n*nθ row-major), u.theta_hat (nθ), u.u_f (n)
    # outputs  y.tau = (K + delta_mu mu) r + Pi^T theta_hat - u_f                  (eq. 9)
    # params   K (n x n, positive definite), delta_mu in (0, 1), ntheta
    n = K.shape[0]
    r = u.r
    Pi = as_matrix(u.Pi, n, ntheta)
    for i in range(n):
        s = delta_mu * u.mu[0] * r[i] - u.u_f[i]
        for j in range(n):
            s += K[i, j] * r[j]
        for j in range(ntheta):
            s += Pi[i, j] * u.theta_hat[j]
        y.tau[i] = s


def inertia_scaled_control_law_output(t, x, u, y, K, delta_mu, ntheta, theta_nominal,
                                      nominal):
    # inputs   u.q (n), u.r (n), u.mu[0], u.Pi (Pi^T, n*nθ row-major), u.theta_hat (nθ),
    #          u.u_f (n)
    # outputs  y.tau = M̂(q)(K + delta_mu mu) r + Pi^T theta_hat - u_f  (eq. 9, inertia-scaled)
    #          M̂(q) w = Phi_M^T(q, w) theta_nominal                        (Property 1)
    # params   K (n x n, positive definite, 1/s), delta_mu in (0, 1), ntheta,
    #          theta_nominal (nθ)
    n = K.shape[0]
    r = u.r
    Pi = as_matrix(u.Pi, n, ntheta)
    w = stack_empty(n)
    for i in range(n):
        s = delta_mu * u.mu[0] * r[i]
        for j in range(n):
            s += K[i, j] * r[j]
        w[i] = s
    PM = stack_empty((n, ntheta))
    model.Phi_M(u.q, w, PM)
    for i in range(n):
        s = -u.u_f[i]
        for j in range(ntheta):
            s += PM[i, j] * theta_nominal[j] + Pi[i, j] * u.theta_hat[j]
        y.tau[i] = s


def nominal_injection_control_law_output(t, x, u, y, K, delta_mu, ntheta, theta_nominal,
                                         nominal):
    # inputs   u.q (n), u.r (n), u.mu[0], u.Pi (Pi_X^T = Phi^T - Phi_f^T, n*nθ row-major),
    #          u.theta_hat (nθ), u.u_f (n), u.chi (n)
    # outputs  y.tau = M̂(q)(K + delta_mu mu) r + Pi_X^T theta_hat + chi - u_f
    #          (eq. 9 inertia-scaled, the observer's injection chi at theta_nominal)
    # params   as inertia_scaled_control_law_output
    n = K.shape[0]
    r = u.r
    Pi = as_matrix(u.Pi, n, ntheta)
    w = stack_empty(n)
    for i in range(n):
        s = delta_mu * u.mu[0] * r[i]
        for j in range(n):
            s += K[i, j] * r[j]
        w[i] = s
    PM = stack_empty((n, ntheta))
    model.Phi_M(u.q, w, PM)
    for i in range(n):
        s = u.chi[i] - u.u_f[i]
        for j in range(ntheta):
            s += PM[i, j] * theta_nominal[j] + Pi[i, j] * u.theta_hat[j]
        y.tau[i] = s


def control_law(n, ntheta, K=2.0, delta_mu=0.8, *, design="paper", model=None,
                theta_nominal=None, injection=None, name="control_law"):
    """tau = (K + delta_mu mu(t)) r + Pi^T theta_hat - u_f   (eq. 9), or with the feedback
    scaled by the nominal inertia (``design="inertia-scaled"``).

    ======  ==========================================================
    states  none
    inputs  r[n], mu, Pi[n*nθ], theta_hat[nθ], u_f[n]; "inertia-scaled": q[n] first
    output  tau[n]
    params  K (n x n positive definite; scalar or diagonal accepted; 1/s when
            inertia-scaled), delta_mu in (0, 1); "inertia-scaled": theta_nominal[nθ]
            (default the model's theta_values, the URDF's own parameters)
    ======  ==========================================================

    ``model`` (the robot model whose M̂(q) scales the feedback) is needed by
    "inertia-scaled" only.  ``injection`` (default :func:`default_injection` of the design):
    "nominal" (inertia-scaled only) adds the input chi[n] (the torque observer's injection
    at theta_nominal, its Pi then Pi_X^T = Phi^T - Phi_f^T): tau = M̂(q)(K + delta_mu mu) r
    + Pi^T theta_hat + chi - u_f.
    """
    if design not in DESIGNS:
        raise ParameterError(f"block '{name}': design = {design!r} is not a design of (9); "
                             f"choose one of {', '.join(map(repr, DESIGNS))}")
    scaled = design == "inertia-scaled"
    injection = default_injection(design) if injection is None else injection
    if injection not in INJECTIONS or (injection == "nominal" and not scaled):
        raise ParameterError(f"block '{name}': injection = {injection!r} is not an option of "
                             f"design {design!r}; choose 'estimate'"
                             + (" or 'nominal'" if scaled else ""))
    nominal = injection == "nominal"

    def validate(p):
        p = dict(p)
        p["K"] = checks.square(name, "K", p["K"], n, pd=True)
        p["delta_mu"] = checks.scalar(name, "delta_mu", p["delta_mu"], lo=0.0, hi=1.0)
        if scaled:
            p["theta_nominal"] = checks.vector(name, "theta_nominal", p["theta_nominal"],
                                               ntheta)
        return p
    common = [("r", n), ("mu", 1), ("Pi", n * ntheta), ("theta_hat", ntheta), ("u_f", n)]
    if not scaled:
        spec = BlockSpec(name=name, inputs=common,
                         outputs=[("tau", n)], states=[], x0=np.zeros(0),
                         param_names=("K", "delta_mu", "ntheta"), output=control_law_output,
                         direct=("r", "mu", "Pi", "theta_hat", "u_f"), validate=validate,
                         named_ports=True, jacobian=control_law_jacobian,
                         constants={"ntheta": ntheta})
        return make_block(spec, {"K": K, "delta_mu": delta_mu})
    if model is None or model.n != n or model.ntheta != ntheta:
        raise ParameterError(f"block '{name}': design 'inertia-scaled' needs the robot model "
                             f"(n = {n}, ntheta = {ntheta}) whose nominal inertia scales the "
                             "feedback: control_law(n, ntheta, design=..., model=model)")
    if theta_nominal is None:
        theta_nominal = model.theta_values
        if theta_nominal is None:
            raise ParameterError(f"block '{name}': design 'inertia-scaled' needs the nominal "
                                 f"parameters theta_nominal (model {model.name!r} has none)")
    spec = BlockSpec(name=name, inputs=[("q", n)] + common + ([("chi", n)] if nominal else []),
                     outputs=[("tau", n)], states=[], x0=np.zeros(0),
                     param_names=("K", "delta_mu", "ntheta", "theta_nominal", "nominal"),
                     output=(nominal_injection_control_law_output if nominal
                             else inertia_scaled_control_law_output),
                     direct=("q", "r", "mu", "Pi", "theta_hat", "u_f")
                     + (("chi",) if nominal else ()), validate=validate,
                     model=model, named_ports=True,
                     jacobian=inertia_scaled_control_law_jacobian,
                     constants={"ntheta": ntheta, "nominal": 1.0 if nominal else 0.0})
    return make_block(spec, {"K": K, "delta_mu": delta_mu, "theta_nominal": theta_nominal})
