"""Max-hold of (Y_b, Psi_b) at t_e = argmax lambda_min(Psi_b) (composite learning, eq. 35)."""
from __future__ import annotations

import numpy as np

from ._core import BlockSpec, make_block
from . import _validate as checks


def max_hold(nvec, nmat, epsilon=1e-9, *, dt_sample=1e-3, input="window_y", output="held",
             score="lambda_min_held", name="max_hold"):
    """Hold the input [v (nvec), A (nmat x nmat)] at the sampling time maximising lambda_min(A).

    lambda_min of the symmetric part of A is sampled on the fixed grid t0 + k dt_sample,
    read from the integrator's dense output, so the held value and the hold time t_e do not
    depend on the step sequence or the method.  The hold updates when the sample beats both
    the running maximum and epsilon; the simulator ends a step at each update, which is a
    discontinuity of the right-hand side.  Before the first update the output is zero.
    python-control cannot simulate this block.

    ======  ==========================================================
    states  none (the held values live in the simulator)
    inputs  <input>[nvec + nmat*nmat]
    output  <output>[nvec + nmat*nmat], <score> (lambda_min at t_e, 0 before)
    params  epsilon > 0, dt_sample > 0 (s, sampling period of lambda_min)
    ======  ==========================================================
    """
    eps = checks.scalar(name, "epsilon", epsilon, positive=True)
    dts = checks.scalar(name, "dt_sample", dt_sample, positive=True)
    size = nvec + nmat * nmat
    spec = BlockSpec(name=name, inputs=[(input, size)], outputs=[(output, size), (score, 1)],
                     states=[], x0=np.zeros(0), param_names=("epsilon", "dt_sample"),
                     output=None, kind="maxhold",
                     info={"epsilon": eps, "nvec": nvec, "nmat": nmat, "size": size})

    spec.validate = lambda p: {**p,
                               "epsilon": checks.scalar(name, "epsilon", p["epsilon"], positive=True),
                               "dt_sample": checks.scalar(name, "dt_sample", p["dt_sample"],
                                                     positive=True)}
    return make_block(spec, {"epsilon": eps, "dt_sample": dts})
