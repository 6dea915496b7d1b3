"""Exact discrete updates of the controller's linear filters over one sample [t, t + h].

Every filter of the controller is linear in its own state, x_f' = a(t) (x - x_f), with
its input x held over the sample (zero-order hold).  Its exact solution is

    x_f(t + h) = x + exp(-int_t^{t+h} a ds) (x_f(t) - x),

which is stable at any gain (the factor lies in (0, 1]); explicit Euler would need
a h < 2.  The gains are: mu(t) for Phi_f and u_f (7), mu + mu'/mu for Phi_Mf (7 with
erratum E1, whose integral is int mu + ln(mu(t+h)/mu(t))), l for (13), (14), and
F'/F for the averaging (15b), whose integral is ln(F(t+h)/F(t)).

mu(t) = min(mu0 t + mu1, mu_max): the saturation that a 1 kHz loop needs (the sampled
loop diverges once h (lambda_max(K) + delta_mu mu)/m_min approaches 2).
"""
from __future__ import annotations

import math

__all__ = ["mu_saturated", "mu_integral", "observer_decay", "filter_step",
           "averaging_factor"]


def mu_saturated(t, mu0, mu1, mu_max):
    """(mu, dmu) with mu = min(mu0 t + mu1, mu_max); dmu = 0 once saturated."""
    m = mu0 * t + mu1
    if m >= mu_max:
        return mu_max, 0.0
    return m, mu0


def mu_integral(t, h, mu0, mu1, mu_max):
    """int_t^{t+h} min(mu0 s + mu1, mu_max) ds, in closed form (piecewise linear)."""
    t1 = t + h
    ts = (mu_max - mu1) / mu0 if mu0 > 0 else math.inf   # time mu reaches mu_max
    if t1 <= ts:
        return mu0 * 0.5 * (t1 * t1 - t * t) + mu1 * h
    if t >= ts:
        return mu_max * h
    return mu0 * 0.5 * (ts * ts - t * t) + mu1 * (ts - t) + mu_max * (t1 - ts)


def observer_decay(t, h, mu0, mu1, mu_max, corrected=True):
    """Decay factors (for Phi_f and u_f, for Phi_Mf) of the observer (7) over one sample.

    Phi_Mf's gain is mu + mu'/mu (erratum E1): its integral adds ln(mu(t+h)/mu(t)).
    ``corrected=False``: the paper's literal gain mu for Phi_Mf too."""
    I = mu_integral(t, h, mu0, mu1, mu_max)
    d = math.exp(-I)
    if not corrected:
        return d, d
    m0 = mu_saturated(t, mu0, mu1, mu_max)[0]
    m1 = mu_saturated(t + h, mu0, mu1, mu_max)[0]
    return d, d * (m0 / m1)


def filter_step(xf, x, decay, out=None):
    """x_f(t + h) = x + decay (x_f - x) (element-wise; ``out`` may be ``xf``)."""
    if out is None:
        return x + decay * (xf - x)
    out[...] = x + decay * (xf - x)
    return out


def averaging_factor(t, h, p, F0):
    """F(t)/F(t + h) with F = t^p + F0: Y(t + h) = y + factor (Y - y) solves (15b) exactly."""
    if not (F0 > 0):
        raise ValueError(f"F0 must be > 0 (erratum E3), got {F0!r}")
    return (t ** p + F0) / ((t + h) ** p + F0)
