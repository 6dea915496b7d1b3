"""Block library: one module per subsystem; each factory returns a ct.NonlinearIOSystem.

Every block declares its ports, states and parameters up front (``sys.ivdrem``, a
:class:`~ivdrem.blocks._core.BlockSpec`) and supplies pure kernels shared by the
python-control reference path and the compiled path.
"""
from ._core import BlockSpec, make_block, ParameterError
from .plant import plant
from .sources import trajectory, disturbance, mu_schedule
from .tracking_error import tracking_error
from .torque_observer import torque_observer
from .control_law import control_law, DESIGNS, INJECTIONS, inertia_scaled_gain
from .adaptation_law import adaptation_law
from .regression_filter import regression_filter
from .instrument import instrument
from .extension import extension
from .sliding_window import sliding_window, transport_delay, windowed_integral
from .averaging import averaging
from .mixing import mixing
from .max_hold import max_hold
from .composite_terms import (drem_term, drem_channel_term, term_start, composite_learning_term, sigma_modification_term,
                              zero_term)

__all__ = ["BlockSpec", "make_block", "ParameterError", "plant", "trajectory", "disturbance",
           "mu_schedule", "tracking_error", "torque_observer", "control_law", "DESIGNS", "INJECTIONS", "inertia_scaled_gain", "adaptation_law",
           "regression_filter", "instrument", "extension", "sliding_window", "transport_delay",
           "windowed_integral", "averaging", "mixing", "max_hold", "drem_term", "drem_channel_term", "term_start",
           "composite_learning_term", "sigma_modification_term", "zero_term"]
