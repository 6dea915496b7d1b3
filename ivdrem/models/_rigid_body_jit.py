"""numba-compiled versions of the kernels of :mod:`ivdrem.models.rigid_body`, compiled once
(and cached on disk by numba) for every URDF model: the models' own code only calls them
with its constant chain arrays, so a new arm compiles only its thin functions.

Every kernel is rebound to this module's namespace, so that a kernel calling another one
calls its compiled version.
"""
import types

import numba
import numpy as np  # noqa: F401  (the kernels' global)

from . import rigid_body as _src

SINGULAR_INERTIA_MESSAGE = _src.SINGULAR_INERTIA_MESSAGE
PIVOT_RTOL = _src.PIVOT_RTOL

for _fn in _src.KERNELS:
    globals()[_fn.__name__] = numba.njit(cache=True)(
        types.FunctionType(_fn.__code__, globals(), _fn.__name__, _fn.__defaults__))
del _fn
