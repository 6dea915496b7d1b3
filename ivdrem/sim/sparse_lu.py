"""Symbolic LU of the Newton matrix A = c I - J, fixed when the diagram's tables are built.

The pattern of A is the structural pattern of df/dx (:class:`~ivdrem.sim.jacobian.
JacobianProgram`) plus the diagonal.  A symmetric permutation P is chosen among the
natural order and SuperLU's fill-reducing orderings (scipy.sparse.linalg.splu: COLAMD and
minimum degree on A^T + A), keeping the one with the least fill under elimination in the
diagonal order (the first of these three on a tie); where the states come in named groups
(a block's state vector: ``plant.q``, ``window_integrator.window_I``), that order is then
refined by moving whole groups (:func:`refine_by_groups`), and the filled pattern of L + U
of P A P^T is stored row by row (CSR, columns sorted).

Why the refinement: minimum degree works on the symmetrised pattern A^T + A, and an
adaptation law is far from symmetric (theta_hat reads every averaged entry of Psi, which
never reads theta_hat).  On the Panda's IV-DREM loop, moving the regressor filters and the
instrument ahead of the window integral, and the plant's velocity and theta_hat to the end,
takes the factorisation from 3.11 to 0.64 million multiply-adds and L + U from 278,297 to
194,057 entries.  The
numeric factorisation (``slu_factor`` in ``stepper.c``) then pivots statically
on the diagonal: for the small steps a stiff method takes, c = 1/(gamma h) dominates
|J| and A is strongly diagonally dominant; a pivot that is tiny or not finite returns
SINGULAR so that the integrator shrinks the step.

Panels: the factorisation eliminates row by row (row i subtracts the rows of U its L
entries name, in increasing column order).  Where LU_PANEL consecutive rows share most of a
long L part (the adaptation law's rows of a real arm's IV-DREM loop: each sees every
averaged entry of Psi, 97 % of the Panda's factorisation), they are eliminated together:
each row of U they share is read once and subtracted from all of them as one short dense
update.  Every entry receives the same subtractions in the same order as row by row, so the
factor is bit for bit the same; :func:`panels` chooses them.
"""
from __future__ import annotations

import hashlib
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from .._atomic import write_file_atomic
from ._diagram import LU_PANEL
from ..compile_cache import cache_dir, package_digest

__all__ = ["symbolic_lu", "SymbolicLU", "panels", "refine_by_groups", "elimination_cost"]

#: a panel is worth its bookkeeping when its rows' updates are at least this many
#: multiply-adds, and at least this share of them fall on L entries all its rows have
PANEL_MIN_WORK = 64 * LU_PANEL
PANEL_MIN_SHARED = 0.5
#: ... and when the rows of U it subtracts are on average at least this long: each costs the
#: panel LU_PANEL multipliers, so short ones are cheaper row by row (Panda, t = 60 s: rows of
#: U 28 long, 2.45 -> 2.0 ms with panels; 4.7 long after the group refinement, 0.83 -> 0.92)
PANEL_MIN_ULEN = 12

#: linear solves per factorisation (Rodas5P: one factor, eight stages each solving once): an
#: entry of L + U costs a solve's multiply-add this many times for one of the factorisation's
SOLVES_PER_FACTOR = 8
#: a group move is kept when it lowers the cost by at least this share; the search stops
#: after REFINE_MAX_ROUNDS passes over every move or REFINE_MAX_TRIES evaluated orders
REFINE_MIN_GAIN = 0.005
REFINE_MAX_ROUNDS = 8
REFINE_MAX_TRIES = 2000


class SymbolicLU:
    """perm, rowptr, diagp (int64) and colidx (int32) of the filled pattern; nnz_a, nnz_lu,
    fill; the panels (:func:`panels`): first rows, and for each the columns it eliminates."""

    #: the arrays a SymbolicLU is kept on disk as (with nnz_a and the ordering's name)
    ARRAYS = ("perm", "rowptr", "colidx", "diagp", "panel_rows", "panel_kptr", "panel_k")

    def __init__(self, perm, rows, nnz_a, ordering):
        n = len(rows)
        sizes = np.fromiter((r.size for r in rows), dtype=np.int64, count=n)
        rowptr = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
        # int32, as the factorisation and the solves read them (tables._i32)
        colidx = (np.concatenate(rows).astype(np.int32) if n
                  else np.zeros(0, dtype=np.int32))
        diagp = rowptr[:-1] + np.fromiter(
            (int(np.searchsorted(r, i)) for i, r in enumerate(rows)), dtype=np.int64, count=n)
        self._set(np.asarray(perm, dtype=np.int64), rowptr, colidx, diagp,
                  *panels(rowptr, colidx, diagp), nnz_a=nnz_a, ordering=ordering)

    @classmethod
    def from_arrays(cls, arrays, nnz_a, ordering):
        """The SymbolicLU whose :data:`ARRAYS` are `arrays` (a dict), as kept on disk."""
        self = cls.__new__(cls)
        self._set(*(arrays[k] for k in cls.ARRAYS), nnz_a=nnz_a, ordering=ordering)
        return self

    def _set(self, perm, rowptr, colidx, diagp, panel_rows, panel_kptr, panel_k, *, nnz_a,
             ordering):
        self.n = int(perm.size)
        self.perm, self.rowptr, self.colidx, self.diagp = perm, rowptr, colidx, diagp
        self.panel_rows, self.panel_kptr, self.panel_k = panel_rows, panel_kptr, panel_k
        self.ordering = ordering
        self.nnz_a = int(nnz_a)
        self.nnz_lu = int(self.colidx.size)
        self.fill = self.nnz_lu - self.nnz_a
        for a in (self.perm, self.rowptr, self.colidx, self.diagp, self.panel_rows,
                  self.panel_kptr, self.panel_k):
            a.flags.writeable = False     # shared by every run of the same pattern


def panels(rowptr, colidx, diagp, width=LU_PANEL):
    """The row panels of a filled pattern (CSR, columns sorted; diagp: each row's diagonal):
    (first rows, kptr, k) with panel p the rows first[p] .. first[p] + width - 1, and
    k[kptr[p]:kptr[p + 1]] the columns its rows' L parts hold, merged and increasing.

    Rows are taken from the top: a panel starts at row s when its rows' elimination costs
    at least PANEL_MIN_WORK multiply-adds (the sum over each row's L entries k of the length
    of row k of U) and at least PANEL_MIN_SHARED of that falls on columns k < s in every
    row's L part, and the rows of U it reads are on average PANEL_MIN_ULEN long, the
    updates done for all rows at once; otherwise row s is eliminated alone and the search
    moves on by one row."""
    rowptr, colidx, diagp = (np.asarray(a, dtype=np.int64) for a in (rowptr, colidx, diagp))
    n = diagp.size
    ulen = rowptr[1:] - diagp - 1
    work = np.zeros(n, dtype=np.int64)
    lower = [colidx[rowptr[i]:diagp[i]] for i in range(n)]
    for i in range(n):
        work[i] = ulen[lower[i]].sum()
    csum = np.concatenate(([0], np.cumsum(work)))
    first, ks = [], []
    s = 0
    while s + width <= n:
        total = int(csum[s + width] - csum[s])
        if total >= PANEL_MIN_WORK:
            shared = lower[s][lower[s] < s]
            for r in range(s + 1, s + width):
                shared = np.intersect1d(shared, lower[r], assume_unique=True)
            merged = np.unique(np.concatenate(lower[s:s + width]))
            if (width * int(ulen[shared].sum()) >= PANEL_MIN_SHARED * total
                    and merged.size and ulen[merged].mean() >= PANEL_MIN_ULEN):
                first.append(s)
                ks.append(merged)
                s += width
                continue
        s += 1
    kptr = np.concatenate(([0], np.cumsum([k.size for k in ks]))).astype(np.int64)
    k = np.concatenate(ks).astype(np.int64) if ks else np.zeros(0, dtype=np.int64)
    return np.asarray(first, dtype=np.int64), kptr, k


def elimination_cost(rows):
    """(multiply-adds of the numeric factorisation, entries of L + U) of a filled pattern
    given as its rows (:func:`_filled_rows`): row i costs, for every k in its L part, the
    length of the strict upper part of row k."""
    n = len(rows)
    if n == 0:
        return 0, 0
    sizes = np.fromiter((r.size for r in rows), dtype=np.int64, count=n)
    flat = np.concatenate(rows)
    owner = np.repeat(np.arange(n), sizes)
    lower = flat < owner
    ulen = sizes - np.bincount(owner[lower], minlength=n) - 1
    return int(ulen[flat[lower]].sum()), int(sizes.sum())


#: patterns of at least this many states are searched with the cost compiled from
#: elimination_cost.c (a real arm's loop: 0.1 s an order in Python, 25 s for the Panda's
#: search; 5 ms compiled); smaller ones, or all where no C compiler builds it, in Python
REFINE_COMPILED_FROM = 1000
_C_COST = {}            # the loaded library's function (None: not built), by its path
_C_SOURCE_HASH = {}


def _compiled_cost():
    """The C elimination cost (elimination_cost.c, built with ivdrem._cc into the compile
    cache on first use: a fraction of a second, where numba compiling the same loop took
    6-7 s of a cold run), or None where no C compiler builds it."""
    import ctypes

    from .._cc import CompilerError, compile_shared
    src = Path(__file__).with_name("elimination_cost.c")
    if src not in _C_SOURCE_HASH:
        _C_SOURCE_HASH[src] = hashlib.sha256(src.read_bytes()).hexdigest()[:20]
    path = cache_dir() / "lu-orders" / f"cost-{_C_SOURCE_HASH[src]}.so"
    fn = _C_COST.get(str(path))
    if fn is not None or str(path) in _C_COST:
        return fn
    try:
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
                built = Path(tmp) / path.name
                compile_shared([src], built, what="ivdrem's elimination_cost.c")
                os.replace(built, path)
        fn = ctypes.CDLL(str(path)).ivdrem_elimination_cost
    except (CompilerError, OSError):
        fn = None           # the search runs in Python: slower, the same orders
    else:
        i64p = ctypes.POINTER(ctypes.c_int64)
        fn.argtypes = [ctypes.c_int64, i64p, i64p, i64p, ctypes.c_double, ctypes.c_double,
                       ctypes.c_double, i64p]
        fn.restype = ctypes.c_int
    _C_COST[str(path)] = fn
    return fn


def _order_cost(A, order, cost_limit, *, fill_only=False):
    """(madds, nnz) of `order` on the CSR pattern A, None above cost_limit (of
    :func:`_cost`, or with `fill_only` of nnz alone)."""
    fn = _compiled_cost() if A.shape[0] >= REFINE_COMPILED_FROM else None
    if fn is None:
        if fill_only:
            rows = _filled_rows(A, order, limit=None if np.isinf(cost_limit) else cost_limit)
        else:
            rows = _filled_rows(A, order, cost_limit=cost_limit)
        return None if rows is None else elimination_cost(rows)
    import ctypes
    i64p = ctypes.POINTER(ctypes.c_int64)
    arrays = [np.ascontiguousarray(a, dtype=np.int64) for a in (A.indptr, A.indices, order)]
    out = np.zeros(2, dtype=np.int64)
    status = fn(A.shape[0], *(a.ctypes.data_as(i64p) for a in arrays),
                0.0 if fill_only else 1.0, 1.0 if fill_only else float(SOLVES_PER_FACTOR),
                float(cost_limit), out.ctypes.data_as(i64p))
    if status < 0:
        raise MemoryError("the symbolic LU's ordering search ran out of memory")
    return None if status else (int(out[0]), int(out[1]))


def _cost(madds, nnz):
    """What one factorisation and its solves cost, in multiply-adds."""
    return madds + SOLVES_PER_FACTOR * nnz


def refine_by_groups(A, order, groups):
    """A better order than `order` for the CSR pattern A (diagonal stored), found by moving
    whole groups of states (`groups[i]`: the group of state i), each group keeping the
    order of its states: (order, madds, nnz), or None where no move gains.

    The cost is that of a step of the implicit method: one factorisation and
    SOLVES_PER_FACTOR solves (:func:`_cost`).  The search is greedy: every move of a group
    to just before another group's first state, or to the end, is tried in turn, and kept
    when it lowers the cost by REFINE_MIN_GAIN; a pass without a kept move ends it.  An
    order is abandoned as soon as its rows so far cost more than the best (the cost
    limit of :func:`_order_cost`)."""
    groups = np.asarray(groups)
    names = list(dict.fromkeys(groups[order].tolist()))
    if len(names) < 2:
        return None
    best = _order_cost(A, order, np.inf)
    best_cost = start = _cost(*best)
    tries = 0
    for _ in range(REFINE_MAX_ROUNDS):
        kept = False
        for g in names:
            # g's states and the others, each in their order, are the same whichever move
            # of g is kept
            moved = groups[order] == g
            block, rest = order[moved], order[~moved]
            for before in names + [None]:
                if before == g or tries >= REFINE_MAX_TRIES:
                    continue
                at = rest.size if before is None else int(np.argmax(groups[rest] == before))
                cand = np.concatenate([rest[:at], block, rest[at:]])
                if np.array_equal(cand, order):
                    continue
                tries += 1
                got = _order_cost(A, cand, best_cost)
                if got is None:
                    continue
                if _cost(*got) < (1.0 - REFINE_MIN_GAIN) * best_cost:
                    order, best, best_cost, kept = cand, got, _cost(*got), True
        if not kept:
            break
    return None if best_cost >= start else (order, best[0], best[1])


def _filled_rows(A, order, limit=None, cost_limit=None):
    """Rows of the filled pattern of L + U of P A P^T eliminated in the diagonal order, each
    a sorted int64 array of columns (A: CSR with its diagonal stored; P: row i of P A P^T
    is row order[i] of A); None as soon as more than `limit` entries are found (an
    ordering that can no longer have the least fill), or the rows so far cost more than
    `cost_limit` (:func:`_cost`: one that can no longer be the cheapest).

    Row i of L + U is row i of A together with, for every column j < i in row i of L (the
    fill included), the strict upper part of row j of U; the columns of row i are therefore
    the columns reachable from row i of A through rows j < i of U (Rose and Tarjan's fill
    paths, George and Liu, "Computer Solution of Large Sparse Positive Definite Systems",
    ch. 5, for the symmetric case; Gilbert and Peierls' reach for the unsymmetric one).
    The search reaches each entry of L once and scans that row of U: the work is the
    elimination's symbolic count, not the n^3 of eliminating a dense boolean matrix.
    """
    n = A.shape[0]
    inv = np.empty(n, dtype=np.int64)
    inv[order] = np.arange(n)
    indptr, indices = A.indptr, inv[A.indices]
    upper = [None] * n          # strict upper part of each finished row of U
    mark = np.zeros(n, dtype=bool)
    rows, total, cost = [], 0, 0
    ulen = np.zeros(n, dtype=np.int64)
    for i in range(n):
        k = order[i]
        cols = indices[indptr[k]:indptr[k + 1]]
        mark[cols] = True
        parts = [cols]
        front = cols[cols < i]
        while front.size:           # breadth first: one gather per level, not per entry
            u = np.concatenate([upper[j] for j in front.tolist()])
            new = np.unique(u[~mark[u]])
            mark[new] = True
            parts.append(new)
            front = new[new < i]
        row = np.sort(np.concatenate(parts))
        mark[row] = False
        d = int(np.searchsorted(row, i))
        upper[i] = row[d + 1:]
        ulen[i] = row.size - d - 1
        rows.append(row)
        total += row.size
        if limit is not None and total > limit:
            return None
        if cost_limit is not None:
            cost += _cost(int(ulen[row[:d]].sum()), row.size)
            if cost > cost_limit:
                return None
    return rows


#: symbolic LUs of this process by their pattern: every simulate() of the same diagram
#: (the calibration of gamma = "auto", then the run) needs the same one
_SYMBOLIC: dict = {}
_SYMBOLIC_MAX = 64


def symbolic_lu(pattern, groups=None):
    """The ordering and filled pattern of c I - J for a boolean pattern of J: the least
    fill among the candidate orderings (:func:`_symbolic_lu`), refined by moving whole
    groups where `groups` (the group of each state, e.g. its block and state name) is given
    (:func:`refine_by_groups`).  Computed once per process for a pattern and its groups;
    the result (the refined order, its filled rows and panels) is kept on disk (the search
    takes seconds on a real arm's loop, the elimination in its order 0.4 s on the Panda's).
    SymbolicLU is read-only."""
    A = np.asarray(pattern, dtype=bool)
    g = None if groups is None else np.unique(np.asarray(groups), return_inverse=True)[1]
    if g is not None and g.shape != A.shape[:1]:
        raise ValueError(f"groups has {g.size} entries for a {A.shape[0]}-state pattern")
    key = (A.shape, np.packbits(A).tobytes(), None if g is None else g.astype(np.int64).tobytes())
    hit = _SYMBOLIC.get(key)
    if hit is None:
        if len(_SYMBOLIC) >= _SYMBOLIC_MAX:
            _SYMBOLIC.pop(next(iter(_SYMBOLIC)))
        hit = _SYMBOLIC[key] = _symbolic_lu(A) if g is None else _grouped_symbolic_lu(A, g)
    return hit


def _order_path(pattern, groups):
    """Where the symbolic LU of (pattern, groups) is kept: named by both and by the
    digest of ivdrem's sources (a changed search never reads a stale order)."""
    digest = package_digest()
    if digest is None:
        return None
    h = hashlib.sha256(digest.encode())
    h.update(repr(pattern.shape).encode())
    h.update(np.packbits(pattern).tobytes())
    h.update(np.ascontiguousarray(groups, dtype=np.int64).tobytes())
    return cache_dir() / "lu-orders" / f"{h.hexdigest()[:40]}.npz"


def _read_kept(path, n):
    """The SymbolicLU kept at `path` (its order with its filled rows and panels, so that a
    new process neither searches nor eliminates: 0.4 s of CPU on the Panda's loop), or None
    where there is none or it is not a whole one of n states (a damaged file is searched
    again and rewritten)."""
    if path is None:
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            got = {k: np.asarray(z[k]) for k in SymbolicLU.ARRAYS}
            name, nnz_a = str(z["name"]), int(z["nnz_a"])
    except (OSError, ValueError, EOFError, KeyError, TypeError):
        return None
    perm, rowptr, colidx, diagp = (got[k] for k in ("perm", "rowptr", "colidx", "diagp"))
    ints = all(got[k].dtype == np.int64 and got[k].ndim == 1
               for k in SymbolicLU.ARRAYS if k != "colidx")
    if not (ints and colidx.dtype == np.int32 and colidx.ndim == 1 and perm.shape == (n,)
            and rowptr.shape == (n + 1,) and diagp.shape == (n,)
            and np.array_equal(np.sort(perm), np.arange(n)) and rowptr[0] == 0
            and rowptr[-1] == colidx.size and np.all(np.diff(rowptr) > 0)
            and np.all((colidx >= 0) & (colidx < n)) and np.all(diagp >= rowptr[:-1])
            and np.all(diagp < rowptr[1:]) and np.array_equal(colidx[diagp], np.arange(n))
            and got["panel_kptr"].shape == (got["panel_rows"].size + 1,)
            and got["panel_kptr"][-1] == got["panel_k"].size):
        return None
    return SymbolicLU.from_arrays(got, nnz_a, name)


def _grouped_symbolic_lu(pattern, groups):
    n = pattern.shape[0]
    path = _order_path(pattern, groups)
    kept = _read_kept(path, n)
    if kept is not None:
        return kept
    A = _pattern_csr(pattern)
    base_name, base_order = _least_fill_order(A)
    refined = refine_by_groups(A, base_order, groups)
    if refined is None:
        order, name = np.array(base_order), base_name
    else:
        order, name = refined[0], f"{base_name}, groups moved"
    slu = SymbolicLU(order, _filled_rows(A, order), A.nnz, name)
    if path is not None:
        try:
            write_file_atomic(path, lambda fh: np.savez(
                fh, name=np.array(name), nnz_a=np.array(slu.nnz_a),
                **{k: getattr(slu, k) for k in SymbolicLU.ARRAYS}))
        except OSError:
            pass            # an unwritable cache costs the search next time
    return slu


def _pattern_csr(pattern):
    """The pattern of c I - J as CSR (ones), its diagonal stored."""
    n = pattern.shape[0]
    A = (sparse.csr_matrix(np.asarray(pattern, dtype=bool), dtype=float)
         + sparse.identity(n, format="csr"))
    A.data[:] = 1.0
    return A


def _symbolic_lu(pattern, A=None):
    """The least-fill candidate ordering of `pattern` (A: its _pattern_csr, if built)."""
    A = _pattern_csr(pattern) if A is None else A
    name, order = _least_fill_order(A)
    return SymbolicLU(order, _filled_rows(A, order), A.nnz, name)


def _least_fill_order(A):
    """(name, order) of the candidate ordering with the least fill of L + U on the CSR
    pattern A (the first of natural, COLAMD, MMD_AT_PLUS_A on a tie)."""
    n = A.shape[0]
    # candidates in the order that breaks ties: the first with the least fill wins
    candidates = [("natural", np.arange(n))]
    if n > 1:
        # values that make every ordering's pivots safe (diagonally dominant): only the
        # column permutation is used
        M = (A + n * sparse.identity(n, format="csr")).tocsc()
        for spec in ("COLAMD", "MMD_AT_PLUS_A"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lu = sparse_linalg.splu(M, permc_spec=spec, diag_pivot_thresh=0.0)
            # perm_c[i] is the new position of column i; we need new -> old
            candidates.append((spec, np.argsort(np.asarray(lu.perm_c))))
    # the fill-reducing orderings first: the natural order of a real arm's loop fills most
    # of the matrix (4.9 M of 14.5 M entries on the UR5's), and its elimination stops as
    # soon as it has more entries than the best so far (it can no longer be the least)
    found = {}                  # rank in candidates -> nnz of L + U
    for rank in list(range(1, len(candidates))) + [0]:
        best = min(found.values(), default=np.inf)
        got = _order_cost(A, candidates[rank][1], best, fill_only=True)
        if got is not None:
            found[rank] = got[1]
    rank = min(found, key=lambda r: (found[r], r))
    return candidates[rank]
