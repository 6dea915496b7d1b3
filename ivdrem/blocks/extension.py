"""Integrands of the regressor extension (15a) and of the baseline (35).

IV-DREM uses zeta z and zeta phi^T; composite learning and DREM without IV use phi z and
phi phi^T (the instrument replaced by the regressor itself).
"""
from __future__ import annotations

import numpy as np

from .jacobians import extension_jacobian
from ._core import BlockSpec, make_block
from ._kernels import matT_vec, matT_mat


def extension_output(t, x, u, y, n, ntheta, has_instrument):
    # inputs   u = [z (n), phi^T (n*nθ)] + [zeta^T (n*nθ)] if has_instrument
    # outputs  y = [zeta z (nθ), zeta phi^T (nθ*nθ)]  (zeta := phi without instrument)
    m = n * ntheta
    z = u[0:n]
    phiT = u[n:n + m].reshape((n, ntheta))
    if has_instrument == 1:
        zetaT = u[n + m:n + 2 * m].reshape((n, ntheta))
    else:
        zetaT = phiT
    matT_vec(zetaT, z, y[0:ntheta])
    matT_mat(zetaT, phiT, y[ntheta:ntheta + ntheta * ntheta].reshape((ntheta, ntheta)))


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
                     output=extension_output, direct=tuple(p for p, _ in inputs),
                     jacobian=extension_jacobian,
                     constants={"n": n, "ntheta": ntheta, "has_instrument": int(instrument)})
    return make_block(spec, {})
