"""Symbolic LU of the Newton matrix A = c I - J, fixed when the diagram's tables are built.

The pattern of A is the structural pattern of df/dx (:class:`~ivdrem.sim.jacobian.
JacobianProgram`) plus the diagonal.  A symmetric permutation P is chosen among the
natural order and SuperLU's fill-reducing orderings (scipy.sparse.linalg.splu: COLAMD and
minimum degree on A^T + A), keeping the one with the least fill under elimination in the
diagonal order (the first of these three on a tie), and the
filled pattern of L + U of P A P^T is stored row by row (CSR, columns sorted).  The
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

import warnings

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from ._diagram import LU_PANEL

__all__ = ["symbolic_lu", "SymbolicLU", "panels"]

#: a panel is worth its bookkeeping when its rows' updates are at least this many
#: multiply-adds, and at least this share of them fall on L entries all its rows have
PANEL_MIN_WORK = 64 * LU_PANEL
PANEL_MIN_SHARED = 0.5


class SymbolicLU:
    """perm, rowptr, colidx, diagp (int64) of the filled pattern; nnz_a, nnz_lu, fill; the
    panels (:func:`panels`): first rows, and for each the columns it eliminates."""

    def __init__(self, perm, rows, nnz_a, ordering):
        n = len(rows)
        self.n = n
        self.perm = np.asarray(perm, dtype=np.int64)
        self.ordering = ordering
        sizes = np.fromiter((r.size for r in rows), dtype=np.int64, count=n)
        self.rowptr = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
        self.colidx = (np.concatenate(rows).astype(np.int64) if n
                       else np.zeros(0, dtype=np.int64))
        self.diagp = self.rowptr[:-1] + np.fromiter(
            (int(np.searchsorted(r, i)) for i, r in enumerate(rows)), dtype=np.int64, count=n)
        self.nnz_a = int(nnz_a)
        self.nnz_lu = int(self.colidx.size)
        self.fill = self.nnz_lu - self.nnz_a
        self.panel_rows, self.panel_kptr, self.panel_k = panels(self.rowptr, self.colidx,
                                                                self.diagp)
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
    row's L part, the updates done for all rows at once; otherwise row s is eliminated
    alone and the search moves on by one row."""
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
            if width * int(ulen[shared].sum()) >= PANEL_MIN_SHARED * total:
                first.append(s)
                ks.append(np.unique(np.concatenate(lower[s:s + width])))
                s += width
                continue
        s += 1
    kptr = np.concatenate(([0], np.cumsum([k.size for k in ks]))).astype(np.int64)
    k = np.concatenate(ks).astype(np.int64) if ks else np.zeros(0, dtype=np.int64)
    return np.asarray(first, dtype=np.int64), kptr, k


def _filled_rows(A, order, limit=None):
    """Rows of the filled pattern of L + U of P A P^T eliminated in the diagonal order, each
    a sorted int64 array of columns (A: CSR with its diagonal stored; P: row i of P A P^T
    is row order[i] of A); None as soon as more than `limit` entries are found (an
    ordering that can no longer have the least fill).

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
    rows, total = [], 0
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
        upper[i] = row[np.searchsorted(row, i) + 1:]
        rows.append(row)
        total += row.size
        if limit is not None and total > limit:
            return None
    return rows


#: symbolic LUs of this process by their pattern: every simulate() of the same diagram
#: (the calibration of gamma = "auto", then the run) needs the same one
_SYMBOLIC: dict = {}
_SYMBOLIC_MAX = 64


def symbolic_lu(pattern):
    """The fill-reducing ordering and filled pattern of c I - J for a boolean pattern of J
    (computed once per process for a given pattern; SymbolicLU is read-only)."""
    A = np.asarray(pattern, dtype=bool)
    key = (A.shape, np.packbits(A).tobytes())
    hit = _SYMBOLIC.get(key)
    if hit is None:
        if len(_SYMBOLIC) >= _SYMBOLIC_MAX:
            _SYMBOLIC.pop(next(iter(_SYMBOLIC)))
        hit = _SYMBOLIC[key] = _symbolic_lu(A)
    return hit


def _symbolic_lu(pattern):
    n = pattern.shape[0]
    A = (sparse.csr_matrix(np.asarray(pattern, dtype=bool), dtype=float)
         + sparse.identity(n, format="csr"))
    A.data[:] = 1.0
    nnz_a = A.nnz
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
    found = {}                  # rank in candidates -> (nnz of L + U, rows)
    for rank in list(range(1, len(candidates))) + [0]:
        best = min((nnz for nnz, _ in found.values()), default=None)
        rows = _filled_rows(A, candidates[rank][1], limit=best)
        if rows is not None:
            found[rank] = (sum(r.size for r in rows), rows)
    rank = min(found, key=lambda r: (found[r][0], r))
    name, order = candidates[rank]
    return SymbolicLU(order, found[rank][1], nnz_a, name)
