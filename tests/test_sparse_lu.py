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
from ivdrem.sim._stepper_codes import SINGULAR


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


def _loop_plan(n_joints):
    from ivdrem.diagrams import closed_loop
    from ivdrem.experiments.config import closed_loop_kwargs, read_config, resolve_config, model_from_config
    from ivdrem.sim.compiled import _check_kernels
    from ivdrem.sim.plan import DiagramPlan
    # gamma pinned: "auto" would calibrate it by a run, which the pattern does not need
    cfg = resolve_config(read_config(overrides={"model.name": f"planar-{n_joints}", "iv_drem.gamma": 1.0}))[0]
    loop = closed_loop("iv-drem", model_from_config(cfg), **closed_loop_kwargs(cfg, "iv-drem"))
    plan = DiagramPlan.from_diagram(loop)
    _check_kernels(plan)
    return plan


def _loop_pattern(n_joints):
    from ivdrem.sim.jacobian import JacobianProgram
    return JacobianProgram(_loop_plan(n_joints)).pattern


@pytest.mark.parametrize("n_joints", [3, 4])
def test_filled_pattern_equals_dense_elimination_on_planar_loops(n_joints):
    pattern = _loop_pattern(n_joints)
    got = assert_same_as_reference(pattern)
    assert got.n == pattern.shape[0] > 150


# ------------------------------------------------------------------ the panels
def _factor(slu, values, c, *, panels):
    """slu_factor of c I - J (J's values in the pattern's order) with or without the panels:
    (status, the work array: L + U values, inverse pivots, ...)."""
    from ivdrem.sim import _diagram
    from ivdrem.sim.compiled import load_c_stepper
    n = slu.n
    LU, piv = np.zeros(slu.nnz_lu + _diagram.LU_WORK_ROWS * n), np.zeros(n, dtype=np.int64)
    parts = ((slu.panel_rows, slu.panel_kptr, slu.panel_k) if panels else
             (np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64),
              np.zeros(0, dtype=np.int64)))
    st = load_c_stepper().slu_factor(values, n, float(c), LU, piv, slu.perm, slu.rowptr,
                                     slu.colidx, slu.diagp, *parts)
    return st, LU[:slu.nnz_lu + n]


def _adaptation_like(seed, n_slow=100, n_theta=20, n_fast=24, reads=16):
    """A pattern shaped as the IV-DREM loop's: slow rows (the window and the averages) each
    fed by `reads` fast columns, parameter rows reading every slow column and a few of each
    other, fast rows reading the parameters; natural order, so the parameter rows come
    after the slow ones with long, shared L parts."""
    rng = np.random.default_rng(seed)
    n = n_slow + n_theta + n_fast
    P = np.zeros((n, n), dtype=bool)
    th, fa = n_slow, n_slow + n_theta
    for i in range(n_slow):
        P[i, fa + rng.choice(n_fast, reads, replace=False)] = True
    P[th:fa, :n_slow] = rng.random((n_theta, n_slow)) < 0.9
    P[th:fa, th:fa] = rng.random((n_theta, n_theta)) < 0.3
    P[fa:, th:] = rng.random((n_fast, n_theta + n_fast)) < 0.3
    csr = as_csr(P)
    order = np.arange(n)
    return P, sparse_lu.SymbolicLU(order, sparse_lu._filled_rows(csr, order), csr.nnz, "natural")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_panels_give_the_row_by_row_factor_bit_for_bit(seed):
    """Rows eliminated in panels get the same operations in the same order as row by row:
    every value of L + U and every inverse pivot equal, also with exact zeros among the
    multipliers (the row-by-row elimination skips them); and the solve agrees with numpy."""
    from ivdrem.sim.tables import dense_to_sparse
    P, slu = _adaptation_like(seed)
    n = slu.n
    assert slu.panel_rows.size >= 2            # the parameter rows come in panels
    assert np.all(np.diff(slu.panel_rows) >= sparse_lu.LU_PANEL)
    rng = np.random.default_rng(seed)
    J = np.where(P, rng.standard_normal((n, n)), 0.0)
    J[rng.random((n, n)) < 0.05] = 0.0         # exact zeros at structural entries
    values = dense_to_sparse(J, slu.perm, slu.rowptr, slu.colidx)
    for c in (3.0, 50.0):
        st1, rows = _factor(slu, values, c, panels=False)
        st2, panel = _factor(slu, values, c, panels=True)
        assert st1 == st2 == 0
        assert np.array_equal(rows, panel)
    from ivdrem.sim.compiled import load_c_stepper
    b = rng.standard_normal(n)
    x = b.copy()
    _, LU = _factor(slu, values, 50.0, panels=True)
    LU = np.concatenate([LU, np.zeros(n)])
    load_c_stepper().slu_solve(LU, n, slu.perm, slu.rowptr, slu.colidx, slu.diagp, x)
    np.testing.assert_allclose(x, np.linalg.solve(50.0 * np.eye(n) - J, b), rtol=1e-12,
                               atol=1e-14)
    # the long rows of L are solved four or two side by side: the same sums as one row
    # at a time
    assert np.array_equal(x, _solve_one_row_at_a_time(slu, LU, b))


@pytest.mark.parametrize("n_joints", [2, 4])
def test_rows_solved_side_by_side_give_the_one_row_at_a_time_solve(n_joints):
    """The solve takes rows with at least SOLVE_GROUP_MIN entries of L four (or two) side by
    side over the columns before the first of them: on the loops' own patterns (the paper's
    two-link loop, 123 states; planar-4), where both paths are taken, the same values as one
    row at a time, bit for bit, for several right-hand sides and factors."""
    from ivdrem.sim._diagram import SOLVE_GROUP_MIN
    from ivdrem.sim.compiled import load_c_stepper
    from ivdrem.sim.tables import dense_to_sparse
    pattern, groups = _loop_pattern_and_groups(n_joints)
    slu = sparse_lu.symbolic_lu(pattern, groups)
    n = slu.n
    long_rows = (slu.diagp - slu.rowptr[:-1]) >= SOLVE_GROUP_MIN
    fours = [i for i in range(n - 3) if long_rows[i:i + 4].all()]
    alone = [i for i in range(n - 1) if long_rows[i] and not long_rows[i + 1]]
    assert fours and alone                     # both side-by-side paths are exercised
    rng = np.random.default_rng(n_joints)
    stepper = load_c_stepper()
    for c in (2.0, 30.0):
        J = np.where(pattern, rng.standard_normal(pattern.shape), 0.0)
        values = dense_to_sparse(J, slu.perm, slu.rowptr, slu.colidx)
        st, LU = _factor(slu, values, c, panels=True)
        assert st == 0
        LU = np.concatenate([LU, np.zeros(n)])
        for _ in range(3):
            b = rng.standard_normal(n) * 10.0 ** rng.integers(-3, 4, n)
            x = b.copy()
            stepper.slu_solve(LU, n, slu.perm, slu.rowptr, slu.colidx, slu.diagp, x)
            assert np.array_equal(x, _solve_one_row_at_a_time(slu, LU, b))
            np.testing.assert_allclose(x, np.linalg.solve(c * np.eye(n) - J, b), rtol=1e-9,
                                       atol=1e-12 * np.abs(b).max())


def _solve_one_row_at_a_time(slu, LU, b):
    """Forward and back substitution with the factor's values, each row's sum in the
    pattern's order (Python floats: the same double operations, one at a time)."""
    n, rp, ci, dp = slu.n, slu.rowptr, slu.colidx, slu.diagp
    vals, inv = LU[:slu.nnz_lu], LU[slu.nnz_lu:slu.nnz_lu + n]
    y = [float(b[slu.perm[i]]) for i in range(n)]
    for i in range(n):
        s = y[i]
        for p in range(rp[i], dp[i]):
            s -= float(vals[p]) * y[ci[p]]
        y[i] = s
    for i in range(n - 1, -1, -1):
        s = y[i]
        for p in range(dp[i] + 1, rp[i + 1]):
            s -= float(vals[p]) * y[ci[p]]
        y[i] = s * float(inv[i])
    out = np.empty(n)
    out[slu.perm] = y
    return out


def test_a_singular_pivot_inside_a_panel_is_reported():
    from ivdrem.sim.tables import dense_to_sparse
    P, slu = _adaptation_like(0)
    n = slu.n
    row = int(slu.panel_rows[0]) + 3            # a row in the middle of the first panel
    J = np.where(P, 0.1, 0.0)
    J[slu.perm[row], slu.perm[row]] = 7.0       # c = 7: a zero pivot before elimination
    J[slu.perm[row], :slu.perm[row]] = 0.0      # ... and after it (nothing subtracted)
    values = dense_to_sparse(J, slu.perm, slu.rowptr, slu.colidx)
    assert _factor(slu, values, 7.0, panels=False)[0] == _factor(slu, values, 7.0,
                                                                 panels=True)[0] == SINGULAR
    values[slu.rowptr[row]] = np.nan
    assert _factor(slu, values, 50.0, panels=True)[0] == SINGULAR


def test_panels_are_chosen_only_over_long_rows_of_u(monkeypatch):
    """Each row of U a panel reads costs it LU_PANEL multipliers: over short rows the row by
    row elimination is cheaper, and no panel is chosen."""
    for reads in (3, 16):
        slu = _adaptation_like(0, reads=reads)[1]
        ulen = slu.rowptr[1:] - slu.diagp - 1
        for p in range(slu.panel_rows.size):
            cols = slu.panel_k[slu.panel_kptr[p]:slu.panel_kptr[p + 1]]
            assert ulen[cols].mean() >= sparse_lu.PANEL_MIN_ULEN
    assert _adaptation_like(0, reads=16)[1].panel_rows.size >= 2
    monkeypatch.setattr(sparse_lu, "PANEL_MIN_ULEN", 10**6)
    assert _adaptation_like(0, reads=16)[1].panel_rows.size == 0


def test_the_planar_loop_adaptation_rows_are_panels_with_the_same_factor(monkeypatch):
    from ivdrem.sim.tables import dense_to_sparse
    # the panel code on a real loop's pattern, whatever the cost rule would choose there
    monkeypatch.setattr(sparse_lu, "PANEL_MIN_ULEN", 0)
    pattern = _loop_pattern(4)
    slu = sparse_lu._symbolic_lu(pattern)
    assert slu.panel_rows.size >= 1
    rng = np.random.default_rng(4)
    n = slu.n
    J = np.where(pattern, rng.standard_normal(pattern.shape), 0.0)
    values = dense_to_sparse(J, slu.perm, slu.rowptr, slu.colidx)
    st1, rows = _factor(slu, values, 30.0, panels=False)
    st2, panel = _factor(slu, values, 30.0, panels=True)
    assert st1 == st2 == 0 and np.array_equal(rows, panel)


# ------------------------------------------------------------------ the group refinement
def dense_cost(pattern, order):
    """(multiply-adds, entries of L + U) of eliminating P A P^T, counted on the dense boolean
    elimination: row i subtracts, for every k < i in its filled row, row k's upper part."""
    n = pattern.shape[0]
    F = dense_elimination(np.asarray(pattern, bool) | np.eye(n, dtype=bool), order)
    upper = np.array([F[k, k + 1:].sum() for k in range(n)], dtype=int)
    madds = sum(int(upper[np.flatnonzero(F[i, :i])].sum()) for i in range(n))
    return madds, int(F.sum())


@pytest.mark.parametrize("n,density", [(1, 0.5), (12, 0.2), (60, 0.05), (120, 0.03)])
def test_elimination_cost_equals_the_dense_count_on_every_path(n, density, monkeypatch):
    """The cost the search minimises, two ways: from the filled rows (Python) and from
    elimination_cost.c (the search of a real arm's loop), each against the dense
    elimination; a cost limit below the cost stops both, one at the cost does not; the
    fill-only limit (the candidate orderings' comparison) the same."""
    rng = np.random.default_rng(n)
    pattern = rng.random((n, n)) < density
    csr = as_csr(pattern)
    w = sparse_lu.SOLVES_PER_FACTOR
    assert sparse_lu._compiled_cost() is not None          # a C compiler is required here
    for order in (np.arange(n), rng.permutation(n)):
        ref = dense_cost(pattern, order)
        assert sparse_lu.elimination_cost(sparse_lu._filled_rows(csr, order)) == ref
        total = float(ref[0] + w * ref[1])
        for compiled_from in (10 ** 9, 0):                 # in Python, then in C
            monkeypatch.setattr(sparse_lu, "REFINE_COMPILED_FROM", compiled_from)
            assert sparse_lu._order_cost(csr, order, np.inf) == ref
            assert sparse_lu._order_cost(csr, order, total) == ref
            assert sparse_lu._order_cost(csr, order, total - 1.0) is None
            assert sparse_lu._order_cost(csr, order, ref[1], fill_only=True) == ref
            assert sparse_lu._order_cost(csr, order, ref[1] - 1, fill_only=True) is None
        assert sparse_lu._filled_rows(csr, order, cost_limit=total - 1) is None


def test_no_c_compiler_searches_in_python(tmp_path, monkeypatch):
    """Without a C compiler the cost is counted in Python: the same orders, nothing
    raised (the C library is built once per cache and source, else not at all)."""
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setattr(sparse_lu, "_C_COST", {})
    monkeypatch.setattr(sparse_lu, "REFINE_COMPILED_FROM", 0)
    assert sparse_lu._compiled_cost() is None
    P, groups = _two_stage_adaptation(seed=0)
    csr = as_csr(P)
    base = sparse_lu._symbolic_lu(P)
    assert sparse_lu._order_cost(csr, base.perm, np.inf) == dense_cost(P, base.perm)


def _two_stage_adaptation(n_slow=30, n_theta=6, n_fast=8, seed=0):
    """An IV-DREM-shaped pattern with its groups: fast states (filters), slow states each
    read from two fast ones (the window), parameters reading every slow state and feeding
    the fast ones (the control).  Minimum degree on A^T + A does not see that nothing reads
    the parameters but the fast states."""
    rng = np.random.default_rng(seed)
    n = n_fast + n_slow + n_theta
    fast, slow, theta = (np.arange(n_fast), n_fast + np.arange(n_slow),
                         n_fast + n_slow + np.arange(n_theta))
    P = np.zeros((n, n), dtype=bool)
    for i in slow:
        P[i, rng.choice(fast, 2, replace=False)] = True
    P[np.ix_(theta, slow)] = True
    P[np.ix_(fast, fast)] = rng.random((n_fast, n_fast)) < 0.3
    P[np.ix_(fast[:2], theta)] = True
    groups = np.concatenate([np.zeros(n_fast), np.ones(n_slow), 2 * np.ones(n_theta)])
    return P, groups.astype(int)


@pytest.mark.parametrize("seed", [0, 1])
def test_group_moves_lower_the_cost_and_keep_every_group_in_order(seed):
    P, groups = _two_stage_adaptation(seed=seed)
    n = P.shape[0]
    base = sparse_lu._symbolic_lu(P)
    csr = as_csr(P)
    start = dense_cost(P, base.perm)
    found = sparse_lu.refine_by_groups(csr, base.perm, groups)
    assert found is not None
    order, madds, nnz = found
    assert np.array_equal(np.sort(order), np.arange(n))
    assert (madds, nnz) == dense_cost(P, order)       # what the search reports, recounted
    w = sparse_lu.SOLVES_PER_FACTOR
    assert madds + w * nnz < (1 - sparse_lu.REFINE_MIN_GAIN) * (start[0] + w * start[1])
    for g in np.unique(groups):                        # a group moved whole, in its order
        assert np.array_equal(order[groups[order] == g], base.perm[groups[base.perm] == g])
    # a single group has nothing to move
    assert sparse_lu.refine_by_groups(csr, base.perm, np.zeros(n, dtype=int)) is None


def test_the_compiled_search_finds_the_python_search_s_order(monkeypatch):
    """The search of a real arm's loop evaluates its orders with the cost compiled from
    elimination_cost.c (REFINE_COMPILED_FROM states or more): the same moves, the same
    order as in Python; the candidate orderings too."""
    P, groups = _two_stage_adaptation(seed=1)
    base, csr = sparse_lu._symbolic_lu(P), as_csr(P)
    in_python = sparse_lu.refine_by_groups(csr, base.perm, groups)
    monkeypatch.setattr(sparse_lu, "REFINE_COMPILED_FROM", 0)
    compiled = sparse_lu.refine_by_groups(csr, base.perm, groups)
    assert np.array_equal(compiled[0], in_python[0]) and compiled[1:] == in_python[1:]
    assert np.array_equal(sparse_lu._symbolic_lu(P).perm, base.perm)


def test_the_refined_order_factors_and_solves_as_numpy(tmp_path, monkeypatch):
    """The planar-4 loop's real pattern with its state groups: the refined order costs less
    than the least-fill one, and c I - J factored in it solves as numpy does."""
    from ivdrem.sim.compiled import load_c_stepper
    from ivdrem.sim.tables import dense_to_sparse
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    pattern, groups = _loop_pattern_and_groups(4)
    sparse_lu._SYMBOLIC.clear()
    slu = sparse_lu.symbolic_lu(pattern, groups)
    base = sparse_lu._symbolic_lu(pattern)
    w = sparse_lu.SOLVES_PER_FACTOR
    cost = [m + w * e for m, e in (dense_cost(pattern, s.perm) for s in (slu, base))]
    assert cost[0] < cost[1] and slu.ordering.endswith("groups moved")
    rng = np.random.default_rng(8)
    n = slu.n
    J = np.where(pattern, rng.standard_normal(pattern.shape), 0.0)
    values = dense_to_sparse(J, slu.perm, slu.rowptr, slu.colidx)
    st, LU = _factor(slu, values, 40.0, panels=True)
    assert st == 0
    b = rng.standard_normal(n)
    x = b.copy()
    load_c_stepper().slu_solve(np.concatenate([LU, np.zeros(n)]), n, slu.perm, slu.rowptr,
                               slu.colidx, slu.diagp, x)
    np.testing.assert_allclose(x, np.linalg.solve(40.0 * np.eye(n) - J, b), rtol=1e-12,
                               atol=1e-14)


def _loop_pattern_and_groups(n_joints):
    from ivdrem.sim.jacobian import JacobianProgram
    plan = _loop_plan(n_joints)
    return JacobianProgram(plan).pattern, plan.state_groups()


def test_state_groups_are_the_blocks_state_vectors():
    plan = _loop_plan(2)
    loop, groups = plan.diagram, plan.state_groups()
    labels = np.array([f"{s.name}.{lab.split('[', 1)[0]}" for s in loop.syslist
                       for lab in s.state_labels])
    assert groups.shape == (loop.nstates,)
    for a in range(loop.nstates):               # the same group exactly where the same vector
        assert np.array_equal(groups == groups[a], labels == labels[a])
    assert groups.max() + 1 == len(set(labels.tolist())) > 5


def test_the_refined_order_is_kept_on_disk_and_a_damaged_file_is_searched_again(
        tmp_path, monkeypatch):
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    P, groups = _two_stage_adaptation()
    sparse_lu._SYMBOLIC.clear()
    first = sparse_lu.symbolic_lu(P, groups)
    assert sparse_lu.symbolic_lu(P, groups) is first            # the same process
    files = list((tmp_path / "lu-orders").glob("*.npz"))
    assert len(files) == 1
    sparse_lu._SYMBOLIC.clear()

    def no_search(*a, **k):
        raise AssertionError("searched again")
    with monkeypatch.context() as m:
        m.setattr(sparse_lu, "refine_by_groups", no_search)
        m.setattr(sparse_lu, "_filled_rows", no_search)         # nor eliminated
        again = sparse_lu.symbolic_lu(P, groups)                 # another process: from disk
    assert again.ordering == first.ordering
    assert (again.n, again.nnz_a, again.nnz_lu, again.fill) == \
        (first.n, first.nnz_a, first.nnz_lu, first.fill)
    for k in sparse_lu.SymbolicLU.ARRAYS:
        a, b = getattr(again, k), getattr(first, k)
        assert a.dtype == b.dtype and np.array_equal(a, b) and not a.flags.writeable, k
    files[0].write_bytes(b"not an npz")
    sparse_lu._SYMBOLIC.clear()
    assert np.array_equal(sparse_lu.symbolic_lu(P, groups).perm, first.perm)
    assert sparse_lu._read_kept(files[0], P.shape[0]) is not None  # rewritten
    # a file whose rows do not fit the pattern's size is not read
    assert sparse_lu._read_kept(files[0], P.shape[0] + 1) is None
    # groups of the wrong size are refused before any work
    with pytest.raises(ValueError, match="groups has 3 entries"):
        sparse_lu.symbolic_lu(P, [0, 1, 2])
