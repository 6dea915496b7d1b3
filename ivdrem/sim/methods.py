"""The integration methods: one registry that everything asking about a method reads (the
simulator, the cost guards, the co-simulation, the command line), never a method by name.
Adding a method is its step function in ``stepper.c`` and its row here (docs/simulation.md,
"Adding a method"); ``tests/test_methods.py`` checks every row.

This module imports nothing of ivdrem: every other module of ``sim`` may import it.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["MethodInfo", "METHOD_TABLE", "METHODS", "DEFAULT_METHOD", "STIFF_METHOD",
           "REFERENCE_METHOD", "DEFAULT_TOLERANCES", "method_info", "RK4", "DP45", "RODAS5P",
           "BS23"]


@dataclass(frozen=True)
class MethodInfo:
    """One row of the method table."""
    name: str
    id: int               # dispatch id of the stepper's method_step
    step: str             # the step function in stepper.c
    order: int            # order of the solution
    error_order: int      # order of the embedded solution the error is estimated by (0: none)
    adaptive: bool        # error-controlled steps (else fixed steps h)
    l_stable: bool
    dense_order: int      # order of the interpolant of outputs, history and max-hold samples
    dense_outputs: bool   # outputs read from the dense output (else the steps land on them)
    rtol: float           # default tolerances (of an adaptive method)
    atol: float
    user: bool            # offered to users (False: a stepper-internal method)
    description: str

    @property
    def fixed_step(self) -> bool:
        return not self.adaptive


#: Every method the stepper dispatches on, by name; the user methods first, the default
#: first of all.  Default tolerances: for the stiff method, the paper run's
#: theta_hat(300 s) is within 1e-6 relative of a 100x tighter run
#: (benchmarks/bench_paper.py measures it: 5.0e-7 in 5 863 steps; 1e-4 gave 1.9e-7 in
#: 7 165 steps, 3e-4 1.1e-6: too loose).
_ROWS = (
    MethodInfo("rodas5p", 2, "rodas5p_step", 5, 4, True, True, 4, True, 2e-4, 2e-6, True,
               "Rodas5P: L-stable, stiffly accurate Rosenbrock 5(4) with a fresh Jacobian "
               "each step, dense output of order 4"),
    MethodInfo("dp45", 1, "dp45_step", 5, 4, True, False, 3, False, 1e-6, 1e-8, True,
               "Dormand-Prince 5(4), explicit, error-controlled"),
    MethodInfo("rk4", 0, "rk4_step", 4, 0, False, False, 3, False, 1e-6, 1e-8, True,
               "classical Runge-Kutta 4, fixed step h"),
    # not a user method: the explicit steps a Rodas5P run takes while max-hold updates pin
    # its steps to the sampling grid (stepper's step_loop)
    MethodInfo("bs23", 3, "bs23_step", 3, 2, True, False, 3, True, 1e-6, 1e-8, False,
               "Bogacki-Shampine 3(2), explicit, FSAL: a Rodas5P run's pinned steps"),
)
_ALL = {m.name: m for m in _ROWS}
if len({m.id for m in _ROWS}) != len(_ROWS):           # pragma: no cover - a table typo
    raise RuntimeError("two methods share a dispatch id")

#: The user methods, by name (the first is the default).
METHOD_TABLE = {name: m for name, m in _ALL.items() if m.user}
#: Names of the user methods (``simulate(..., method=NAME)``).
METHODS = tuple(METHOD_TABLE)
#: The method of a run that names none: Rodas5P (stiff, L-stable).
DEFAULT_METHOD = "rodas5p"
#: the method a StiffnessWarning recommends (L-stable)
STIFF_METHOD = "rodas5p"
#: the fixed-step method of the all-Python reference run that the FMU co-simulation check
#: compares against (its O(h^4) error far below the coupling's O(H), ivdrem.fmu.cosim)
REFERENCE_METHOD = "rk4"
#: default (rtol, atol) per user method
DEFAULT_TOLERANCES = {name: (m.rtol, m.atol) for name, m in METHOD_TABLE.items()}

# the dispatch ids, named for the stepping code (_stepper_codes.py; stepper.c gets them from
# the generated header)
#: Dispatch id of fixed-step RK4.
RK4 = _ALL["rk4"].id
#: Dispatch id of Dormand-Prince 5(4).
DP45 = _ALL["dp45"].id
#: Dispatch id of Rodas5P.
RODAS5P = _ALL["rodas5p"].id
#: Dispatch id of Bogacki-Shampine 3(2) (the pinned steps of a Rodas5P run).
BS23 = _ALL["bs23"].id


def method_info(method) -> MethodInfo:
    """The table row of a user method's name; an unknown name is an error naming the valid
    ones."""
    if not isinstance(method, str) or method not in METHOD_TABLE:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    return METHOD_TABLE[method]


def all_methods():
    """Every row, the stepper-internal methods too (the generic suite tests them all)."""
    return _ROWS
