"""Max-hold of (Y_b, Psi_b) at t_e = argmax lambda_min(Psi_b) (composite learning, eq. 35)."""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as V


def max_hold(nvec, nmat, epsilon=1e-9, *, input="window_y", output="held",
             score="lambda_min_held", name="max_hold"):
    """Hold the input [v (nvec), A (nmat x nmat)] of the accepted step maximising lambda_min(A).

    The simulator updates the hold after every accepted step, when lambda_min of the
    symmetric part of A exceeds both the running maximum and epsilon.  Before the first
    update the output is zero.  python-control cannot simulate this block.

    ======  ==========================================================
    states  none (the held values live in the simulator)
    inputs  <input>[nvec + nmat*nmat]
    output  <output>[nvec + nmat*nmat], <score> (lambda_min at t_e, 0 before)
    params  epsilon > 0
    ======  ==========================================================
    """
    eps = V.scalar(name, "epsilon", epsilon, positive=True)
    size = nvec + nmat * nmat
    spec = BlockSpec(name=name, inputs=[(input, size)], outputs=[(output, size), (score, 1)],
                     states=[], x0=np.zeros(0), param_names=("epsilon",), output=None,
                     kind="maxhold", info={"epsilon": eps, "nvec": nvec, "nmat": nmat,
                                           "size": size})

    spec.validate = lambda p: {**p, "epsilon": V.scalar(name, "epsilon", p["epsilon"],
                                                         positive=True)}
    return make_block(spec, {"epsilon": eps})
