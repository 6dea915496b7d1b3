"""Simulators for diagrams with transport delays and max-holds (reference + compiled)."""
from .methods import (METHODS, METHOD_TABLE, DEFAULT_METHOD, STIFF_METHOD,
                      DEFAULT_TOLERANCES, MethodInfo, method_info)
from .simulator import simulate, Simulator, SimulationError, StiffnessWarning, ENGINES, Workspace
from .plan import DiagramPlan, AlgebraicLoopError, SignalSizeError
from .foreign import declare_feedthrough, PythonBlockNotice
from .compiled import CCompilerMissing
from .sampled import sampled, continuous_diagram

__all__ = ["simulate", "Simulator", "SimulationError", "StiffnessWarning", "METHODS",
           "METHOD_TABLE", "DEFAULT_METHOD", "STIFF_METHOD", "DEFAULT_TOLERANCES", "ENGINES",
           "MethodInfo", "Workspace", "method_info", "DiagramPlan", "AlgebraicLoopError",
           "SignalSizeError", "declare_feedthrough", "PythonBlockNotice", "CCompilerMissing",
           "sampled", "continuous_diagram"]
