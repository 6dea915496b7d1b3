"""Tests of ivdrem.models: generated regressors vs the paper, Property 1/3, codegen, numba."""
import math

import numpy as np
import pytest
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ivdrem.models import (EulerLagrangeModel, get_model, planar_arm,
                           planar_physical_theta, two_link)

G0 = 9.81
TH_PAPER = np.array([1.3, 0.28, 0.32, 0.4, 1.4])


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def m2():
    return two_link()


@pytest.fixture(scope="module")
def p3():
    return planar_arm(3, friction=True)


@pytest.fixture(scope="module")
def jit_models():
    """Compile (once per session) the numba versions of two models, warming every function."""
    models = [two_link(), planar_arm(2, friction=True)]
    for m in models:
        jf = m.jit_functions
        rng = np.random.default_rng(0)
        for name, args in _call_args(m, rng).items():
            getattr(jf, name)(*args)
    return models


def _call_args(m, rng):
    """Random arguments (with fresh out buffers) for every generated function."""
    n, nt = m.n, m.ntheta
    q, dq, v, dv, a = (rng.uniform(-np.pi, np.pi, n) for _ in range(5))
    tau = rng.normal(size=n) * 5
    th = np.array(m.theta_values)
    R = lambda: np.full((n, nt), np.nan)  # noqa: E731
    return {
        "Phi_M": (q, a, R()), "Phi_C": (q, dq, v, R()), "Phi_dM": (q, dq, a, R()),
        "Phi_G": (q, R()), "Phi_F": (dq, R()), "Phi": (q, dq, v, dv, R()),
        "M": (q, th, np.full((n, n), np.nan)), "C": (q, dq, th, np.full((n, n), np.nan)),
        "G": (q, th, np.full(n, np.nan)), "F": (dq, th, np.full(n, np.nan)),
        "forward_dynamics": (q, dq, tau, th, np.full(n, np.nan)),
    }


def _ev(m, th=None):
    """Small numeric evaluators built on the generated (pure Python) functions."""
    f = m.functions
    n, nt = m.n, m.ntheta
    th = m.theta_values if th is None else th

    def call(name, *args, shape):
        out = np.full(shape, np.nan)
        getattr(f, name)(*[np.asarray(x, float) for x in args], out)
        return out

    return dict(
        M=lambda q: call("M", q, th, shape=(n, n)),
        C=lambda q, dq: call("C", q, dq, th, shape=(n, n)),
        G=lambda q: call("G", q, th, shape=(n,)),
        F=lambda dq: call("F", dq, th, shape=(n,)),
        Phi=lambda q, dq, v, dv: call("Phi", q, dq, v, dv, shape=(n, nt)),
        Phi_M=lambda q, a: call("Phi_M", q, a, shape=(n, nt)),
        Phi_C=lambda q, dq, v: call("Phi_C", q, dq, v, shape=(n, nt)),
        Phi_dM=lambda q, dq, a: call("Phi_dM", q, dq, a, shape=(n, nt)),
        Phi_G=lambda q: call("Phi_G", q, shape=(n, nt)),
        Phi_F=lambda dq: call("Phi_F", dq, shape=(n, nt)),
        fd=lambda q, dq, tau: call("forward_dynamics", q, dq, tau, th, shape=(n,)),
    )


def _mdot_from_phi_dm(ev, th, q, dq):
    n = len(q)
    return np.column_stack([ev["Phi_dM"](q, dq, e) @ th for e in np.eye(n)])


# ----------------------------------------------------------------------------- paper oracle
def paper_regressors(q, dq, v, dv, a):
    """The paper's Section 4 hand-written regressors and matrices, typed independently."""
    q1, q2 = q
    dq1, dq2 = dq
    c1, c2, s2, c12 = math.cos(q1), math.cos(q2), math.sin(q2), math.cos(q1 + q2)
    th1, th2, th3, th4, th5 = TH_PAPER
    PhiM = np.array([[dv[0], c2 * (2 * dv[0] + dv[1]), dv[1], 0, 0],
                     [0, c2 * dv[0], dv[0] + dv[1], 0, 0]])
    PhiC = np.array([[0, -s2 * (dq2 * v[0] + (dq1 + dq2) * v[1]), 0, 0, 0],
                     [0, s2 * dq1 * v[0], 0, 0, 0]])
    PhiFG = np.array([[0, 0, 0, G0 * c12, G0 * c1],
                      [0, 0, 0, G0 * c12, 0]])
    PhidM = np.array([[0, -s2 * dq2 * (2 * a[0] + a[1]), 0, 0, 0],
                      [0, -s2 * dq2 * a[0], 0, 0, 0]])
    M = np.array([[th1 + 2 * th2 * c2, th3 + th2 * c2], [th3 + th2 * c2, th3]])
    C = np.array([[-th2 * s2 * dq2, -th2 * s2 * (dq1 + dq2)], [th2 * s2 * dq1, 0.0]])
    G = np.array([th4 * G0 * c12 + th5 * G0 * c1, th4 * G0 * c12])
    return dict(Phi_M=PhiM, Phi_C=PhiC, Phi_FG=PhiFG, Phi_dM=PhidM, M=M, C=C, G=G)


def test_two_link_matches_paper_section4(m2):
    assert m2.name == "two-link" and (m2.n, m2.ntheta) == (2, 5)
    np.testing.assert_array_equal(m2.theta_values, TH_PAPER)
    ev = _ev(m2)
    rng = np.random.default_rng(1)
    for _ in range(250):
        q, dq, v, dv, a = (rng.uniform(-4, 4, 2) for _ in range(5))
        ref = paper_regressors(q, dq, v, dv, a)
        np.testing.assert_allclose(ev["Phi_M"](q, dv), ref["Phi_M"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ev["Phi_C"](q, dq, v), ref["Phi_C"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ev["Phi_F"](dq) + ev["Phi_G"](q), ref["Phi_FG"],
                                   rtol=0, atol=1e-12)
        np.testing.assert_allclose(ev["Phi_dM"](q, dq, a), ref["Phi_dM"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ev["M"](q), ref["M"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ev["C"](q, dq), ref["C"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ev["G"](q), ref["G"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ev["Phi"](q, dq, v, dv),
                                   ref["Phi_M"] + ref["Phi_C"] + ref["Phi_FG"], rtol=0, atol=1e-12)


def test_two_link_symbolic_C_is_papers(m2):
    q1, q2 = m2.q
    dq1, dq2 = m2.dq
    th2 = m2.theta[1]
    s2 = sp.sin(q2)
    C_paper = sp.Matrix([[-th2 * s2 * dq2, -th2 * s2 * (dq1 + dq2)], [th2 * s2 * dq1, 0]])
    assert sp.simplify(sp.Matrix(m2.C) - C_paper) == sp.zeros(2, 2)
    assert m2.F == sp.zeros(2, 1)


def test_symbolic_regressors_are_theta_jacobians(m2):
    th = sp.Matrix(m2.theta)
    a, v, dv = (sp.Matrix(x) for x in (m2.a, m2.v, m2.dv))
    M, C = sp.Matrix(m2.M), sp.Matrix(m2.C)
    Mdot = sum((M.diff(qi) * dqi for qi, dqi in zip(m2.q, m2.dq)), sp.zeros(2, 2))
    checks = [(m2.Phi_M, (M * a).jacobian(th)), (m2.Phi_C, (C * v).jacobian(th)),
              (m2.Phi_dM, (Mdot * a).jacobian(th)), (m2.Phi_G, sp.Matrix(m2.G).jacobian(th)),
              (m2.Phi_F, sp.zeros(2, 5)),
              (m2.Phi, (M * dv + C * v + sp.Matrix(m2.G)).jacobian(th))]
    for got, want in checks:
        assert got.shape == (2, 5)
        assert sp.simplify(sp.Matrix(got) - want) == sp.zeros(2, 5)


# ----------------------------------------------------------------------------- Property 1
def _sympy_numeric(m):
    """Lambdified M, C, G, F from the symbolic attributes (independent of the code generator)."""
    sub = dict(m.constants)
    args = list(m.q) + list(m.dq) + list(m.theta)
    fs = {k: sp.lambdify(args, sp.Matrix(getattr(m, k).subs(sub)).tolist(), modules="math")
          for k in "MCGF"}

    def ev(k, q, dq, th):
        return np.array(fs[k](*q, *dq, *th), dtype=float)

    return ev


@pytest.mark.parametrize("which", ["two-link", "planar3f"])
def test_property1_regressor_identity(which, m2, p3):
    m = m2 if which == "two-link" else p3
    ev = _ev(m)
    sy = _sympy_numeric(m)
    th = np.array(m.theta_values)
    rng = np.random.default_rng(2)
    for _ in range(60):
        q, dq, v, dv = (rng.uniform(-3, 3, m.n) for _ in range(4))
        lhs = ev["Phi"](q, dq, v, dv) @ th
        num = ev["M"](q) @ dv + ev["C"](q, dq) @ v + ev["F"](dq) + ev["G"](q)
        np.testing.assert_allclose(lhs, num, rtol=1e-12, atol=1e-11)
        symb = (sy("M", q, dq, th) @ dv + sy("C", q, dq, th) @ v
                + sy("F", q, dq, th).ravel() + sy("G", q, dq, th).ravel())
        np.testing.assert_allclose(lhs, symb, rtol=1e-12, atol=1e-11)
        # the parts separately
        parts = (ev["Phi_M"](q, dv) + ev["Phi_C"](q, dq, v) + ev["Phi_F"](dq) + ev["Phi_G"](q))
        np.testing.assert_allclose(ev["Phi"](q, dq, v, dv), parts, rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(ev["Phi_F"](dq) @ th, sy("F", q, dq, th).ravel(),
                                   rtol=1e-13, atol=1e-13)


def _planar_reference(q, dq, masses, lengths, g=G0):
    """Independent numeric planar-arm dynamics: Jacobians of the centres of mass."""
    n = len(q)
    m, l = np.asarray(masses, float), np.asarray(lengths, float)
    c, I = l / 2, m * l ** 2 / 12

    def mass_matrix(qq):
        phi = np.cumsum(qq)
        M = np.zeros((n, n))
        for i in range(n):
            Jv = np.zeros((2, n))
            for j in range(i + 1):
                r = l[j] if j < i else c[i]
                for k in range(j + 1):  # phi_j depends on q_0..q_j
                    Jv[:, k] += r * np.array([-np.sin(phi[j]), np.cos(phi[j])])
            Jw = np.array([1.0 if k <= i else 0.0 for k in range(n)])
            M += m[i] * Jv.T @ Jv + I[i] * np.outer(Jw, Jw)
        return M

    def gravity(qq):
        phi = np.cumsum(qq)
        G = np.zeros(n)
        for i in range(n):
            for j in range(i + 1):
                r = l[j] if j < i else c[i]
                G[: j + 1] += m[i] * g * r * np.cos(phi[j])
        return G

    # Christoffel C from central differences of the reference M
    h = 1e-5
    dM = [(mass_matrix(q + h * e) - mass_matrix(q - h * e)) / (2 * h) for e in np.eye(n)]
    C = np.zeros((n, n))
    for k in range(n):
        for j in range(n):
            C[k, j] = sum(0.5 * (dM[i][k, j] + dM[j][k, i] - dM[k][i, j]) * dq[i] for i in range(n))
    return mass_matrix(q), C, gravity(q)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_planar_arm_against_independent_derivation(n):
    rng = np.random.default_rng(10 + n)
    masses = rng.uniform(0.5, 3.0, n)
    lengths = rng.uniform(0.3, 1.5, n)
    fric = rng.uniform(0.05, 0.5, n)
    base = planar_arm(n, lengths=lengths, friction=True,
                      theta_values=planar_physical_theta(masses, lengths, friction=fric))
    full = planar_arm(n, lengths=lengths, parameters="full",
                      theta_values=planar_physical_theta(masses, lengths, parameters="full"))
    assert base.ntheta == 3 * n and full.ntheta == 3 * n and base.name == f"planar-{n}"
    eb, ef = _ev(base), _ev(full)
    for _ in range(20):
        q, dq = rng.uniform(-3, 3, n), rng.uniform(-2, 2, n)
        M, C, G = _planar_reference(q, dq, masses, lengths)
        np.testing.assert_allclose(eb["M"](q), M, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(eb["G"](q), G, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(eb["C"](q, dq), C, rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(eb["F"](dq), fric * dq, rtol=1e-14, atol=1e-14)
        # the literal per-link parameters give the same plant
        np.testing.assert_allclose(ef["M"](q), M, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ef["G"](q), G, rtol=1e-12, atol=1e-12)
    # the full parameter set is not identifiable (m_1 has a zero regressor column);
    # the base set is: its regressor stacked over random points has full column rank
    rows_b, rows_f = [], []
    for _ in range(4 * n):
        q, dq, v, dv = (rng.uniform(-3, 3, n) for _ in range(4))
        rows_b.append(eb["Phi"](q, dq, v, dv))
        rows_f.append(ef["Phi"](q, dq, v, dv))
    assert np.linalg.matrix_rank(np.vstack(rows_b)) == base.ntheta
    assert np.linalg.matrix_rank(np.vstack(rows_f)) == 2 * n < full.ntheta


# ----------------------------------------------------------------------------- Property 3
@pytest.mark.parametrize("which", ["two-link", "planar3f"])
def test_property3_skew_symmetry(which, m2, p3):
    m = m2 if which == "two-link" else p3
    ev = _ev(m)
    th = np.array(m.theta_values)
    rng = np.random.default_rng(3)
    Md = sp.lambdify(list(m.q) + list(m.dq) + list(m.theta),
                     sp.Matrix(m.Mdot.subs(m.constants)).tolist(), modules="math")
    for _ in range(50):
        q, dq, x = (rng.uniform(-3, 3, m.n) for _ in range(3))
        N = _mdot_from_phi_dm(ev, th, q, dq) - 2 * ev["C"](q, dq)
        np.testing.assert_allclose(N + N.T, 0.0, atol=1e-12)
        assert abs(x @ N @ x) < 1e-11
        # Phi_dM^T(q, dq, a) theta = Mdot a, with the symbolic Mdot
        a = rng.normal(size=m.n)
        np.testing.assert_allclose(ev["Phi_dM"](q, dq, a) @ th,
                                   np.array(Md(*q, *dq, *th), float) @ a, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("which", ["two-link", "planar3f"])
def test_mdot_against_finite_differences_along_trajectory(which, m2, p3):
    m = m2 if which == "two-link" else p3
    ev = _ev(m)
    th = np.array(m.theta_values)
    rng = np.random.default_rng(4)
    q0, A, w, ph = (rng.uniform(-1, 1, m.n), rng.uniform(0.5, 1.5, m.n),
                    rng.uniform(0.5, 2.0, m.n), rng.uniform(0, 2 * np.pi, m.n))
    qt = lambda t: q0 + A * np.sin(w * t + ph)  # noqa: E731
    dqt = lambda t: A * w * np.cos(w * t + ph)  # noqa: E731
    for t in (0.3, 1.7):
        exact = _mdot_from_phi_dm(ev, th, qt(t), dqt(t))
        errs = []
        for h in (4e-2, 2e-2, 1e-2):
            fd = (ev["M"](qt(t + h)) - ev["M"](qt(t - h))) / (2 * h)
            errs.append(np.max(np.abs(fd - exact)))
        ratios = [errs[0] / errs[1], errs[1] / errs[2]]
        assert all(3.5 < r < 4.5 for r in ratios), (errs, ratios)  # O(h^2)
        assert errs[-1] < 1e-3 * max(1.0, np.max(np.abs(exact)))


@settings(max_examples=150, deadline=None)
@given(arrays(np.float64, (3, 2), elements=st.floats(-10, 10, allow_nan=False)))
def test_skew_symmetry_property_hypothesis(data):
    m = _HYP_MODEL
    ev = _HYP_EV
    q, dq, x = data
    N = _mdot_from_phi_dm(ev, m.theta_values, q, dq) - 2 * ev["C"](q, dq)
    scale = 1.0 + np.max(np.abs(N)) * (x @ x)
    assert abs(x @ N @ x) <= 1e-13 * scale


_HYP_MODEL = two_link()
_HYP_EV = _ev(_HYP_MODEL)


# ----------------------------------------------------------------------------- forward dynamics
@pytest.mark.parametrize("which", ["two-link", "planar3f"])
def test_forward_dynamics_inverts_the_plant(which, m2, p3):
    m = m2 if which == "two-link" else p3
    ev = _ev(m)
    rng = np.random.default_rng(5)
    for _ in range(50):
        q, dq = rng.uniform(-3, 3, m.n), rng.uniform(-3, 3, m.n)
        tau = rng.normal(size=m.n) * 10
        qdd = ev["fd"](q, dq, tau)
        res = ev["M"](q) @ qdd + ev["C"](q, dq) @ dq + ev["F"](dq) + ev["G"](q)
        np.testing.assert_allclose(res, tau, rtol=1e-11, atol=1e-10)
        np.testing.assert_allclose(m.acceleration(q, dq, tau), qdd, rtol=1e-14, atol=0)
        np.testing.assert_allclose(m.inverse_dynamics(q, dq, qdd), tau, rtol=1e-11, atol=1e-10)


@pytest.mark.parametrize("bad", [[1.3, 0.28, 0.0, 0.4, 1.4],      # M22 = 0
                                 [0.1, 0.28, 0.32, 0.4, 1.4],     # det M < 0 near q2 = 0
                                 [-1.3, 0.28, 0.32, 0.4, 1.4]])
def test_forward_dynamics_raises_on_singular_inertia(m2, jit_models, bad):
    q, dq, tau = np.array([0.1, 0.05]), np.zeros(2), np.zeros(2)
    th = np.array(bad)
    for f in (m2.functions.forward_dynamics, jit_models[0].jit_functions.forward_dynamics):
        with pytest.raises(ValueError, match="not positive definite"):
            f(q, dq, tau, th, np.empty(2))
    with pytest.raises(ValueError, match="not positive definite"):
        m2.functions.forward_dynamics(q, dq, tau, np.array([np.nan, 0.28, 0.32, 0.4, 1.4]),
                                      np.empty(2))


# ----------------------------------------------------------------------------- code generation
def test_numba_matches_python(jit_models):
    for m in jit_models:
        for seed in range(5):
            args_py = _call_args(m, np.random.default_rng(100 + seed))
            args_jit = _call_args(m, np.random.default_rng(100 + seed))
            for name in args_py:
                getattr(m.functions, name)(*args_py[name])
                getattr(m.jit_functions, name)(*args_jit[name])
                out_py, out_jit = args_py[name][-1], args_jit[name][-1]
                assert np.all(np.isfinite(out_py)), name
                np.testing.assert_allclose(out_jit, out_py, rtol=1e-13, atol=1e-13, err_msg=name)
    # the planar model exercises a nonzero friction regressor
    out = np.empty((2, jit_models[1].ntheta))
    jit_models[1].jit_functions.Phi_F(np.array([1.0, -2.0]), out)
    assert np.count_nonzero(out) == 2


def test_source_prefix_and_self_contained(m2):
    src = m2.source("m0_")
    for name in ("Phi_M", "Phi_C", "Phi_dM", "Phi_G", "Phi_F", "Phi", "M", "C", "G", "F",
                 "forward_dynamics", "Phi_M_jac", "Phi_C_jac", "Phi_dM_jac", "Phi_G_jac",
                 "Phi_F_jac", "Phi_jac"):
        assert f"def m0_{name}(" in src
    assert "sympy" not in src and "lambda" not in src
    glb = {"math": math, "np": np}
    exec(src, glb)
    out = np.empty((2, 5))
    glb["m0_Phi"](np.array([0.2, 0.3]), np.ones(2), np.ones(2), np.ones(2), out)
    ref = np.empty((2, 5))
    m2.functions.Phi(np.array([0.2, 0.3]), np.ones(2), np.ones(2), np.ones(2), ref)
    np.testing.assert_array_equal(out, ref)
    with pytest.raises(ValueError, match="prefix"):
        m2.source("0bad")


def test_float_constants_are_exact():
    # 0.1 + 0.2 is not 0.3: a 15-digit printer would change the constant
    g = 0.1 + 0.2
    m = two_link(g=g)
    out = np.empty((2, 5))
    m.functions.Phi_G(np.array([0.0, 0.0]), out)
    assert out[0, 4] == g


def test_key_is_stable_and_content_sensitive():
    k = two_link().key
    assert isinstance(k, str) and len(k) == 64 and int(k, 16) >= 0
    assert two_link().key == k
    assert two_link(theta=[1, 1, 1, 1, 1]).key == k  # theta values are data, not model
    assert two_link(g=9.8).key != k
    assert planar_arm(2).key != k
    assert planar_arm(2, lengths=[1.0, 0.5]).key != planar_arm(2).key


def test_registry():
    assert get_model("two-link").name == "two-link"
    m = get_model("planar-3", friction=True)
    assert (m.name, m.n, m.ntheta) == ("planar-3", 3, 9)
    for bad in ("three-link", "planar-0", "planar-x"):
        with pytest.raises(ValueError, match="valid names.*two-link.*planar-N"):
            get_model(bad)


# ----------------------------------------------------------------------------- validation
def _syms():
    q = list(sp.symbols("x1 x2"))
    th = list(sp.symbols("a b c"))
    return q, th


def test_validation_errors():
    q, (a, b, c) = _syms()
    th = [a, b, c]
    c2 = sp.cos(q[1])
    good = sp.Matrix([[a + 2 * b * c2, b * c2], [b * c2, c]])
    P = c * sp.sin(q[0])
    EulerLagrangeModel("ok", q, th, good, potential=P, theta_values=[1, 0.1, 1])

    with pytest.raises(ValueError, match="not symmetric"):
        EulerLagrangeModel("x", q, th, sp.Matrix([[a, b * c2], [0, c]]), potential=P)
    with pytest.raises(ValueError, match="square"):
        EulerLagrangeModel("x", q, th, sp.Matrix([[a, b], [b, c], [a, a]]), potential=P)
    with pytest.raises(ValueError, match="not linear in theta.*second derivative"):
        EulerLagrangeModel("x", q, th, sp.Matrix([[a ** 2, b], [b, c]]), potential=P)
    with pytest.raises(ValueError, match="not linear in theta.*second derivative"):
        EulerLagrangeModel("x", q, th, sp.Matrix([[a, b * c], [b * c, c]]), potential=P)
    with pytest.raises(ValueError, match="theta-free"):
        EulerLagrangeModel("x", q, th, sp.Matrix([[a + 1, b], [b, c]]), potential=P)
    with pytest.raises(ValueError, match="potential.*theta-free"):
        EulerLagrangeModel("x", q, th, good, potential=P + sp.sin(q[1]))
    with pytest.raises(ValueError, match="G is not linear.*second derivative"):
        EulerLagrangeModel("x", q, th, good, G=sp.Matrix([c * b * sp.cos(q[0]), 0]))
    with pytest.raises(ValueError, match="theta_values must have length ntheta = 3"):
        EulerLagrangeModel("x", q, th, good, potential=P, theta_values=[1.0, 2.0])
    with pytest.raises(ValueError, match="theta_values must be finite"):
        EulerLagrangeModel("x", q, th, good, potential=P, theta_values=[1.0, np.inf, 1.0])
    with pytest.raises(ValueError, match="F must not depend on q"):
        EulerLagrangeModel("x", q, th, good, potential=P, F=sp.Matrix([a * q[0], 0]))
    with pytest.raises(ValueError, match="exactly one of potential"):
        EulerLagrangeModel("x", q, th, good, potential=P, G=sp.Matrix([0, 0]))
    with pytest.raises(ValueError, match="exactly one of potential"):
        EulerLagrangeModel("x", q, th, good)
    with pytest.raises(ValueError, match="duplicate symbols.*x1"):
        EulerLagrangeModel("x", q, [a, b, q[0]], good, potential=P)
    with pytest.raises(ValueError, match="dq must have the same length"):
        EulerLagrangeModel("x", q, th, good, potential=P, dq=[sp.Symbol("w")])
    with pytest.raises(ValueError, match="unknown symbols.*zz"):
        EulerLagrangeModel("x", q, th, good + sp.Matrix([[sp.Symbol("zz") * a, 0], [0, 0]]),
                           potential=P)
    with pytest.raises(ValueError, match="M must not depend on dq"):
        dq = list(sp.symbols("y1 y2"))
        EulerLagrangeModel("x", q, th, good + sp.Matrix([[a * dq[0], 0], [0, 0]]),
                           potential=P, dq=dq)
    with pytest.raises(ValueError, match="theta_names must have length"):
        EulerLagrangeModel("x", q, th, good, potential=P, theta_names=["a"])


def test_linear_but_written_nonlinearly_is_accepted():
    q, (a, b, c) = _syms()
    c2 = sp.cos(q[1])
    M = sp.Matrix([[a * (a + 1) - a ** 2 + 2 * b * c2, b * c2], [b * c2, c]])
    m = EulerLagrangeModel("x", q, [a, b, c], M, potential=c * sp.sin(q[0]),
                           constants={sp.Symbol("k"): 2.0})
    assert m.theta_values is None and m.theta_names == ["a", "b", "c"]
    assert [str(s) for s in m.dq] == ["dq0", "dq1"]
    out = np.empty((2, 3))
    m.functions.Phi_M(np.array([0.0, 0.0]), np.array([1.0, 0.0]), out)
    np.testing.assert_allclose(out, [[1, 2, 0], [0, 1, 0]])


# ----------------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("which", ["two-link", "planar-3"])
def test_regressor_derivatives_match_central_differences(which, m2):
    """Each generated R_jac (exact, from sympy diff) against central differences of the
    generated regressor R itself, at random arguments: out[i, j, a n + m] = dR_ij/dw_a[m]."""
    from ivdrem.models.euler_lagrange import REGRESSOR_ARGS
    m = m2 if which == "two-link" else planar_arm(3, friction=True)
    f, n, nt = m.functions, m.n, m.ntheta
    rng = np.random.default_rng(21)
    for name, argnames in REGRESSOR_ARGS.items():
        k = len(argnames)
        for _ in range(2):
            w = rng.uniform(-2.0, 2.0, k * n)

            def R(w):
                out = np.empty((n, nt))
                getattr(f, name)(*[w[a * n:(a + 1) * n] for a in range(k)], out)
                return out
            J = np.full((n, nt, k * n), np.nan)
            getattr(f, name + "_jac")(*[w[a * n:(a + 1) * n].copy() for a in range(k)], J)
            ref = np.empty_like(J)
            for c in range(k * n):
                h = 1e-5 * max(abs(w[c]), 1.0)
                wp, wm = w.copy(), w.copy()
                wp[c] += h
                wm[c] -= h
                ref[:, :, c] = (R(wp) - R(wm)) / (wp[c] - wm[c])
            assert np.all(np.isfinite(J)), name
            scale = np.abs(ref).max()
            if scale == 0.0:            # Phi_F without friction: the derivative is zero
                assert np.all(J == 0.0), name
                continue
            np.testing.assert_allclose(J, ref, rtol=1e-7, atol=1e-7 * scale, err_msg=name)
    # d/dv of Phi_C and d/ddv of Phi are the regressors themselves at unit vectors (linear)
    q, dq = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    J = np.empty((n, nt, 3 * n))
    f.Phi_C_jac(q, dq, np.zeros(n), J)
    for c in range(n):
        e = np.zeros(n)
        e[c] = 1.0
        ref = np.empty((n, nt))
        f.Phi_C(q, dq, e, ref)
        np.testing.assert_allclose(J[:, :, 2 * n + c], ref, rtol=1e-13, atol=1e-14)
    with pytest.raises(ValueError, match="unknown regressor 'Phi_X'"):
        m.regressor_jacobian("Phi_X")


def test_regressor_derivatives_compile_with_numba(jit_models):
    """The numba versions of the derivatives agree with the plain Python ones."""
    from ivdrem.models.euler_lagrange import REGRESSOR_ARGS
    m = jit_models[1]
    n, nt = m.n, m.ntheta
    rng = np.random.default_rng(5)
    for name, argnames in REGRESSOR_ARGS.items():
        args = [rng.uniform(-2, 2, n) for _ in argnames]
        a, b = (np.full((n, nt, len(args) * n), np.nan) for _ in range(2))
        getattr(m.functions, name + "_jac")(*args, a)
        getattr(m.jit_functions, name + "_jac")(*args, b)
        np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-13, err_msg=name)
