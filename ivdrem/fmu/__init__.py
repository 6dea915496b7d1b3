"""Plant FMU: export of the robot plant as an FMI 2.0 FMU (generated C, model exchange and
co-simulation in one binary), see :mod:`ivdrem.fmu.export`; the FMU as a python-control
block: :func:`ivdrem.blocks.fmu_plant.fmu_plant`.
"""
from .export import DEFAULT_SUBSTEP, export_fmu, generate_sources

__all__ = ["export_fmu", "generate_sources", "DEFAULT_SUBSTEP"]
