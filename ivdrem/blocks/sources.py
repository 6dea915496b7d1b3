"""Exogenous signals: reference trajectory, external torque, and the mu(t) schedule."""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks


def sinusoid_trajectory_output(t, x, u, y, amplitude, omega, phase, offset):
    # outputs  y.q_d, y.dq_d, y.ddq_d (n each)
    # params   q_d,i = A_i sin(w_i t + phi_i) + c_i   (A, w, phi, c: n each)
    for i in range(amplitude.shape[0]):
        s = np.sin(omega[i] * t + phase[i])
        c = np.cos(omega[i] * t + phase[i])
        y.q_d[i] = amplitude[i] * s + offset[i]
        y.dq_d[i] = amplitude[i] * omega[i] * c
        y.ddq_d[i] = -amplitude[i] * omega[i] * omega[i] * s


def sinusoid_output(t, x, u, y, amplitude, omega, phase, offset):
    # outputs  y.signal (n): A_i sin(w_i t + phi_i) + c_i
    for i in range(amplitude.shape[0]):
        y.signal[i] = amplitude[i] * np.sin(omega[i] * t + phase[i]) + offset[i]


_SINE = ("amplitude", "omega", "phase", "offset")


def _sine_params(name, n, prefix, amplitude, omega, phase, offset):
    # python-control params share one namespace per diagram: prefix them by the signal
    vals = {"amplitude": amplitude, "omega": omega,
            "phase": np.zeros(n) if phase is None else phase,
            "offset": np.zeros(n) if offset is None else offset}
    return {f"{prefix}_{k}": checks.vector(name, f"{prefix}_{k}", v, n) for k, v in vals.items()}


def _sine_validate(name, n, prefix):
    def validate(q):
        return {**q, **_sine_params(name, n, prefix, *(q[f"{prefix}_{k}"] for k in _SINE))}
    return validate


def trajectory(n, amplitude, omega, phase=None, offset=None, *, name="trajectory"):
    """Desired joint trajectory q_d(t) = A sin(w t + phi) + c, with its derivatives.

    ======  =============================================
    states  none
    inputs  none
    output  q_d[n], dq_d[n], ddq_d[n]
    params  q_d_amplitude[n], q_d_omega[n] (rad/s), q_d_phase[n], q_d_offset[n]
    ======  =============================================
    """
    p = _sine_params(name, n, "q_d", amplitude, omega, phase, offset)
    spec = BlockSpec(name=name, inputs=[], outputs=[("q_d", n), ("dq_d", n), ("ddq_d", n)],
                     states=[], x0=np.zeros(0), param_names=tuple(p),
                     output=sinusoid_trajectory_output, validate=_sine_validate(name, n, "q_d"),
                     named_ports=True)
    return make_block(spec, p)


def disturbance(n, amplitude, omega, phase=None, offset=None, *, name="disturbance",
                signal="tau_d"):
    """External torque tau_d(t) = A sin(w t + phi) + c (paper Section 4).

    ======  =============================================
    states  none
    inputs  none
    output  tau_d[n]
    params  tau_d_amplitude[n] (N m), tau_d_omega[n] (rad/s), tau_d_phase[n], tau_d_offset[n]
    ======  =============================================
    """
    p = _sine_params(name, n, signal, amplitude, omega, phase, offset)
    spec = BlockSpec(name=name, inputs=[], outputs=[(signal, n)], states=[], x0=np.zeros(0),
                     param_names=tuple(p), output=sinusoid_output,
                     validate=_sine_validate(name, n, signal), named_ports=True,
                     kernel_names={signal: "signal"})
    return make_block(spec, p)


def mu_schedule_output(t, x, u, y, mu0, mu1):
    # outputs  y.mu[0] = mu0 t + mu1 (Remark 1), y.dmu[0] = mu0
    # params   mu0 >= 0, mu1 > 0
    y.mu[0] = mu0 * t + mu1
    y.dmu[0] = mu0


def mu_schedule(mu0=1.0, mu1=15.0, *, name="mu_schedule"):
    """Observer gain mu(t) = mu0 t + mu1 > 0 of Property 4 (default t + 15).

    ======  =============================================
    states  none
    inputs  none
    output  mu, dmu
    params  mu0 >= 0, mu1 > 0
    ======  =============================================
    """
    def validate(p):
        p = dict(p)
        p["mu0"] = checks.scalar(name, "mu0", p["mu0"], nonneg=True)
        p["mu1"] = checks.scalar(name, "mu1", p["mu1"], positive=True)
        return p
    spec = BlockSpec(name=name, inputs=[], outputs=[("mu", 1), ("dmu", 1)], states=[],
                     x0=np.zeros(0), param_names=("mu0", "mu1"), output=mu_schedule_output,
                     validate=validate, named_ports=True)
    return make_block(spec, {"mu0": mu0, "mu1": mu1})
