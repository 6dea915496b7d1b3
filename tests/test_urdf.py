"""URDF arms (ivdrem.models.from_urdf / arm) against Pinocchio, the reference library.

* At 1000 random states per arm (q uniform in the joint limits, velocities and
  accelerations standard normal), the relative error max|x - ref| / max|ref| of
  M vs crba, C vs computeCoriolisMatrix, G vs computeGeneralizedGravity,
  Phi(q, dq, v, dv) theta vs M dv + C v + G, Phi_dM(q, dq, a) theta vs (C + C^T) a
  (Property 3: Mdot = C + C^T) and forward_dynamics vs aba is at most 1e-10 (measured
  below 1e-13); an inertia perturbed by 1 % in Pinocchio's model breaks every check.
* Base parameters: the rank is Pinocchio's regressor rank (Panda, iiwa, xArm7 43, UR5 36;
  with viscous and Coulomb friction 57 and 48), and the base regressor times theta_base is
  the standard regressor times theta_standard to 1e-12, for the URDF's values and for
  random standard parameters.
* Every regressor's derivative (``*_jac``) against central differences of the regressor.
* The URDFs of the named arms are written by others (example-robot-data, pybullet).
"""
from __future__ import annotations

import time

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")

from ivdrem.models import (ARM_NAMES, RANK_RTOL, URDFError, arm, from_urdf, get_model,  # noqa: E402
                           model_names, two_link)
from ivdrem.models import urdf as urdf_mod  # noqa: E402

RANKS = {"panda": (43, 57), "iiwa": (43, 57), "xarm7": (43, 57), "ur5": (36, 48)}


def _available(name):
    try:
        urdf_mod.arm_urdf(name)
        return True
    except ImportError:
        return False


ARMS = [pytest.param(a, marks=pytest.mark.skipif(not _available(a), reason="arms extra missing"))
        for a in ARM_NAMES]


@pytest.fixture(scope="module")
def models():
    return {}


def _model(models, name, **opt):
    key = (name, repr(sorted(opt.items())))
    if key not in models:
        models[key] = arm(name, **opt)
    return models[key]


def _states(m, N, seed):
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(m.position_limits[:, 0]), m.position_limits[:, 0], -np.pi)
    hi = np.where(np.isfinite(m.position_limits[:, 1]), m.position_limits[:, 1], np.pi)
    for _ in range(N):
        yield (rng.uniform(lo, hi), rng.standard_normal(m.n), rng.standard_normal(m.n),
               rng.standard_normal(m.n))


def _rel(x, ref):
    return float(np.max(np.abs(x - ref)) / max(np.max(np.abs(ref)), 1e-300))


def _errors(m, pm, N=1000, seed=0):
    """Max relative errors of M, C, G, Phi, Phi_dM, forward dynamics over N states."""
    f = m.jit_functions
    pd = pm.createData()
    n, nt, th = m.n, m.ntheta, np.asarray(m.theta_values)
    Mo, Co, Go = np.empty((n, n)), np.empty((n, n)), np.empty(n)
    P, D, acc = np.empty((n, nt)), np.empty((n, nt)), np.empty(n)
    err = dict.fromkeys(("M", "C", "G", "Phi", "Phi_dM", "aba"), 0.0)
    for q, dq, v, dv in _states(m, N, seed):
        qp = m.pinocchio_configuration(q)
        Mp = pin.crba(pm, pd, qp)
        Mp = np.triu(Mp) + np.triu(Mp, 1).T
        Cp = pin.computeCoriolisMatrix(pm, pd, qp, dq)
        Gp = pin.computeGeneralizedGravity(pm, pd, qp)
        f.M(q, th, Mo)
        f.C(q, dq, th, Co)
        f.G(q, th, Go)
        f.Phi(q, dq, v, dv, P)
        f.Phi_dM(q, dq, v, D)
        tau = Mp @ dv + Cp @ dq + Gp        # any torque: the one of a known acceleration
        f.forward_dynamics(q, dq, tau, th, acc)
        ref = Mp @ dv + Cp @ v + Gp
        Fo = np.empty(n)
        f.F(dq, th, Fo)
        for k, e in (("M", _rel(Mo, Mp)), ("C", _rel(Co, Cp)), ("G", _rel(Go, Gp)),
                     ("Phi", _rel(P @ th - Fo, ref)), ("Phi_dM", _rel(D @ th, (Cp + Cp.T) @ v)),
                     ("aba", _rel(acc, pin.aba(pm, pd, qp, dq, tau - Fo)))):
            err[k] = max(err[k], e)
    return err


@pytest.mark.parametrize("name", ARMS)
def test_against_pinocchio(models, name):
    m = _model(models, name)
    err = _errors(m, m.pinocchio_model())
    print(name, {k: f"{v:.1e}" for k, v in err.items()})
    assert all(v <= 1e-10 for v in err.values()), err


def test_friction_and_armature_against_pinocchio(models):
    """Panda with viscous + Coulomb friction and armature: Pinocchio's crba/aba with the
    same armature, the friction torque added by hand (Pinocchio has none)."""
    if not _available("panda"):
        pytest.skip("arms extra missing")
    arm_vals = np.linspace(0.1, 0.4, 7)
    m = _model(models, "panda", friction={"viscous": 0.5, "coulomb": 1.5},
               armature=tuple(arm_vals))
    # 57 + 5: the armatures of the first two joints group with link parameters (Izz1, and
    # for the second, a regrouped inertia), as Pinocchio's regressor rank says
    assert m.ntheta == 62
    pm = m.pinocchio_model()
    pm.armature = arm_vals
    err = _errors(m, pm, N=200, seed=1)
    assert all(v <= 1e-10 for v in err.values()), err
    Fo = np.empty(7)
    dq = np.linspace(-1, 1, 7)
    m.jit_functions.F(dq, np.asarray(m.theta_values), Fo)
    w = m.friction_width
    assert np.allclose(Fo, 0.5 * dq + 1.5 * np.tanh(dq / w), rtol=1e-14, atol=1e-14)


def test_perturbed_inertia_breaks_the_check(models):
    """The check can fail: Pinocchio's model with one link 1 % heavier disagrees."""
    if not _available("panda"):
        pytest.skip("arms extra missing")
    m = _model(models, "panda")
    pm = m.pinocchio_model()
    I3 = pm.inertias[3]
    pm.inertias[3] = pin.Inertia(I3.mass * 1.01, I3.lever, I3.inertia)
    err = _errors(m, pm, N=20)
    print(err)
    assert all(v > 1e-5 for v in err.values()), err


@pytest.mark.parametrize("name", ARMS)
def test_base_parameter_rank(models, name):
    m = _model(models, name)
    mf = _model(models, name, friction="viscous+coulomb")
    assert (m.ntheta, mf.ntheta) == RANKS[name]
    assert len(set(m.theta_names)) == m.ntheta
    assert m.nstandard == 10 * m.n and mf.nstandard == 12 * m.n
    # the rank does not hang on the tolerance: the stacked regressor's singular values
    # jump by many decades across RANK_RTOL (SVD, independent of the pivoted QR)
    rng = np.random.default_rng(5)
    W = urdf_mod._stacked_regressor(m.pinocchio_model(), m._chain, rng, 60)
    s = np.linalg.svd(W, compute_uv=False)
    s = s / s[0]
    r = m.ntheta
    assert s[r - 1] > 1e3 * RANK_RTOL and s[r] < 1e-3 * RANK_RTOL, (s[r - 1], s[r])


@pytest.mark.parametrize("name", ARMS)
def test_base_regressor_equals_standard(models, name):
    """Y_base theta_base = Y_standard theta_standard (Pinocchio's regressor, with gravity),
    for the URDF's parameters and for random standard parameters mapped by K."""
    m = _model(models, name)
    pm = m.pinocchio_model()
    pd = pm.createData()
    rng = np.random.default_rng(3)
    thetas = [m.theta_standard] + [rng.standard_normal(m.nstandard) for _ in range(3)]
    P = np.empty((m.n, m.ntheta))
    worst = 0.0
    for q, dq, _, ddq in _states(m, 100, 2):
        Y = np.array(pin.computeJointTorqueRegressor(pm, pd, m.pinocchio_configuration(q), dq,
                                                     ddq))
        m.jit_functions.Phi(q, dq, dq, ddq, P)
        for ts in thetas:
            ref = Y @ ts
            worst = max(worst, np.max(np.abs(P @ (m.base_matrix @ ts) - ref))
                        / max(1.0, np.max(np.abs(ref))))
    assert worst <= 1e-12, worst


def test_parameter_table(models):
    if not _available("panda"):
        pytest.skip("arms extra missing")
    m = _model(models, "panda")
    rows = m.parameter_table()
    assert [r[0] for r in rows] == m.theta_names
    for (nm, val, unit, terms), tv, b in zip(rows, m.theta_values, range(m.ntheta)):
        assert val == tv
        assert val == pytest.approx(sum(c * m.theta_standard[m.standard_names.index(s)]
                                        for c, s in terms), rel=1e-14, abs=1e-15)
        assert nm.rstrip("R") == m.standard_names[m.base_columns[b]]
        assert unit in ("kg", "kg.m", "kg.m2")
    # the first joint is about a vertical axis: only Izz1 (regrouped) of link 1 is seen
    assert [nm for nm in m.theta_names if nm.endswith("1") or nm.endswith("1R")] == ["Izz1R"]
    assert "Izz1R" in m.parameter_table_text()


@pytest.mark.parametrize("reg", ["Phi_M", "Phi_C", "Phi_dM", "Phi_G", "Phi_F", "Phi"])
def test_regressor_jacobians_vs_central_differences(models, reg):
    if not _available("panda"):
        pytest.skip("arms extra missing")
    m = _model(models, "panda", friction="viscous+coulomb", friction_width=0.5)
    from ivdrem.models.base import REGRESSOR_ARGS
    f = m.jit_functions
    args = REGRESSOR_ARGS[reg]
    n, nt = m.n, m.ntheta
    rng = np.random.default_rng(11)
    for _ in range(3):
        w = [rng.uniform(-1, 1, n) for _ in args]
        J = np.empty((n, nt, len(args) * n))
        getattr(f, reg + "_jac")(*w, J)
        R0 = np.empty((n, nt))
        getattr(f, reg)(*w, R0)
        h = 1e-6
        for a in range(len(args)):
            for k in range(n):
                wp = [x.copy() for x in w]
                wm = [x.copy() for x in w]
                wp[a][k] += h
                wm[a][k] -= h
                Rp, Rm = np.empty((n, nt)), np.empty((n, nt))
                getattr(f, reg)(*wp, Rp)
                getattr(f, reg)(*wm, Rm)
                fd = (Rp - Rm) / (2 * h)
                scale = max(1.0, np.max(np.abs(R0)))
                assert np.max(np.abs(J[:, :, a * n + k] - fd)) <= 1e-7 * scale, (reg, a, k)


def test_phi_dM_is_the_time_derivative_of_phi_M(models):
    """Phi_dM(q, dq, a) = d/dt Phi_M(q(t), a) along q' = dq (central differences)."""
    if not _available("ur5"):
        pytest.skip("arms extra missing")
    m = _model(models, "ur5")
    f = m.jit_functions
    n, nt = m.n, m.ntheta
    for q, dq, a, _ in _states(m, 5, 4):
        D = np.empty((n, nt))
        f.Phi_dM(q, dq, a, D)
        h = 1e-6
        Pp, Pm = np.empty((n, nt)), np.empty((n, nt))
        f.Phi_M(q + h * dq, a, Pp)
        f.Phi_M(q - h * dq, a, Pm)
        assert np.max(np.abs(D - (Pp - Pm) / (2 * h))) <= 1e-7


def test_plain_python_path_equals_compiled(models):
    if not _available("iiwa"):
        pytest.skip("arms extra missing")
    m = _model(models, "iiwa")
    q, dq, v, dv = next(_states(m, 1, 9))
    P1, P2 = np.empty((m.n, m.ntheta)), np.empty((m.n, m.ntheta))
    m.python_functions.Phi(q, dq, v, dv, P1)
    m.jit_functions.Phi(q, dq, v, dv, P2)
    assert np.array_equal(P1, P2) or np.max(np.abs(P1 - P2)) < 1e-13
    assert np.allclose(m.inverse_dynamics(q, dq, dv),
                       m.regressor(q, dq, dq, dv) @ m.theta_values, rtol=1e-14, atol=1e-12)
    tau = m.inverse_dynamics(q, dq, dv)
    assert np.allclose(m.acceleration(q, dq, tau), dv, rtol=1e-10, atol=1e-10)


# ----------------------------------------------------------------------------- interface
def test_names_and_limits(models):
    names = model_names()
    assert "two-link" in names and all(a in names for a in ("panda", "ur5", "iiwa", "xarm7"))
    tl = get_model("two-link")
    assert tl.name == two_link().name
    # symbolic models have the same attributes, without limits
    assert tl.joint_names == ["joint1", "joint2"] and np.isinf(tl.position_limits).all()
    assert np.isinf(tl.velocity_limits).all() and np.isinf(tl.effort_limits).all()
    assert tl.parameter_units["theta1"] == "kg.m2"
    if not _available("panda"):
        return
    m = get_model("panda")
    assert m.joint_names == [f"panda_joint{i}" for i in range(1, 8)]
    assert m.position_limits.shape == (7, 2)
    assert m.position_limits[3].tolist() == [-3.0718, -0.0698]
    assert m.velocity_limits.tolist() == [2.175] * 4 + [2.61] * 3
    assert m.effort_limits.tolist() == [87.0] * 4 + [12.0] * 3
    assert set(m.parameter_units) == set(m.theta_names)
    for attr in ("name", "n", "ntheta", "theta_values", "theta_names", "key", "functions",
                 "jit_functions", "regressor", "inverse_dynamics", "acceleration"):
        assert hasattr(m, attr)
    assert "def Phi(" in m.source("") and "def p1_Phi(" in m.source("p1_")
    with pytest.raises(ValueError):
        m.source("0bad")


def test_pickle(models):
    import pickle
    if not _available("ur5"):
        pytest.skip("arms extra missing")
    m = _model(models, "ur5")
    m.jit_functions                       # cached compiled functions do not travel
    m2 = pickle.loads(pickle.dumps(m))
    assert m2.key == m.key and m2.theta_names == m.theta_names
    q, dq, v, dv = next(_states(m, 1, 7))
    assert np.array_equal(m2.regressor(q, dq, v, dv), m.regressor(q, dq, v, dv))


def test_cache(tmp_path, monkeypatch):
    if not _available("ur5"):
        pytest.skip("arms extra missing")
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    src = urdf_mod.arm_urdf("ur5")
    f = tmp_path / "ur5.urdf"
    f.write_text(src.read_text())
    t = time.perf_counter()
    m1 = from_urdf(f)
    t1 = time.perf_counter() - t
    assert len(list((tmp_path / "urdf").glob("*.json"))) == 1
    t = time.perf_counter()
    m2 = from_urdf(f)
    t2 = time.perf_counter() - t
    print(f"build {t1:.2f} s, from cache {t2:.3f} s")
    assert m2.key == m1.key and np.array_equal(m2.theta_values, m1.theta_values)
    assert t2 < 2.0
    m3 = from_urdf(f, friction="viscous")   # other options: another entry
    assert m3.ntheta == 42
    assert len(list((tmp_path / "urdf").glob("*.json"))) == 2
    # another content: another entry, other values
    f.write_text(src.read_text().replace('<mass value="3.7"/>', '<mass value="3.9"/>', 1))
    m4 = from_urdf(f)
    assert m4.theta_standard[0] == 3.9 and m1.theta_standard[0] == 3.7
    assert m4.key == m1.key      # the code depends on the geometry only, theta is data
    assert len(list((tmp_path / "urdf").glob("*.json"))) == 3


def test_a_cached_build_names_the_file_it_was_read_from(tmp_path, monkeypatch):
    """The cache is keyed by the URDF's content: the same text at another place (another
    environment's copy, the first file deleted) gives a model whose ``urdf`` is that
    place, so that Pinocchio's model of it can be built (it named the deleted file)."""
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path / "cache"))
    (tmp_path / "a").mkdir()
    first = _two_links(tmp_path / "a")
    m1 = from_urdf(first)
    moved = tmp_path / "b.urdf"
    moved.write_text(first.read_text())
    first.unlink()
    m2 = from_urdf(moved)
    assert len(list((tmp_path / "cache" / "urdf").glob("*.json"))) == 1   # one content, one entry
    assert m2.urdf == str(moved.resolve()) and m1.urdf != m2.urdf
    assert m2.key == m1.key
    err = _errors(m2, m2.pinocchio_model(), N=20)
    assert all(v <= 1e-10 for v in err.values()), err


# ----------------------------------------------------------------------------- bad input
_LINK = ('<link name="{n}"><inertial><origin xyz="0 0 0.1"/><mass value="1"/>'
         '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>')


def _urdf(tmp_path, body, name="r.urdf"):
    p = tmp_path / name
    p.write_text(f'<?xml version="1.0"?>\n<robot name="test">{body}</robot>\n')
    return p


def _joint(name, parent, child, jtype="revolute", extra=""):
    return (f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/>'
            f'<child link="{child}"/><origin xyz="0 0 0.2"/><axis xyz="0 1 0"/>'
            f'<limit lower="-1" upper="1" effort="10" velocity="2"/>{extra}</joint>')


def _two_links(tmp_path):
    body = (_LINK.format(n="base") + _LINK.format(n="l1") + _LINK.format(n="l2")
            + _joint("j1", "base", "l1") + _joint("j2", "l1", "l2"))
    return _urdf(tmp_path, body)


def test_small_urdf_written_here(tmp_path):
    m = from_urdf(_two_links(tmp_path), cache=False)
    assert (m.n, m.joint_names, m.name) == (2, ["j1", "j2"], "test")
    err = _errors(m, m.pinocchio_model(), N=50)
    assert all(v <= 1e-10 for v in err.values()), err


def test_continuous_and_prismatic_joints(tmp_path):
    body = (_LINK.format(n="base") + _LINK.format(n="l1") + _LINK.format(n="l2")
            + _LINK.format(n="l3")
            + _joint("j1", "base", "l1", "continuous") + _joint("j2", "l1", "l2", "prismatic")
            + _joint("j3", "l2", "l3"))
    m = from_urdf(_urdf(tmp_path, body), cache=False, friction="viscous")
    assert np.isinf(m.position_limits[0]).all()
    assert m.parameter_units["fv2"] == "N.s/m"
    err = _errors(m, m.pinocchio_model(), N=100)
    assert all(v <= 1e-10 for v in err.values()), err


@pytest.mark.parametrize("case, match", [
    ("missing", "does not exist"),
    ("not_xml", "not a URDF file"),
    ("sdf", "root element is <sdf>"),
    ("xacro", "unexpanded xacro"),
    ("floating", "joint 'fj' is of type 'floating'"),
    ("mimic", "joint 'j2' is a mimic joint"),
    ("closed", "link 'l2' is the child of several joints"),
    ("no_inertial", "link 'l2' .*has no <inertial>"),
    ("unknown_joint", "joint 'jx' is not in the URDF"),
    ("branch", "branch after joint 'j1'"),
    ("not_chain", "do not form a chain"),
])
def test_bad_urdf_names_the_problem(tmp_path, case, match):
    L = _LINK.format
    kw = {}
    if case == "missing":
        p = tmp_path / "none.urdf"
    elif case == "not_xml":
        p = tmp_path / "x.urdf"
        p.write_text("this is not xml <")
    elif case == "sdf":
        p = tmp_path / "x.sdf"
        p.write_text('<?xml version="1.0"?><sdf version="1.6"><model name="a"/></sdf>')
    elif case == "xacro":
        p = _urdf(tmp_path, '<xacro:property name="l" value="1"/>' + L(n="base"))
        p.write_text(p.read_text().replace('<robot name="test">',
                     '<robot name="test" xmlns:xacro="http://www.ros.org/wiki/xacro">'))
    elif case == "floating":
        p = _urdf(tmp_path, L(n="w") + L(n="base") + L(n="l1")
                  + '<joint name="fj" type="floating"><parent link="w"/><child link="base"/></joint>'
                  + _joint("j1", "base", "l1"))
    elif case == "mimic":
        p = _urdf(tmp_path, L(n="base") + L(n="l1") + L(n="l2") + _joint("j1", "base", "l1")
                  + _joint("j2", "l1", "l2", extra='<mimic joint="j1"/>'))
    elif case == "closed":
        p = _urdf(tmp_path, L(n="base") + L(n="l1") + L(n="l2") + _joint("j1", "base", "l1")
                  + _joint("j2", "l1", "l2") + _joint("j3", "base", "l2"))
    elif case == "no_inertial":
        p = _urdf(tmp_path, L(n="base") + L(n="l1") + '<link name="l2"/>'
                  + _joint("j1", "base", "l1") + _joint("j2", "l1", "l2"))
    elif case == "unknown_joint":
        p = _two_links(tmp_path)
        kw = dict(joints=["j1", "jx"])
    elif case == "branch":
        p = _urdf(tmp_path, L(n="base") + L(n="l1") + L(n="l2") + L(n="l3")
                  + _joint("j1", "base", "l1") + _joint("j2", "l1", "l2")
                  + _joint("j3", "l1", "l3"))
    elif case == "not_chain":
        p = _two_links(tmp_path)
        kw = dict(joints=["j2", "j1"])
    with pytest.raises(URDFError, match=match):
        from_urdf(p, cache=False, **kw)


def test_bad_options(tmp_path):
    p = _two_links(tmp_path)
    with pytest.raises(ValueError, match="friction must be"):
        from_urdf(p, friction="stiction", cache=False)
    with pytest.raises(ValueError, match="friction_width"):
        from_urdf(p, friction="viscous+coulomb", friction_width=0.0, cache=False)
    with pytest.raises(ValueError, match="gravity"):
        from_urdf(p, gravity=[0, 1], cache=False)
    with pytest.raises(ValueError, match="unknown model"):
        get_model("pandas")


@pytest.mark.parametrize("options", [
    dict(gravity=[1.0, -2.0, -9.0]),            # a gravity vector
    dict(joints=[f"panda_joint{i}" for i in range(1, 5)]),   # a shorter chain, rest locked
    dict(base=False),                           # the standard parameters themselves
])
def test_options_against_pinocchio(models, options):
    if not _available("panda"):
        pytest.skip("arms extra missing")
    m = _model(models, "panda", **options)
    if "joints" in options:
        assert m.n == 4 and m.joint_names == options["joints"]
    if options.get("base") is False:
        assert m.ntheta == 70 and np.array_equal(m.theta_values, m.theta_standard)
    err = _errors(m, m.pinocchio_model(), N=100, seed=6)
    assert all(v <= 1e-10 for v in err.values()), err
