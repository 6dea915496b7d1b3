"""Numba kernels shared by every generated diagram module (compiled once, cached on disk).

* :func:`jac_chain` runs the chain rule's multiply-adds (:class:`ivdrem.sim.jacobian.
  JacobianProgram`) and scatters df/dx into a dense J;
* :func:`slu_factor` / :func:`slu_solve`: an LU of A = c I - J with the static pattern,
  ordering and fill computed at generation time (:mod:`ivdrem.sim.sparse_lu`).

They take the index arrays as arguments, so their machine code does not depend on the
diagram.  None allocates or returns an array, so all are compiled without reference
counting (``_nrt=False``): numba's atomic counts on every view and array argument cost
more than the arithmetic of a solve.
"""
import numpy as np
from numba import njit, uint64

OK = 0
SINGULAR = 6          # the stepping template's status for a zero / non-finite pivot

# UNSIGNED_INDICES: the index tables hold int64 (one packed table for every diagram); an
# int64 index makes numba add the wraparound of negative indices to every access, which
# kept LLVM from simple loads and doubled these loops' time (IV-DREM: factor 15.5 -> 7.6
# us, solve 3.7 -> 2.0 us, the chain 8.7 -> 4.6 us).  Read as uint64 they are plain loads;
# the tables' indices are never negative where they are read so.

# a pivot smaller than this times the largest entry of its row of A is refused: with
# static (diagonal) pivoting it signals a near-singular A or growth; the integrator then
# shrinks the step, which makes c I - J more diagonally dominant
PIVOT_RTOL = 1e-12


@njit(cache=True, _nrt=False)
def jac_chain(F, S, dst, fidx, src, j_row, j_col, j_slot, J):
    """S[dst] += F[f] * S[src] (or + F[f] where src < 0), in order, from S = 0 (S: one entry
    per slot, scratch); then J[r, c] = S on the structural pattern.  J's other entries are
    not written: zero them once, when J is allocated (zeroing IV-DREM's 123^2 entries on
    every call is 15 k stores, against the chain's 2.7 k multiply-adds).  Table indices are
    read as uint64 (see UNSIGNED_INDICES)."""
    for i in range(S.shape[0]):
        S[i] = 0.0
    for i in range(dst.shape[0]):
        s = src[i]
        d = uint64(dst[i])
        if s < 0:
            S[d] += F[uint64(fidx[i])]
        else:
            S[d] += F[uint64(fidx[i])] * S[uint64(s)]
    for e in range(j_row.shape[0]):
        J[uint64(j_row[e]), uint64(j_col[e])] = S[uint64(j_slot[e])]


@njit(cache=True, _nrt=False)
def fd_shift(xb, ub, xb0, ub0, nx, col, c0, c1, sign, hh):
    """Set the columns col[c0:c1] of the block to base + sign h (h = eps^(1/3) max(|v|, 1));
    with sign 0 restore them.  hh[c] receives (v + h) - (v - h) as represented."""
    for c in range(c0, c1):
        j = col[c]
        v = xb0[j] if j < nx else ub0[j - nx]
        h = 6.055454452393343e-06 * max(abs(v), 1.0)
        w = v + sign * h
        if sign > 0:
            hh[c] = (v + h) - (v - h)
        if j < nx:
            xb[j] = w
        else:
            ub[j - nx] = w


@njit(cache=True, _nrt=False)
def fd_scatter(yp, ym, hh, c0, c1, e_ptr, e_row, e_slot, JB):
    for c in range(c0, c1):
        inv = 1.0 / hh[c]
        for e in range(e_ptr[c], e_ptr[c + 1]):
            r = uint64(e_row[uint64(e)])
            JB[uint64(e_slot[uint64(e)])] = (yp[r] - ym[r]) * inv


@njit(cache=True, _nrt=False)
def fd_forward(xb, ub, xb0, ub0, nx, col, c0, c1, on, hh):
    """Move the columns col[c0:c1] of the block to base + h (h = sqrt(eps) max(|v|, 1)),
    or back to the base (on = 0.0; a float, so that numba compiles one version).  hh[c] receives (v + h) - v as represented."""
    for c in range(c0, c1):
        j = col[c]
        v = xb0[j] if j < nx else ub0[j - nx]
        w = v
        if on != 0.0:
            w = v + 1.4901161193847656e-08 * max(abs(v), 1.0)
            hh[c] = w - v
        if j < nx:
            xb[j] = w
        else:
            ub[j - nx] = w


@njit(cache=True, _nrt=False)
def fd_forward_scatter(yp, y0, hh, c0, c1, e_ptr, e_row, e_slot, JB):
    """Forward differences (yp - y0) / h of the group's columns into their JB slots."""
    for c in range(c0, c1):
        inv = 1.0 / hh[c]
        for e in range(e_ptr[c], e_ptr[c + 1]):
            r = uint64(e_row[uint64(e)])
            JB[uint64(e_slot[uint64(e)])] = (yp[r] - y0[r]) * inv


@njit(cache=True, _nrt=False)
def slu_factor(J, c, LU, piv, perm, rowptr, colidx, diagp):
    """Factor A = c I - J as L U of P A P^T (perm = P) on the static filled pattern.

    Row-oriented (IKJ) elimination with a dense work row; values go to LU.reshape(-1)[:nnz],
    the inverse pivots to row n of LU (LU has n + 2 rows: a division per pivot rather than
    per entry of L, 706 for IV-DREM, and per row of each solve) and perm to piv; row n + 1
    is the work row.  Returns SINGULAR for a pivot that is
    not finite or smaller than PIVOT_RTOL times the largest |A| entry of its row.
    Indices are read as uint64 (see UNSIGNED_INDICES).
    """
    n = J.shape[0]
    vals = LU.reshape(LU.shape[0] * n)
    inv = LU[n]
    w = LU[n + 1]            # every entry read in row i is written first (filled pattern)
    for i in range(n):
        piv[i] = perm[i]
    for i in range(n):
        pi = uint64(perm[i])
        rmax = 0.0
        for p in range(rowptr[i], rowptr[i + 1]):
            j = uint64(colidx[uint64(p)])
            a = -J[pi, uint64(perm[j])]
            if j == i:
                a += c
            w[j] = a
            if not (abs(a) <= rmax):      # also catches NaN / inf entries
                rmax = abs(a)
        for p in range(rowptr[i], diagp[i]):
            k = uint64(colidx[uint64(p)])
            l = w[k] * inv[k]
            w[k] = l
            if l != 0.0:
                for q in range(diagp[k] + 1, rowptr[k + 1]):
                    w[uint64(colidx[uint64(q)])] -= l * vals[uint64(q)]
        for p in range(rowptr[i], rowptr[i + 1]):
            vals[uint64(p)] = w[uint64(colidx[uint64(p)])]
        d = vals[uint64(diagp[i])]
        if not (abs(d) > PIVOT_RTOL * rmax) or not np.isfinite(d) or not np.isfinite(rmax):
            return SINGULAR
        inv[i] = 1.0 / d
    return OK


@njit(cache=True, _nrt=False)
def slu_solve(LU, perm, rowptr, colidx, diagp, b):
    """b = A^{-1} b for the factorisation of slu_factor (LU's row n + 1 is the work row).
    Indices are read as uint64 (see UNSIGNED_INDICES)."""
    n = b.shape[0]
    vals = LU.reshape(LU.shape[0] * n)
    inv = LU[n]
    y = LU[n + 1]
    for i in range(n):
        y[i] = b[uint64(perm[i])]
    for i in range(n):
        s = y[i]
        for p in range(rowptr[i], diagp[i]):
            q = uint64(p)
            s -= vals[q] * y[uint64(colidx[q])]
        y[i] = s
    for i in range(n - 1, -1, -1):
        r = uint64(i)
        s = y[r]
        for p in range(diagp[i] + 1, rowptr[i + 1]):
            q = uint64(p)
            s -= vals[q] * y[uint64(colidx[q])]
        y[r] = s * inv[r]
    for i in range(n):
        b[uint64(perm[i])] = y[i]
