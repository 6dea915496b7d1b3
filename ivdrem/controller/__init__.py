"""The sampled-data controller (fixed step h): building blocks of the discrete update.

So far: the sliding window of (15a) with bounded memory (:class:`BlockWindow`) and the
exact discrete update of the first-order filters of (7), (13), (14) and the averaging
(15b) (:mod:`ivdrem.controller.discrete`).  See docs/conventions.md for the equations.
"""
from .discrete import (averaging_factor, filter_step, mu_integral, mu_saturated,
                       observer_decay)
from .window import BlockWindow

__all__ = ["BlockWindow", "filter_step", "mu_saturated", "mu_integral", "observer_decay",
           "averaging_factor"]
