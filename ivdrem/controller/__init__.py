"""The sampled-data controller (fixed step h): the paper's controller (eqs. 7-21) as a
Python reference (:class:`SampledController`), a generated C library
(:mod:`ivdrem.controller.codegen`, :class:`ivdrem.controller.clib.CController`) and an FMI
2.0 co-simulation FMU (:func:`ivdrem.controller.fmu_export.export_controller_fmu`); the
building blocks of the discrete update: the sliding window of (15a) with bounded memory
(:class:`BlockWindow`) and the exact discrete update of the first-order filters of (7),
(13), (14) and the averaging (15b) (:mod:`ivdrem.controller.discrete`).  See
docs/controller.md.
"""
from .discrete import (averaging_factor, filter_step, mu_integral, mu_saturated,
                       observer_decay)
from .sampled import SAMPLED_LAWS, SampledController
from .window import BlockWindow

__all__ = ["BlockWindow", "filter_step", "mu_saturated", "mu_integral", "observer_decay",
           "averaging_factor", "SampledController", "SAMPLED_LAWS"]
