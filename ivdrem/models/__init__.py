"""Robot models: symbolic Euler-Lagrange models (sympy) and arms from URDF files, with their
generated regressor code.

See :mod:`ivdrem.models.euler_lagrange` for the model/data separation and the list of
generated functions, :mod:`ivdrem.models.urdf` (docs/models.md) for URDF arms,
:mod:`ivdrem.models.card` for a symbolic model read back without sympy.  The symbolic
names (``EulerLagrangeModel``, ``two_link``, ...) load sympy on first use, so that a run of
a cached model never imports it.
"""
from .base import RobotModel
from .card import CardModel
from .registry import MODEL_NAMES, get_model, model_names
from .urdf import (ARM_NAMES, DEFAULT_FRICTION_WIDTH, RANK_RTOL, RigidBodyModel, URDFError,
                   arm, from_urdf)

__all__ = ["RobotModel", "EulerLagrangeModel", "RigidBodyModel", "CardModel",
           "CODEGEN_VERSION", "two_link", "planar_arm", "get_model", "model_names",
           "planar_physical_theta", "MODEL_NAMES", "TWO_LINK_THETA", "from_urdf", "arm",
           "ARM_NAMES", "URDFError", "RANK_RTOL", "DEFAULT_FRICTION_WIDTH"]

#: names defined by the sympy modules, and where
_SYMBOLIC = {"EulerLagrangeModel": "euler_lagrange", "CODEGEN_VERSION": "euler_lagrange",
             "two_link": "robots", "planar_arm": "robots", "planar_physical_theta": "robots",
             "TWO_LINK_THETA": "robots"}


def __getattr__(name):
    if name in _SYMBOLIC:
        import importlib
        value = getattr(importlib.import_module(f"{__name__}.{_SYMBOLIC[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
