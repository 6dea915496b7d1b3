"""Exogenous signals: reference trajectories (sinusoid, finite Fourier series), external
torque, and the mu(t) schedule."""
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


# ----------------------------------------------------------------- Fourier trajectory
def fourier_trajectory_output(t, x, u, y, omega_f, a, b, offset):
    # outputs  y.q_d, y.dq_d, y.ddq_d (n each)
    # params   finite Fourier series per joint (Swevers et al. 1997), H harmonics of
    #          omega_f:  q_d,i = c_i + sum_l [a_il sin(l w t) - b_il cos(l w t)] / (l w)
    #          dq_d,i = sum_l a_il cos(l w t) + b_il sin(l w t)
    #          ddq_d,i = sum_l l w [b_il cos(l w t) - a_il sin(l w t)]
    #          (omega_f scalar, a and b n x H, offset c: n)
    n = a.shape[0]
    H = a.shape[1]
    for i in range(n):
        q = offset[i]
        dq = 0.0
        ddq = 0.0
        for l in range(H):
            w = omega_f * (l + 1)
            s = np.sin(w * t)
            c = np.cos(w * t)
            q += (a[i, l] * s - b[i, l] * c) / w
            dq += a[i, l] * c + b[i, l] * s
            ddq += w * (b[i, l] * c - a[i, l] * s)
        y.q_d[i] = q
        y.dq_d[i] = dq
        y.ddq_d[i] = ddq


def fourier_series(t, omega_f, a, b, offset):
    """(q_d, dq_d, ddq_d) of :func:`fourier_trajectory` at the times `t`, each
    (len(t), n): the same series evaluated with numpy, for design and limit checks."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    w = float(omega_f) * np.arange(1, a.shape[1] + 1)          # (H,)
    s, c = np.sin(np.outer(t, w)), np.cos(np.outer(t, w))      # (N, H)
    q = np.asarray(offset, dtype=float) + (s / w) @ a.T - (c / w) @ b.T
    dq = c @ a.T + s @ b.T
    ddq = (c * w) @ b.T - (s * w) @ a.T
    return q, dq, ddq


def fourier_bounds(omega_f, a, b):
    """Bounds valid at every t: max |q_d,i − c_i| <= Σ_l |(a_il, b_il)| / (l ω_f) and
    max |dq_d,i| <= Σ_l |(a_il, b_il)| (each harmonic is a sinusoid of that amplitude)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    amp = np.hypot(a, b)
    w = float(omega_f) * np.arange(1, a.shape[1] + 1)
    return (amp / w).sum(axis=1), amp.sum(axis=1)


def _fourier_params(name, n, omega_f, a, b, offset):
    a = checks._arr(name, "q_d_a", a)
    b = checks._arr(name, "q_d_b", b)
    for key, m in (("q_d_a", a), ("q_d_b", b)):
        if m.ndim != 2 or m.shape[0] != n or m.shape[1] < 1:
            raise checks.ParameterError(
                f"block '{name}': parameter '{key}' must be an {n} x H matrix (H >= 1 "
                f"harmonics), got shape {m.shape}")
    if a.shape != b.shape:
        raise checks.ParameterError(f"block '{name}': parameters 'q_d_a' {a.shape} and "
                                    f"'q_d_b' {b.shape} must have the same shape")
    return {"q_d_omega_f": checks.scalar(name, "q_d_omega_f", omega_f, positive=True),
            "q_d_a": a, "q_d_b": b,
            "q_d_offset": checks.vector(name, "q_d_offset", np.zeros(n) if offset is None
                                        else offset, n)}


def fourier_trajectory(n, omega_f, a, b, offset=None, *, name="trajectory"):
    """Desired joint trajectory as a finite Fourier series per joint, the excitation
    trajectory of identification practice (Swevers, Ganseman, Tükel, De Schutter,
    Van Brussel, IEEE Trans. Robot. Autom. 13(5), 1997), with its analytic derivatives:
    q_d,i(t) = c_i + Σ_{l=1..H} [a_il sin(l ω_f t) − b_il cos(l ω_f t)] / (l ω_f).
    Periodic with period 2π/ω_f; docs/experiment.md (the real-arm experiment).

    ======  =============================================
    states  none
    inputs  none
    output  q_d[n], dq_d[n], ddq_d[n]
    params  q_d_omega_f (rad/s, > 0), q_d_a[n x H] (rad/s), q_d_b[n x H] (rad/s),
            q_d_offset[n] (rad)
    ======  =============================================
    """
    p = _fourier_params(name, n, omega_f, a, b, offset)

    def validate(q):
        return {**q, **_fourier_params(name, n, q["q_d_omega_f"], q["q_d_a"], q["q_d_b"],
                                       q["q_d_offset"])}
    spec = BlockSpec(name=name, inputs=[], outputs=[("q_d", n), ("dq_d", n), ("ddq_d", n)],
                     states=[], x0=np.zeros(0), param_names=tuple(p),
                     output=fourier_trajectory_output, validate=validate, named_ports=True)
    return make_block(spec, p)
