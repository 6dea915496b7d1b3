"""The arm as a MuJoCo model (ivdrem.plants.mujoco): what MuJoCo computes equals ivdrem's
model of the same arm (M and bias forces at random states); what it would change is
refused with the cause; the payload's θ against the paper's formulas."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco")

from ivdrem.models import ARM_NAMES  # noqa: E402
from ivdrem.plants.mujoco import (MujocoError, Payload, check_model,  # noqa: E402
                                  closed_loop, load)


def test_the_papers_two_link_as_mjcf_equals_the_papers_formulas():
    """M and G of the MJCF against the paper's hand-written M(q), G(q) (Section 4)."""
    p = load("two-link")
    t1, t2, t3, t4, t5 = 1.3, 0.28, 0.32, 0.4, 1.4
    g = 9.81
    rng = np.random.default_rng(1)
    for _ in range(50):
        q, dq = rng.uniform(-np.pi, np.pi, 2), rng.uniform(-2, 2, 2)
        M, bias, passive = p.dynamics(q, dq)
        c2, s2 = np.cos(q[1]), np.sin(q[1])
        Mp = np.array([[t1 + 2 * t2 * c2, t3 + t2 * c2], [t3 + t2 * c2, t3]])
        C = np.array([[-t2 * s2 * dq[1], -t2 * s2 * (dq[0] + dq[1])], [t2 * s2 * dq[0], 0]])
        G = np.array([t4 * g * np.cos(q[0] + q[1]) + t5 * g * np.cos(q[0]),
                      t4 * g * np.cos(q[0] + q[1])])
        assert np.abs(M - Mp).max() < 1e-14
        assert np.abs(bias - (C @ dq + G)).max() < 1e-13
        assert np.all(passive == 0)
    assert p.check["M"] < 1e-14 and p.check["bias"] < 1e-14
    assert p.mj.opt.timestep == 1e-3 and p.integrator == "implicit"


@pytest.mark.parametrize("name", ["planar-2", "planar-3"])
def test_planar_arms_as_mjcf_equal_ivdrems_model(name):
    p = load(name, states=200)
    assert p.check["M"] < 1e-12 and p.check["bias"] < 1e-12


def test_planar_arm_with_friction_becomes_joint_damping():
    from ivdrem.models import planar_arm
    model = planar_arm(2, friction=True)
    p = load(model)
    assert np.allclose(p.mj.dof_damping, [0.1, 0.1])
    _, _, passive = p.dynamics(np.zeros(2), np.array([1.0, -2.0]))
    assert np.allclose(passive, [-0.1, 0.2])            # F = f q̇, the model's friction


@pytest.mark.parametrize("name", ARM_NAMES)
def test_every_named_arm_in_mujoco_equals_ivdrems_model(name):
    """M and bias forces at 200 random states within the joint limits, 1e-12 relative."""
    p = load(name, states=200, tol=1e-12)
    assert p.check["states"] == 200
    assert p.check["M"] < 1e-12 and p.check["bias"] < 1e-12
    r = p.report
    assert r["armature"] == [0.0] * p.n                 # MuJoCo's URDF import adds none
    assert r["inertia_changes"] == ""
    assert not r["joint_friction_in_plant"]
    assert np.all(p.mj.dof_damping == 0) and np.all(p.mj.dof_frictionloss == 0)
    if name == "panda":
        assert r["locked_joints"] == ["panda_finger_joint1", "panda_finger_joint2"]
        assert "panda_hand" in r["welded_bodies"]
        assert r["damping"] == [0.003] * 7              # the URDF's, reported and removed


def test_the_urdfs_joint_damping_and_dry_friction_are_left_in_on_request():
    p = load("xarm7", joint_friction=True, states=0)
    assert p.report["joint_friction_in_plant"]
    assert np.all(p.mj.dof_damping > 0)
    assert list(p.mj.dof_damping) == p.report["damping"]


def test_a_model_with_other_gravity_is_refused_with_the_numbers_and_the_cause():
    from ivdrem.models import two_link
    p = load("two-link")
    with pytest.raises(MujocoError, match=r"(?s)M [0-9.e-]+, bias forces [0-9.e-]+.*gravity"):
        check_model(p, two_link(g=9.7))
    with pytest.raises(MujocoError, match="the inertias differ"):
        check_model(p, two_link(theta=[1.3, 0.28, 0.33, 0.4, 1.4]))


URDF = """<?xml version="1.0"?>
<robot name="bad">
  <link name="base"/>
  <link name="l1">
    <inertial><origin xyz="0.1 0 0"/><mass value="1.0"/>
      <inertia ixx="{ixx}" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>
  </link>
  <link name="l2">
    <inertial><origin xyz="0.1 0 0"/><mass value="1.0"/>
      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>
  </link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="10" velocity="3"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.3 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="3"/></joint>
</robot>
"""


def test_a_urdf_whose_inertia_mujoco_would_alter_is_refused(tmp_path):
    """ixx > iyy + izz breaks the triangle inequality MuJoCo demands; with balanceinertia
    off it refuses rather than change the inertia (naming the body)."""
    from ivdrem.models import from_urdf
    good = tmp_path / "good.urdf"
    good.write_text(URDF.format(ixx="0.01"))
    assert load(from_urdf(good, cache=False), urdf=good).check["M"] < 1e-12
    bad = tmp_path / "bad.urdf"
    bad.write_text(URDF.format(ixx="0.05"))
    # ivdrem's own URDF checks refuse the file first (docs/models.md) ...
    from ivdrem.models.urdf import URDFError
    with pytest.raises(URDFError, match="triangle inequality"):
        from_urdf(bad, cache=False)
    # ... and MuJoCo, handed the file beside a model that passed, refuses it too
    with pytest.raises(MujocoError, match="MuJoCo refused the arm"):
        load(from_urdf(good, cache=False), urdf=bad)


def test_the_payloads_theta_equals_the_papers_formulas():
    """A point-like load m_p with inertia I_p at distance d on link 2 of the 2-link arm:
    θ1 += m_p(l1² + d²) + I_p, θ2 += m_p l1 d, θ3 += m_p d² + I_p, θ4 += m_p d, θ5 += m_p l1."""
    mp, d, Ip, l1 = 0.8, 0.35, 0.02, 0.7
    p = load("two-link", payload=Payload(mp, com=(d, 0.0, 0.0), inertia=(Ip, Ip, Ip)))
    want = np.array([mp * (l1 ** 2 + d * d) + Ip, mp * l1 * d, mp * d * d + Ip, mp * d, mp * l1])
    assert np.abs(p.theta_payload - p.theta - want).max() < 1e-12
    assert p.check["M"] < 1e-14                          # the check is of the arm alone
    assert np.array_equal(p.theta_at(0.0), p.theta_payload)


def test_a_payload_grasped_later_changes_the_plant_then():
    p = load("two-link", payload=Payload(1.0, com=(0.2, 0, 0), at=0.5))
    p.reset([0.0, 1.0])
    M0, _, _ = p.dynamics(np.zeros(2), np.zeros(2))
    assert np.array_equal(p.theta_at(0.25), p.theta)
    for _ in range(501):                 # grasped for the sample that starts at t = 0.5
        p.step(np.zeros(2))
    M1, _, _ = p.dynamics(np.zeros(2), np.zeros(2))
    assert M1[1, 1] == pytest.approx(M0[1, 1] + 0.2 ** 2)
    assert np.array_equal(p.theta_at(0.5), p.theta_payload)


@pytest.mark.parametrize("kw, word", [
    (dict(integrator="rk45"), "integrator"), (dict(h=0.0), "h must"),
    (dict(substeps=0), "substeps"), (dict(payload=(1.0, 0.1)), "Payload")])
def test_bad_options_are_refused_before_loading(kw, word):
    with pytest.raises(ValueError, match=word):
        load("two-link", **kw)


def test_bad_payloads_are_refused():
    with pytest.raises(ValueError, match="mass"):
        Payload(0.0)
    with pytest.raises(ValueError, match="com"):
        Payload(1.0, com=(0.1, 0.2))
    with pytest.raises(ValueError, match="inertia"):
        Payload(1.0, inertia=(-1, 0, 0))


def test_a_diverging_plant_stops_saying_where():
    p = load("two-link", integrator="euler", states=0)
    p.reset([0.0, 1.0])
    with pytest.raises(FloatingPointError, match="diverged near t = "):
        for _ in range(100):
            p.step(np.array([1e300, -1e300]))


class _Runaway:
    """A controller asking for 1e300 N·m: the plant diverges in its first step."""
    h, n = 1e-3, 2
    theta_hat, tau_d_hat = np.zeros(5), np.zeros(2)

    def step(self, t, q, dq):
        return np.array([1e300, -1e300])


def test_a_diverging_plant_leaves_nothing_in_the_working_directory(tmp_path, monkeypatch):
    """MuJoCo's default warning handler prints the warning and appends it to
    MUJOCO_LOG.TXT in the working directory: the plant keeps it instead, quotes it in the
    error, and leaves a handler of the user's in place (called too)."""
    import mujoco
    monkeypatch.chdir(tmp_path)
    p = load("two-link", integrator="euler", states=0)
    assert mujoco.get_mju_user_warning() is None
    with pytest.raises(FloatingPointError, match="MuJoCo: Nan, Inf or huge value in QACC"):
        closed_loop(p, 0.01, controller=_Runaway(), q0=[0.0, 1.0])
    assert mujoco.get_mju_user_warning() is None           # MuJoCo's default again
    with pytest.raises(FloatingPointError, match="MuJoCo: Nan, Inf or huge value"):
        p.reset([0.0, 1.0])
        for _ in range(3):
            p.step(np.array([1e300, -1e300]))
    theirs = []
    mujoco.set_mju_user_warning(theirs.append)
    try:
        p.reset([0.0, 1.0])
        with pytest.raises(FloatingPointError, match="diverged near t = "):
            closed_loop(p, 0.01, controller=_Runaway(), q0=[0.0, 1.0])
        assert mujoco.get_mju_user_warning() == theirs.append
        assert theirs and "unstable" in theirs[0]
    finally:
        mujoco.set_mju_user_warning(None)
    assert len(p.warnings) == 3 and list(tmp_path.iterdir()) == []


def test_a_payload_on_a_urdf_arm_sits_on_the_last_joints_link():
    """UR5: the payload's body is the child of the chain's last joint; its θ is the fit of
    MuJoCo's forces (residual checked inside load) and moves the gravity by m g."""
    p = load("ur5", payload=Payload(1.0, com=(0.0, 0.0, 0.05)), states=20)
    assert p.mj.body(p._payload_body).parentid == p.mj.body("wrist_3_link").id
    q = np.zeros(p.n)
    p._set_payload(False)
    _, g0, _ = p.dynamics(q, np.zeros(p.n))
    p._set_payload(True)
    _, g1, _ = p.dynamics(q, np.zeros(p.n))
    G = np.zeros(p.n)
    p.model.functions.G(q, p.theta_payload, G)
    assert np.abs(G - g1).max() < 1e-9 * np.abs(g1).max()
    assert np.abs(g1 - g0).max() > 1.0                     # a 1 kg load on a 0.8 m arm
