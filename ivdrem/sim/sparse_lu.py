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
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

__all__ = ["symbolic_lu", "SymbolicLU"]


class SymbolicLU:
    """perm, rowptr, colidx, diagp (int64) of the filled pattern; nnz_a, nnz_lu, fill."""

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
        for a in (self.perm, self.rowptr, self.colidx, self.diagp):
            a.flags.writeable = False     # shared by every run of the same pattern


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
