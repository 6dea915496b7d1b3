"""Sliding-window integral y(t) = int_{t-T}^{t} g ds, eq. (15a), drift-free.

The window keeps I(t) = int_{t0}^{t} g ds as a state and forms y = I(t) - I(t - T) with
a TransportDelay block (docs/conventions.md), not dy = g(t) - g(t - T), which would drift.
"""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks


def sliding_window_update(t, x, u, dx):
    # states   x.I (m) = int_{t0}^{t} g ds ;  inputs u.g (m), u.I_delayed (m) = I(t - T)
    # dI = g   (15a)
    for i in range(x.I.shape[0]):
        dx.I[i] = u.g[i]


def sliding_window_output(t, x, u, y):
    # outputs  y.I = I (m), y.dI = g (m), y.window = I - I(t - T) (m): the integral (15a)
    for i in range(x.I.shape[0]):
        y.I[i] = x.I[i]
        y.dI[i] = u.g[i]
        y.window[i] = x.I[i] - u.I_delayed[i]


def sliding_window(size, *, input="ext_g", prefix="window", name="sliding_window"):
    """The integrator half of a sliding window; pair it with transport_delay.

    ======  ==========================================================
    states  <prefix>_I[m]
    inputs  <input>[m] (integrand g), <prefix>_I_delayed[m] (I(t - T))
    output  <prefix>_I[m], <prefix>_dI[m] (= g), <prefix>_y[m] (window integral)
    params  none
    ======  ==========================================================
    """
    spec = BlockSpec(name=name, inputs=[(input, size), (f"{prefix}_I_delayed", size)],
                     outputs=[(f"{prefix}_I", size), (f"{prefix}_dI", size),
                              (f"{prefix}_y", size)],
                     states=[(f"{prefix}_I", size)], x0=np.zeros(size), param_names=(),
                     update=sliding_window_update, output=sliding_window_output,
                     direct=(input, f"{prefix}_I_delayed"), named_ports=True,
                     kernel_names={input: "g", f"{prefix}_I_delayed": "I_delayed",
                                   f"{prefix}_I": "I", f"{prefix}_dI": "dI",
                                   f"{prefix}_y": "window"})
    return make_block(spec, {})


def transport_delay(size, T, *, input, output, derivative=None, name="transport_delay"):
    """Transport delay y(t) = u(t - T); u(t - T) := u(t0) for t - T < t0.

    Fed by the simulator from its dense history of accepted steps: cubic Hermite
    interpolation when the derivative of u is wired to the ``derivative`` input (as the
    sliding window does), otherwise Hermite with slopes from a quadratic through the last
    three accepted points (third order).  python-control cannot simulate this block.

    ======  ==========================================================
    states  none (the history lives in the simulator)
    inputs  <input>[m], and <derivative>[m] if given
    output  <output>[m]
    params  T > 0 (s)
    ======  ==========================================================
    """
    T = checks.scalar(name, "T", T, positive=True)
    inputs = [(input, size)] + ([(derivative, size)] if derivative else [])
    spec = BlockSpec(name=name, inputs=inputs, outputs=[(output, size)], states=[],
                     x0=np.zeros(0), param_names=("T",), output=None, kind="delay",
                     info={"T": T, "hermite": derivative is not None, "size": size})

    spec.validate = lambda p: {**p, "T": checks.scalar(name, "T", p["T"], positive=True)}
    return make_block(spec, {"T": T})


def windowed_integral(size, T, *, input="ext_g", prefix="window"):
    """The pair (sliding_window, transport_delay) that computes int_{t-T}^{t} input."""
    win = sliding_window(size, input=input, prefix=prefix, name=f"{prefix}_integrator")
    dly = transport_delay(size, T, input=f"{prefix}_I", derivative=f"{prefix}_dI",
                          output=f"{prefix}_I_delayed", name=f"{prefix}_delay")
    return win, dly
