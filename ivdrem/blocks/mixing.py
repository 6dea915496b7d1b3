"""Mixing step, paper eq. (17) with erratum E4.

s = 1 + ||Psi||_F, Psi_n = Psi/s, Delta = det Psi_n, calY = adj(Psi_n) Y / s, so that
calY_i = Delta theta_i + calW_i with calW = adj(Psi_n) W / s.  The adjugate is used, never
an inverse: Psi is singular at the start of every run.
"""
from __future__ import annotations

import math

import numpy as np

from .jacobians import mixing_jacobian
from ._core import BlockSpec, make_block
from ._kernels import det_adj


def mixing_output(t, x, u, y, ntheta):
    # inputs   u.Y_Psi = [Y (nθ), Psi (nθ*nθ row-major)]
    # outputs  y.Delta[0] = det Psi_n, y.calY (nθ) = adj(Psi_n) Y / s   (17), erratum E4
    nn = ntheta * ntheta
    Y = u.Y_Psi[0:ntheta]
    Psi = u.Y_Psi[ntheta:ntheta + nn]
    big = 0.0
    for k in range(nn):
        big = max(big, abs(Psi[k]))
    ss = 0.0
    if big > 0.0:
        for k in range(nn):
            r = Psi[k] / big                             # scaled: no overflow for huge Psi
            ss += r * r
    s = 1.0 + big * math.sqrt(ss)                        # 1 + ||Psi||_F
    Pn = np.empty((ntheta, ntheta))
    for i in range(ntheta):
        for j in range(ntheta):
            Pn[i, j] = Psi[i * ntheta + j] / s
    adj = np.empty((ntheta, ntheta))
    y.Delta[0] = det_adj(Pn, adj)
    for i in range(ntheta):
        acc = 0.0
        for j in range(ntheta):
            acc += adj[i, j] * Y[j]
        y.calY[i] = acc / s


def mixing(ntheta, *, input="avg", name="mixing"):
    """Determinant/adjugate mixing (17): nθ scalar regressions calY_i = Delta theta_i + calW_i.

    ======  ==========================================================
    states  none
    inputs  <input>[nθ + nθ*nθ] = [Y, Psi]
    output  Delta, calY[nθ]
    params  none
    ======  ==========================================================
    """
    spec = BlockSpec(name=name, inputs=[(input, ntheta + ntheta * ntheta)],
                     outputs=[("Delta", 1), ("calY", ntheta)], states=[], x0=np.zeros(0),
                     param_names=("ntheta",), output=mixing_output, direct=(input,),
                     named_ports=True, kernel_names={input: "Y_Psi"}, jacobian=mixing_jacobian,
                     constants={"ntheta": ntheta})
    return make_block(spec, {})
