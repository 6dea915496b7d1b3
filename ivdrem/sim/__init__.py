"""Simulators for diagrams with transport delays and max-holds (reference + compiled).

The names below are imported from their modules when first used (PEP 562), so that
importing one light submodule (the method table :mod:`.methods`, the C stepper's
compiler check) does not import python-control: the command line checks its options
with them before the heavy imports."""
import importlib
import sys
import types

class _Package(types.ModuleType):
    """``sampled`` names both a submodule and its function: the package's name is the
    function (``ivdrem.sim.sampled(sys)``), also after the import system set it to the
    submodule when that was first imported (the modules here import the submodule's names
    with ``from .sampled import ...``)."""

    @property
    def sampled(self):
        return importlib.import_module(f"{__name__}.sampled").sampled

    @sampled.setter
    def sampled(self, value):      # the import system naming the submodule: kept as is
        pass


sys.modules[__name__].__class__ = _Package

#: name -> the submodule that defines it
_HOME = {
    "METHODS": "methods", "METHOD_TABLE": "methods", "DEFAULT_METHOD": "methods",
    "STIFF_METHOD": "methods", "DEFAULT_TOLERANCES": "methods", "MethodInfo": "methods",
    "method_info": "methods",
    "simulate": "simulator", "Simulator": "simulator", "SimulationError": "simulator",
    "StiffnessWarning": "simulator", "ENGINES": "simulator", "Workspace": "simulator",
    "DiagramPlan": "plan", "AlgebraicLoopError": "plan", "SignalSizeError": "plan",
    "declare_feedthrough": "foreign", "PythonBlockNotice": "foreign",
    "CCompilerMissing": "compiled",
    "sampled": "sampled", "continuous_diagram": "sampled",
}

__all__ = list(_HOME)


def __getattr__(name):
    home = _HOME.get(name)
    if home is None:      # a submodule not imported yet (``ivdrem.sim.guards``)
        try:
            return importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(f".{home}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_HOME))
