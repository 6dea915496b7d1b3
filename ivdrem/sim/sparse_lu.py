"""Symbolic LU of the Newton matrix A = c I - J, fixed when the diagram's tables are built.

The pattern of A is the structural pattern of df/dx (:class:`~ivdrem.sim.jacobian.
JacobianProgram`) plus the diagonal.  A fill-reducing symmetric permutation P is chosen
among SuperLU's orderings (scipy.sparse.linalg.splu: COLAMD and minimum degree on A^T + A),
keeping the one with the least fill under elimination in the diagonal order, and the
filled pattern of L + U of P A P^T is stored row by row (CSR, columns sorted).  The
numeric factorisation (``slu_factor`` in ``stepper.c``) then pivots statically
on the diagonal: for the small steps a stiff method takes, c = 1/(gamma h) dominates
|J| and A is strongly diagonally dominant; a pivot that is tiny or not finite returns
SINGULAR so that the integrator shrinks the step.
"""
from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["symbolic_lu", "SymbolicLU"]


class SymbolicLU:
    """perm, rowptr, colidx, diagp (int64) of the filled pattern; nnz_a, nnz_lu, fill."""

    def __init__(self, perm, filled, nnz_a, ordering):
        n = filled.shape[0]
        self.n = n
        self.perm = np.asarray(perm, dtype=np.int64)
        self.ordering = ordering
        rowptr, colidx, diagp = [0], [], []
        for i in range(n):
            cols = np.flatnonzero(filled[i])
            diagp.append(len(colidx) + int(np.searchsorted(cols, i)))
            colidx += cols.tolist()
            rowptr.append(len(colidx))
        self.rowptr = np.asarray(rowptr, dtype=np.int64)
        self.colidx = np.asarray(colidx, dtype=np.int64)
        self.diagp = np.asarray(diagp, dtype=np.int64)
        self.nnz_a = int(nnz_a)
        self.nnz_lu = len(colidx)
        self.fill = self.nnz_lu - self.nnz_a
        for a in (self.perm, self.rowptr, self.colidx, self.diagp):
            a.flags.writeable = False     # shared by every run of the same pattern


def _filled(pattern, perm):
    """Pattern of L + U for P A P^T eliminated in order (boolean n x n)."""
    B = pattern[np.ix_(perm, perm)].copy()
    n = B.shape[0]
    for k in range(n):
        rows = np.flatnonzero(B[k + 1:, k]) + k + 1
        if rows.size:
            B[np.ix_(rows, np.arange(k + 1, n))] |= B[k, k + 1:]
    return B


#: symbolic LUs of this process by their pattern: the elimination is dense boolean work
#: (about 30 s for the UR5's loop), paid again by every simulate() of the same diagram
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
    A = np.asarray(pattern, dtype=bool) | np.eye(n, dtype=bool)
    nnz_a = int(A.sum())
    best = None
    candidates = [("natural", np.arange(n))]
    if n > 1:
        # values that make every ordering's pivots safe (diagonally dominant): only the
        # column permutation is used
        M = sp.csc_matrix(np.where(A, 1.0, 0.0) + n * np.eye(n))
        for spec in ("COLAMD", "MMD_AT_PLUS_A"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lu = spla.splu(M, permc_spec=spec, diag_pivot_thresh=0.0)
            candidates.append((spec, np.asarray(lu.perm_c)))
    for name, perm in candidates:
        # perm_c[i] is the new position of column i; we need new -> old
        order = np.argsort(perm) if name != "natural" else perm
        F = _filled(A, order)
        nnz = int(F.sum())
        if best is None or nnz < best[0]:
            best = (nnz, name, order, F)
    _, name, order, F = best
    return SymbolicLU(order, F, nnz_a, name)
