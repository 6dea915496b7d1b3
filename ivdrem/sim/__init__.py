"""Simulators for diagrams with transport delays and max-holds (reference + compiled)."""
from .simulator import simulate, Simulator, SimulationError, METHODS, ENGINES
from .plan import DiagramPlan, AlgebraicLoopError

__all__ = ["simulate", "Simulator", "SimulationError", "METHODS", "ENGINES", "DiagramPlan",
           "AlgebraicLoopError"]
