"""Small numeric helpers that block kernels call (numba-compiled, cached on disk).

Kept free of Python objects so that the same call works from a kernel running in plain
Python (reference path) and from generated numba code (compiled path).
"""
import numpy as np
from numba import njit


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


@njit(cache=True)
def det_adj(A, adj):
    """det(A) and adj(A) by the Faddeev-LeVerrier recursion; returns det(A).

    A polynomial identity, so it is exact in exact arithmetic for singular A too (the
    mixing step (17) meets a singular Psi at the start of every run); adj(A) A = det(A) I.
    """
    n = A.shape[0]
    Mk = np.zeros((n, n))      # M_1 = I
    tmp = np.zeros((n, n))
    AM = np.zeros((n, n))
    for i in range(n):
        Mk[i, i] = 1.0
    c = 1.0
    for k in range(1, n + 1):
        # AM = A M_k ; c_{n-k} = -tr(AM)/k ; M_{k+1} = AM + c I
        for i in range(n):
            for j in range(n):
                s = 0.0
                for l in range(n):
                    s += A[i, l] * Mk[l, j]
                AM[i, j] = s
        tr = 0.0
        for i in range(n):
            tr += AM[i, i]
        c = -tr / k
        if k < n:
            for i in range(n):
                for j in range(n):
                    tmp[i, j] = AM[i, j]
                tmp[i, i] += c
            for i in range(n):
                for j in range(n):
                    Mk[i, j] = tmp[i, j]
    # p(A) = 0 gives A M_n = -c_0 I, so adj(A) = (-1)^(n+1) M_n and det(A) = (-1)^n c_0.
    sign = 1.0 if (n % 2 == 1) else -1.0
    for i in range(n):
        for j in range(n):
            adj[i, j] = sign * Mk[i, j]
    return -sign * c


@njit(cache=True)
def spd_solve(A, B):
    """B <- A^{-1} B for a symmetric positive definite A (n, n), B (n, k), by Cholesky
    (A is not modified): the plant's Jacobian solves with the inertia matrix M(q)."""
    n = A.shape[0]
    k = B.shape[1]
    L = np.zeros((n, n))
    for j in range(n):
        d = A[j, j]
        for l in range(j):
            d -= L[j, l] * L[j, l]
        if not (d > 0.0 and d < np.inf):
            raise ValueError("inertia matrix M(q) is not positive definite (singular inertia)")
        d = np.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for l in range(j):
                s -= L[i, l] * L[j, l]
            L[i, j] = s / d
    for c in range(k):
        for i in range(n):
            s = B[i, c]
            for l in range(i):
                s -= L[i, l] * B[l, c]
            B[i, c] = s / L[i, i]
        for i in range(n - 1, -1, -1):
            s = B[i, c]
            for l in range(i + 1, n):
                s -= L[l, i] * B[l, c]
            B[i, c] = s / L[i, i]
