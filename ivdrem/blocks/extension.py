"""Integrands of the regressor extension (15a) and of the baseline (35).

IV-DREM uses zeta z and zeta phi^T; composite learning and DREM without IV use phi z and
phi phi^T (the instrument replaced by the regressor itself).
"""
from __future__ import annotations

import numpy as np

from .jacobians import extension_jacobian
from ._core import BlockSpec, make_block
from ._kernels import as_matrix, matT_vec, matT_mat


def extension_output(t, x, u, y, n, ntheta, has_instrument):
    # inputs   u.z (n), u.phi (phi^T, n*nθ row-major)
    # outputs  y.g = [phi z (nθ), phi phi^T (nθ*nθ)]: (15a) with zeta := phi (baseline, 35)
    # params   n, ntheta, has_instrument (0 here; shared with the block's Jacobian kernel)
    phiT = as_matrix(u.phi, n, ntheta)
    matT_vec(phiT, u.z, y.g[0:ntheta])
    matT_mat(phiT, phiT, as_matrix(y.g[ntheta:ntheta + ntheta * ntheta], ntheta, ntheta))


def iv_extension_output(t, x, u, y, n, ntheta, has_instrument):
    # inputs   u.z (n), u.phi (phi^T), u.zeta (zeta^T, instrument (14)), n*nθ row-major
    # outputs  y.g = [zeta z (nθ), zeta phi^T (nθ*nθ)]: the integrand of (15a)
    # params   n, ntheta, has_instrument (1 here; shared with the block's Jacobian kernel)
    phiT = as_matrix(u.phi, n, ntheta)
    zetaT = as_matrix(u.zeta, n, ntheta)
    matT_vec(zetaT, u.z, y.g[0:ntheta])
    matT_mat(zetaT, phiT, as_matrix(y.g[ntheta:ntheta + ntheta * ntheta], ntheta, ntheta))


def extension(n, ntheta, *, instrument=True, output="ext_g", name="extension"):
    """Products that the sliding window integrates.

    ======  ==========================================================
    states  none
    inputs  z[n], phi[n*nθ], and zeta[n*nθ] if instrument
    output  <output>[nθ + nθ*nθ] = [zeta z, zeta phi^T] (row-major)
    params  none
    ======  ==========================================================
    """
    m = n * ntheta
    inputs = [("z", n), ("phi", m)] + ([("zeta", m)] if instrument else [])
    spec = BlockSpec(name=name, inputs=inputs, outputs=[(output, ntheta + ntheta * ntheta)],
                     states=[], x0=np.zeros(0), param_names=("n", "ntheta", "has_instrument"),
                     output=iv_extension_output if instrument else extension_output,
                     direct=tuple(p for p, _ in inputs), named_ports=True,
                     kernel_names={output: "g"}, jacobian=extension_jacobian,
                     constants={"n": n, "ntheta": ntheta, "has_instrument": int(instrument)})
    return make_block(spec, {})
