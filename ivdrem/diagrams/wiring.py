"""Blocks wired by signal name, as ``ct.interconnect`` wires them, with sparse maps.

``ct.interconnect(blocks, inputs=..., outputs=...)`` with no connections given connects
every block input to every block output of the same label, and the diagram's inputs and
outputs to the block signals of those names.  It finds the pairs by searching every
block's outputs for every block input (a real arm's loop: 12,937 inputs against 12,487
outputs, 13 s) and keeps the result as dense maps (1.2 GiB for the connection map alone,
whose 12,937 entries are all ones).  :func:`wire_by_name` makes the same pairs from a
table of labels and keeps them sparse, in a :class:`ivdrem.sim._control.SparseInterconnect`:
the same inputs, outputs, states and parameters, and python-control's maps equal entry by
entry (tests/test_wiring.py compares them with ``ct.interconnect``'s).

It takes what ivdrem's diagrams give: signal names without a block prefix, a gain or a
slice.  Anything else (a name that is also a block's name, one found nowhere, a signal
found in several blocks with different sizes, a transfer function, a block of open size,
all-linear blocks, which python-control turns into a ``LinearICSystem``) is
:data:`NOT_PLAIN`, and the caller asks
``ct.interconnect`` itself, which also words the errors.
"""
from __future__ import annotations

import re

import control as ct
from scipy import sparse

from ..sim._control import SparseInterconnect

__all__ = ["wire_by_name", "NOT_PLAIN"]

#: what :func:`wire_by_name` returns for names or blocks it leaves to ``ct.interconnect``
NOT_PLAIN = None

#: a plain signal name: python-control's own pattern of a base name (iosys._find_signals)
_PLAIN = re.compile(r"[\w$]+$")


def _external(blocks, names, kind, offsets):
    """(labels, rows, columns) of the diagram's external `kind` ("input" or "output")
    signals `names` as ``ct.interconnect`` makes them, or NOT_PLAIN: a name matching
    several entries of a block becomes one external signal per entry (labelled with the
    block's labels), a name one entry keeps its own label, and a name found in several
    blocks sums (outputs) or feeds (inputs) them all, entry by entry."""
    labels, rows, cols = [], [], []
    bases = [{lab.partition("[")[0] for lab in getattr(b, f"{kind}_labels")} for b in blocks]
    for name in names:
        if not isinstance(name, str) or not _PLAIN.match(name) \
                or any(b.name == name for b in blocks):
            return NOT_PLAIN
        found = None
        for k, b in enumerate(blocks):
            if name not in bases[k]:
                continue
            # python-control's lookup: the label itself, else name[0], name[1], ...
            idx = b.find_inputs(name) if kind == "input" else b.find_outputs(name)
            if not idx:
                continue
            if found is None:
                found = len(idx)
                labels += ([name] if len(idx) == 1 else
                           [getattr(b, f"{kind}_labels")[i] for i in idx])
            elif len(idx) != found:
                return NOT_PLAIN
            for j, i in enumerate(idx):
                rows.append(len(labels) - found + j)
                cols.append(offsets[k] + i)
        if found is None:
            return NOT_PLAIN
    return labels, rows, cols


def wire_by_name(blocks, inputs=(), outputs=(), *, name=None):
    """``ct.interconnect(blocks, inputs=inputs, outputs=outputs, name=name,
    check_unused=False)`` with sparse maps (:class:`~ivdrem.sim._control.SparseInterconnect`),
    or NOT_PLAIN where the names or blocks are not the plain ones this handles."""
    blocks = list(blocks)
    if any(not isinstance(b, ct.NonlinearIOSystem) or isinstance(b, ct.InterconnectedSystem)
           or None in (b.ninputs, b.noutputs, b.nstates) for b in blocks) \
            or all(isinstance(b, ct.StateSpace) for b in blocks):
        return NOT_PLAIN
    in_off, out_off = [0], [0]
    for b in blocks:
        in_off.append(in_off[-1] + b.ninputs)
        out_off.append(out_off[-1] + b.noutputs)
    nu, ny = in_off[-1], out_off[-1]
    # every block output by its label, in block order: a block input is fed by each
    sources = {}
    for k, b in enumerate(blocks):
        for i, lab in enumerate(b.output_labels):
            sources.setdefault(lab, []).append(out_off[k] + i)
    rows, cols = [], []
    for k, b in enumerate(blocks):
        for i, lab in enumerate(b.input_labels):
            for j in sources.get(lab, ()):
                rows.append(in_off[k] + i)
                cols.append(j)
    ins = _external(blocks, list(inputs), "input", in_off)
    outs = _external(blocks, list(outputs), "output", out_off)
    if ins is NOT_PLAIN or outs is NOT_PLAIN:
        return NOT_PLAIN
    in_labels, in_rows, in_cols = ins
    out_labels, out_rows, out_cols = outs

    def ones(r, c, shape):      # duplicates sum, as python-control's += does
        return sparse.csr_array(([1.0] * len(r), (r, c)), shape=shape)

    return SparseInterconnect(
        blocks, ones(rows, cols, (nu, ny)),
        ones(in_cols, in_rows, (nu, len(in_labels))),   # block input <- diagram input
        ones(out_rows, out_cols, (len(out_labels), ny + nu)),
        inputs=in_labels, outputs=out_labels, name=name)
