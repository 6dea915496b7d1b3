"""Plant FMU: export of the robot plant as an FMI 2.0 FMU (generated C, model exchange and
co-simulation in one binary), see :mod:`ivdrem.fmu.export`; the FMU as a block of the
closed loop: :func:`fmu_plant` (:mod:`ivdrem.fmu.plant`); one FMU instance, shared by the
plant block and the co-simulation: :class:`~ivdrem.fmu.instance.FmuInstance`.
"""
#: Default bound of the co-simulation RK4 sub-step (parameter ``cs_substep``), seconds
#: (defined here, not in the exporter: the command line's parser reads it without SymPy).
DEFAULT_SUBSTEP = 1e-3

__all__ = ["export_fmu", "generate_sources", "DEFAULT_SUBSTEP", "fmu_plant", "FmuInstance",
           "FmuError"]


def __getattr__(name):
    # imported on first use: fmpy and SymPy (the exporter's) load only when needed
    if name in ("export_fmu", "generate_sources"):
        from . import export
        value = getattr(export, name)
    elif name == "fmu_plant":
        from .plant import fmu_plant as value
    elif name in ("FmuInstance", "FmuError"):
        from . import instance
        value = getattr(instance, name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value
