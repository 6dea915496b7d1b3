"""python-control's private evaluation of a diagram, in one file.

The reference engine evaluates a diagram with python-control's own interconnection code
(``InterconnectedSystem._rhs``, ``_out``, ``_compute_static_io``, with the parameters set by
``_update_params``).  These are private, so every use of them is here, checked against the
version below by ``tests/test_control_private.py``; a new python-control release is
supported by rerunning that test.

The parameters of a run are set on a private copy of the diagram (and of each of its
blocks), never on the caller's system: ``_update_params`` writes each block's current
parameters into the block.

:class:`SparseInterconnect` is python-control's InterconnectedSystem with its three maps
kept sparse (a real arm's loop: 12,937 block inputs x 12,487 block outputs, 1.2 GiB dense
for 12,937 entries); :func:`sparse_maps` reads the maps of any InterconnectedSystem spar
:func:`flatten` turns a nested diagram (or one block) into the one-level diagram the
simulator runs (``simulate`` and the drop-in :mod:`ivdrem.pycontrol` both call it).
"""
from __future__ import annotations

import copy
import warnings

import numpy as np
import control as ct
from scipy import sparse
from scipy.linalg import block_diag

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


#: the maps of python-control's InterconnectedSystem, in the order :func:`sparse_maps` returns
MAP_NAMES = ("connect_map", "input_map", "output_map")


def _map_property(name):
    """A map attribute of :class:`SparseInterconnect`: reading it gives python-control's
    dense array, built from the sparse one on first read and kept from then on (the
    caller may write into it, as into python-control's own); writing it (python-control's
    ``set_connect_map`` and its siblings) keeps what is written."""
    key = "_" + name

    def read(self):
        value = self.__dict__[key]
        if sparse.issparse(value):
            value = value.toarray()
            self.__dict__[key] = value
        return value

    def write(self, value):
        if self.__dict__.get("_constructing", False):
            # python-control's constructor: its all-zero dense map (np.zeros: pages the
            # OS maps only when written, and nothing writes them), dropped at once
            return
        self.__dict__[key] = value

    return property(read, write, doc=f"python-control's ``{name}`` (dense on first read)")


class SparseInterconnect(ct.InterconnectedSystem):
    """python-control's InterconnectedSystem of `syslist` whose connect_map, input_map and
    output_map are given as scipy.sparse arrays and kept so (:func:`sparse_maps` reads
    them); its inputs, outputs, states, parameters and evaluation are python-control's.

    Reading ``connect_map`` (or another map) gives the dense array python-control would
    hold, built then; ivdrem's simulator never reads them so.  `connection_type` is what
    ``ct.interconnect`` records ("implicit": connected by signal name).
    """

    connect_map = _map_property("connect_map")
    input_map = _map_property("input_map")
    output_map = _map_property("output_map")

    def __init__(self, syslist, connect_map, input_map, output_map, *, inputs, outputs,
                 name=None, params=None, connection_type="implicit", **kwargs):
        self.__dict__["_constructing"] = True
        try:
            # no connections, inputs or outputs given: python-control's maps stay zero
            super().__init__(syslist, connections=None, inplist=None, outlist=None,
                             inputs=list(inputs), outputs=list(outputs), name=name,
                             params=params, connection_type=connection_type, **kwargs)
        finally:
            self.__dict__["_constructing"] = False
        nu = sum(s.ninputs for s in self.syslist)
        ny = sum(s.noutputs for s in self.syslist)
        for key, value, shape in (("connect_map", connect_map, (nu, ny)),
                                  ("input_map", input_map, (nu, self.ninputs)),
                                  ("output_map", output_map, (self.noutputs, ny + nu))):
            value = sparse.csr_array(value, dtype=float)
            if value.shape != shape:
                raise ValueError(f"{key} has shape {value.shape}, the blocks need {shape}")
            self.__dict__["_" + key] = value


def sparse_maps(diagram):
    """(connect_map, input_map, output_map) of an InterconnectedSystem as scipy.sparse CSR
    arrays (float64, column indices sorted in each row, no stored zeros): a
    :class:`SparseInterconnect`'s own, or python-control's dense maps converted.  The
    entries are the maps' own values; reading them row by row visits them in the order
    ``np.nonzero`` of the dense map gives."""
    out = []
    for name in MAP_NAMES:
        value = diagram.__dict__.get("_" + name) \
            if isinstance(diagram, SparseInterconnect) else None
        if value is None:
            value = getattr(diagram, name)
        if sparse.issparse(value):
            value = sparse.csr_array(value, dtype=float, copy=True)
        else:
            value = sparse.csr_array(np.asarray(value, dtype=float))
        value.eliminate_zeros()
        value.sum_duplicates()
        value.sort_indices()
        out.append(value)
    return tuple(out)


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
        C, M, _ = plan.maps
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


# ------------------------------------------------ a nested diagram as one level (flatten)
def _leaf(system):
    """A system the simulator takes as a block: a TransferFunction becomes its state-space
    form (python-control's own conversion, names kept)."""
    if isinstance(system, ct.TransferFunction):
        return ct.ss(system, name=system.name, inputs=system.input_labels,
                     outputs=system.output_labels)
    if not isinstance(system, ct.NonlinearIOSystem):
        raise TypeError(f"System of type {type(system)} not valid: ivdrem simulates "
                        "python-control input/output systems")
    return system


def _flat_maps(system):
    """(leaves, C, M, OY, OU) of `system` over its leaf systems' stacked inputs U and
    outputs Y: U = C Y + M u, y = OY Y + OU U (u, y: the system's own inputs and outputs;
    python-control's output map reads subsystem outputs and subsystem inputs).  A nested
    InterconnectedSystem is expanded; an output map that reads a nested subsystem's input
    passes it through, which is solved for as python-control's static sweep would."""
    if not isinstance(system, ct.InterconnectedSystem):
        leaf = _leaf(system)
        p, q = leaf.ninputs, leaf.noutputs
        return [leaf], np.zeros((p, q)), np.eye(p), np.eye(q), np.zeros((q, p))
    parts = [_flat_maps(s) for s in system.syslist]
    leaves = [leaf for part in parts for leaf in part[0]]
    Cb, Mb, OYb, OUb = (block_diag(*[part[k] for part in parts]) for k in range(1, 5))
    # a nested diagram's own maps, dense for the algebra below (diagrams a user nests)
    Cd, Md, Od = (m.toarray() for m in sparse_maps(system))
    nys = Cd.shape[1]
    Ody, Odu = Od[:, :nys], Od[:, nys:]          # subsystem outputs, subsystem inputs
    # the subsystems' outputs in the leaves' signals: y_sub = P Y + Q u_sub
    P, Q = OYb + OUb @ Cb, OUb @ Mb
    # the subsystems' inputs: u_sub = Cd y_sub + Md u, solved for u_sub
    try:
        A = np.linalg.inv(np.eye(Cd.shape[0]) - Cd @ Q)
    except np.linalg.LinAlgError:
        raise ValueError(f"system '{system.name}' has an algebraic loop through the inputs "
                         "its subsystems pass straight to their outputs") from None
    C = Cb + Mb @ A @ Cd @ P
    M = Mb @ A @ Md
    OY, OU = Ody @ OYb, Ody @ OUb
    if np.any(Odu):
        # an output reading a subsystem input: u_sub = Mb^+ (U - Cb Y), exact when every
        # subsystem input reaches a leaf input (Mb of full column rank)
        if np.linalg.matrix_rank(Mb) < Mb.shape[1]:
            raise ValueError(f"system '{system.name}' reads a subsystem input that no leaf "
                             "system receives: it cannot be flattened")
        Mp = np.linalg.pinv(Mb)
        OY, OU = OY - Odu @ Mp @ Cb, OU + Odu @ Mp
    return leaves, C, M, OY, OU


def _merged_params(system):
    """The parameters of every interconnection level, the outer ones overriding (the order
    of python-control's ``InterconnectedSystem._update_params``)."""
    if not isinstance(system, ct.InterconnectedSystem):
        return {}
    merged = {}
    for s in system.syslist:
        merged.update(_merged_params(s))
    merged.update(system.params)
    return merged


def flatten(system):
    """`system` as a one-level ``InterconnectedSystem`` of its leaf systems (a plain
    system: a diagram of one block; a TransferFunction: its state-space form), with the
    same inputs, outputs and state order.  The system given is not changed (a one-level
    diagram of plain blocks is returned as it is, its maps unread)."""
    if not isinstance(system, ct.InterconnectedSystem) or \
            any(isinstance(s, ct.InterconnectedSystem) for s in system.syslist) or \
            any(isinstance(s, ct.TransferFunction) for s in system.syslist):
        leaves, C, M, OY, OU = _flat_maps(system)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")     # no connections given: none are "unused"
            flat = ct.InterconnectedSystem(
                leaves, inputs=list(system.input_labels),
                outputs=list(system.output_labels), params=_merged_params(system),
                name=system.name)
        flat.set_connect_map(C)
        flat.set_input_map(M)
        flat.set_output_map(np.hstack([OY, OU]))
        return flat
    return system
