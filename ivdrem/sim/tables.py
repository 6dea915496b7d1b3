"""A diagram as tables for the compiled engine's table-driven diagram functions.

:func:`build_tables` turns a :class:`~ivdrem.sim.plan.DiagramPlan` (with its parameter
layout, kernel wrapper indices, Jacobian program and symbolic LU) into
:class:`DiagramTables`, a namedtuple of int64 / float64 arrays that the shared, compiled
once ``ivdrem/sim/_diagram.py`` reads.  The field types are the same for every diagram, so
numba compiles that code once; only the values differ.
"""
from __future__ import annotations

import os
from collections import namedtuple
from pathlib import Path

import numpy as np

from .._atomic import write_file_atomic

from . import _diagram

__all__ = ["DiagramTables", "TABLES_LAYOUT", "DIMS", "build_tables", "empty_tables", "pack",
           "load_tables", "save_tables", "prune_kept_tables",
           "with_fill_runs", "INT_FIELDS", "FLOAT_FIELDS", "jacobian_positions", "sparse_to_dense",
           "dense_to_sparse"]

#: (field, dtype, ndim) of DiagramTables
TABLES_LAYOUT = (
    ("blocks", "int64", 2), ("order", "int64", 1), ("fill_order", "int64", 1),
    ("fill_rest", "int64", 1), ("probe_order", "int64", 1), ("probe_fill", "int64", 1),
    ("record_order", "int64", 1), ("record_fill", "int64", 1),
    ("history_order", "int64", 1), ("history_fill", "int64", 1), ("in_ptr", "int64", 1), ("in_src", "int64", 1),
    ("in_gain", "float64", 1), ("delays", "int64", 2), ("holds", "int64", 2),
    ("rec_ptr", "int64", 1), ("rec_src", "int64", 1), ("rec_gain", "float64", 1),
    ("wrapper_nx", "int64", 1), ("dims", "int64", 1),
    ("fd", "int64", 2), ("fd_g_ptr", "int64", 1), ("fd_g_kind", "int64", 1),
    ("fd_gc_ptr", "int64", 1), ("fd_col", "int64", 1), ("fd_e_ptr", "int64", 1),
    ("fd_e_row", "int32", 1), ("fd_e_slot", "int32", 1), ("jac_run_dst", "int32", 1),
    ("jac_run_f", "int32", 1), ("jac_run_src", "int32", 1), ("jac_run_len", "int32", 1),
    ("jac_j_pos", "int32", 1), ("jac_j_slot", "int32", 1), ("jac_gains", "float64", 1),
    ("lu_perm", "int64", 1), ("lu_rowptr", "int64", 1), ("lu_colidx", "int32", 1),
    ("lu_diagp", "int64", 1), ("lu_panel_rows", "int64", 1), ("lu_panel_kptr", "int64", 1),
    ("lu_panel_k", "int64", 1), ("fill_runs", "int64", 2), ("fill_run_gain", "float64", 1),
    ("fill_run_ranges", "int64", 1), ("scratch_offsets", "int64", 1),
    ("slope_flags", "int64", 1))
DiagramTables = namedtuple("DiagramTables", [f for f, _, _ in TABLES_LAYOUT])
DiagramTables.__doc__ = """The diagram as the compiled engine reads it, one array per row of
:data:`TABLES_LAYOUT`: blocks in evaluation order, connections, delays, max-holds, the
Jacobian's program and the LU pattern."""
#: the int64 and float64 fields, in the order pack() concatenates them; an "int32" field (an
#: index table read a million times per Jacobian or solve) is packed among the int64 ones as
#: its count, then its values two to an int64 entry (stepper.c i32_table)
INT_FIELDS = tuple(f for f, dt, _ in TABLES_LAYOUT if dt in ("int64", "int32"))
#: the float64 fields, in the order pack() concatenates them
FLOAT_FIELDS = tuple(f for f, dt, _ in TABLES_LAYOUT if dt == "float64")
#: entries of DiagramTables.dims (scalars of the diagram the compiled code reads)
DIMS = ("NJB",)
_FD_COLUMNS = _diagram.N_FD_COLUMNS


def empty_tables():
    """Tables of no diagram (the reference engine's workspace carries these)."""
    out = {}
    for name, dtype, ndim in TABLES_LAYOUT:
        shape = (0,) if ndim == 1 else (0, {"blocks": _diagram.N_BLOCK_COLUMNS,
                                           "delays": _diagram.N_DELAY_COLUMNS,
                                           "holds": _diagram.N_HOLD_COLUMNS,
                                           "fd": _FD_COLUMNS,
                                           "fill_runs": _diagram.N_RUN_COLUMNS}[name])
        out[name] = np.zeros(shape, dtype=dtype)
    out["dims"] = np.zeros(len(DIMS), dtype=np.int64)
    return DiagramTables(**out)


def slope_flags(plan):
    """1 for each delayed entry whose slope the history estimates (no derivative wired to
    its delay), else 0: what both engines hand the history push."""
    est = np.zeros(plan.nd, dtype=np.int64)
    for d in plan.delays:
        if not d["hermite"]:
            est[d["off"]:d["off"] + d["size"]] = 1
    return est


def scratch_size(tables):
    """Length of the workspace field scratch for `tables` (0 for empty tables)."""
    so = tables.scratch_offsets
    return int(so[-1]) if so.size else 0


def hold_nmat(plan):
    """The largest matrix order of the diagram's max-holds (1 without one)."""
    return max([hd["nmat"] for hd in plan.holds] + [1])


def save_tables(path, tables):
    """Keep `tables` at `path` for later processes, every field in one ``.npz`` (one file
    read instead of the block patterns, the Jacobian program and the LU order it is built
    from), written atomically (two processes filling the cache at once both succeed); an
    unwritable cache only costs the build next time."""
    try:
        write_file_atomic(path, lambda fh: np.savez(fh, **tables._asdict()))
    except OSError:
        pass


#: the most the kept tables (``tables/`` of the compile cache) may hold: a study that runs a
#: real arm's loop at many parameter values keeps one file per value (the Panda's: 8 MB);
#: beyond this the least recently used files are removed
TABLES_KEPT_BYTES = 256 * 2 ** 20


def prune_kept_tables(directory, limit=TABLES_KEPT_BYTES):
    """Remove the least recently used ``.npz`` files of `directory` (by modification time,
    which :func:`load_tables` renews on every read) until they hold at most `limit` bytes;
    a file another process removes meanwhile is skipped."""
    files = []
    for f in Path(directory).glob("*.npz"):
        try:
            st = f.stat()
        except OSError:
            continue
        files.append((st.st_mtime, st.st_size, f))
    total = sum(size for _, size, _ in files)
    for _, size, f in sorted(files, key=lambda e: e[0]):
        if total <= limit:
            break
        f.unlink(missing_ok=True)
        total -= size


def load_tables(path):
    """The DiagramTables kept at `path`, read-only; None where there is none or it does not
    hold every field of :data:`TABLES_LAYOUT` with its type and dimensions (a damaged file
    is built again and rewritten)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            got = {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError, KeyError):
        return None
    if set(got) != set(DiagramTables._fields):
        return None
    for name, dtype, ndim in TABLES_LAYOUT:
        a = got[name]
        if a.dtype != np.dtype(dtype) or a.ndim != ndim:
            return None
        a.flags.writeable = False
    try:
        os.utime(path)            # recently used: the last to be pruned
    except OSError:
        pass
    return DiagramTables(**got)


def _i64(v, cols=None):
    a = np.asarray(v, dtype=np.int64)
    if cols is not None:
        a = a.reshape(-1, cols)
    return np.ascontiguousarray(a)


def _i32(v):
    """An index table as int32: the Jacobian's chain and gathers and the LU's solves read
    about a million indices per step on a real arm's loop, half the bytes of int64 (Panda:
    the chain alone 0.7-0.87 -> 0.57-0.62 ms)."""
    a = np.asarray(v, dtype=np.int64).reshape(-1)
    bad = a[(a < -2 ** 31) | (a >= 2 ** 31)]
    if bad.size:
        raise OverflowError(f"an index table holds {bad[0]}, beyond int32: the diagram's "
                            f"Jacobian is too large for the compiled engine")
    return np.ascontiguousarray(a, dtype=np.int32)


def _packed_i32(a):
    """int32 table `a` as pack() stores it: the count, then the values two to an int64."""
    out = np.zeros(1 + (a.size + 1) // 2, dtype=np.int64)
    out[0] = a.size
    out[1:].view(np.int32)[:a.size] = a
    return out


def _scalar_offset(slot, what):
    """The offset in P of a block's one float parameter (a delay's T, a max-hold's eps)."""
    if getattr(slot, "shape", None) != ():
        raise ValueError(f"{what}: expected a float parameter in P, got {slot!r}")
    return slot.offset


def build_tables(plan, playout, pbase, windex, wrapper_nx, prog, slu):
    """The DiagramTables of `plan`.

    `playout[k]`: block k's parameter slots (compiled._param_layout); `pbase[k]` the
    start of block k's parameters in P; `windex[(k, role)]` the wrapper index of block k's
    kernel `role`; `wrapper_nx[j]` the state count of wrapper j's block; `prog` the
    JacobianProgram and `slu` its symbolic LU.
    """
    ny_total = sum(b.sys.noutputs for b in plan.blocks)
    nu_total = sum(b.sys.ninputs for b in plan.blocks)
    blocks = np.full((len(plan.blocks), _diagram.N_BLOCK_COLUMNS), -1, dtype=np.int64)
    delays, holds = [], []
    fill_order, filled = [], set()
    for b in plan.blocks:
        row = blocks[b.index]
        kind = {"ode": 0, "delay": 1, "maxhold": 2}[b.spec.kind]
        row[_diagram.B_KIND] = kind
        row[_diagram.B_X0], row[_diagram.B_NX] = b.x.start, b.sys.nstates
        row[_diagram.B_U0], row[_diagram.B_NU] = b.u.start, b.sys.ninputs
        row[_diagram.B_Y0], row[_diagram.B_NY] = b.y.start, b.sys.noutputs
        row[_diagram.B_P0] = pbase.get(b.index, 0)
        row[_diagram.B_OUT] = windex.get((b.index, "output"), -1)
        row[_diagram.B_UPD] = windex.get((b.index, "update"), -1)
        if kind == 1:
            dl = next(x for x in plan.delays if x["block"] == b.index)
            row[_diagram.B_SPECIAL] = len(delays)
            delays.append([dl["off"], dl["size"],
                           _scalar_offset(playout[b.index][0], f"delay '{b.sys.name}'"),
                           int(bool(dl["hermite"])), dl["u"], dl["du"]])
        elif kind == 2:
            hd = next(x for x in plan.holds if x["block"] == b.index)
            row[_diagram.B_SPECIAL] = len(holds)
            holds.append([hd["k"], hd["off"], hd["size"], hd["nvec"], hd["nmat"], hd["u"],
                          _scalar_offset(playout[b.index][0], f"max-hold '{b.sys.name}'")])
    for k in plan.order:
        b = plan.blocks[k]
        direct = [int(i) for i in b.direct_inputs] if b.spec.kind == "ode" else []
        blocks[k, _diagram.B_FILL0] = len(fill_order)
        fill_order += direct
        filled |= set(direct)
        blocks[k, _diagram.B_FILL1] = len(fill_order)
    rest = [i for i in range(nu_total) if i not in filled]
    hold_inputs = [i for b in plan.blocks if b.spec.kind == "maxhold"
                   for i in range(b.u.start, b.u.stop)]
    probe_order = _needed_blocks(plan, prog, inputs=hold_inputs)
    # a history point inside a step: the same for the delays' inputs (values and slopes)
    delay_inputs = sorted(
        {int(dl[_diagram.D_U]) + i for dl in delays for i in range(dl[_diagram.D_SIZE])}
        | {int(dl[_diagram.D_DU]) + i for dl in delays if dl[_diagram.D_HERMITE]
           for i in range(dl[_diagram.D_SIZE])})
    history_order = _needed_blocks(plan, prog, inputs=delay_inputs)
    # recording the diagram outputs: the same for the entries the output map reads (block
    # outputs, and block inputs, which are filled from their sources)
    _, Cin, Om = plan.maps          # sparse (CSR): each row's entries in column order
    read = np.unique(Om.indices).tolist()
    rec_inputs = [j - ny_total for j in read if j >= ny_total]
    record_order = _needed_blocks(plan, prog, outputs=[j for j in read if j < ny_total],
                                  inputs=rec_inputs)
    # the connection map (and input map) as sparse rows: sources >= 0 are block outputs,
    # -1 - j is diagram input j
    in_ptr, in_src, in_gain = [0], [], []
    for k in range(nu_total):
        for j, g in plan.conn[k]:
            in_src.append(j)
            in_gain.append(g)
        for p in range(Cin.indptr[k], Cin.indptr[k + 1]):
            in_src.append(-1 - int(Cin.indices[p]))
            in_gain.append(float(Cin.data[p]))
        in_ptr.append(len(in_src))
    rec_ptr, rec_src, rec_gain = [0], [], []
    for r in range(Om.shape[0]):
        for p in range(Om.indptr[r], Om.indptr[r + 1]):
            j = int(Om.indices[p])
            rec_src.append(j if j < ny_total else -1 - (j - ny_total))
            rec_gain.append(float(Om.data[p]))
        rec_ptr.append(len(rec_src))
    # the Jacobian's FD program, one row per differenced block
    fd = []
    for kb, b in enumerate(prog.fd_blocks):
        fd.append([prog.fd_x0[kb], prog.fd_nx[kb], prog.fd_u0[kb], prog.fd_nu[kb],
                   prog.fd_ny[kb], windex.get((b.index, "output"), -1),
                   windex.get((b.index, "update"), -1), windex.get((b.index, "jacobian"), -1),
                   pbase.get(b.index, 0), prog.fd_y0[kb], prog.fd_central[kb]])
    maxx = int(max(prog.fd_nx.max(initial=0), 1))
    maxu = int(max(prog.fd_nu.max(initial=0), 1))
    maxyf = int(max((prog.fd_ny + prog.fd_nx).max(initial=0), 1))
    # a block with a Jacobian kernel has a (ny + nx) x (nx + nu) buffer of its own, one
    # after the other in the order of fd (stepper.c's diagram_jacobian_at)
    jl_size = sum(int((prog.fd_ny[kb] + prog.fd_nx[kb]) * (prog.fd_nx[kb] + prog.fd_nu[kb]))
                  for kb, row in enumerate(fd) if row[_diagram.FD_WJAC] >= 0)
    # the sizes of the work arrays in the workspace field scratch (_diagram.SC_*), the one
    # place they are laid out: the history push's vectors, the max-hold eigensolver's
    # matrix, eigenvalues and dsyevd work (its minimum for eigenvectors), the Jacobian's
    nm = hold_nmat(plan)
    sizes = {_diagram.SC_V: plan.nd, _diagram.SC_DV: plan.nd,
             _diagram.SC_HOLD_A: nm * nm, _diagram.SC_HOLD_W: nm,
             _diagram.SC_HOLD_WORK: _diagram.dsyevd_lwork(nm),
             _diagram.SC_F: prog.n_jb + len(prog.gains), _diagram.SC_XB: maxx,
             _diagram.SC_XB0: maxx, _diagram.SC_UB: maxu, _diagram.SC_UB0: maxu,
             _diagram.SC_YP: maxyf, _diagram.SC_Y0: maxyf, _diagram.SC_YM: maxyf,
             _diagram.SC_HH: max(len(prog.col), 1), _diagram.SC_JL: max(jl_size, 1),
             _diagram.SC_S: prog.n_slots}
    scratch_offsets = np.cumsum([0] + [sizes[i] for i in range(_diagram.N_SCRATCH)])
    dims = dict(NJB=prog.n_jb)
    return with_fill_runs(DiagramTables(
        fill_runs=np.zeros((0, _diagram.N_RUN_COLUMNS), dtype=np.int64),
        fill_run_gain=np.zeros(0), fill_run_ranges=np.zeros(0, dtype=np.int64),
        blocks=blocks, order=_i64(plan.order), fill_order=_i64(fill_order),
        fill_rest=_i64(rest), probe_order=_i64(probe_order), probe_fill=_i64(hold_inputs),
        record_order=_i64(record_order), record_fill=_i64(rec_inputs),
        history_order=_i64(history_order), history_fill=_i64(delay_inputs),
        in_ptr=_i64(in_ptr), in_src=_i64(in_src),
        in_gain=np.asarray(in_gain, dtype=float), delays=_i64(delays, _diagram.N_DELAY_COLUMNS),
        holds=_i64(holds, _diagram.N_HOLD_COLUMNS), rec_ptr=_i64(rec_ptr), rec_src=_i64(rec_src),
        rec_gain=np.asarray(rec_gain, dtype=float), wrapper_nx=_i64(wrapper_nx),
        dims=_i64([dims[k] for k in DIMS]), fd=_i64(fd, _FD_COLUMNS),
        fd_g_ptr=_i64(prog.g_ptr), fd_g_kind=_i64(prog.g_kind), fd_gc_ptr=_i64(prog.gc_ptr),
        fd_col=_i64(prog.col), fd_e_ptr=_i64(prog.e_ptr), fd_e_row=_i32(prog.e_row),
        fd_e_slot=_i32(prog.e_slot), jac_run_dst=_i32(prog.run_dst),
        jac_run_f=_i32(prog.run_f), jac_run_src=_i32(prog.run_src),
        jac_run_len=_i32(prog.run_len),
        **_jacobian_stores(prog, slu),
        jac_gains=np.asarray(prog.gains, dtype=float), lu_perm=_i64(slu.perm),
        lu_rowptr=_i64(slu.rowptr), lu_colidx=_i32(slu.colidx), lu_diagp=_i64(slu.diagp),
        lu_panel_rows=_i64(slu.panel_rows), lu_panel_kptr=_i64(slu.panel_kptr),
        lu_panel_k=_i64(slu.panel_k),
        scratch_offsets=_i64(scratch_offsets), slope_flags=slope_flags(plan)))


def jacobian_positions(prog, slu):
    """Where each structural entry (j_row, j_col) of df/dx sits among the values of the
    filled LU pattern of P (cI - J) P^T (row i of the pattern is row perm[i] of J): the
    compiled engine stores J in that order, zero at the fill, so that the factorisation
    reads it row by row (a dense n x n J read by the permutation missed the cache on
    every entry of the real arms' 110-180 thousand)."""
    n = slu.n
    inv = np.empty(n, dtype=np.int64)
    inv[slu.perm] = np.arange(n)
    rows, cols = inv[np.asarray(prog.j_row, dtype=np.int64)], inv[np.asarray(prog.j_col,
                                                                               dtype=np.int64)]
    # entries of row i are colidx[rowptr[i]:rowptr[i + 1]], sorted: search row by row at once
    key = rows * n + cols
    pattern_key = _value_rows(slu.rowptr) * n + slu.colidx
    pos = np.searchsorted(pattern_key, key)
    if key.size and (pos.max() >= pattern_key.size or (pattern_key[pos] != key).any()):
        raise AssertionError("an entry of df/dx is not in the LU pattern")
    return _i64(pos)


def _jacobian_stores(prog, slu):
    """jac_j_pos and jac_j_slot: the chain's slot of each entry of df/dx and its position
    in the filled LU pattern (:func:`jacobian_positions`), in the order of the positions,
    so that the stores into the Newton matrix's values go through them once from the first
    to the last (in df/dx's row order they jumped around the permuted rows, a cache miss
    each on the real arms; each store is a copy, so J is the same bit for bit)."""
    pos = jacobian_positions(prog, slu)
    order = np.argsort(pos, kind="stable")
    return dict(jac_j_pos=_i32(pos[order]),
                jac_j_slot=_i32(np.asarray(prog.j_slot, dtype=np.int64)[order]))


def _value_rows(rowptr):
    """The pattern row of each stored value (CSR rowptr)."""
    return np.repeat(np.arange(rowptr.size - 1, dtype=np.int64), np.diff(rowptr))


def sparse_to_dense(values, perm, rowptr, colidx):
    """The n x n matrix whose entries are `values` in the filled LU pattern's order
    (perm, rowptr, colidx: the tables' lu_perm, lu_rowptr, lu_colidx)."""
    n = perm.size
    out = np.zeros((n, n))
    out[perm[_value_rows(rowptr)], perm[colidx]] = values
    return out


def dense_to_sparse(J, perm, rowptr, colidx):
    """J's entries at the filled LU pattern's positions (the inverse of sparse_to_dense
    where J is zero outside the pattern)."""
    J = np.asarray(J, dtype=float)
    return np.ascontiguousarray(J[perm[_value_rows(rowptr)], perm[colidx]])


def _runs(seq, in_ptr, in_src, in_gain):
    """The fill sequence `seq` (block input rows, filled in this order) as runs
    [kind, first input, first source, length] with a gain each: consecutive rows with one
    source each, consecutive sources of one kind (block outputs: RUN_SIGNALS, diagram
    inputs: RUN_INPUTS) and one gain make one run, copied in a vectorisable loop; any
    other row is a RUN_ROW of its own (a sum over its connection row)."""
    runs, gains = [], []
    for k in (int(i) for i in seq):
        if in_ptr[k + 1] - in_ptr[k] != 1:
            runs.append([_diagram.RUN_ROW, k, 0, 1])
            gains.append(0.0)
            continue
        j, g = int(in_src[in_ptr[k]]), float(in_gain[in_ptr[k]])
        kind, src = (_diagram.RUN_SIGNALS, j) if j >= 0 else (_diagram.RUN_INPUTS, -1 - j)
        last = runs[-1] if runs else None
        if (last is not None and last[0] == kind and gains[-1] == g
                and last[1] + last[3] == k and last[2] + last[3] == src):
            last[3] += 1
        else:
            runs.append([kind, k, src, 1])
            gains.append(g)
    return runs, gains


def with_fill_runs(tables):
    """`tables` with fill_runs / fill_run_gain / fill_run_ranges made from its fill
    sequences and connection rows (what diagram_eval fills from): first each block's
    range of runs (before its output), in block order, then the ranges of fill_rest,
    probe_fill, record_fill and history_fill.  Call again after replacing a sequence."""
    runs, gains, ranges = [], [], []
    B = tables.blocks
    seqs = [tables.fill_order[B[k, _diagram.B_FILL0]:B[k, _diagram.B_FILL1]]
            for k in range(B.shape[0])]
    seqs += [tables.fill_rest, tables.probe_fill, tables.record_fill, tables.history_fill]
    for seq in seqs:
        r, g = _runs(seq, tables.in_ptr, tables.in_src, tables.in_gain)
        ranges += [len(runs), len(runs) + len(r)]
        runs += r
        gains += g
    return tables._replace(fill_runs=_i64(runs, _diagram.N_RUN_COLUMNS),
                           fill_run_gain=np.asarray(gains, dtype=float),
                           fill_run_ranges=_i64(ranges))


def _needed_blocks(plan, prog, *, outputs=(), inputs=()):
    """The blocks to evaluate, in evaluation order, for the block output entries `outputs`
    and the block input entries `inputs` (indices into the signal and input vectors)
    alone: the owners of those outputs and of the inputs' sources and, through each
    block's local pattern (prog.patterns: which inputs an output entry moves), the entries
    those depend on.  A block without a pattern counts as depending on all its direct
    inputs.

    Used where the loop needs a few signals at an interpolated point: a max-hold probe
    (composite learning's hold reads the window I - I(t - T), the integrator's state and
    the delay's history, not the regressor chain behind the integrand that the integrator
    also passes on), a history point of the delays and the recorded outputs."""
    owner = plan.output_owner()

    def sources(entries):
        return [src for i in entries for src, _ in plan.conn[int(i)]]

    needed = set()                     # blocks to evaluate
    seen = set()                       # global output entries already followed
    stack = list(outputs) + sources(inputs)
    while stack:
        j = int(stack.pop())
        if j in seen:
            continue
        seen.add(j)
        k = int(owner[j])
        needed.add(k)
        b = plan.blocks[k]
        if b.spec.kind != "ode":       # delays read their history, holds their record
            continue
        pat = prog.patterns.get(k)
        if pat is None:
            stack += sources(b.direct_inputs)
        else:
            row = pat[j - b.y.start, b.sys.nstates:]
            stack += sources(b.u.start + np.flatnonzero(row))
    return [k for k in plan.order if k in needed]


def pack(tables):
    """(ints, floats): the tables as one int64 and one float64 vector, as the compiled code
    reads them (two workspace fields rather than thirty: a namedtuple argument is passed
    field by field on every call).  ints starts with the offsets of the int fields
    (len(INT_FIELDS) + 1 entries, relative to the start of ints), floats' offsets follow
    them; 2-D tables are stored row-major."""
    int32 = {f for f, dt, _ in TABLES_LAYOUT if dt == "int32"}

    def flatten(fields, dtype, start):
        """(offsets of the fields from `start`, plus the end; the flattened fields)"""
        offsets, parts, pos = [], [], start
        for f in fields:
            a = (_packed_i32(_i32(getattr(tables, f))) if f in int32 else
                 np.ascontiguousarray(getattr(tables, f), dtype=dtype).reshape(-1))
            offsets.append(pos)
            parts.append(a)
            pos += a.size
        return offsets + [pos], parts
    ioff, iparts = flatten(INT_FIELDS, np.int64, len(INT_FIELDS) + 1 + len(FLOAT_FIELDS) + 1)
    foff, fparts = flatten(FLOAT_FIELDS, np.float64, 0)
    ints = np.concatenate([np.asarray(ioff + foff, dtype=np.int64)] + iparts)
    floats = np.concatenate(fparts) if fparts else np.zeros(0)
    return ints, floats


def reference_tables(plan):
    """(tables, P) of the reference engine, whose diagram is python-control's evaluation
    (a callback): only what the stepper's own after-step work and Jacobian read, the delays
    and max-holds (their T and epsilon in P), the history's slope flags and the scratch for
    the history push, the max-hold eigensolver and the forward-difference Jacobian."""
    P = [float(d["T"]) for d in plan.delays] + [float(hd["eps"]) for hd in plan.holds]
    nd = len(plan.delays)
    delays = [[d["off"], d["size"], k, int(bool(d["hermite"])), d["u"], d["du"]]
              for k, d in enumerate(plan.delays)]
    holds = [[hd["k"], hd["off"], hd["size"], hd["nvec"], hd["nmat"], hd["u"], nd + k]
             for k, hd in enumerate(plan.holds)]
    nm = hold_nmat(plan)
    n = plan.diagram.nstates
    sizes = {_diagram.SC_V: plan.nd, _diagram.SC_DV: plan.nd, _diagram.SC_HOLD_A: nm * nm,
             _diagram.SC_HOLD_W: nm, _diagram.SC_HOLD_WORK: _diagram.dsyevd_lwork(nm),
             _diagram.SC_YP: n, _diagram.SC_YM: n}
    offsets = np.cumsum([0] + [sizes.get(i, 0) for i in range(_diagram.N_SCRATCH)])
    tables = empty_tables()._replace(
        delays=_i64(delays, _diagram.N_DELAY_COLUMNS), holds=_i64(holds, _diagram.N_HOLD_COLUMNS),
        slope_flags=slope_flags(plan), scratch_offsets=_i64(offsets))
    return tables, np.asarray(P, dtype=float)
