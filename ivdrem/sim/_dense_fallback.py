"""Dense fallbacks for the Jacobian and the Newton matrix (numba-compatible source).

Pasted into a generated diagram module only when the stepping template does not define
these names itself (the template's versions win).  ``fd_jacobian`` differentiates the
whole right-hand side by forward differences; ``dense_factor`` / ``dense_solve`` are an
LU with partial pivoting of A = c I - J.  They are the slow, general baseline that the
structured Jacobian (:mod:`ivdrem.sim.jacobian`) and the static-pattern sparse LU
(:mod:`ivdrem.sim.sparse_lu`) are measured and tested against.
"""
import numpy as np

SINGULAR = 6


def fd_jacobian(t, x, P, W, J):
    """J = df/dx by forward differences of diagram_eval(RHS), step sqrt(eps) max(|x_j|, 1)."""
    n = x.shape[0]
    f0 = np.empty(n)
    f1 = np.empty(n)
    xp = x.copy()
    diagram_eval(RHS, t, x, P, W, f0)
    for j in range(n):
        h = 1.4901161193847656e-08 * max(abs(x[j]), 1.0)
        xp[j] = x[j] + h
        h = xp[j] - x[j]
        diagram_eval(RHS, t, xp, P, W, f1)
        for i in range(n):
            J[i, j] = (f1[i] - f0[i]) / h
        xp[j] = x[j]
    return OK


def dense_factor(J, c, LU, piv):
    """LU = P (c I - J) factored with partial pivoting; SINGULAR on a zero/non-finite pivot."""
    n = J.shape[0]
    for i in range(n):
        for j in range(n):
            LU[i, j] = -J[i, j]
        LU[i, i] += c
    for k in range(n):
        p = k
        amax = abs(LU[k, k])
        for i in range(k + 1, n):
            a = abs(LU[i, k])
            if a > amax:
                amax = a
                p = i
        if not (amax > 0.0) or not np.isfinite(amax):
            return SINGULAR
        piv[k] = p
        if p != k:
            for j in range(n):
                tmp = LU[k, j]
                LU[k, j] = LU[p, j]
                LU[p, j] = tmp
        inv = 1.0 / LU[k, k]
        for i in range(k + 1, n):
            l = LU[i, k] * inv
            LU[i, k] = l
            if l != 0.0:
                for j in range(k + 1, n):
                    LU[i, j] -= l * LU[k, j]
    return OK


def dense_solve(LU, piv, b):
    """b = (c I - J)^{-1} b for the factorisation of dense_factor."""
    n = b.shape[0]
    for k in range(n):
        p = piv[k]
        if p != k:
            tmp = b[k]
            b[k] = b[p]
            b[p] = tmp
    for i in range(n):
        s = b[i]
        for j in range(i):
            s -= LU[i, j] * b[j]
        b[i] = s
    for i in range(n - 1, -1, -1):
        s = b[i]
        for j in range(i + 1, n):
            s -= LU[i, j] * b[j]
        b[i] = s / LU[i, i]
