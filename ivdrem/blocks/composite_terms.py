"""Composite terms vartheta_c of the adaptation law (11)."""
from __future__ import annotations

import numpy as np

from .jacobians import drem_term_jacobian, composite_learning_term_jacobian
from ._core import BlockSpec, make_block
from ._kernels import as_matrix, start_weight
from . import _validate as checks


def term_start_output(t, x, u, y, t_on, t_ramp):
    # outputs  y.start_weight[0] = w(t): 0 before t_on, C1 ramp over t_ramp, then 1
    # params   t_on >= 0, t_ramp >= 0 (s); w = 1 exactly when both are 0
    y.start_weight[0] = start_weight(t, t_on, t_ramp)


def term_start(t_on=0.0, t_ramp=0.0, *, name="term_start"):
    """The weight w(t) that switches the composite term (21) on (``_kernels.start_weight``).

    With t_on = T the term starts when the window (15a) is full, where the excitation (18)
    of Proposition 1 is defined; before, θ̂ follows the plain adaptive law.  A source block
    (time only), so that the term's own Jacobian and its structure do not depend on t.

    ======  ==========================================================
    states  none;  inputs none
    output  start_weight[1]
    params  t_on >= 0, t_ramp >= 0 (s)
    ======  ==========================================================
    """
    def validate(p):
        out = dict(p)
        for key in ("t_on", "t_ramp"):
            v = checks.scalar(name, key, p[key])
            if not v >= 0:
                raise checks.ParameterError(f"block '{name}': parameter '{key}' must be >= 0 "
                                            f"(seconds), got {v}")
            out[key] = v
        return out
    spec = BlockSpec(name=name, inputs=[], outputs=[("start_weight", 1)], states=[],
                     x0=np.zeros(0), param_names=("t_on", "t_ramp"), output=term_start_output,
                     validate=validate, named_ports=True)
    return make_block(spec, {"t_on": t_on, "t_ramp": t_ramp})


def drem_term_output(t, x, u, y, gamma):
    # inputs   u.Delta[0], u.calY (nθ), u.theta_hat (nθ), u.start_weight[0] = w(t)
    # outputs  y.theta_c = w gamma Delta (calY - Delta theta_hat)             (eq. 21)
    # params   gamma > 0
    g = gamma * u.start_weight[0]
    D = u.Delta[0]
    for i in range(y.theta_c.shape[0]):
        y.theta_c[i] = g * D * (u.calY[i] - D * u.theta_hat[i])


def drem_term(ntheta, gamma=1e10, *, name="drem_term"):
    """IV-DREM (or plain DREM) composite term, eq. (21), weighted by the start w(t) of
    :func:`term_start` (w = 1: (21) as in the paper).

    ======  ==========================================================
    states  none
    inputs  Delta, calY[nθ], theta_hat[nθ], start_weight
    output  theta_c[nθ]
    params  gamma > 0
    ======  ==========================================================
    """
    def validate(p):
        return {**p, "gamma": checks.scalar(name, "gamma", p["gamma"], positive=True)}
    spec = BlockSpec(name=name, inputs=[("Delta", 1), ("calY", ntheta), ("theta_hat", ntheta),
                                        ("start_weight", 1)],
                     outputs=[("theta_c", ntheta)], states=[], x0=np.zeros(0),
                     param_names=("gamma",), output=drem_term_output,
                     direct=("Delta", "calY", "theta_hat", "start_weight"), validate=validate,
                     named_ports=True, jacobian=drem_term_jacobian)
    return make_block(spec, {"gamma": gamma})


def drem_channel_term_output(t, x, u, y, gamma):
    # inputs   u.Delta (nθ), u.calY (nθ), u.theta_hat (nθ), u.start_weight[0] = w(t)
    # outputs  y.theta_c_i = w gamma_i Delta_i (calY_i - Delta_i theta_hat_i)  (eq. 21 per channel)
    # params   gamma (nθ) > 0
    w = u.start_weight[0]
    for i in range(y.theta_c.shape[0]):
        D = u.Delta[i]
        y.theta_c[i] = w * gamma[i] * D * (u.calY[i] - D * u.theta_hat[i])


def drem_channel_term_jacobian(t, x, u, jac, gamma):
    # inputs   u = [Delta (nθ), calY (nθ), theta_hat (nθ), w]
    # output   theta_c_i = w gamma_i Delta_i (calY_i - Delta_i theta_hat_i)
    nth = jac.shape[0]
    w = u[3 * nth]
    for i in range(nth):
        D = u[i]
        g = w * gamma[i]
        jac[i, i] = g * (u[nth + i] - 2.0 * D * u[2 * nth + i])
        jac[i, nth + i] = g * D
        jac[i, 2 * nth + i] = -g * D * D
        jac[i, 3 * nth] = gamma[i] * D * (u[nth + i] - D * u[2 * nth + i])


def drem_channel_term(ntheta, gamma=1.0, *, name="drem_term"):
    """The composite term (21) channel by channel, for a mixing with one Δ_i per channel
    ("channel" of docs/mixing.md): ϑ_c,i = γ_i Δ_i (𝒴_i − Δ_i θ̂_i) = γ_i Δ_i² θ̃_i + γ_i Δ_i 𝒲_i,
    so each channel is the scalar regression of (17) with its own gain; weighted by the
    start w(t) of :func:`term_start` like :func:`drem_term`.

    ======  ==========================================================
    states  none
    inputs  Delta[nθ], calY[nθ], theta_hat[nθ], start_weight
    output  theta_c[nθ]
    params  gamma[nθ] > 0 (a number is used for every channel)
    ======  ==========================================================
    """
    def validate(p):
        g = np.asarray(p["gamma"], dtype=float)
        if g.ndim == 0 or g.size == 1:
            g = np.full(ntheta, float(g.reshape(-1)[0]))
        g = checks.vector(name, "gamma", g, ntheta)
        if not np.all(g > 0):
            raise checks.ParameterError(f"block '{name}': parameter 'gamma' must be > 0 in "
                                        f"every channel, got {g}")
        return {**p, "gamma": g}
    spec = BlockSpec(name=name, inputs=[("Delta", ntheta), ("calY", ntheta),
                                        ("theta_hat", ntheta), ("start_weight", 1)],
                     outputs=[("theta_c", ntheta)], states=[], x0=np.zeros(0),
                     param_names=("gamma",), output=drem_channel_term_output,
                     direct=("Delta", "calY", "theta_hat", "start_weight"), validate=validate,
                     named_ports=True, jacobian=drem_channel_term_jacobian)
    g = np.asarray(gamma, dtype=float)
    return make_block(spec, {"gamma": np.full(ntheta, float(g)) if g.ndim == 0 else g})


def composite_learning_term_output(t, x, u, y, gamma):
    # inputs   u.held = [Y_b(t_e) (nθ), Psi_b(t_e) (nθ*nθ row-major)], u.theta_hat (nθ)
    # outputs  y.theta_c = gamma (Y_b(t_e) - Psi_b(t_e) theta_hat)           (eq. 35)
    # params   gamma > 0
    nth = y.theta_c.shape[0]
    Psi = as_matrix(u.held[nth:nth + nth * nth], nth, nth)
    for i in range(nth):
        s = u.held[i]
        for j in range(nth):
            s -= Psi[i, j] * u.theta_hat[j]
        y.theta_c[i] = gamma * s


def composite_learning_term(ntheta, gamma=1.0, *, input="held", name="composite_learning_term"):
    """Composite-learning term of Pan & Yu, eq. (35), on the max-held (Y_b, Psi_b).

    ======  ==========================================================
    states  none
    inputs  <input>[nθ + nθ*nθ] = [Y_b(t_e), Psi_b(t_e)], theta_hat[nθ]
    output  theta_c[nθ]
    params  gamma > 0
    ======  ==========================================================
    """
    def validate(p):
        return {**p, "gamma": checks.scalar(name, "gamma", p["gamma"], positive=True)}
    spec = BlockSpec(name=name, inputs=[(input, ntheta + ntheta * ntheta), ("theta_hat", ntheta)],
                     outputs=[("theta_c", ntheta)], states=[], x0=np.zeros(0),
                     param_names=("gamma",), output=composite_learning_term_output,
                     direct=(input, "theta_hat"), validate=validate, named_ports=True,
                     kernel_names={input: "held"}, jacobian=composite_learning_term_jacobian)
    return make_block(spec, {"gamma": gamma})


def sigma_modification_output(t, x, u, y, sigma, theta_star):
    # inputs   u.theta_hat (nθ)
    # outputs  y.theta_c = sigma (theta_star - theta_hat)                    (erratum E5)
    # params   sigma > 0, theta_star (nθ)
    for i in range(y.theta_c.shape[0]):
        y.theta_c[i] = sigma * (theta_star[i] - u.theta_hat[i])


def sigma_modification_term(ntheta, sigma=0.1, theta_star=None, *,
                            name="sigma_modification_term"):
    """Leakage toward a prior guess theta*: sigma (theta* - theta_hat) (erratum E5).

    ======  ==========================================================
    states  none
    inputs  theta_hat[nθ]
    output  theta_c[nθ]
    params  sigma > 0, theta_star[nθ]
    ======  ==========================================================
    """
    def validate(p):
        return {**p, "sigma": checks.scalar(name, "sigma", p["sigma"], positive=True),
                "theta_star": checks.vector(name, "theta_star", p["theta_star"], ntheta)}
    ts = np.zeros(ntheta) if theta_star is None else theta_star
    spec = BlockSpec(name=name, inputs=[("theta_hat", ntheta)], outputs=[("theta_c", ntheta)],
                     states=[], x0=np.zeros(0), param_names=("sigma", "theta_star"),
                     output=sigma_modification_output, direct=("theta_hat",), validate=validate,
                     named_ports=True)
    return make_block(spec, {"sigma": sigma, "theta_star": ts})


def zero_output(t, x, u, y):
    # outputs  y.theta_c = 0
    y.theta_c[:] = 0.0


def zero_term(ntheta, *, name="zero_term"):
    """vartheta_c = 0: plain disturbance-rejection adaptive control.

    ======  ======================
    states  none;  inputs none
    output  theta_c[nθ]
    ======  ======================
    """
    spec = BlockSpec(name=name, inputs=[], outputs=[("theta_c", ntheta)], states=[],
                     x0=np.zeros(0), param_names=(), output=zero_output, named_ports=True)
    return make_block(spec, {})
