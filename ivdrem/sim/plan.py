"""What the simulator needs to know about a diagram, read off python-control's structures.

The plan is computed from the InterconnectedSystem itself (its ``syslist``,
``connect_map``, ``input_map`` and ``output_map``), so a user's rewired diagram is
simulated exactly as python-control wires it.  The maps are read sparse
(:func:`ivdrem.sim._control.sparse_maps`): a real arm's connection map is 1.2 GiB dense
for its 12,937 entries.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import control as ct

from ..blocks._core import effective_params
from ._control import sparse_maps
from .foreign import direct_inputs

__all__ = ["DiagramPlan", "AlgebraicLoopError", "SignalSizeError", "check_signal_sizes",
           "signal_sizes"]


class AlgebraicLoopError(ValueError):
    """Blocks whose outputs depend on each other's outputs without a state in between."""


class SignalSizeError(ValueError):
    """A vector output wired by name to an input of another size."""


def signal_sizes(labels):
    """{base name: size} of vector signals labelled ``name[i]`` (plain labels count 1)."""
    return Counter(lab.split("[", 1)[0] for lab in labels)


@lru_cache(maxsize=256)
def _signal_entries(labels):
    """(block's (base, entry, size) per label) of a tuple of labels: read once per process
    for the same labels (a diagram's sizes are checked when it is built and again when it
    is simulated; a real arm's loop has 12,937 input labels)."""
    sizes = signal_sizes(labels)
    return tuple((b, i, sizes[b]) for b, i in _signals(labels))


def _signals(labels):
    """[(base name, entry index)] per label; a plain label is entry 0 of itself."""
    out = []
    for lab in labels:
        base, _, rest = lab.partition("[")
        try:
            idx = int(rest.rstrip("]")) if rest else 0
        except ValueError:
            base, idx = lab, 0
        out.append((base, idx))
    return out


def rows_with_entries(m):
    """Boolean per row of a :func:`sparse_maps` map: the row has an entry (they store no
    zeros)."""
    return np.diff(m.indptr) > 0


def columns_with_entries(m):
    """Boolean per column of a :func:`sparse_maps` map: the column has an entry."""
    return np.bincount(m.indices, minlength=m.shape[1]) > 0


def check_signal_sizes(diagram, maps=None):
    """Raise SignalSizeError where an output vector is wired entry by entry (``y[i]`` to
    ``u[i]``, as ct.interconnect connects signals of the same name) to an input vector of
    another size and the surplus entries would be lost silently: output entries wired
    nowhere, or input entries fed by nothing.

    Wiring that re-indexes on purpose (``y[1]`` to ``u[0]``), and an input vector assembled
    from several signals, are not errors.  `maps`: the diagram's :func:`sparse_maps` when
    the caller has them.
    """
    C, Cin, _ = sparse_maps(diagram) if maps is None else maps
    outs, ins = [], []            # per absolute index: (block, base, entry, size)
    for sys in diagram.syslist:
        for kind, acc in (("output", outs), ("input", ins)):
            labels = tuple(getattr(sys, f"{kind}_labels"))
            acc += [(sys.name, *e) for e in _signal_entries(labels)]
    fed = rows_with_entries(C) | rows_with_entries(Cin)       # inputs with a source
    used = columns_with_entries(C)                              # outputs wired somewhere
    seen = set()
    for i, j in zip(*C.nonzero()):
        bi, si, ki, ni = ins[i]
        bo, so, ko, no = outs[j]
        if ki != ko or ni == no or (bi, si, bo, so) in seen:
            continue
        seen.add((bi, si, bo, so))
        # only a real loss is an error: output entries that go nowhere, or input entries
        # fed by nothing (a vector input assembled from several signals is fine)
        if no > ni:
            rest = [jj for jj, (b, sg, k, _) in enumerate(outs) if (b, sg) == (bo, so) and k >= ni]
            if any(used[jj] for jj in rest):
                continue
        else:
            rest = [ii for ii, (b, sg, k, _) in enumerate(ins) if (b, sg) == (bi, si) and k >= no]
            if any(fed[ii] for ii in rest):
                continue
        raise SignalSizeError(
            f"block '{bo}' output {so!r} has {no} entries but is wired to block '{bi}' "
            f"input {si!r}, which has {ni}: {so}[{min(ni, no)}:] would be "
            f"{'dropped' if no > ni else 'missing'}. Give both the same size.")


@dataclass
class BlockEntry:
    index: int
    sys: object
    spec: object            # BlockSpec or None (a plain nlsys)
    x: slice
    u: slice
    y: slice
    direct_inputs: np.ndarray   # absolute input indices the outputs depend on


@dataclass
class DiagramPlan:
    """What a simulation needs from a diagram, read once: its blocks with their slices of
    the state, input and output vectors, the initial state, the connection map, the
    blocks' evaluation order (direct feedthrough), the transport delays and the max-holds;
    ``maps``: the diagram's (connect_map, input_map, output_map), sparse."""
    diagram: object
    blocks: list
    x0: np.ndarray
    conn: list              # per absolute input index: [(output index, gain)]
    order: list             # block indices in output-evaluation order
    delays: list = field(default_factory=list)   # dicts: block, off, size, T, hermite, u, du
    holds: list = field(default_factory=list)    # dicts: block, off, size, nvec, nmat, eps, dt, u
    nd: int = 0
    nh: int = 0

    @classmethod
    def from_diagram(cls, diagram, x0=None, params=None):
        if not isinstance(diagram, ct.InterconnectedSystem):
            raise TypeError("simulate() needs a ct.InterconnectedSystem (from ct.interconnect "
                            f"or ivdrem.diagrams), got {type(diagram).__name__}")
        reached = check_params(diagram, params) if params else []
        blocks = []
        xi = ui = yi = 0
        for k, sys in enumerate(diagram.syslist):
            spec = getattr(sys, "ivdrem", None)
            nx, nu, ny = sys.nstates, sys.ninputs, sys.noutputs
            # what the block says (BlockSpec.direct, D of a StateSpace, a declaration),
            # else a numerical probe of its output function (ivdrem.sim.foreign)
            p = None if spec is not None else effective_params(sys, diagram, params)
            direct = [ui + i for i in direct_inputs(sys, p)]
            blocks.append(BlockEntry(k, sys, spec, slice(xi, xi + nx), slice(ui, ui + nu),
                                     slice(yi, yi + ny), np.array(direct, dtype=int)))
            xi += nx
            ui += nu
            yi += ny
        if x0 is None:
            parts = []
            # a diagram's start values for blocks that declare none (closed_loop: the
            # experiment's q(0), q̇(0) for a user's plant), by block and state name
            start = getattr(diagram, "ivdrem_start", None) or {}
            for b in blocks:
                if b.spec is not None:
                    parts.append(np.asarray(b.spec.x0, float))
                else:
                    x = np.zeros(b.sys.nstates)
                    given = start.get(b.sys.name, {})
                    for i, label in enumerate(b.sys.state_labels):
                        if label in given:
                            x[i] = given[label]
                    parts.append(x)
            x0 = np.concatenate(parts) if parts else np.zeros(0)
        else:
            x0 = np.asarray(x0, float).reshape(-1)
            if x0.size != diagram.nstates:
                raise ValueError(f"x0 has {x0.size} entries, the diagram has "
                                 f"{diagram.nstates} states")
        maps = sparse_maps(diagram)
        check_signal_sizes(diagram, maps)
        cmap = maps[0]              # CSR: each row's sources in column order
        ptr, src, gain = cmap.indptr, cmap.indices.tolist(), cmap.data.tolist()
        conn = [list(zip(src[ptr[i]:ptr[i + 1]], gain[ptr[i]:ptr[i + 1]]))
                for i in range(cmap.shape[0])]
        plan = cls(diagram, blocks, x0, conn, [])
        plan.maps = maps
        plan.params = dict(params or {})
        plan._block_params = {}
        # the overrides, checked once here: every name known, every block they reach
        # validated (its validated parameters kept for the engines)
        for k in reached:
            plan.block_params(blocks[k])
        plan.order = plan._topological_order()
        plan._collect_special()
        return plan

    def output_owner(self):
        owner = np.empty(sum(b.sys.noutputs for b in self.blocks), dtype=int)
        for b in self.blocks:
            owner[b.y] = b.index
        return owner

    def _topological_order(self):
        owner = self.output_owner()
        deps = {}
        for b in self.blocks:
            d = set()
            if b.spec is None or b.spec.kind == "ode":
                for i in b.direct_inputs:
                    for j, _ in self.conn[i]:
                        d.add(int(owner[j]))
            deps[b.index] = d
        order, state = [], {}

        def visit(k, stack):
            if state.get(k) == 2:
                return
            if state.get(k) == 1:
                cyc = stack[stack.index(k):] + [k]
                names = " -> ".join(self.blocks[i].sys.name for i in cyc)
                raise AlgebraicLoopError(f"algebraic loop through blocks: {names}")
            state[k] = 1
            stack.append(k)
            for j in sorted(deps[k]):
                visit(j, stack)
            stack.pop()
            state[k] = 2
            order.append(k)
        for b in self.blocks:
            visit(b.index, [])
        return order

    def block_params(self, b):
        """Validated parameters block b sees in this run (python-control merge order),
        validated once per plan."""
        key = (b.index, id(b.spec))     # a block without a spec may be given one later
        if key not in self._block_params:
            p = effective_params(b.sys, self.diagram, self.params)
            if b.spec is not None and b.spec.validate is not None:
                p = b.spec.validate(p)
            self._block_params[key] = p
        return self._block_params[key]

    def _collect_special(self):
        nd = nh = 0
        for b in self.blocks:
            spec = b.spec
            if spec is None or spec.kind == "ode":
                continue
            p = self.block_params(b)
            if spec.kind == "delay":
                size = spec.info["size"]
                hermite = spec.info["hermite"]
                self.delays.append(dict(block=b.index, off=nd, size=size, T=p["T"],
                                        hermite=hermite, u=b.u.start,
                                        du=b.u.start + size if hermite else -1, y=b.y.start))
                nd += size
            elif spec.kind == "maxhold":
                size = spec.info["size"]
                self.holds.append(dict(block=b.index, off=nh, size=size,
                                       nvec=spec.info["nvec"], nmat=spec.info["nmat"],
                                       eps=p["epsilon"], dt=p.get("dt_sample", 1e-3),
                                       u=b.u.start, y=b.y.start, k=len(self.holds)))
                nh += size
        self.nd, self.nh = nd, nh

    def state_labels(self):
        return list(self.diagram.state_labels)

    def state_groups(self):
        """The group of every state, numbered from 0: its block and the name of its state
        vector (``q`` of ``q[3]``), so that a block's vectors are moved as wholes when the
        Newton matrix's ordering is refined (sparse_lu.refine_by_groups)."""
        ids, out = {}, np.zeros(self.diagram.nstates, dtype=np.int64)
        for b in self.blocks:
            for i, label in enumerate(b.sys.state_labels):
                out[b.x.start + i] = ids.setdefault((b.index, label.split("[", 1)[0]),
                                                    len(ids))
        return out

    def state_owner(self, i):
        for b in self.blocks:
            if b.x.start <= i < b.x.stop:
                return f"{b.sys.name}.{b.sys.state_labels[i - b.x.start]}"
        return f"x[{i}]"


def check_params(diagram, params):
    """The syslist indices of the blocks that the overrides `params` reach; a clear error
    for a non-dict or a name no block takes."""
    if not isinstance(params, dict):
        raise TypeError(f"params must be a dict, got {type(params).__name__}")
    known, reached = set(), []
    for k, block in enumerate(diagram.syslist):
        known |= set(block.params)
        if set(params) & set(block.params):
            reached.append(k)
    unknown = set(params) - known
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)}; the diagram's blocks "
                         f"take {sorted(known)}")
    return reached
