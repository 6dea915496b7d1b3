"""The symbolic LU of the Newton matrix (ivdrem/sim/sparse_lu.py) against the dense boolean
Gaussian elimination it replaced, kept here as the reference: the filled pattern of every
candidate ordering entry by entry, on random patterns of several sizes and densities, on
structured ones, and on the real Jacobian patterns of the planar-3 and planar-4 loops; the
ordering chosen and the stored CSR arrays equal to what the dense rule gives."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from ivdrem.sim import sparse_lu


# ------------------------------------------------------------------ the reference
def dense_elimination(pattern, order):
    """Pattern of L + U of P A P^T, eliminated in the diagonal order on a dense boolean
    matrix: row k (final) is or-ed into every row below with an entry in column k."""
    B = pattern[np.ix_(order, order)].copy()
    n = B.shape[0]
    for k in range(n):
        rows = np.flatnonzero(B[k + 1:, k]) + k + 1
        if rows.size:
            B[np.ix_(rows, np.arange(k + 1, n))] |= B[k, k + 1:]
    return B


def reference_symbolic_lu(pattern):
    """(ordering name, order, filled dense pattern, rowptr, colidx, diagp) by the dense rule:
    the natural order, then SuperLU's COLAMD and MMD on A^T + A, the first least fill."""
    n = pattern.shape[0]
    A = np.asarray(pattern, dtype=bool) | np.eye(n, dtype=bool)
    candidates = [("natural", np.arange(n))]
    if n > 1:
        M = sparse.csc_matrix(np.where(A, 1.0, 0.0) + n * np.eye(n))
        for spec in ("COLAMD", "MMD_AT_PLUS_A"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lu = sparse_linalg.splu(M, permc_spec=spec, diag_pivot_thresh=0.0)
            candidates.append((spec, np.argsort(np.asarray(lu.perm_c))))
    best = None
    for name, order in candidates:
        F = dense_elimination(A, order)
        if best is None or F.sum() < best[2].sum():
            best = (name, order, F)
    name, order, F = best
    cols = [np.flatnonzero(F[i]) for i in range(n)]
    rowptr = np.concatenate(([0], np.cumsum([c.size for c in cols])))
    colidx = np.concatenate(cols) if n else np.zeros(0, dtype=np.int64)
    diagp = np.array([rowptr[i] + np.searchsorted(cols[i], i) for i in range(n)], dtype=int)
    return name, order, F, rowptr, colidx, diagp


def as_csr(pattern):
    n = pattern.shape[0]
    return sparse.csr_matrix((np.asarray(pattern, bool) | np.eye(n, dtype=bool)).astype(float))


def rows_as_dense(rows, n):
    F = np.zeros((n, n), dtype=bool)
    for i, r in enumerate(rows):
        assert np.all(np.diff(r) > 0)            # sorted, no repeats
        F[i, r] = True
    return F


def assert_same_as_reference(pattern):
    n = pattern.shape[0]
    A = np.asarray(pattern, bool) | np.eye(n, dtype=bool)
    name, order, F, rowptr, colidx, diagp = reference_symbolic_lu(pattern)
    got = sparse_lu._symbolic_lu(pattern)
    assert got.ordering == name
    assert np.array_equal(got.perm, order)
    assert np.array_equal(got.rowptr, rowptr)
    assert np.array_equal(got.colidx, colidx)
    assert np.array_equal(got.diagp, diagp)
    assert (got.nnz_a, got.nnz_lu) == (int(A.sum()), int(F.sum()))
    # every candidate ordering's rows, not only the winner's
    csr = as_csr(pattern)
    rng = np.random.default_rng(n)
    orders = [np.arange(n), rng.permutation(n)]
    if n > 1:
        M = (csr + n * sparse.identity(n)).tocsc()
        for spec in ("COLAMD", "MMD_AT_PLUS_A"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lu = sparse_linalg.splu(M, permc_spec=spec, diag_pivot_thresh=0.0)
            orders.append(np.argsort(np.asarray(lu.perm_c)))
    for o in orders:
        ref = dense_elimination(A, o)
        assert np.array_equal(rows_as_dense(sparse_lu._filled_rows(csr, o), n), ref)
    return got


# ------------------------------------------------------------------ the tests
@pytest.mark.parametrize("n", [1, 2, 3, 7, 30, 90, 200])
@pytest.mark.parametrize("density", [0.01, 0.05, 0.2, 0.6])
def test_filled_pattern_equals_dense_elimination_on_random_patterns(n, density):
    rng = np.random.default_rng(1000 * n + int(1000 * density))
    pattern = rng.random((n, n)) < density
    assert_same_as_reference(pattern)


def _structured(kind, n):
    P = np.zeros((n, n), dtype=bool)
    i = np.arange(n)
    if kind == "arrow-first":          # dense first row and column: the natural order fills all
        P[0, :] = P[:, 0] = True
    elif kind == "arrow-last":         # the same with the dense row last: no fill at all
        P[-1, :] = P[:, -1] = True
    elif kind == "lower":              # triangular: nothing to eliminate into
        P[np.tril_indices(n, -1)] = np.random.default_rng(0).random(n * (n - 1) // 2) < 0.3
    elif kind == "band":
        for d in (-2, -1, 1, 3):
            j = i + d
            ok = (j >= 0) & (j < n)
            P[i[ok], j[ok]] = True
    elif kind == "blocks":             # an unsymmetric chain of dense blocks, as a diagram's
        for s in range(0, n - 5, 5):
            P[s:s + 5, s:s + 5] = True
            P[s + 5, s] = True
    elif kind == "empty":
        pass
    return P


@pytest.mark.parametrize("kind", ["arrow-first", "arrow-last", "lower", "band", "blocks",
                                  "empty"])
def test_filled_pattern_equals_dense_elimination_on_structured_patterns(kind):
    got = assert_same_as_reference(_structured(kind, 40))
    if kind in ("arrow-last", "lower", "empty"):
        assert got.fill == 0 and got.ordering == "natural"    # a tie: the natural order
    if kind == "arrow-first":
        assert got.ordering != "natural"


def test_an_ordering_stops_once_it_has_more_entries_than_the_limit():
    rng = np.random.default_rng(3)
    pattern = rng.random((60, 60)) < 0.05
    csr, order = as_csr(pattern), np.arange(60)
    nnz = sum(r.size for r in sparse_lu._filled_rows(csr, order))
    assert nnz == int(dense_elimination(csr.toarray() != 0, order).sum())
    assert sparse_lu._filled_rows(csr, order, limit=nnz) is not None     # a tie can still win
    assert sparse_lu._filled_rows(csr, order, limit=nnz - 1) is None


def _loop_pattern(n_joints):
    from ivdrem.diagrams import closed_loop
    from ivdrem.experiments.config import closed_loop_kwargs, load_config, model_from_config
    from ivdrem.sim.compiled import _check_kernels
    from ivdrem.sim.jacobian import JacobianProgram
    from ivdrem.sim.plan import DiagramPlan
    # gamma pinned: "auto" would calibrate it by a run, which the pattern does not need
    cfg = load_config(overrides={"model.name": f"planar-{n_joints}", "iv_drem.gamma": 1.0})
    loop = closed_loop("iv-drem", model_from_config(cfg), **closed_loop_kwargs(cfg, "iv-drem"))
    plan = DiagramPlan.from_diagram(loop)
    _check_kernels(plan)
    return JacobianProgram(plan).pattern


@pytest.mark.parametrize("n_joints", [3, 4])
def test_filled_pattern_equals_dense_elimination_on_planar_loops(n_joints):
    pattern = _loop_pattern(n_joints)
    got = assert_same_as_reference(pattern)
    assert got.n == pattern.shape[0] > 150
