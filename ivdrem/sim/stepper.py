"""The compiled stepper: the stepping template compiled once, for every diagram.

The stepping code (:mod:`ivdrem.sim._template`: the methods, the loop, the history and
max-hold helpers) is the same for every diagram; only the four diagram functions it calls
differ (``diagram_eval``, ``diagram_jacobian``, ``newton_factor``, ``newton_solve``).  If
the template were pasted into each diagram's module, numba would compile all of it again
for every law, robot or rewiring (most of a cold first run).  Instead this module
generates, once per version of the template, a *stepper module* in which those four names
are small trampolines that call the diagram's functions by address (``call_c``):

* each diagram's module (:mod:`ivdrem.sim.compiled`) adds C-callable wrappers of its
  functions (numba ``cfunc``, cached), whose addresses the simulator puts in the
  workspace field ``fns``;
* a trampoline packs the workspace into a table of addresses and shapes (field ``tab``),
  calls the wrapper, and the wrapper rebuilds the same workspace from the table (numba
  ``carray``), so the diagram code sees exactly the arrays the loop owns.

Addresses are runtime values, so both modules stay cacheable on disk.  A diagram function
that raises (a block's kernel) cannot propagate the exception through C: its wrapper
returns ``BLOCK_RAISED`` and the trampoline raises :data:`BLOCK_RAISED_MESSAGE`; the
simulator then re-evaluates the diagram from Python to report the block's own error.
"""
from __future__ import annotations

import re
from pathlib import Path

from .. import __version__
from . import _template
from .simulator import WORKSPACE_LAYOUT, BLOCK_RAISED_MESSAGE

__all__ = ["stepper_source", "wrapper_source", "BLOCK_RAISED", "BLOCK_RAISED_MESSAGE",
           "TRAMPOLINES"]

#: status a C-callable wrapper returns when a kernel or the diagram function raised
BLOCK_RAISED = _template.BLOCK_RAISED
#: the diagram functions, in the order of the workspace field ``fns``
TRAMPOLINES = ("diagram_eval", "diagram_jacobian", "newton_factor", "newton_solve")

_FIELD = {name: i for i, (name, _, _) in enumerate(WORKSPACE_LAYOUT)}


def _pack_source():
    """pack_workspace(W): W's arrays as (address, rows, cols) triples in W.tab."""
    tab = _FIELD["tab"]
    lines = ["def pack_workspace(W):", f"    tab = W[{tab}]"]
    for i, (name, _, ndim) in enumerate(WORKSPACE_LAYOUT):
        lines.append(f"    tab[{3 * i}] = W[{i}].ctypes.data")
        lines.append(f"    tab[{3 * i + 1}] = W[{i}].shape[0]")
        lines.append(f"    tab[{3 * i + 2}] = " + (f"W[{i}].shape[1]" if ndim == 2 else "0"))
    lines.append("    return tab.ctypes.data")
    return "\n".join(lines) + "\n"


def _unpack_source():
    """unpack_workspace(address): the workspace of pack_workspace, as numba carrays."""
    lines = ["def unpack_workspace(address):",
             f"    tab = carray(int_pointer(address), {3 * len(WORKSPACE_LAYOUT)})",
             "    return Workspace("]
    for i, (name, dtype, ndim) in enumerate(WORKSPACE_LAYOUT):
        ptr = "float_pointer" if dtype == "float64" else "int_pointer"
        shape = f"(tab[{3 * i + 1}], tab[{3 * i + 2}])" if ndim == 2 else f"(tab[{3 * i + 1}],)"
        lines.append(f"        carray({ptr}(tab[{3 * i}]), {shape}),")
    lines.append("    )")
    return "\n".join(lines) + "\n"


_TRAMPOLINES = f'''
def _raised(st):
    if st == {BLOCK_RAISED}:
        raise RuntimeError("{BLOCK_RAISED_MESSAGE}")
    return st


def diagram_eval(mode, t, x, P, W, out):
    tab = pack_workspace(W)
    return _raised(call_c(W[{_FIELD["fns"]}][0], (mode, t, x.ctypes.data, x.shape[0],
                                               P.ctypes.data, P.shape[0], tab,
                                               out.ctypes.data, out.shape[0])))


def diagram_jacobian(t, x, P, W, J):
    tab = pack_workspace(W)
    return _raised(call_c(W[{_FIELD["fns"]}][1], (t, x.ctypes.data, x.shape[0], P.ctypes.data,
                                               P.shape[0], tab, J.ctypes.data)))


def newton_factor(W, J, c, LU, piv):
    return _raised(call_c(W[{_FIELD["fns"]}][2], (J.ctypes.data, J.shape[0], c,
                                               LU.ctypes.data, piv.ctypes.data)))


def newton_solve(W, LU, piv, b):
    _raised(call_c(W[{_FIELD["fns"]}][3], (LU.ctypes.data, piv.ctypes.data, b.ctypes.data,
                                        b.shape[0])))
'''

#: the C signatures of the wrappers (all pointers and sizes int64)
WRAPPER_SIGNATURES = {
    "diagram_eval": "int32(int64, float64, int64, int64, int64, int64, int64, int64, int64)",
    "diagram_jacobian": "int32(float64, int64, int64, int64, int64, int64, int64)",
    "newton_factor": "int32(int64, int64, float64, int64, int64)",
    "newton_solve": "int32(int64, int64, int64, int64)",
}


def wrapper_source():
    """The C-callable wrappers a diagram module appends (after its diagram functions and
    its sparse_factor / sparse_solve)."""
    s = WRAPPER_SIGNATURES
    return f'''
# ---- C-callable wrappers called by the shared stepper (ivdrem/sim/stepper.py)
@cfunc("{s["diagram_eval"]}", cache=True)
def diagram_eval_c(mode, t, xp, n, pp, np_, tab, outp, nout):
    x = carray(float_pointer(xp), (n,))
    P = carray(float_pointer(pp), (np_,))
    W = unpack_workspace(tab)
    out = carray(float_pointer(outp), (nout,))
    try:
        return diagram_eval(mode, t, x, P, W, out)
    except Exception:
        return {BLOCK_RAISED}


@cfunc("{s["diagram_jacobian"]}", cache=True)
def diagram_jacobian_c(t, xp, n, pp, np_, tab, jp):
    x = carray(float_pointer(xp), (n,))
    P = carray(float_pointer(pp), (np_,))
    W = unpack_workspace(tab)
    J = carray(float_pointer(jp), (n, n))
    try:
        return diagram_jacobian(t, x, P, W, J)
    except Exception:
        return {BLOCK_RAISED}


@cfunc("{s["newton_factor"]}", cache=True)
def newton_factor_c(jp, n, c, lup, pivp):
    J = carray(float_pointer(jp), (n, n))
    LU = carray(float_pointer(lup), (n, n))
    piv = carray(int_pointer(pivp), (n,))
    return sparse_factor(J, c, LU, piv)


@cfunc("{s["newton_solve"]}", cache=True)
def newton_solve_c(lup, pivp, bp, n):
    LU = carray(float_pointer(lup), (n, n))
    piv = carray(int_pointer(pivp), (n,))
    b = carray(float_pointer(bp), (n,))
    sparse_solve(LU, piv, b)
    return 0
'''


def stepper_source():
    """Source of the stepper module: the template, the workspace (un)packing and the
    trampolines, every function compiled by numba with its machine code cached."""
    tsrc = Path(_template.__file__).read_text()
    template_names = re.findall(r"^def\s+(\w+)\s*\(", tsrc, flags=re.M)
    own = ["pack_workspace", "unpack_workspace", "_raised", *TRAMPOLINES]
    out = [f"# Generated by ivdrem {__version__}: the shared stepper. Do not edit.",
           "import math", "import numpy as np", "from numba import njit, carray",
           "from ivdrem.sim._native import call_c, float_pointer, int_pointer",
           "from ivdrem.sim.simulator import Workspace", "",
           "# ---- stepping template (ivdrem/sim/_template.py, verbatim)", tsrc,
           "# ---- the workspace as a table of addresses and shapes, and back",
           _pack_source(), _unpack_source(),
           "# ---- the diagram functions, called by address", _TRAMPOLINES,
           f"_JIT = {sorted(set(template_names + own))!r}",
           "for _n in _JIT:\n    globals()[_n] = njit(cache=True)(globals()[_n])\n"]
    return "\n".join(out)
