"""The regressors' derivatives of a URDF arm (``*_jac``, ivdrem.models.rigid_body: the poses
and joint axes computed once per call, every column a projection onto the axes) against a
second evaluation path and an independent library:

* every column equals the one the recursion itself gives, to rounding (relative 1e-12), at
  independent arguments and at v = dq (where Phi_jac and Phi_C_jac take the columns of v
  from those of dq, C(q, dq) e_m = C(q, e_m) dq):
  d/dq_m the tangent of ``_rb_std`` along e_m (the force carried frame by frame,
  ``_rb_project``; d/dq of Phi_dM, a second derivative, by the complex step of that
  tangent, step 1e-20), d/d of a linear argument the
  model's regressor at e_m (Phi_C(q, e_m, v), Phi_M(q, e_m), ...), on the Panda, the UR5
  with friction and armature, and planar arms written here (revolute, and one prismatic
  joint); Phi_F_jac (no recursion, unchanged) is checked by differences in
  tests/test_c_engine.py;
* Phi_jac contracted with theta is Pinocchio's derivatives of the inverse dynamics
  (computeRNEADerivatives: dtau/dq, dtau/dv, dtau/da), to 1e-9 relative;
* the C library, the numba path and plain Python give the same numbers (to 0.0 between C
  and numba: tests/test_c_engine.py; plain Python to rounding here).
"""
from __future__ import annotations

import numpy as np
import pytest

from ivdrem.models import rigid_body as rb
from ivdrem.models.base import REGRESSOR_ARGS

RTOL = 1e-12


def _arm(name, **opt):
    from ivdrem.models import arm
    try:
        return arm(name, **opt)
    except ImportError as exc:          # the arms' data packages (ivdrem[arms])
        pytest.skip(str(exc))


_LINK = ('<link name="{n}"><inertial><origin xyz="0.05 0.01 0.1"/><mass value="{m}"/>'
         '<inertia ixx="0.03" ixy="0.001" ixz="0.002" iyy="0.025" iyz="0.003" izz="0.02"/>'
         '</inertial></link>')


def _joint(name, parent, child, jtype="revolute", axis="0 0 1", xyz="0.3 0 0"):
    return (f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/>'
            f'<child link="{child}"/><origin xyz="{xyz}" rpy="0 0 0"/><axis xyz="{axis}"/>'
            f'<limit lower="-2" upper="2" effort="10" velocity="2"/></joint>')


def _planar(tmp_path, joints):
    """A planar arm (every joint about z, links along x, gravity in the plane's y) or, with
    a prismatic joint, a planar arm with a slider."""
    from ivdrem.models import from_urdf
    body = _LINK.format(n="base", m=1.0)
    for k, jt in enumerate(joints):
        body += _LINK.format(n=f"l{k + 1}", m=1.0 + 0.5 * k)
        body += _joint(f"j{k + 1}", "base" if k == 0 else f"l{k}", f"l{k + 1}", jt,
                       axis="1 0 0" if jt == "prismatic" else "0 0 1")
    path = tmp_path / "planar.urdf"
    path.write_text(f'<?xml version="1.0"?><robot name="planar">{body}</robot>')
    return from_urdf(path, cache=False, gravity=(0.0, -9.81, 0.0))


@pytest.fixture(scope="module")
def arms(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("planar")
    out = {"panda": _arm("panda"),
           "ur5_friction": _arm("ur5", friction={"viscous": 0.8, "coulomb": 1.5},
                                armature=[0.1, 0.2, 0.1, 0.05, 0.05, 0.02])}
    (tmp / "r").mkdir()
    (tmp / "p").mkdir()
    out["planar-3"] = _planar(tmp / "r", ["revolute"] * 3)
    out["planar-slider"] = _planar(tmp / "p", ["revolute", "prismatic", "revolute"])
    return out


def _std(model, q, x, y, acc, grav, fdq, fric, arm, d):
    """Today's path (_rb_std: the force carried through every frame) in plain Python: the
    standard regressor and its tangent along d (complex arrays for the complex step)."""
    c = model._chain
    fv, fc, ia = model._offsets()
    dt = np.result_type(q, x, y, acc, d)
    Y = np.zeros((model.n, model.nstandard), dtype=dt)
    dY = np.zeros_like(Y)
    ints = [np.asarray(c[k], dtype=np.int64) for k in ("parent", "jtype")]
    floats = [np.asarray(c[k], dtype=float) for k in ("axis", "Rp", "pp", "gravity")]
    rb._rb_std(q, x, y, acc, grav, fdq, fric, arm, True, d, *ints, *floats, fv, fc, ia,
               model.friction_width, Y, dY)
    return Y[:, model.base_columns], dY[:, model.base_columns]


def _reference(model, name, w, fn):
    """The columns of name_jac at arguments w from the recursion itself and the model's
    regressors (the path the blocks' Jacobians took before the axes; d/dq of Phi_dM its
    complex step)."""
    n, nb = model.n, model.ntheta
    z = np.zeros(n)
    cols = []
    reg = getattr(fn, name)

    def at(*args):
        out = np.empty((n, nb))
        reg(*args, out)
        return out
    for k, arg in enumerate(REGRESSOR_ARGS[name]):
        for m in range(n):
            e = np.zeros(n)
            e[m] = 1.0
            if arg == "q" and name == "Phi_dM":     # complex step of the tangent along dq
                h = 1e-20                     # exact to rounding: no difference
                qc = w[0].astype(complex)
                qc[m] += h * 1j
                zc = np.zeros(n, complex)
                _, dY = _std(model, qc, zc, zc, w[2].astype(complex), 0.0, zc, False, False,
                             w[1].astype(complex))
                cols.append(dY.imag / h)
            elif arg == "q":
                if name == "Phi_M":
                    x, y, acc, grav, fdq, fric, arm = z, z, w[1], 0.0, z, False, True
                elif name == "Phi_C":
                    x, y, acc, grav, fdq, fric, arm = w[1], w[2], z, 0.0, z, False, False
                elif name == "Phi_G":
                    x, y, acc, grav, fdq, fric, arm = z, z, z, 1.0, z, False, False
                else:
                    x, y, acc, grav, fdq, fric, arm = w[1], w[2], w[3], 1.0, w[1], True, True
                cols.append(_std(model, w[0], x, y, acc, grav, fdq, fric, arm, e)[1])
            elif name == "Phi":
                # Phi = Phi_M(q, dv) + Phi_C(q, dq, v) + Phi_F(dq) + Phi_G(q)
                if arg == "dq":
                    F = np.empty((n, nb, n))
                    fn.Phi_F_jac(w[1], F)
                    C = np.empty((n, nb))
                    fn.Phi_C(w[0], e, w[2], C)
                    cols.append(C + F[:, :, m])
                elif arg == "v":
                    C = np.empty((n, nb))
                    fn.Phi_C(w[0], w[1], e, C)
                    cols.append(C)
                else:
                    M = np.empty((n, nb))
                    fn.Phi_M(w[0], e, M)
                    cols.append(M)
            else:                                   # linear in this argument
                v2 = list(w)
                v2[k] = e
                cols.append(at(*v2))
    return np.stack(cols, axis=2)


@pytest.mark.parametrize("which", ["panda", "ur5_friction", "planar-3", "planar-slider"])
@pytest.mark.parametrize("name", [r for r in REGRESSOR_ARGS if r != "Phi_F"])
def test_jacobians_equal_the_recursion_column_by_column(arms, which, name):
    model = arms[which]
    fn = model.functions
    n, nb = model.n, model.ntheta
    rng = np.random.default_rng(7)
    worst = 0.0
    for k in range(3):
        w = [rng.uniform(-1.5, 1.5, n) for _ in REGRESSOR_ARGS[name]]
        if k == 2 and name in ("Phi_C", "Phi", "Phi_dM"):
            w[2] = w[1].copy()          # v = dq, as the plant, the instrument, the filter call
        got = np.full((n, nb, len(w) * n), np.nan)
        getattr(fn, name + "_jac")(*w, got)
        want = _reference(model, name, w, fn)
        scale = max(1.0, float(np.max(np.abs(want))))
        worst = max(worst, float(np.max(np.abs(got - want))) / scale)
    print(f"\n{which} {name}_jac: max |new - recursion| / max |recursion| = {worst:.1e}")
    assert worst <= RTOL, (which, name, worst)


def test_phi_jac_against_pinocchio_rnea_derivatives(arms):
    """tau = Phi(q, dq, dq, ddq) theta: its derivatives by q, dq (both of Phi's velocity
    arguments) and ddq are Pinocchio's computeRNEADerivatives."""
    pin = pytest.importorskip("pinocchio")
    model = arms["panda"]
    pm = model.pinocchio_model()
    pd = pm.createData()
    th = np.asarray(model.theta_values, float)
    n, nb = model.n, model.ntheta
    rng = np.random.default_rng(3)
    for _ in range(3):
        q, dq, ddq = (rng.uniform(-1.5, 1.5, n) for _ in range(3))
        J = np.empty((n, nb, 4 * n))
        model.functions.Phi_jac(q, dq, dq, ddq, J)
        d = np.einsum("ijc,j->ic", J, th)
        qp = model.pinocchio_configuration(q)
        dtau_dq, dtau_dv, dtau_da = pin.computeRNEADerivatives(pm, pd, qp, dq, ddq)
        dtau_da = np.triu(dtau_da) + np.triu(dtau_da, 1).T
        for got, ref in ((d[:, :n], dtau_dq), (d[:, n:2 * n] + d[:, 2 * n:3 * n], dtau_dv),
                         (d[:, 3 * n:], dtau_da)):
            assert np.max(np.abs(got - ref)) <= 1e-9 * max(1.0, np.max(np.abs(ref)))


def test_plain_python_equals_the_c_library(arms):
    """The kernels as plain Python (no numba, no C): the same derivatives to rounding."""
    model = arms["planar-slider"]
    n, nb = model.n, model.ntheta
    rng = np.random.default_rng(1)
    for name, args in REGRESSOR_ARGS.items():
        w = [rng.uniform(-1, 1, n) for _ in args]
        a, b = np.empty((n, nb, len(args) * n)), np.empty((n, nb, len(args) * n))
        getattr(model.functions, name + "_jac")(*w, a)
        getattr(model.python_functions, name + "_jac")(*w, b)
        assert np.max(np.abs(a - b)) <= 1e-13 * max(1.0, np.max(np.abs(b))), name
