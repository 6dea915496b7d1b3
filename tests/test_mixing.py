"""The mixing step (17) and its variants at the size of real arms (docs/mixing.md).

Oracles: mpmath at 60-80 digits (determinant, adjugate as det * inverse, which is exact in
that precision for the floating-point matrices below, including the ones of rank nθ - 1
and nθ - 3 built from products, which are singular only up to rounding), the Jacobian's
nonsingular closed form d(adj Y)_c/dP_ab = (C_ba (CY)_c - C_ca (CY)_b)/det evaluated in
mpmath, and central differences of the kernels themselves.
"""
from __future__ import annotations

import math

import mpmath as mp
import numpy as np
import pytest

import ivdrem.blocks as block_library
from ivdrem.blocks._core import ParameterError
from ivdrem.blocks._kernels import (det_adj, mixing_values, mixing_derivatives,
                                    LOG10_ZERO_SIGMA)

F_REL, GUARD = 1e-6, 1e-3
CODES = {"paper": 0, "eigen": 1, "channel": 2}


def matrix(n, kind, rng):
    """Random n x n test matrix of the given kind (rank by construction up to rounding)."""
    if kind == "random":
        return rng.standard_normal((n, n))
    if kind == "zero":
        return np.zeros((n, n))
    drop = {"rank-1": 1, "rank-3": 3}[kind]
    r = n - drop
    return rng.standard_normal((n, r)) @ rng.standard_normal((r, n))


def mp_det_adj(A, dps=80):
    with mp.workdps(dps):
        M = mp.matrix(A.tolist())
        d = mp.det(M)
        if d == 0:
            raise ValueError("exactly singular")
        return d, d * M ** -1


def to_np(M):
    return np.array(M.tolist(), dtype=float)


@pytest.mark.parametrize("n", [5, 20, 43])
@pytest.mark.parametrize("kind", ["random", "rank-1", "rank-3", "zero"])
def test_det_adj_against_mpmath(n, kind):
    """det and adj by the signed SVD: relative error <= 1e-10 where the value is determined
    by the matrix to double precision (random, rank nθ - 1); rank nθ - 3: adj and det are
    zero up to rounding of the data, so the error is measured against the adjugate's own
    scale sigma_1^(n-1); Psi = 0: exactly zero."""
    rng = np.random.default_rng(1000 + n + len(kind))
    A = matrix(n, kind, rng)
    adj = np.empty((n, n))
    d = det_adj(A, adj)
    if kind == "zero":
        assert d == 0.0 and np.array_equal(adj, np.zeros((n, n)))
        return
    dm, adjm = mp_det_adj(A)
    ref = to_np(adjm)
    err = np.linalg.norm(adj - ref) / np.linalg.norm(ref)
    s1 = np.linalg.norm(A, 2)
    if kind in ("random", "rank-1"):
        assert err <= 1e-10, f"adj rel. error {err:.2e}"
        if kind == "random":
            assert abs(d - float(dm)) <= 1e-10 * abs(float(dm))
        else:   # det is zero up to rounding: its size is eps * sigma_1 * |adj|
            assert abs(d - float(dm)) <= 1e-12 * s1 * np.linalg.norm(ref)
            assert np.linalg.matrix_rank(adj, tol=1e-8 * np.abs(adj).max()) == 1
    else:
        assert np.linalg.norm(adj - ref) <= 1e-12 * s1 ** (n - 1)
        assert abs(d - float(dm)) <= 1e-12 * s1 ** n


def test_det_adj_exactly_singular_rank_one_adjugate():
    """An exactly singular integer matrix of rank n - 1: adj = (prod of the other sigma) v u^T,
    against the exact cofactors from mpmath (minors of an integer matrix are exact)."""
    rng = np.random.default_rng(5)
    n = 6
    B = rng.integers(-3, 4, (n, n - 1))
    C = rng.integers(-3, 4, (n - 1, n))
    A = (B @ C).astype(float)
    adj = np.empty((n, n))
    d = det_adj(A, adj)
    exact = np.empty((n, n))
    with mp.workdps(40):
        for i in range(n):
            for j in range(n):
                minor = np.delete(np.delete(A, i, 0), j, 1)
                exact[j, i] = (-1) ** (i + j) * float(mp.det(mp.matrix(minor.tolist())))
    assert abs(d) <= 1e-12 * np.linalg.norm(A, 2) ** n
    assert np.linalg.norm(adj - exact) <= 1e-11 * np.linalg.norm(exact)


def run_values(variant, Y, Psi):
    n = Y.size
    k = n if variant == "channel" else 1
    D, calY, L = np.full(k, np.nan), np.full(n, np.nan), np.full(k, np.nan)
    mixing_values(CODES[variant], Y.copy(), Psi.ravel().copy(), F_REL, GUARD, D, calY, L)
    return D, calY, L


def run_jac(variant, Y, Psi):
    n = Y.size
    k = n if variant == "channel" else 1
    jac = np.zeros((2 * k + n, n + n * n))
    mixing_derivatives(CODES[variant], Y.copy(), Psi.ravel().copy(), F_REL, GUARD, jac)
    return jac


@pytest.mark.parametrize("n", [5, 43])
def test_log_delta_where_delta_underflows(n):
    """log10 |Delta| from the singular values, against mpmath, where Delta itself is far
    below the smallest double (n = 43: sigma_i(Psi/s) about 1e-9 to 1e-8, Delta ~ 1e-370)."""
    rng = np.random.default_rng(n)
    Q1, _ = np.linalg.qr(rng.standard_normal((n, n)))
    Q2, _ = np.linalg.qr(rng.standard_normal((n, n)))
    sig = 10.0 ** rng.uniform(-9, -8, n) if n == 43 else 10.0 ** rng.uniform(-3, 0, n)
    Psi = Q1 @ np.diag(sig) @ Q2.T
    D, calY, L = run_values("paper", np.ones(n), Psi)
    with mp.workdps(60):
        M = mp.matrix(Psi.tolist())
        s = 1 + mp.sqrt(sum(mp.mpf(x) ** 2 for x in Psi.ravel()))
        ref = mp.log10(abs(mp.det(M / s)))
    assert abs(L[0] - float(ref)) <= 1e-10 * abs(float(ref))
    if n == 43:
        assert D[0] == 0.0 and float(ref) < -330          # underflowed, yet reported
    else:
        assert D[0] == pytest.approx(10.0 ** float(ref), rel=1e-10)


@pytest.mark.parametrize("variant", ["paper", "eigen", "channel"])
@pytest.mark.parametrize("n", [1, 5, 20])
def test_every_variant_keeps_the_scalar_regressions_exact(variant, n):
    """Y = Psi theta (W = 0) gives calY_i = Delta_i theta_i exactly (to rounding) in every
    variant, for symmetric positive definite and for non-symmetric (instrumental) Psi."""
    rng = np.random.default_rng(7 * n)
    theta = 3 * rng.standard_normal(n)
    for Psi in (rng.standard_normal((n, n)),
                (lambda M: M @ M.T + 1e-3 * np.eye(n))(rng.standard_normal((n, n))),
                1e6 * rng.standard_normal((n, n))):
        D, calY, L = run_values(variant, Psi @ theta, Psi)
        D = np.broadcast_to(D, (n,))
        assert np.all(np.isfinite(calY)) and np.all(D != 0)
        assert np.abs(calY - D * theta).max() <= 1e-9 * np.abs(D * theta).max()
        assert np.allclose(L, np.log10(np.abs(D[:L.size])), rtol=1e-12, atol=1e-12)


def test_variants_against_their_definitions():
    """Each Delta against its formula evaluated independently (numpy, float64):
    paper det(Psi/s); eigen prod sigma/(sigma + f0), f0 = f_rel ||Psi||_F; channel
    det Psi / c_i with c_i = sqrt(C_ii^2 + guard^2 ||C_i,:||^2), C = adj(Psi)."""
    rng = np.random.default_rng(3)
    n = 6
    Psi = rng.standard_normal((n, n))
    nrm = np.linalg.norm(Psi)
    Y = rng.standard_normal(n)
    C = np.linalg.det(Psi) * np.linalg.inv(Psi)
    D, calY, _ = run_values("paper", Y, Psi)
    s = 1 + nrm
    assert D[0] == pytest.approx(np.linalg.det(Psi / s), rel=1e-12)
    sig = np.linalg.svd(Psi, compute_uv=False)
    N = np.prod(sig + F_REL * nrm)
    D, calY, _ = run_values("eigen", Y, Psi)
    assert D[0] == pytest.approx(np.linalg.det(Psi) / N, rel=1e-11)
    assert np.allclose(calY, C @ Y / N, rtol=1e-11)
    D, calY, _ = run_values("channel", Y, Psi)
    c = np.sqrt(np.diag(C) ** 2 + GUARD ** 2 * np.sum(C ** 2, axis=1))
    assert np.allclose(D, np.linalg.det(Psi) / c, rtol=1e-11)
    assert np.allclose(calY, C @ Y / c, rtol=1e-11)
    # symmetric positive definite: channel Delta_i = 1/[Psi^-1]_ii up to the guard
    S = Psi @ Psi.T + np.eye(n)
    D, _, _ = run_values("channel", Y, S)
    inv = np.linalg.inv(S)
    assert np.allclose(D, 1 / np.diag(inv), rtol=GUARD ** 2 * np.max(
        np.sum(inv ** 2, 1) / np.diag(inv) ** 2))
    lam = np.linalg.eigvalsh(S)
    assert np.all(D >= lam[0] * (1 - 1e-12)) and np.all(D <= np.diag(S) * (1 + 1e-12))


def test_mixing_at_psi_zero_is_zero_in_every_variant():
    for variant in CODES:
        D, calY, L = run_values(variant, np.ones(5), np.zeros((5, 5)))
        assert np.all(D == 0.0) and np.all(calY == 0.0) and np.all(np.isfinite(L))
        assert np.all(L <= LOG10_ZERO_SIGMA)


def mp_paper_jacobian(Y, Psi, dps=60):
    """d(Delta, calY)/dPsi of the paper's mixing in mpmath from the nonsingular closed form
    (C = adj P, P = Psi/s): dDelta/dP_ab = C_ba, d(CY)_c/dP_ab = (C_ba (CY)_c - C_ca (CY)_b)/det,
    chained through s = 1 + ||Psi||_F (an independent route: no SVD, no rank-one pieces)."""
    n = Y.size
    with mp.workdps(dps):
        Pm = mp.matrix(Psi.tolist())
        nrm = mp.sqrt(sum(mp.mpf(x) ** 2 for x in Psi.ravel()))
        s = 1 + nrm
        P = Pm / s
        d = mp.det(P)
        C = d * P ** -1
        Ym = mp.matrix(Y.tolist())
        CY = C * Ym
        J = np.zeros((1 + n, n + n * n))
        for i in range(n):
            for j in range(n):
                J[1 + i, j] = float(C[i, j] / s)
        for a in range(n):
            for b in range(n):
                g = mp.mpf(Psi[a, b]) / nrm
                col = n + a * n + b
                J[0, col] = float((C[b, a] - n * d * g) / s)
                for c in range(n):
                    dF = (C[b, a] * CY[c] - C[c, a] * CY[b]) / d
                    J[1 + c, col] = float((dF - n * CY[c] * g) / s ** 2)
        return J


@pytest.mark.parametrize("n,kind", [(5, "random"), (5, "rank-1"), (20, "random"),
                                    (20, "rank-1")])
def test_paper_jacobian_against_mpmath(n, kind):
    """The O(nθ^3) analytic Jacobian against mpmath's closed form (rank nθ - 1 up to
    rounding: the closed form divides by det, fine in 60 digits)."""
    rng = np.random.default_rng(50 + n)
    Psi = matrix(n, kind, rng)
    Y = rng.standard_normal(n)
    J = run_jac("paper", Y, Psi)[:1 + n]
    ref = mp_paper_jacobian(Y, Psi)
    for rows in (slice(0, 1), slice(1, 1 + n)):
        err = np.abs(J[rows] - ref[rows]).max() / np.abs(ref[rows]).max()
        assert err <= 1e-10, f"rows {rows}: {err:.2e}"


def central_fd(variant, Y, Psi, h_rel=1e-6):
    n = Y.size
    v = np.concatenate([Y, Psi.ravel()])

    def f(w):
        return np.concatenate(run_values(variant, w[:n], w[n:].reshape(n, n)))
    cols = []
    for c in range(v.size):
        h = h_rel * max(1.0, abs(v[c]))
        vp, vm = v.copy(), v.copy()
        vp[c] += h
        vm[c] -= h
        cols.append((f(vp) - f(vm)) / (2 * h))
    return np.array(cols).T


@pytest.mark.parametrize("variant", ["paper", "eigen", "channel"])
@pytest.mark.parametrize("n,kind", [(5, "random"), (5, "rank-1"), (12, "random"),
                                    (12, "spd")])
def test_variant_jacobians_against_central_differences(variant, n, kind):
    """Every output row (Delta, calY, log10|Delta|) against central differences; at rank
    nθ - 1 the log row (singular there) and "eigen" (|sigma| has a kink at 0) are left out."""
    rng = np.random.default_rng(90 + n)
    if kind == "spd":
        M = rng.standard_normal((n, n))
        Psi = M @ M.T + 0.01 * np.eye(n)
    else:
        Psi = matrix(n, kind, rng)
    if kind == "rank-1" and variant == "eigen":
        pytest.skip("eigen: prod sigma/(sigma + f) has a kink at sigma = 0")
    Y = rng.standard_normal(n)
    J = run_jac(variant, Y, Psi)
    ref = central_fd(variant, Y, Psi)
    k = n if variant == "channel" else 1
    if variant == "eigen":
        # Delta = prod sigma/(sigma + f) is 1 - O(f/sigma): its differences lose digits to
        # rounding at small steps and to truncation (h^2/sigma_min^2) at long ones: the
        # step of 1e-4, 1e-5, 1e-6 that agrees best
        J0 = J[:k]
        refs = [central_fd(variant, Y, Psi, h_rel=h)[:k] for h in (1e-4, 1e-5, 1e-6)]
        ref[:k] = min(refs, key=lambda r: np.abs(J0 - r).max())
    groups = [slice(0, k), slice(k, k + n)] + ([] if kind == "rank-1" else [slice(k + n, None)])
    for rows in groups:
        err = np.abs(J[rows] - ref[rows]).max() / np.abs(ref[rows]).max()
        assert err <= 1e-6, f"{variant} rows {rows}: {err:.2e}"


def test_mixing_factory_checks_its_arguments():
    with pytest.raises(ParameterError, match="unknown mixing variant 'foo'"):
        block_library.mixing(5, "foo")
    with pytest.raises(ParameterError, match="f_rel"):
        block_library.mixing(5, "eigen", f_rel=-1.0)
    spec = block_library.mixing(5, "channel").ivdrem
    assert spec.outputs == [("Delta", 5), ("calY", 5), ("Delta_log10", 5)]


@pytest.mark.parametrize("n", [5, 20, 43])
@pytest.mark.parametrize("cond", [1e2, 1e5, 1e7, 1e8, 1e10])
def test_eigen_values_against_mpmath_on_both_routes(n, cond):
    """"eigen" takes singular values and an LU solve while sigma_min/sigma_max of P is
    above EIGEN_FAST_MIN_RATIO, the signed SVD below it: on either side Delta and calY
    agree with their definition in mpmath (60 digits) to a few cond(P) eps, the accuracy
    of the problem itself (1e-10 where cond <= 1e5)."""
    from ivdrem.blocks._kernels import EIGEN_FAST_MIN_RATIO
    rng = np.random.default_rng(int(n * 17 + np.log10(cond)))
    Q1, _ = np.linalg.qr(rng.standard_normal((n, n)))
    Q2, _ = np.linalg.qr(rng.standard_normal((n, n)))
    Psi = 50.0 * Q1 @ np.diag(np.logspace(0, -np.log10(cond), n)) @ Q2.T
    Y = rng.standard_normal(n)
    D, calY, L = run_values("eigen", Y, Psi)
    with mp.workdps(60):
        M = mp.matrix(Psi.tolist())
        nrm = mp.mnorm(M, "f")
        s = 1 + nrm
        P = M / s
        f = F_REL * nrm / s
        N = mp.fprod([sv + f for sv in mp.svd_r(P, compute_uv=False)])
        d = mp.det(P)
        ref_D = float(d / N)
        ref_Y = np.array([float(v / (s * N)) for v in d * (P ** -1) * mp.matrix(Y.tolist())])
        ref_L = float(mp.log10(abs(d / N)))
    tol = max(1e-10, 100 * cond * np.finfo(float).eps)
    assert abs(D[0] - ref_D) <= tol * abs(ref_D)
    assert np.abs(calY - ref_Y).max() <= tol * np.abs(ref_Y).max()
    assert abs(L[0] - ref_L) <= tol          # decades: the relative error of Delta / ln 10
    assert (1.0 / cond > EIGEN_FAST_MIN_RATIO) == (cond < 1e9)   # both routes are covered


def _conditioned(n, cond, rng, scale=50.0):
    """scale Q1 diag(1 ... 1/cond) Q2^T: a Psi of 2-norm condition number cond."""
    Q1, _ = np.linalg.qr(rng.standard_normal((n, n)))
    Q2, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return scale * Q1 @ np.diag(np.logspace(0, -np.log10(cond), n)) @ Q2.T


@pytest.mark.parametrize("n", [5, 20, 43])
@pytest.mark.parametrize("cond", [1e2, 1e5, 1e7, 1e8, 1e10, 1e14])
def test_paper_values_against_mpmath_on_both_routes(n, cond):
    """The paper's mixing takes adj P = det(P) P^-1 from one LU while 1/cond_1(P) is at
    least LU_MIN_RCOND, the signed SVD below it (cond 1e10 and up at these sizes: the
    bound is checked to put each case on the route named): on either side Delta, calY and
    log10|Delta| agree with their definition in mpmath (60 digits) to a few cond(P) eps."""
    from ivdrem.blocks._kernels import LU_MIN_RCOND
    rng = np.random.default_rng(int(n * 31 + np.log10(cond)))
    Psi = _conditioned(n, cond, rng)
    Y = rng.standard_normal(n)
    D, calY, L = run_values("paper", Y, Psi)
    with mp.workdps(60):
        M = mp.matrix(Psi.tolist())
        s = 1 + mp.mnorm(M, "f")
        P = M / s
        d = mp.det(P)
        P_inv = P ** -1                     # once: at n = 43 a third of the test's time
        ref_D = float(d)
        ref_Y = np.array([float(v / s) for v in d * P_inv * mp.matrix(Y.tolist())])
        ref_L = float(mp.log10(abs(d)))
        rcond = float(1 / (mp.mnorm(P, 1) * mp.mnorm(P_inv, 1)))
    tol = max(1e-10, 100 * cond * np.finfo(float).eps)
    assert abs(D[0] - ref_D) <= tol * abs(ref_D)
    assert np.abs(calY - ref_Y).max() <= tol * np.abs(ref_Y).max()
    assert abs(L[0] - ref_L) <= tol
    assert (rcond >= LU_MIN_RCOND) == (cond <= 1e8)      # both routes are covered


@pytest.mark.parametrize("n", [5, 20])
@pytest.mark.parametrize("cond", [1e2, 1e5, 1e8, 1e10])
def test_paper_jacobian_against_mpmath_on_both_routes(n, cond):
    """The paper's Jacobian, LU route (d det = det tr(P^-1 dP), d adj Y from the inverse)
    for cond <= 1e8 and signed-SVD route above, against mpmath's closed form: every row to
    a few cond(P) eps of its largest entry."""
    rng = np.random.default_rng(int(n * 37 + np.log10(cond)))
    Psi = _conditioned(n, cond, rng)
    Y = rng.standard_normal(n)
    J = run_jac("paper", Y, Psi)
    ref = mp_paper_jacobian(Y, Psi)
    tol = max(1e-10, 100 * cond * np.finfo(float).eps)
    for rows in (slice(0, 1), slice(1, 1 + n)):
        err = np.abs(J[rows] - ref[rows]).max() / np.abs(ref[rows]).max()
        assert err <= tol, f"rows {rows}: {err:.2e}"
    # log10|Delta|: d/dPsi_ab = ((P^-1)_ba - n g_ab) / (s ln 10), g = Psi/||Psi||_F
    s = 1 + np.linalg.norm(Psi)
    inv = np.linalg.inv(Psi / s)
    ref_L = (inv.T - n * Psi / np.linalg.norm(Psi)).ravel() / (s * np.log(10.0))
    assert np.abs(J[1 + n, n:] - ref_L).max() <= tol * np.abs(ref_L).max()


def test_lu_helpers_against_numpy():
    """lu_inverse / lu_solve: P A = L U with the pivots recorded, A^-1, det A and its
    log10 and the exact 1-norm reciprocal condition, against numpy; a zero pivot (an
    exactly singular A) reports 1/cond = 0; log10 |det| where det underflows."""
    from ivdrem.blocks._kernels import lu_inverse, lu_solve
    rng = np.random.default_rng(11)
    for n in (1, 2, 5, 17):
        A = rng.standard_normal((n, n))
        LU, inv, piv = np.empty((n, n)), np.empty((n, n)), np.empty(n, np.int64)
        d, logd, rc = lu_inverse(A, LU, piv, inv)
        assert np.allclose(inv, np.linalg.inv(A), rtol=1e-12, atol=1e-12 * np.abs(inv).max())
        sign_np, logabs_np = np.linalg.slogdet(A)
        assert np.sign(d) == sign_np and logd == pytest.approx(logabs_np / np.log(10.0),
                                                                abs=1e-13)
        assert d == pytest.approx(np.linalg.det(A), rel=1e-12)
        assert rc == pytest.approx(1 / np.linalg.cond(A, 1), rel=1e-10)
        b = rng.standard_normal(n)
        x = b.copy()
        lu_solve(LU, piv, x)
        assert np.allclose(A @ x, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    A = np.ones((4, 4))
    LU, inv, piv = np.empty((4, 4)), np.empty((4, 4)), np.empty(4, np.int64)
    assert lu_inverse(A, LU, piv, inv)[2] == 0.0
    n = 40                                   # det = 1e-400: underflows, its log10 does not
    A = np.diag(np.full(n, 1e-10)) + 1e-13 * rng.standard_normal((n, n))
    LU, inv, piv = np.empty((n, n)), np.empty((n, n)), np.empty(n, np.int64)
    d, logd, rc = lu_inverse(A, LU, piv, inv)
    assert d == 0.0 and logd == pytest.approx(np.linalg.slogdet(A)[1] / np.log(10.0),
                                              rel=1e-12)


def test_lu_inverse_columns_are_lu_solve_bit_for_bit():
    """lu_inverse_into solves the identity's columns side by side: each column is the
    value lu_solve gives for that column alone, bit for bit (the same operations in the
    same order), so the route test of the mixing reads the same 1/cond_1 as before."""
    from ivdrem.blocks._kernels import lu_factor, lu_inverse_into, lu_solve
    rng = np.random.default_rng(7)
    for n in (1, 2, 5, 9, 20):
        for cond in (1.0, 1e4, 1e9):
            A = _conditioned(n, cond, rng) if n > 1 else rng.standard_normal((1, 1))
            LU, piv = A.copy(), np.empty(n, np.int64)
            assert lu_factor(LU, piv)
            X = np.full((n, n), np.nan)
            lu_inverse_into(LU, piv, X)
            for j in range(n):
                e = np.zeros(n)
                e[j] = 1.0
                lu_solve(LU, piv, e)
                assert np.array_equal(X[:, j], e), (n, cond, j)


@pytest.mark.parametrize("n", [2, 5, 20, 43])
@pytest.mark.parametrize("cond", [1e0, 1e3, 1e8, 1e12])
def test_rcond_lower_bound_is_below_the_exact_value(n, cond):
    """lu_rcond_lower_bound (comparison matrices of the LU factors, O(n^2)) never exceeds
    1/cond_1 computed in mpmath from the matrix itself; at the paper's sizes (n <= 5) it
    stays within a factor 1e3 of it, so the mixing's LU route skips the exact n solves
    wherever 1/cond_1 is well above LU_MIN_RCOND (at n = 20 and 43 the bound of L's
    comparison matrix grows like 2^n and the exact test decides); an exactly singular
    factor gives 0."""
    from ivdrem.blocks._kernels import lu_factor, lu_rcond_lower_bound
    rng = np.random.default_rng(int(n * 17 + np.log10(cond)))
    A = _conditioned(n, cond, rng)
    LU, piv = A.copy(), np.empty(n, np.int64)
    assert lu_factor(LU, piv)
    lb = lu_rcond_lower_bound(LU, np.abs(A).sum(axis=0).max(), np.empty(n))
    with mp.workdps(60):
        M = mp.matrix(A.tolist())
        exact = float(1 / (mp.mnorm(M, 1) * mp.mnorm(M ** -1, 1)))
    assert 0.0 < lb <= exact
    if n <= 5:
        assert exact / lb <= 1e3, f"bound {lb:.3e} against {exact:.3e}"
    Z = np.ones((3, 3))
    LU, piv = Z.copy(), np.empty(3, np.int64)
    lu_factor(LU, piv)                       # a zero pivot: factored in part
    LU[2, 2] = 0.0
    assert lu_rcond_lower_bound(LU, 3.0, np.empty(3)) == 0.0


def test_paper_route_unchanged_by_the_cheap_bound():
    """The LU route decided by the O(n^2) bound first is the route the exact 1/cond_1
    decides: matrices on both sides of LU_MIN_RCOND (and near it) give Delta, calY and
    log10|Delta| bit for bit equal to the route taken from the exact test alone."""
    from ivdrem.blocks._kernels import (LU_MIN_RCOND, lu_factor, lu_rcond, lu_det,
                                        lu_solve, _frobenius, _norm1)
    rng = np.random.default_rng(3)
    routes = set()
    for n in (3, 5, 12):
        for cond in (1e1, 1e6, 3e8, 1e9, 3e9, 1e12):
            Psi = _conditioned(n, cond, rng) * rng.uniform(0.1, 10.0)
            Y = rng.standard_normal(n)
            D, calY, L = run_values("paper", Y, Psi)
            # the route from the exact test alone, and its values computed here
            s = 1.0 + _frobenius(Psi.ravel())
            P = Psi / s
            LU, piv = P.copy(), np.empty(n, np.int64)
            lu_ok = bool(lu_factor(LU, piv)) and lu_rcond(
                LU, piv, _norm1(P), np.empty((n, n))) >= LU_MIN_RCOND
            routes.add(lu_ok)
            if lu_ok:
                d, logd = lu_det(LU, piv)
                x = Y.copy()
                lu_solve(LU, piv, x)
                ref = d * x / s
            else:                        # the signed SVD's det and adjugate
                C = np.empty((n, n))
                d = det_adj(P, C)
                ref = np.array([sum_in_order(C[i], Y) for i in range(n)]) / s
            assert D[0] == d, (n, cond, lu_ok)
            assert np.array_equal(calY, ref), (n, cond, lu_ok)
    assert routes == {True, False}           # both sides of the threshold were met


def sum_in_order(a, b):
    """sum_j a_j b_j accumulated left to right (the kernels' order)."""
    acc = 0.0
    for u, v in zip(a, b):
        acc += float(u) * float(v)
    return acc
