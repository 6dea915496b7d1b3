"""python-control's private evaluation of a diagram, in one file.

The reference engine evaluates a diagram with python-control's own interconnection code
(``InterconnectedSystem._rhs``, ``_out``, ``_compute_static_io``, with the parameters set by
``_update_params``).  These are private, so every use of them is here, checked against the
version below by ``tests/test_control_private.py``; a new python-control release is
supported by rerunning that test.

The parameters of a run are set on a private copy of the diagram (and of each of its
blocks), never on the caller's system: ``_update_params`` writes each block's current
parameters into the block.
"""
from __future__ import annotations

import copy

import numpy as np
import control as ct

# python-control's keyword handling, so that the drop-in (ivdrem.pycontrol) refuses and
# renames arguments with python-control's own messages
from control.config import _process_kwargs as process_kwargs
from control.config import _process_param as process_param
from control.timeresp import _timeresp_aliases as timeresp_aliases

#: the python-control release this file is written against (pyproject: >=0.10.1,<0.11)
SUPPORTED_CONTROL = ("0.10.1", "0.10.2")
#: the names of python-control's per-block evaluation frames, for finding the block that
#: raised in a traceback
BLOCK_FRAMES = ("_rhs", "_out")


class PrivateDiagram:
    """A copy of `diagram` with a run's parameter overrides `params` applied in
    python-control's merge order (block, diagram, call), evaluated by python-control.

    ===========  ===============================================================
    states  x    the diagram's states (nstates)
    inputs  ue   the diagram's external inputs (ninputs)
    outputs      rhs: dx/dt; out: the diagram outputs; block_inputs: every
                 block's inputs, in syslist order; signals: (dx/dt, block
                 outputs, block inputs) evaluated block by block in `order`
    params       `params` (dict), merged into each block's own
    ===========  ===============================================================
    """

    def __init__(self, diagram, params=None):
        d = copy.copy(diagram)
        # the blocks are copied too (their functions and ivdrem specs are shared): the
        # parameter update below replaces each block's current parameters in the copy
        d.syslist = [copy.copy(s) for s in diagram.syslist]
        d._update_params(params or {})
        self.diagram = d
        self.blocks = d.syslist        # in the caller's syslist order

    def rhs(self, t, x, ue):
        return self.diagram._rhs(t, x, ue)

    def out(self, t, x, ue):
        return self.diagram._out(t, x, ue)

    def block_inputs(self, t, x, ue):
        return self.diagram._compute_static_io(t, x, ue)[0]

    def signals(self, plan, t, x, ue):
        """(dx/dt, block outputs, block inputs) block by block in the plan's order:
        python-control's own fixed-point sweep does not settle on a NaN."""
        d = self.diagram
        C, M = np.asarray(d.connect_map), np.asarray(d.input_map)
        ys, dx = np.zeros(C.shape[1]), np.zeros(x.size)
        for k in plan.order:
            b, sys = plan.blocks[k], self.blocks[k]
            ub = C[b.u] @ ys + M[b.u] @ ue
            ys[b.y] = np.asarray(sys._out(t, x[b.x], ub), dtype=float).reshape(-1)
        us = C @ ys + M @ ue
        for b, sys in zip(plan.blocks, self.blocks):
            if sys.nstates:
                dx[b.x] = np.asarray(sys._rhs(t, x[b.x], us[b.u]), dtype=float).reshape(-1)
        return dx, ys, us

    def raising_block(self, exc):
        """(syslist index, t) of the innermost block evaluation on `exc`'s traceback that
        is one of this diagram's blocks, or None."""
        index = {id(s): k for k, s in enumerate(self.blocks)}
        found, tb = None, exc.__traceback__
        while tb is not None:
            frame = tb.tb_frame
            me = frame.f_locals.get("self") if frame.f_code.co_name in BLOCK_FRAMES else None
            if id(me) in index:
                found = (index[id(me)], frame.f_locals.get("t"))
            tb = tb.tb_next
        return found


def evaluate_output(system, t, x, u, params=None):
    """y = h(t, x, u) of one python-control system, evaluated on a copy of it with `params`
    merged in python-control's order (the caller's system is not written into)."""
    private = copy.copy(system)
    private._update_params(params or {})
    return np.asarray(private._out(t, x, u), dtype=float)


def control_version_supported():
    """True when the installed python-control is one this file is written against."""
    return ct.__version__ in SUPPORTED_CONTROL
