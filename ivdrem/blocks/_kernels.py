"""Small numeric helpers that block kernels call (numba-compiled, cached on disk).

Kept free of Python objects so that the same call works from a kernel running in plain
Python (reference path) and from generated numba code (compiled path).
"""
import llvmlite.binding as llvm
import numpy as np
from numba import carray, njit, types
from numba.core import cgutils
from numba.core.imputils import impl_ret_borrowed
from numba.extending import get_cython_function_address, intrinsic, overload
from numba.np.arrayobj import make_array, populate_array

from ..models._rigid_body_jit import (SINGULAR_INERTIA_MESSAGE, _rb_cholesky,
                                      _rb_cholesky_solve)

# LAPACK from scipy, called by symbol name from cached machine code: the symbols are bound
# to scipy's routines at import, so a kernel loaded from the disk cache finds them in a new
# process (an address baked into the code would not survive it).
for _name in ("dgesdd", "dgesv"):
    llvm.add_symbol(f"ivdrem_{_name}",
                    get_cython_function_address("scipy.linalg.cython_lapack", _name))
_PTR = types.voidptr
_dgesdd = types.ExternalFunction("ivdrem_dgesdd", types.void(*([_PTR] * 14)))
_dgesv = types.ExternalFunction("ivdrem_dgesv", types.void(*([_PTR] * 8)))


# ------------------------------------------------------------------ scratch on the stack
# A kernel's temporaries (the regressors a block combines, the inertia's Cholesky factor,
# the mixing's LU) are small and live for one call: numba's np.empty takes each from the
# heap through its reference-counted allocator, about 22 allocations per right-hand side
# of the paper's loop (1.2 million a run, a tenth of its time in malloc, free and the
# allocator's bookkeeping).  stack_empty gives the same uninitialised array in the calling
# function's stack frame instead: an LLVM alloca, gone when that function returns.
# Plain Python (the reference path) gets np.empty.  Use it only for a temporary that does
# not outlive the function that creates it (never returned, never stored), at the
# function's top level (an alloca inside a loop grows the frame on every iteration), and
# for sizes of the model (a few regressor matrices: kilobytes, not the stack's megabytes).

@intrinsic
def _stack_buffer(typingctx, count, dtype):
    """A pointer to `count` uninitialised items of `dtype` in the caller's stack frame."""
    item = dtype.dtype if isinstance(dtype, types.DType) else dtype.instance_type

    def codegen(context, builder, signature, args):
        return builder.alloca(context.get_value_type(item), size=args[0])
    return types.CPointer(item)(types.intp, dtype), codegen


def stack_empty(shape, dtype=np.float64):
    """np.empty(shape, dtype) (shape an int or a pair); compiled: on the caller's stack."""
    return np.empty(shape, dtype)


@overload(stack_empty, inline="always")
def _stack_empty_compiled(shape, dtype=np.float64):
    if isinstance(dtype, types.NumberClass):
        item = dtype.instance_type
    elif isinstance(dtype, types.Omitted) or dtype is np.float64:
        item = types.float64
    else:
        return None
    # the item type as a Python object the compiled code can carry (a NumberClass)
    kind = {types.float64: np.float64, types.int64: np.int64}.get(item)
    if kind is None:
        return None
    if isinstance(shape, types.Integer):
        def impl(shape, dtype=np.float64):
            return carray(_stack_buffer(max(shape, 1), kind), (shape,))
        return impl
    if isinstance(shape, types.UniTuple) and shape.count == 2:
        def impl(shape, dtype=np.float64):
            return carray(_stack_buffer(max(shape[0] * shape[1], 1), kind), shape)
        return impl
    return None


# ------------------------------------------------------------------ matrix views
# Matrix-valued signals are flat row-major (ivdrem/blocks/_ports.py): a kernel sees one as a
# matrix through a view.  numba's a.reshape((rows, cols)) calls its C helper
# numba_attempt_nocopy_reshape, which works out the strides of any layout, on every call
# (about 2 % of a run of the paper's loop, a few reshapes per right-hand side); for a
# contiguous vector the view is known without it: the same data, strides (cols, 1) items.
# as_matrix gives that view (plain Python, and compiled for other layouts: a.reshape).

@intrinsic
def _matrix_view(typingctx, a, rows, cols):
    """The rows x cols row-major view of the contiguous vector a (rows cols == a.size)."""
    if not (isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C"):
        return None
    matrix = a.copy(ndim=2, layout="C")

    def codegen(context, builder, signature, args):
        vec = make_array(signature.args[0])(context, builder, args[0])
        out = make_array(signature.return_type)(context, builder)
        r = context.cast(builder, args[1], signature.args[1], types.intp)
        c = context.cast(builder, args[2], signature.args[2], types.intp)
        populate_array(out, data=vec.data, shape=cgutils.pack_array(builder, [r, c]),
                       strides=cgutils.pack_array(builder, [builder.mul(c, vec.itemsize),
                                                            vec.itemsize]),
                       itemsize=vec.itemsize, meminfo=vec.meminfo, parent=vec.parent)
        return impl_ret_borrowed(context, builder, signature.return_type, out._getvalue())
    return matrix(a, rows, cols), codegen


def as_matrix(a, rows, cols):
    """The flat row-major vector a seen as a rows x cols matrix, without a copy."""
    return a.reshape((rows, cols))


@overload(as_matrix, inline="always")
def _as_matrix_compiled(a, rows, cols):
    if isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C":
        def impl(a, rows, cols):
            if rows < 0 or cols < 0 or rows * cols != a.size:
                raise ValueError("as_matrix: rows x cols is not the vector's size")
            return _matrix_view(a, rows, cols)
        return impl

    def impl(a, rows, cols):
        return a.reshape((rows, cols))
    return impl


@njit(cache=True)
def matT_vec(A, x, out):
    """out = A^T x for A (m, k): used for Pi r and zeta z (the paper's nθ x n forms)."""
    m, k = A.shape
    for j in range(k):
        s = 0.0
        for i in range(m):
            s += A[i, j] * x[i]
        out[j] = s


@njit(cache=True)
def matT_mat(A, B, out):
    """out = A^T B for A (m, k), B (m, l): zeta phi^T from the stored n x nθ forms."""
    m, k = A.shape
    l = B.shape[1]
    for a in range(k):
        for b in range(l):
            s = 0.0
            for i in range(m):
                s += A[i, a] * B[i, b]
            out[a, b] = s


# ------------------------------------------------------------------ determinant, adjugate
# By the singular value decomposition A = U diag(sigma) V^T (G. W. Stewart, "On the
# adjugate matrix", Linear Algebra Appl. 283, 1998): with s_UV = det(U) det(V) = +-1,
#     det A = s_UV prod_j sigma_j,      adj A = s_UV V diag(pi) U^T,  pi_i = prod_{j!=i} sigma_j,
# products over the other singular values formed from prefix and suffix products (no
# division), so the adjugate of a singular A (rank n-1: rank one; rank <= n-2 or A = 0:
# zero) is as accurate as that of a regular one.  O(n^3); docs/mixing.md.

@njit(cache=True)
def svd_signed(A):
    """(U, sigma, Vt, s_UV) with A = U diag(sigma) Vt, sigma descending, s_UV = det(U) det(Vt)."""
    U, sig, Vt = np.linalg.svd(A)
    s = 1.0
    if np.linalg.det(U) < 0.0:
        s = -s
    if np.linalg.det(Vt) < 0.0:
        s = -s
    return U, sig, Vt, s


@njit(cache=True)
def svdvals_solve(P, Y, sig, x):
    """The singular values of P (descending, into sig) and x = P^-1 Y, by LAPACK's dgesdd
    without singular vectors and dgesv (an LU with partial pivoting): about a third of the
    cost of the full SVD (none of U, V).  Returns sign(det P), or 0.0 where P is singular
    to working precision or LAPACK fails (the caller then takes the SVD route)."""
    n = P.shape[0]
    a = np.empty((n, n))             # column-major copies of P (LAPACK's order)
    b = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            a[j, i] = P[i, j]
            b[j, i] = P[i, j]
    lwork = 10 * n + 10              # dgesdd, JOBZ = 'N': 3n + max(n, 7n) suffices
    work = np.empty(lwork)
    iwork = np.empty(8 * n, np.int32)
    ipiv = np.empty(n, np.int32)
    nn = np.array([n], np.int32)     # Fortran's arguments by reference
    one = np.array([1], np.int32)
    lw = np.array([lwork], np.int32)
    info = np.zeros(1, np.int32)
    job = np.array([ord("N")], np.uint8)
    dummy = np.empty(1)
    _dgesdd(job.ctypes, nn.ctypes, nn.ctypes, a.ctypes, nn.ctypes, sig.ctypes, dummy.ctypes,
            one.ctypes, dummy.ctypes, one.ctypes, work.ctypes, lw.ctypes, iwork.ctypes,
            info.ctypes)
    if info[0] != 0:
        return 0.0
    for i in range(n):
        x[i] = Y[i]
    _dgesv(nn.ctypes, one.ctypes, b.ctypes, nn.ctypes, ipiv.ctypes, x.ctypes, nn.ctypes,
           info.ctypes)
    if info[0] != 0:
        return 0.0
    sgn = 1.0
    for i in range(n):               # det P = prod u_ii, one sign flip per row interchange
        if ipiv[i] != i + 1:
            sgn = -sgn
        if b[i, i] < 0.0:
            sgn = -sgn
    return sgn


@njit(cache=True)
def products_without(sig, skip, out):
    """out[i] = prod_{j != i, j != skip} sig[j] (skip < 0: leave none out besides i);
    out[skip] = 0.  Prefix and suffix products, O(n), no division."""
    n = sig.shape[0]
    pre = 1.0
    for i in range(n):
        out[i] = pre
        if i != skip:
            pre *= sig[i]
    suf = 1.0
    for i in range(n - 1, -1, -1):
        out[i] *= suf
        if i != skip:
            suf *= sig[i]
    if skip >= 0:
        out[skip] = 0.0


@njit(cache=True)
def adj_from_svd(U, sig, Vt, s_uv, adj):
    """adj = s_UV V diag(pi) U^T; returns det = s_UV prod sigma."""
    n = sig.shape[0]
    pi = np.empty(n)
    products_without(sig, -1, pi)
    _scaled_adjugate(U, Vt, pi, s_uv, adj)
    d = s_uv
    for k in range(n):
        d *= sig[k]
    return d


@njit(cache=True)
def det_adj(A, adj):
    """det(A) and adj(A) (written into adj) by the signed SVD above; returns det(A).

    Exact in the sense of the SVD's backward error for singular A too (the mixing step
    (17) meets Psi = 0 at the start of every run, then rank-deficient Psi); adj(A) A = det(A) I.
    """
    U, sig, Vt, s = svd_signed(A)
    return adj_from_svd(U, sig, Vt, s, adj)


# ------------------------------------------------------------------ LU route
# For a regular A, adj A = det(A) A^-1 (Cramer), and both come from one LU with partial
# pivoting, P A = L U: det A = (-1)^(interchanges) prod u_kk.  Its error is that of the
# problem, about cond(A) eps, as the signed SVD's is; where A is close to singular (A = 0
# at the start of every run, then of rank < n while the window fills) the adjugate is
# still well determined while det and A^-1 are not, so the callers take this route only
# while 1/cond_1(A) >= LU_MIN_RCOND and the signed SVD otherwise.  Written out rather than
# called from LAPACK (dgetrf, dgecon, dgetrs): at the paper's 5 x 5 those calls cost about
# eight times the arithmetic (3.1 against 0.4 us measured); the arithmetic is LAPACK's
# unblocked dgetf2 (the same pivots, the same operations per entry).

#: the LU route is taken while 1/(||A||_1 ||A^-1||_1) is at least this (the "eigen"
#: variant's singular-value route uses the same bound on sigma_min/sigma_max)
LU_MIN_RCOND = 1e-9


@njit(cache=True)
def lu_factor(A, piv):
    """In place: A <- L\\U of A with partial pivoting (L unit lower, below the diagonal),
    piv[k] the row interchanged with k at step k.  False where a pivot is exactly zero
    (A singular to working precision; A is then partly factored)."""
    n = A.shape[0]
    for k in range(n):
        p = k
        big = abs(A[k, k])
        for i in range(k + 1, n):
            if abs(A[i, k]) > big:
                big = abs(A[i, k])
                p = i
        piv[k] = p
        if not big > 0.0:
            return False
        if p != k:
            for j in range(n):
                t = A[k, j]
                A[k, j] = A[p, j]
                A[p, j] = t
        ukk = A[k, k]
        for i in range(k + 1, n):
            lik = A[i, k] / ukk
            A[i, k] = lik
            if lik != 0.0:
                for j in range(k + 1, n):
                    A[i, j] -= lik * A[k, j]
    return True


@njit(cache=True)
def lu_det(LU, piv):
    """(det A, log10 |det A|) from lu_factor's LU: the product of the pivots, one sign flip
    per interchange; the logarithm of that product where it is a normal double, else the
    sum of the pivots' logarithms (finite where det A underflows)."""
    n = LU.shape[0]
    d = 1.0
    for k in range(n):
        d *= LU[k, k]
        if piv[k] != k:
            d = -d
    if abs(d) >= 2.2250738585072014e-308 and abs(d) < np.inf:
        return d, np.log10(abs(d))
    logd = 0.0
    for k in range(n):
        logd += np.log10(abs(LU[k, k]))
    return d, logd


@njit(cache=True)
def lu_solve(LU, piv, b):
    """In place: b <- A^-1 b from lu_factor's LU and piv."""
    n = LU.shape[0]
    for k in range(n):
        p = piv[k]
        if p != k:
            t = b[k]
            b[k] = b[p]
            b[p] = t
    for i in range(n):
        acc = b[i]
        for j in range(i):
            acc -= LU[i, j] * b[j]
        b[i] = acc
    for i in range(n - 1, -1, -1):
        acc = b[i]
        for j in range(i + 1, n):
            acc -= LU[i, j] * b[j]
        b[i] = acc / LU[i, i]


@njit(cache=True)
def _norm1(A):
    big = 0.0
    for j in range(A.shape[1]):
        c = 0.0
        for i in range(A.shape[0]):
            c += abs(A[i, j])
        big = max(big, c)
    return big


@njit(cache=True)
def lu_inverse_into(LU, piv, X):
    """X <- A^-1 from lu_factor's LU and piv: lu_solve on each column of the identity, the
    columns side by side.  Each column's operations, and their order, are lu_solve's (so the
    same values, bit for bit); the n columns are n independent chains of subtractions and
    divisions in flight at once instead of one after another (at 5 x 5 about 3x faster)."""
    n = LU.shape[0]
    for i in range(n):
        for j in range(n):
            X[i, j] = 0.0
        X[i, i] = 1.0
    for k in range(n):
        p = piv[k]
        if p != k:
            for j in range(n):
                t = X[k, j]
                X[k, j] = X[p, j]
                X[p, j] = t
    for i in range(n):
        for k in range(i):
            lik = LU[i, k]
            for j in range(n):
                X[i, j] -= lik * X[k, j]
    for i in range(n - 1, -1, -1):
        for k in range(i + 1, n):
            uik = LU[i, k]
            for j in range(n):
                X[i, j] -= uik * X[k, j]
        uii = LU[i, i]
        for j in range(n):
            X[i, j] = X[i, j] / uii


@njit(cache=True)
def lu_rcond(LU, piv, anorm, inv):
    """1/cond_1(A) = 1/(||A||_1 ||A^-1||_1) from lu_factor's LU, with the exact 1-norm of
    A^-1 from its columns (lu_inverse_into: O(n^3) like the factorisation, and at the
    mixing's sizes cheaper than an estimator's bookkeeping), written into inv (n x n: the
    caller keeps A^-1 or uses inv as scratch).  0.0 where ||A^-1|| overflows."""
    n = LU.shape[0]
    lu_inverse_into(LU, piv, inv)
    inorm = 0.0
    for j in range(n):
        c = 0.0
        for i in range(n):
            c += abs(inv[i, j])
        inorm = max(inorm, c)
    rc = 1.0 / (anorm * inorm)
    return rc if rc > 0.0 else 0.0


@njit(cache=True)
def lu_rcond_lower_bound(LU, anorm, z):
    """A lower bound of 1/cond_1(A) from lu_factor's LU in O(n^2), z scratch of n: with
    A^-1 = U^-1 L^-1 P and |T^-1| <= M(T)^-1 for a triangular T and its comparison matrix
    M(T) (|t_ii| on the diagonal, -|t_ij| off it; Higham, Accuracy and Stability of
    Numerical Algorithms, Thm 8.12), ||A^-1||_1 <= ||M(U)^-1||_1 ||M(L)^-1||_1, each the
    largest entry of the solution of M(T)^T y = e (sums of positive terms: accurate to a
    few ulp).  0.0 where a pivot is zero or the bound overflows."""
    n = LU.shape[0]
    bu = 0.0
    for j in range(n):                      # M(U)^T y = e, forward
        acc = 1.0
        for i in range(j):
            acc += abs(LU[i, j]) * z[i]
        d = abs(LU[j, j])
        if not d > 0.0:
            return 0.0
        z[j] = acc / d
        if not z[j] < np.inf:               # overflow (or NaN): no bound
            return 0.0
        bu = max(bu, z[j])
    bl = 0.0
    for j in range(n - 1, -1, -1):          # M(L)^T y = e, L unit lower, backward
        acc = 1.0
        for i in range(j + 1, n):
            acc += abs(LU[i, j]) * z[i]
        if not acc < np.inf:
            return 0.0
        z[j] = acc
        bl = max(bl, acc)
    rc = 1.0 / (anorm * bu * bl)
    return rc if rc > 0.0 else 0.0


@njit(cache=True)
def lu_inverse(A, LU, piv, inv):
    """LU of A (into LU and piv, as lu_factor) and A^-1 (into inv).  Returns (det A,
    log10 |det A|, 1/cond_1(A)); 1/cond 0.0 (and det 0.0) where a pivot is zero, inv then
    not written."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            LU[i, j] = A[i, j]
    if not lu_factor(LU, piv):
        return 0.0, LOG10_ZERO_SIGMA * n, 0.0
    d, logd = lu_det(LU, piv)
    return d, logd, lu_rcond(LU, piv, _norm1(A), inv)


@njit(cache=True)
def _paper_lu(Y, P, s, Delta, calY, logD, piv, inv, x):
    """The paper's mixing (17) by the LU route: Delta = det P, calY = adj(P) Y / s =
    det(P) P^-1 Y / s.  P is factored in place; piv (n), inv (n x n) and x (n) are the
    caller's scratch.  False (Delta, calY, logD not written, P overwritten) where
    1/cond_1(P) < LU_MIN_RCOND."""
    n = Y.shape[0]
    anorm = _norm1(P)
    if not lu_factor(P, piv):
        return False
    # the exact 1/cond_1 (n solves) only where the O(n^2) lower bound cannot settle it: a
    # bound twice the threshold (its rounding, a few ulp, far inside the factor 2) means
    # the exact value is above it too, so the route is the one the exact test takes
    if not (lu_rcond_lower_bound(P, anorm, x) >= 2.0 * LU_MIN_RCOND
            or lu_rcond(P, piv, anorm, inv) >= LU_MIN_RCOND):
        return False
    d, logd = lu_det(P, piv)
    for i in range(n):
        x[i] = Y[i]
    lu_solve(P, piv, x)
    # a well-conditioned but tiny P (|P| near the smallest doubles) has an inverse beyond
    # the largest: P^-1 Y overflows where adj(P) Y does not; the SVD route takes it then
    for i in range(n):
        if not np.isfinite(d * x[i]):
            return False
    Delta[0] = d
    logD[0] = logd
    for i in range(n):
        calY[i] = d * x[i] / s
    return True


@njit(cache=True)
def log10_abs_det(sig):
    """log10 |det A| = sum log10 sigma_j, finite where det A underflows; a zero singular
    value counts as LOG10_ZERO_SIGMA (a finite stand-in for -inf, see docs/mixing.md)."""
    acc = 0.0
    for k in range(sig.shape[0]):
        if sig[k] > 0.0:
            acc += np.log10(sig[k])
        else:
            acc += -400.0
    return acc


@njit(cache=True)
def adj_derivative_parts(U, sig, Vt):
    """(A, G, B) with d adj(A)[E_ab] = s_UV sum over three rank-one pieces, O(n^3):

        d adj[E_ab]_ij = s_UV [ (G_ab + B_ba) A_ij - A_ia (G_jb + B_bj) + A_ba B_ij - B_ia A_bj ]

    A = V diag(w) U^T, G = U diag(rho) V^T, B = v_m u_m^T, m the smallest singular value,
    w_i = prod_{l != i, m} sigma_l (w_m = 0), rho_k = sigma_m / sigma_k (rho_m = 0).  From
    adj(P + E) = s_UV V adj(Sigma + U^T E V) U^T and the derivative of the adjugate of a
    diagonal matrix, whose second-order products prod_{l != i, k} sigma_l are the rank-three
    matrix w rho^T + e_m w^T + w e_m^T off the diagonal (the diagonal cancels); no division
    by a singular value that can vanish alone.  docs/mixing.md derives it."""
    n = sig.shape[0]
    m = n - 1
    w = np.empty(n)
    products_without(sig, m, w)
    rho = np.zeros(n)
    for k in range(m):
        if sig[k] > 0.0:
            rho[k] = sig[m] / sig[k]
    A = np.zeros((n, n))
    G = np.zeros((n, n))
    B = np.empty((n, n))
    UT = np.ascontiguousarray(U.T)
    # each entry's sum over k in order, as a row at a time (contiguous inner loops)
    for i in range(n):
        for k in range(n):
            ca = Vt[k, i] * w[k]
            cg = U[i, k] * rho[k]
            for j in range(n):
                A[i, j] += ca * UT[k, j]
                G[i, j] += cg * Vt[k, j]
        for j in range(n):
            B[i, j] = Vt[m, i] * U[j, m]
    return A, G, B


@njit(cache=True)
def spd_solve(A, B):
    """B <- A^{-1} B for a symmetric positive definite A (n, n), B (n, k), by the package's
    one Cholesky (ivdrem.models.rigid_body, its one rule for "singular"; A is not
    modified): the plant's Jacobian solves with the inertia matrix M(q)."""
    n = A.shape[0]
    L = A.copy()
    if _rb_cholesky(L) != 0:
        raise ValueError(SINGULAR_INERTIA_MESSAGE)
    col = np.empty(n)
    for c in range(B.shape[1]):
        for i in range(n):
            col[i] = B[i, c]
        _rb_cholesky_solve(L, col)
        for i in range(n):
            B[i, c] = col[i]


# ------------------------------------------------------------------ start of the composite term
@njit(cache=True)
def start_weight(t, t_on, t_ramp):
    """w(t) = 0 for t <= t_on, 1 for t >= t_on + t_ramp, the C1 ramp 3x^2 - 2x^3
    (x = (t - t_on)/t_ramp) between; exactly 1 when t_ramp <= 0 and t >= t_on."""
    if t >= t_on + t_ramp:
        return 1.0
    if t <= t_on:
        return 0.0
    x = (t - t_on) / t_ramp
    return x * x * (3.0 - 2.0 * x)


# ------------------------------------------------------------------ the mixing step (17)
# Variants (docs/mixing.md), with s = 1 + ||Psi||_F, P = Psi / s (singular values <= 1):
#   0 "paper"    Delta = det P,                      calY = adj(P) Y / s           (17), E4
#   1 "eigen"    Delta = prod sigma_j / (sigma_j + f), calY = adj(P) Y / (s prod (sigma_j + f)),
#                f = f_rel ||P||_F: the per-eigenvalue least-squares-type normalisation
#   2 "channel"  Delta_i = s det P / c_i,            calY_i = (adj(P) Y)_i / c_i,
#                c_i = sqrt(C_ii^2 + eps^2 ||C_i,:||^2), C = adj(P): the (i, i) cofactor,
#                guarded by its row (it can vanish for the instrumental, non-symmetric Psi)
# Every variant divides det P and adj(P) Y by the same known positive signal per channel,
# so calY_i = Delta_i theta_i + calW_i holds exactly.  log10 |Delta| is computed from the
# singular values, so it is finite where Delta underflows.
MIXING_VARIANTS = ("paper", "eigen", "channel")
LOG10_ZERO_SIGMA = -400.0          # log10 of a singular value that is exactly zero


# Each mixing function is written once, with the variant `code` a free variable, and
# compiled once per variant (numba prunes the branches of the other variants before it
# types them, so a run compiles the variant it uses: the Panda's "eigen" mixing step and
# its derivatives in about a third of the time of all three; docs/performance.md).  The
# public function takes `code` as before: from Python it calls the variant's compiled
# function; in a kernel, where `code` is the block's structural constant (a literal in
# its wrapper), the overload calls that variant alone, else it chooses at run time.  The
# arithmetic of every variant is that of the one function it was before.

def _compiled_variants(factory, name):
    """The njit functions factory(code) for the codes of MIXING_VARIANTS, each cached in a
    file of its own (``name_<variant>``: numba names the cache by the qualified name)."""
    out = []
    for code, variant in enumerate(MIXING_VARIANTS):
        fn = factory(code)
        fn.__name__ = fn.__qualname__ = f"{name}_{variant}"
        out.append(njit(cache=True)(fn))
    return tuple(out)


def compile_variant(name, code):
    """Compile variant `code` of the mixing function `name` ("mixing_values",
    "mixing_derivatives") for the argument types every caller passes (C-contiguous float64
    vectors, float64 numbers, the derivatives' C-contiguous matrix): what a kernel's
    wrapper, γ "auto"'s estimate and the Python path then load from numba's cache."""
    vec, mat = types.float64[::1], types.float64[:, ::1]
    args = {"mixing_values": (vec, vec, types.float64, types.float64, vec, vec, vec),
            "mixing_derivatives": (vec, vec, types.float64, types.float64, mat)}[name]
    fn = {"mixing_values": mixing_values, "mixing_derivatives": mixing_derivatives}[name]
    fn.variants[_variant_index(code)].compile(args)


def _variant_index(code):
    """The variant a mixing function takes for `code`: 0 "paper", 1 "eigen", any other
    "channel" (the else branch of the one function they were written as)."""
    return code if code == 0 or code == 1 else 2


@njit(cache=True)
def _frobenius(Psi):
    big = 0.0
    for k in range(Psi.shape[0]):
        big = max(big, abs(Psi[k]))
    ss = 0.0
    if big > 0.0:
        for k in range(Psi.shape[0]):
            r = Psi[k] / big                             # scaled: no overflow for huge Psi
            ss += r * r
    return big * np.sqrt(ss)


@njit(cache=True)
def _log10_sum(sig):
    acc = 0.0
    for k in range(sig.shape[0]):
        acc += np.log10(sig[k]) if sig[k] > 0.0 else LOG10_ZERO_SIGMA
    return acc


@njit(cache=True)
def _scaled_adjugate(U, Vt, coef, s_uv, out):
    """out = s_UV V diag(coef) U^T."""
    n = coef.shape[0]
    UT = np.ascontiguousarray(U.T)
    acc = np.zeros(n)
    for i in range(n):                  # each sum over k in order, a row at a time
        acc[:] = 0.0
        for k in range(n):
            c = Vt[k, i] * coef[k]
            for j in range(n):
                acc[j] += c * UT[k, j]
        for j in range(n):
            out[i, j] = s_uv * acc[j]


@njit(cache=True)
def _channel_divisors(C, guard, c):
    """c_i = sqrt(C_ii^2 + guard^2 ||C_i,:||^2) (any positive common factor of C cancels)."""
    n = C.shape[0]
    for i in range(n):
        r2 = 0.0
        for j in range(n):
            r2 += C[i, j] * C[i, j]
        c[i] = np.sqrt(C[i, i] * C[i, i] + guard * guard * r2)


@njit(cache=True)
def _channel_coefficients(sig, coef):
    """pi_k / K with K = prod_{j != m} sigma_j: sigma_m / sigma_k, 1 at k = m; all zero when
    rank <= n - 2 (then adj = 0 and K = 0)."""
    n = sig.shape[0]
    m = n - 1
    coef[m] = 1.0
    if n > 1 and not sig[m - 1] > 0.0:
        for k in range(n):
            coef[k] = 0.0
        return False
    for k in range(m):
        coef[k] = sig[m] / sig[k]
    return True


#: "eigen" takes the route of :func:`_eigen_fast` while sigma_min/sigma_max of P is above
#: this: its error (that of an LU solve, about cond(P) eps) then stays within that of the
#: SVD route's adjugate (tests/test_mixing.py); below, and at a singular P, the SVD route.
EIGEN_FAST_MIN_RATIO = 1e-9


@njit(cache=True)
def _eigen_fast(Y, P, s, f, Delta, calY, logD):
    """"eigen" without singular vectors: adj(P) = det(P) P^-1 for a regular P, so
    Delta = sign(det P) prod sigma_j/(sigma_j + f) and calY = adj(P) Y/(s prod(sigma_j + f))
    = Delta P^-1 Y / s, from the singular values and one LU solve (svdvals_solve) instead
    of the SVD's vectors and an O(n^3) adjugate.  False (nothing written) where P is too
    close to singular for the solve (EIGEN_FAST_MIN_RATIO)."""
    n = Y.shape[0]
    sig = np.empty(n)
    x = np.empty(n)
    sgn = svdvals_solve(P, Y, sig, x)
    if sgn == 0.0 or not sig[n - 1] > EIGEN_FAST_MIN_RATIO * sig[0]:
        return False
    d = sgn
    acc = 0.0                                           # log10 r_j = -log1p(f/sigma_j)/ln 10
    for k in range(n):
        d *= sig[k] / (sig[k] + f)
        acc += -np.log1p(f / sig[k]) / np.log(10.0)
    Delta[0] = d
    logD[0] = acc
    for i in range(n):
        calY[i] = d * x[i] / s
    return True


def _mixing_values_of(code):
    """mixing_values with its variant `code` fixed: see :func:`_compiled_variants`."""
    def mixing_values_variant(Y, Psi, f_rel, guard, Delta, calY, logD):
        n = Y.shape[0]
        nrm = _frobenius(Psi)
        s = 1.0 + nrm
        # P, then the LU route's scratch, P^-1 and one vector, and its pivots: on the stack
        work = stack_empty((2 * n + 1, n))
        piv = stack_empty(n, np.int64)
        P = work[:n]
        for i in range(n):
            for j in range(n):
                P[i, j] = Psi[i * n + j] / s
        if code == 1 and nrm > 0.0 and _eigen_fast(Y, P, s, f_rel * nrm / s, Delta, calY, logD):
            return
        if code == 0 and nrm > 0.0:
            if _paper_lu(Y, P, s, Delta, calY, logD, piv, work[n:2 * n], work[2 * n]):
                return
            for i in range(n):                              # P was factored in place
                for j in range(n):
                    P[i, j] = Psi[i * n + j] / s
        U, sig, Vt, s_uv = svd_signed(P)
        coef = np.empty(n)
        C = np.empty((n, n))
        if code == 0:
            products_without(sig, -1, coef)
            _scaled_adjugate(U, Vt, coef, s_uv, C)
            d = s_uv
            for k in range(n):
                d *= sig[k]
            Delta[0] = d
            logD[0] = _log10_sum(sig)
            for i in range(n):
                acc = 0.0
                for j in range(n):
                    acc += C[i, j] * Y[j]
                calY[i] = acc / s
        elif code == 1:
            if nrm == 0.0:
                Delta[0] = 0.0
                logD[0] = n * LOG10_ZERO_SIGMA
                calY[:] = 0.0
                return
            f = f_rel * nrm / s
            r = np.empty(n)
            for k in range(n):
                r[k] = sig[k] / (sig[k] + f)
            products_without(r, -1, coef)
            for k in range(n):
                coef[k] /= sig[k] + f                       # pi_k / prod_j (sigma_j + f)
            _scaled_adjugate(U, Vt, coef, s_uv, C)
            d = s_uv
            for k in range(n):
                d *= r[k]
            Delta[0] = d
            acc = 0.0                                       # log10 r_j = -log1p(f/sigma_j)/ln 10
            for k in range(n):
                acc += -np.log1p(f / sig[k]) / np.log(10.0) if sig[k] > 0.0 else LOG10_ZERO_SIGMA
            logD[0] = acc
            for i in range(n):
                acc = 0.0
                for j in range(n):
                    acc += C[i, j] * Y[j]
                calY[i] = acc / s
        else:
            # normalised by K = prod_{j != m} sigma_j (m the smallest): C/K has entries <= 1
            m = n - 1
            _channel_coefficients(sig, coef)
            _scaled_adjugate(U, Vt, coef, s_uv, C)
            c = np.empty(n)
            _channel_divisors(C, guard, c)
            logK = _log10_sum(sig[:m])
            for i in range(n):
                acc = 0.0
                for j in range(n):
                    acc += C[i, j] * Y[j]
                if c[i] > 0.0:
                    calY[i] = acc / c[i]
                    Delta[i] = s * s_uv * sig[m] / c[i]
                    logD[i] = (np.log10(s) + (np.log10(sig[m]) if sig[m] > 0.0
                                              else LOG10_ZERO_SIGMA) - np.log10(c[i]))
                else:
                    calY[i] = 0.0
                    Delta[i] = 0.0
                    logD[i] = np.log10(s) + logK + LOG10_ZERO_SIGMA
    return mixing_values_variant


_MIXING_VALUES = _compiled_variants(_mixing_values_of, "mixing_values")


def mixing_values(code, Y, Psi, f_rel, guard, Delta, calY, logD):
    """The mixing step (17) in variant `code` (MIXING_VARIANTS): writes Delta, calY and
    logD = log10 |Delta| (finite where Delta underflows)."""
    _MIXING_VALUES[_variant_index(code)](Y, Psi, f_rel, guard, Delta, calY, logD)


mixing_values.variants = _MIXING_VALUES


@overload(mixing_values, prefer_literal=True)
def _mixing_values_compiled(code, Y, Psi, f_rel, guard, Delta, calY, logD):
    if isinstance(code, types.IntegerLiteral):      # a kernel's structural constant
        variant = _MIXING_VALUES[_variant_index(code.literal_value)]

        def impl(code, Y, Psi, f_rel, guard, Delta, calY, logD):
            variant(Y, Psi, f_rel, guard, Delta, calY, logD)
        return impl
    paper, eigen, channel = _MIXING_VALUES

    def impl(code, Y, Psi, f_rel, guard, Delta, calY, logD):
        if code == 0:
            paper(Y, Psi, f_rel, guard, Delta, calY, logD)
        elif code == 1:
            eigen(Y, Psi, f_rel, guard, Delta, calY, logD)
        else:
            channel(Y, Psi, f_rel, guard, Delta, calY, logD)
    return impl


@njit(cache=True)
def _adjugate_y_derivative(a, b, A, G, B, AY, BY, GtY, s_uv, out):
    """out[c] = d (adj(P) Y)_c / dP_ab from adj_derivative_parts (A Y, B Y, G^T Y given)."""
    gb = G[a, b] + B[b, a]
    aba = A[b, a]
    t2 = GtY[b] + BY[b]
    for c in range(out.shape[0]):
        out[c] = s_uv * (gb * AY[c] + aba * BY[c] - A[c, a] * t2 - B[c, a] * AY[b])


@njit(cache=True)
def _paper_lu_derivatives(Y, P, s, g, jac):
    """mixing_derivatives of the paper's mixing by the LU route: with C = adj P = det(P) P^-1
    and x = P^-1 Y, d det/dP_ab = C_ba, d log|det|/dP_ab = (P^-1)_ba and
    d(C Y)_c/dP_ab = det ((P^-1)_ba x_c - (P^-1)_ca x_b), chained through s as in
    mixing_derivatives.  False (nothing written) where 1/cond_1(P) < LU_MIN_RCOND."""
    n = Y.shape[0]
    LU = stack_empty((n, n))
    inv = stack_empty((n, n))
    piv = stack_empty(n, np.int64)
    x = stack_empty(n)
    D, logd, rc = lu_inverse(P, LU, piv, inv)
    if not rc >= LU_MIN_RCOND:
        return False
    for i in range(n):
        x[i] = Y[i]
    lu_solve(LU, piv, x)
    for i in range(n):              # an inverse beyond the doubles (a tiny P): SVD route
        if not np.isfinite(x[i]):
            return False
        for j in range(n):
            if not np.isfinite(inv[i, j]):
                return False
    ln10 = np.log(10.0)
    rows_L = 1 + n
    for a in range(n):
        for b in range(n):
            col = n + a * n + b
            gab = g[a * n + b]
            jac[0, col] = (D * inv[b, a] - n * D * gab) / s
            jac[rows_L, col] = (inv[b, a] - n * gab) / (ln10 * s)
    s2 = s * s
    for c in range(n):
        row = 1 + c
        Dxc = D * x[c]
        for a in range(n):
            Dica = D * inv[c, a]
            for b in range(n):
                col = n + a * n + b
                jac[row, col] = (Dxc * inv[b, a] - Dica * x[b] - n * Dxc * g[a * n + b]) / s2
        for j in range(n):
            jac[row, j] = D * inv[c, j] / s
    return True


def _mixing_derivatives_of(code):
    """mixing_derivatives with its variant `code` fixed: see :func:`_compiled_variants`."""
    def mixing_derivatives_variant(Y, Psi, f_rel, guard, jac):
        n = Y.shape[0]
        nn = n * n
        k = n if code == 2 else 1
        nrm = _frobenius(Psi)
        s = 1.0 + nrm
        P = stack_empty((n, n))
        g = stack_empty(nn)
        for i in range(n):
            for j in range(n):
                P[i, j] = Psi[i * n + j] / s
                g[i * n + j] = Psi[i * n + j] / nrm if nrm > 0.0 else 0.0
        if code == 0 and nrm > 0.0 and _paper_lu_derivatives(Y, P, s, g, jac):
            return
        U, sig, Vt, s_uv = svd_signed(P)
        m = n - 1
        ln10 = np.log(10.0)
        C = np.empty((n, n))                  # adj(P), scaled per variant (below)
        coef = np.empty(n)
        A, G, B = adj_derivative_parts(U, sig, Vt)
        # dlogsig[a, b] = sum_j u_aj v_bj / sigma_j = d sum_j log sigma_j / dP_ab
        dls = np.zeros((n, n))
        for a in range(n):                  # each sum over j in order, a row at a time
            for j in range(n):
                if sig[j] > 0.0:
                    u = U[a, j]
                    sj = sig[j]
                    for b in range(n):
                        dls[a, b] += u * Vt[j, b] / sj
        scale_A = 1.0                          # A (and C) carry this factor: N or K below
        rows_D = 0
        rows_Y = k
        rows_L = k + n
        if code == 1 and nrm == 0.0:
            return                             # all outputs are 0 near Psi = 0 along rays
        if code == 0:
            products_without(sig, -1, coef)
        elif code == 1:
            f = f_rel * nrm / s
            r = np.empty(n)
            tau = np.empty(n)
            for j in range(n):
                tau[j] = sig[j] + f
                r[j] = sig[j] / tau[j]
            products_without(r, -1, coef)
            for j in range(n):
                coef[j] /= tau[j]
            # A / N: w_i / N = (1/(tau_i tau_m)) prod_{l != i, m} r_l
            wN = np.empty(n)
            products_without(r, m, wN)
            for i in range(m):
                wN[i] /= tau[i] * tau[m]
            UT = np.ascontiguousarray(U.T)
            A[:, :] = 0.0
            for i in range(n):              # each sum over l in order, a row at a time
                for l in range(n):
                    c = Vt[l, i] * wN[l]
                    for j in range(n):
                        A[i, j] += c * UT[l, j]
            # Lam = d log N / dP = U diag(1/tau) V^T + f_rel P/||P||_F sum 1/tau
            # (||P||_F = nrm / s and f = f_rel ||P||_F, so df/dP = f_rel P / ||P||_F)
            sinv = 0.0
            for j in range(n):
                sinv += 1.0 / tau[j]
            Lam = np.zeros((n, n))
            pn = nrm / s
            for a in range(n):              # each sum over j in order, a row at a time
                for j in range(n):
                    u = U[a, j]
                    tj = tau[j]
                    for b in range(n):
                        Lam[a, b] += u * Vt[j, b] / tj
                for b in range(n):
                    Lam[a, b] = Lam[a, b] + f_rel * P[a, b] / pn * sinv
            # d log10 Delta / dP without the cancellation of dls - Lam:
            # 1/sigma_j - 1/tau_j = f / (sigma_j tau_j)
            dls[:, :] = 0.0
            for a in range(n):              # each sum over j in order, a row at a time
                for j in range(n):
                    u = U[a, j]
                    if sig[j] > 0.0:
                        wj = f / (sig[j] * tau[j])
                        for b in range(n):
                            dls[a, b] += u * Vt[j, b] * wj
                    else:
                        tj = tau[j]
                        for b in range(n):
                            dls[a, b] -= u * Vt[j, b] / tj
                for b in range(n):
                    dls[a, b] = dls[a, b] - f_rel * P[a, b] / pn * sinv
        else:
            full = _channel_coefficients(sig, coef)
            if not full:
                return                         # rank <= n - 2: outputs 0, a kink
            for i in range(n):
                for j in range(n):
                    acc = 0.0
                    for l in range(m):
                        acc += Vt[l, i] * U[j, l] / sig[l]      # A / K: w_l / K = 1 / sigma_l
                    A[i, j] = acc
        _scaled_adjugate(U, Vt, coef, s_uv, C)
        CY = np.empty(n)
        AY = np.empty(n)
        BY = np.empty(n)
        GtY = np.empty(n)
        for i in range(n):
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            a4 = 0.0
            for j in range(n):
                a1 += C[i, j] * Y[j]
                a2 += A[i, j] * Y[j]
                a3 += B[i, j] * Y[j]
                a4 += G[j, i] * Y[j]
            CY[i] = a1
            AY[i] = a2
            BY[i] = a3
            GtY[i] = a4
        # dF[c] = d (C Y)_c / dP_ab, C = adj(P) (times the variant's 1/N or 1/K), for one (a, b)
        # at a time (_adjugate_y_derivative): all n^3 of them at once cost 0.6 MiB per call on
        # the Panda, a fresh allocation whose pages the kernel zeroed on every Jacobian
        dF = np.empty(n)
        if code == 0 or code == 1:
            if code == 0:
                D = s_uv
                for j in range(n):
                    D *= sig[j]
                qD, qF, eF, qL = float(n), float(n - 1), -1.0, n / ln10
            else:
                D = s_uv
                for j in range(n):
                    D *= r[j]
                qD, qF, eF, qL = 0.0, -1.0, -1.0, 0.0
            for a in range(n):
                for b in range(n):
                    col = n + a * n + b
                    dD = C[b, a]
                    dL = dls[a, b] / ln10
                    if code == 1:
                        # C^T/N - D Lam cancels: D dlog|D| (dls, computed directly) when D != 0
                        dD = D * dls[a, b] if sig[m] > 0.0 else dD - D * Lam[a, b]
                    jac[rows_D, col] = (dD - qD * D * g[col - n]) / s
                    jac[rows_L, col] = (dL - qL * g[col - n]) / s
            # d(C Y)_c/dP_ab (_adjugate_y_derivative's sums, term for term) row by row: each
            # row of jac written in order, not one entry per row in turn (a cache line each)
            gbT = np.empty((n, n))               # G_ab + B_ba, A_ba, GtY_b + BY_b
            AT = np.empty((n, n))
            t2 = np.empty(n)
            for a in range(n):
                for b in range(n):
                    gbT[a, b] = G[a, b] + B[b, a]
                    AT[a, b] = A[b, a]
            for b in range(n):
                t2[b] = GtY[b] + BY[b]
            for c in range(n):
                row = rows_Y + c
                for a in range(n):
                    Aca = A[c, a]
                    Bca = B[c, a]
                    for b in range(n):
                        col = n + a * n + b
                        dFc = s_uv * (gbT[a, b] * AY[c] + AT[a, b] * BY[c] - Aca * t2[b]
                                      - Bca * AY[b])
                        if code == 1:
                            dFc -= CY[c] * Lam[a, b]
                        # calY = F s^-1, F of degree qF: s^-2 (dF - (qF + 1) F g)
                        jac[row, col] = (dFc - (qF - eF) * CY[c] * g[col - n]) / (s * s)
            for i in range(n):
                for j in range(n):
                    jac[rows_Y + i, j] = C[i, j] / s
            return
        # "channel", with C, A and c divided by K = prod_{j != m} sigma_j:
        # Delta_i = s Di, Di = s_uv sigma_m / c_i (degree 1); calY_i = (C Y)_i / c_i (degree 0)
        c = np.empty(n)
        _channel_divisors(C, guard, c)
        # d c_i / c_i = [C_ii dC_ii + guard^2 sum_j C_ij dC_ij] / c_i^2, with
        # dC_ij/dP_ab = s_uv [(G_ab + B_ba) A_ij - A_ia (G_jb + B_bj) + A_ba B_ij - B_ia A_bj]
        ACt = np.zeros(n)
        BCt = np.zeros(n)
        CG = np.zeros((n, n))
        CBt = np.zeros((n, n))
        CAt = np.zeros((n, n))
        for i in range(n):
            for j in range(n):
                ACt[i] += A[i, j] * C[i, j]
                BCt[i] += B[i, j] * C[i, j]
            for b in range(n):
                a1 = 0.0
                a2 = 0.0
                a3 = 0.0
                for j in range(n):
                    a1 += C[i, j] * G[j, b]
                    a2 += C[i, j] * B[b, j]
                    a3 += C[i, j] * A[b, j]
                CG[i, b] = a1
                CBt[i, b] = a2
                CAt[i, b] = a3
        g2 = guard * guard
        for a in range(n):
            for b in range(n):
                col = n + a * n + b
                gb = G[a, b] + B[b, a]
                aba = A[b, a]
                _adjugate_y_derivative(a, b, A, G, B, AY, BY, GtY, s_uv, dF)
                for i in range(n):
                    if not c[i] > 0.0:
                        continue
                    dCii = s_uv * (gb * A[i, i] - A[i, a] * (G[i, b] + B[b, i]) + aba * B[i, i]
                                   - B[i, a] * A[b, i])
                    dR = s_uv * (gb * ACt[i] - A[i, a] * (CG[i, b] + CBt[i, b]) + aba * BCt[i]
                                 - B[i, a] * CAt[i, b])
                    dlc = (C[i, i] * dCii + g2 * dR) / (c[i] * c[i])
                    Di = s_uv * sig[m] / c[i]
                    # Delta_i = s Di(P), Di of degree 1: q - e = 0, do/dPsi = dDi/dP
                    jac[rows_D + i, col] = C[b, a] / c[i] - Di * dlc
                    yi = CY[i] / c[i]
                    jac[rows_Y + i, col] = (dF[i] / c[i] - yi * dlc) / s
                    # log10 |Delta_i| = log10 s + log10 |Di|: the s terms cancel
                    jac[rows_L + i, col] = (dls[a, b] - dlc) / (ln10 * s)
        for i in range(n):
            if c[i] > 0.0:
                for j in range(n):
                    jac[rows_Y + i, j] = C[i, j] / c[i]
    return mixing_derivatives_variant


_MIXING_DERIVATIVES = _compiled_variants(_mixing_derivatives_of, "mixing_derivatives")


def mixing_derivatives(code, Y, Psi, f_rel, guard, jac):
    """Jacobian of mixing_values: jac[(k + n + k), (n + n*n)] over (Y, Psi), rows Delta (k
    entries: 1, or n for "channel"), calY, logD; O(n^3) (docs/mixing.md).

    Each output is o = h(P, Y) s^e with h homogeneous of degree q in P (P = Psi/s,
    s = 1 + ||Psi||_F, g = ds/dPsi = Psi/||Psi||_F), so by Euler's identity
        do/dPsi_ab = s^(e-1) (dh/dP_ab - (q - e) h g_ab),      do/dY = s^e dh/dY.
    dh/dP comes from d det = tr(adj dP) and the adjugate's derivative in
    adj_derivative_parts; at Psi = 0 the kink of ||Psi||_F is taken as g = 0."""
    _MIXING_DERIVATIVES[_variant_index(code)](Y, Psi, f_rel, guard, jac)


mixing_derivatives.variants = _MIXING_DERIVATIVES


@overload(mixing_derivatives, prefer_literal=True)
def _mixing_derivatives_compiled(code, Y, Psi, f_rel, guard, jac):
    if isinstance(code, types.IntegerLiteral):      # a kernel's structural constant
        variant = _MIXING_DERIVATIVES[_variant_index(code.literal_value)]

        def impl(code, Y, Psi, f_rel, guard, jac):
            variant(Y, Psi, f_rel, guard, jac)
        return impl
    paper, eigen, channel = _MIXING_DERIVATIVES

    def impl(code, Y, Psi, f_rel, guard, jac):
        if code == 0:
            paper(Y, Psi, f_rel, guard, jac)
        elif code == 1:
            eigen(Y, Psi, f_rel, guard, jac)
        else:
            channel(Y, Psi, f_rel, guard, jac)
    return impl


# ------------------------------------------------------------------ a model-exchange FMU's call
# The FMU plant block (ivdrem.fmu.plant) evaluates its FMU with one sequence of fmi2 calls,
# written here once for both of its kernels (derivatives and outputs).  The C functions are
# called by address (call_c: a leaf of the base layer, so the blocks' helpers may use it);
# the addresses arrive at run time in the float64 table `fmi`, never as literals, so the
# generated code is the same in every process.
from .._native_call import call_c  # noqa: E402 - with the helper that uses it (see above)

#: what the address table ``fmi`` of :func:`fmi2_evaluate` holds, in order (``fmi[k]``):
#: the FMU's component, its fmi2 functions, and the Python side's error report
#: (``report(which, status, t, buffer, size)``: the message's length, the FMU reset);
#: :func:`ivdrem.fmu.plant.fmu_plant` builds the table in this order
FMI2_TABLE = ("component", "fmi2SetTime", "fmi2SetContinuousStates", "fmi2SetReal",
              "fmi2GetDerivatives", "fmi2GetReal", "report")
_FMI2_SET_TIME = FMI2_TABLE.index("fmi2SetTime")
_FMI2_SET_STATES = FMI2_TABLE.index("fmi2SetContinuousStates")
_FMI2_SET_REAL = FMI2_TABLE.index("fmi2SetReal")
_FMI2_GET_DERIVATIVES = FMI2_TABLE.index("fmi2GetDerivatives")
_FMI2_GET_REAL = FMI2_TABLE.index("fmi2GetReal")
_FMI2_REPORT = FMI2_TABLE.index("report")
#: fmi2Status: fmi2OK = 0, fmi2Warning = 1 (the call succeeded), then Discard, Error, Fatal
_FMI2_WARNING = 1
#: bytes of error text fetched from the Python side
_FMI2_MESSAGE_BYTES = 2048


@njit(cache=True)
def fmi2_evaluate(fmi, derivatives, t, x, u, perm, vr_in, vr_out, out):
    """out = a model-exchange FMU's state derivatives (``derivatives`` true:
    fmi2GetDerivatives, in the block's state order) or its outputs ``vr_out``
    (fmi2GetReal) at (t, x, u): fmi2SetTime, fmi2SetContinuousStates (block state k is
    the FMU's state ``perm[k]``), fmi2SetReal of the inputs ``vr_in``, then the get.

    A NaN time, state or input (a diverging trial step) gives NaN, as the Python plant
    does, so the step control rejects the step (the FMU refuses NaN).  A call that fails
    (status above fmi2Warning) raises ValueError with the message of the table's report
    (the FMU's log; the FMU reset for the next call).  ``fmi``: :data:`FMI2_TABLE`'s
    addresses as float64; ``vr_in``, ``vr_out``, ``perm``: integers as float64.
    """
    nx = x.shape[0]
    nu = u.shape[0]
    nout = out.shape[0]
    xf = np.empty(nx)
    uf = np.empty(nu)
    vr = np.empty(nu, dtype=np.uint32)
    got = np.empty(nout)
    finite = np.isfinite(t)
    for k in range(nx):
        xf[np.int64(perm[k])] = x[k]
        finite = finite and np.isfinite(x[k])
    for i in range(nu):
        uf[i] = u[i]
        vr[i] = np.uint32(vr_in[i])
        finite = finite and np.isfinite(u[i])
    if not finite:
        for i in range(nout):
            out[i] = np.nan
        return
    c = np.int64(fmi[0])
    which = _FMI2_SET_TIME
    st = call_c(np.int64(fmi[_FMI2_SET_TIME]), (c, t))
    if st <= _FMI2_WARNING:
        which = _FMI2_SET_STATES
        st = call_c(np.int64(fmi[_FMI2_SET_STATES]), (c, xf.ctypes.data, nx))
    if st <= _FMI2_WARNING:
        which = _FMI2_SET_REAL
        st = call_c(np.int64(fmi[_FMI2_SET_REAL]), (c, vr.ctypes.data, nu, uf.ctypes.data))
    if st <= _FMI2_WARNING:
        if derivatives:
            which = _FMI2_GET_DERIVATIVES
            st = call_c(np.int64(fmi[_FMI2_GET_DERIVATIVES]), (c, got.ctypes.data, nout))
        else:
            vo = np.empty(nout, dtype=np.uint32)
            for i in range(nout):
                vo[i] = np.uint32(vr_out[i])
            which = _FMI2_GET_REAL
            st = call_c(np.int64(fmi[_FMI2_GET_REAL]),
                        (c, vo.ctypes.data, nout, got.ctypes.data))
    if st > _FMI2_WARNING:
        # the FMU's message is on the Python side (its logger): fetch it, then raise
        msg = np.zeros(_FMI2_MESSAGE_BYTES, dtype=np.uint8)
        m = call_c(np.int64(fmi[_FMI2_REPORT]),
                   (which, np.int64(st), t, msg.ctypes.data, _FMI2_MESSAGE_BYTES))
        text = ""
        for i in range(m):
            text += chr(msg[i])
        raise ValueError(text)
    if derivatives:
        for k in range(nout):
            out[k] = got[np.int64(perm[k])]
    else:
        for i in range(nout):
            out[i] = got[i]
