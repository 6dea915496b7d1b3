"""Symbolic Euler-Lagrange robot models (sympy) and generated regressor code.

See :mod:`ivdrem.models.euler_lagrange` for the model/data separation and the list of
generated functions.
"""
from .euler_lagrange import CODEGEN_VERSION, EulerLagrangeModel
from .robots import (MODEL_NAMES, TWO_LINK_THETA, get_model, planar_arm,
                     planar_physical_theta, two_link)

__all__ = ["EulerLagrangeModel", "CODEGEN_VERSION", "two_link", "planar_arm", "get_model",
           "planar_physical_theta", "MODEL_NAMES", "TWO_LINK_THETA"]
