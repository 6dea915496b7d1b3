"""Averaging filter, paper eq. (15b): dY = -(dF/F)(Y - y), F(t) = t^p + F0.

Closed form (zero initial state): Y(t) = (1/F(t)) int_{t0}^{t} dF(s) y(s) ds.
F0 > 0 (erratum E3: F0 = 0 makes dF/F singular at t0 = 0).
"""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks
from ._core import ParameterError


def averaging_update(t, x, u, dx, p, F0):
    # states   x.Y (m) ;  inputs u.y (m)
    # params   p >= 1, F0 > 0 ; t0 = 0
    # dY = -(dF/F)(Y - y), F(t) = t^p + F0   (15b)
    F = t ** p + F0
    dF = p * t ** (p - 1.0) if t > 0.0 else (1.0 if p == 1.0 else 0.0)
    k = dF / F
    for i in range(x.Y.shape[0]):
        dx.Y[i] = -k * (x.Y[i] - u.y[i])


def averaging_output(t, x, u, y, p, F0):
    # outputs  y.Y = x.Y
    for i in range(x.Y.shape[0]):
        y.Y[i] = x.Y[i]


def averaging(size, p=2.0, F0=1.0, *, input="window_y", output="avg", name="averaging"):
    """Averaging (15b) of the extended regression.

    ======  ==========================================================
    states  <output>[m] (zero at t0)
    inputs  <input>[m]
    output  <output>[m]
    params  p >= 1, F0 > 0
    ======  ==========================================================
    """
    def validate(q):
        q = dict(q)
        q["p"] = checks.scalar(name, "p", q["p"])
        if q["p"] < 1:
            raise ParameterError(f"block '{name}': parameter 'p' must be >= 1, got {q['p']}")
        q["F0"] = checks.scalar(name, "F0", q["F0"], positive=True)
        return q
    spec = BlockSpec(name=name, inputs=[(input, size)], outputs=[(output, size)],
                     states=[(output, size)], x0=np.zeros(size), param_names=("p", "F0"),
                     update=averaging_update, output=averaging_output, direct=(),
                     validate=validate, named_ports=True,
                     kernel_names={input: "y", output: "Y"})
    return make_block(spec, {"p": p, "F0": F0})
