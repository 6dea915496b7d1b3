"""Robot models: symbolic Euler-Lagrange models (sympy) and arms from URDF files, with their
generated regressor code.

See :mod:`ivdrem.models.euler_lagrange` for the model/data separation and the list of
generated functions, :mod:`ivdrem.models.urdf` (docs/models.md) for URDF arms.
"""
from .base import RobotModel
from .euler_lagrange import CODEGEN_VERSION, EulerLagrangeModel
from .robots import (MODEL_NAMES, TWO_LINK_THETA, get_model, model_names, planar_arm,
                     planar_physical_theta, two_link)
from .urdf import (ARM_NAMES, DEFAULT_FRICTION_WIDTH, RANK_RTOL, RigidBodyModel, URDFError,
                   arm, from_urdf)

__all__ = ["RobotModel", "EulerLagrangeModel", "RigidBodyModel", "CODEGEN_VERSION",
           "two_link", "planar_arm", "get_model", "model_names", "planar_physical_theta",
           "MODEL_NAMES", "TWO_LINK_THETA", "from_urdf", "arm", "ARM_NAMES", "URDFError",
           "RANK_RTOL", "DEFAULT_FRICTION_WIDTH"]
