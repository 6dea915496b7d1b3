"""MuJoCo as the plant of the sampled controller (docs/mujoco.md; extra ``mujoco``).

:func:`load` makes the arm of an ivdrem model a MuJoCo model:

* a URDF arm (:func:`ivdrem.models.arm`, :func:`ivdrem.models.from_urdf`): the file
  itself, its ``<visual>``/``<collision>`` removed (mesh paths need not resolve), the joints
  ivdrem locks made fixed (the Panda's fingers), and ``<mujoco><compiler
  discardvisual="true" fusestatic="false" balanceinertia="false"/></mujoco>`` added, so
  that every link and inertia stays as written;
* the paper's 2-link arm and the planar arms (``"two-link"``, ``"planar-N"``): written as
  MJCF from the model's own θ (a physical realisation of the base parameters: masses,
  centres of mass, inertias; viscous friction as joint damping), in the vertical x-y plane,
  gravity along −y, angles from the x axis.

What MuJoCo made of the arm (joint damping and dry friction, armature, welded links, locked
joints, joint limits) is in ``plant.report``.  At load the model's M(q) and bias forces
C(q, q̇)q̇ + G(q) are compared with ivdrem's model of the same arm at random states; a
relative difference above ``tol`` (1e-9) is refused with the numbers and their likely
cause.  Joint damping and dry friction (``frictionloss``, a constraint in MuJoCo) are set
to 0 unless ``joint_friction=True``; joint limits are not enforced (the reference stays
inside them).  The integrator defaults to MuJoCo's ``implicit`` at the controller's h.

:func:`closed_loop` closes the sampled controller (the generated C library,
:class:`ivdrem.controller.clib.CController`, or anything with ``step(t, q, dq) -> tau``)
around the plant at its rate, through a real robot's sensors and limits
(:class:`ivdrem.plants.sensing.Imperfections`), and returns a python-control
``TimeResponseData`` with named signals.
"""
from __future__ import annotations

import math
import time
import xml.etree.ElementTree as ET
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .sensing import Imperfections

__all__ = ["MujocoPlant", "MujocoError", "Payload", "load", "check_model", "closed_loop",
           "planar_mjcf", "urdf_mjcf", "INTEGRATORS", "controller_kwargs"]

#: MuJoCo's integrators by name (mjtIntegrator); RK4 diverges at 1 kHz on stiff URDF damping
INTEGRATORS = ("euler", "rk4", "implicit", "implicitfast")

#: The C compiler's flags of the controller library the loop builds: -O3 steps the Panda's
#: controller about a third faster than the library's default -O2 with the same numbers,
#: bit for bit (ISO C99 allows no contraction to FMA nor reassociation;
#: benchmarks/bench_mujoco.py, tests/test_mujoco_loop.py).
CONTROLLER_FLAGS = ("-O3",)

#: The relative difference in M and bias forces at which a plant is refused.
LOAD_TOL = 1e-9


class MujocoError(ValueError):
    """The arm cannot be made a MuJoCo plant, or the plant differs from ivdrem's model."""


def _mujoco():
    try:
        import mujoco
    except ImportError:
        raise ImportError("the MuJoCo plant needs the package 'mujoco': "
                          "pip install 'ivdrem[mujoco]'") from None
    return mujoco


@dataclass(frozen=True)
class Payload:
    """A rigid load on the last link, unknown to the controller.

    ``mass`` (kg); ``com`` (m), its centre of mass in the frame of the last joint's link
    (for the planar arms: x along the link from its joint); ``inertia`` (kg·m²), principal
    moments about the centre of mass along that frame's axes; ``at`` (s), the time at which
    it is grasped (0: from the start)."""

    mass: float
    com: tuple = (0.0, 0.0, 0.0)
    inertia: tuple = (0.0, 0.0, 0.0)
    at: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.mass) and self.mass > 0):
            raise ValueError(f"payload mass must be > 0 kg, got {self.mass!r}")
        for name, v in (("com", self.com), ("inertia", self.inertia)):
            a = np.asarray(v, float)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise ValueError(f"payload {name} must be 3 finite numbers, got {v!r}")
        if min(self.inertia) < 0:
            raise ValueError(f"payload inertia must be >= 0, got {self.inertia!r}")
        if not (math.isfinite(self.at) and self.at >= 0):
            raise ValueError(f"payload time 'at' must be >= 0 s, got {self.at!r}")


# ----------------------------------------------------------------------------- MJCF
def _realise(lengths, H, J, masses=None):
    """Masses, centres of mass and inertias of a planar chain with the base parameters
    H_i = m_i c_i + l_i Σ_{k>i} m_k, J_i = I_i + m_i c_i² + l_i² Σ_{k>i} m_k (see
    ivdrem.models.robots.planar_physical_theta), from the tip to the root.  ``masses`` are
    tried first; a link they cannot realise with I_i > 0 gets m_i = 2 a²/b (I_i = b/2)."""
    n = len(H)
    m, c, I = np.zeros(n), np.zeros(n), np.zeros(n)
    tail = 0.0
    for i in reversed(range(n)):
        a, b = H[i] - lengths[i] * tail, J[i] - lengths[i] ** 2 * tail
        if not b > 0:
            raise MujocoError(f"the parameters of link {i + 1} (H = {H[i]:g}, J = {J[i]:g}) "
                              "have no physical realisation with positive inertia")
        mi = None if masses is None else float(masses[i])
        if mi is None or not (mi > 0 and b - a * a / mi > 0):
            mi = 2.0 * a * a / b if a != 0 else 1.0
        m[i], c[i], I[i] = mi, a / mi, b - a * a / mi
        tail += mi
    return m, c, I


def _planar_links(model):
    """(lengths, masses, com, inertia, damping) of the paper's 2-link arm or a planar arm
    (parameters by name: theta1..5; h_i, J_i [, f_i]; m_i, h_i, J_i [, f_i])."""
    th = dict(zip(model.theta_names, np.asarray(model.theta_values, float)))
    const = {str(k): float(v) for k, v in model.constants.items()}
    n = model.n
    if model.name == "two-link":
        # θ1 = J_1 + θ3, θ2 = m2 l1 c2, θ3 = J_2, θ4 = m2 c2 = H_2, θ5 = m1 c1 + m2 l1 = H_1
        # (paper Section 4): realised with m1 = 1.4, m2 = 1 as l1 = 0.7, c1 = 0.5,
        # I1 = 0.14, c2 = 0.4, I2 = 0.16 for the paper's θ
        t1, t2, t3, t4, t5 = (th[f"theta{i}"] for i in range(1, 6))
        if t4 == 0:
            raise MujocoError("two-link: theta4 = 0 leaves the first link's length undefined")
        l1 = t2 / t4
        H, J = [t5, t4], [t1 - t3, t3]
        m, c, I = _realise([l1, 0.0], H, J, masses=[1.4, 1.0])
        lengths = [l1, 2.0 * abs(c[1]) or 1.0]
        damping = np.zeros(2)
    elif model.name.startswith("planar-"):
        lengths = [const[f"l{i}"] for i in range(1, n + 1)]
        if "m1" in th:           # "full": (m_i, h_i, J_i) with h_i = m_i c_i, J_i = I_i + m_i c_i²
            m = np.array([th[f"m{i}"] for i in range(1, n + 1)])
            h = np.array([th[f"h{i}"] for i in range(1, n + 1)])
            Jf = np.array([th[f"J{i}"] for i in range(1, n + 1)])
            c, I = h / m, Jf - h * h / m
        else:
            H = [th[f"h{i}"] for i in range(1, n + 1)]
            J = [th[f"J{i}"] for i in range(1, n + 1)]
            m, c, I = _realise(lengths, H, J, masses=[2.0] * n)
        damping = np.array([th.get(f"f{i}", 0.0) for i in range(1, n + 1)])
    else:
        raise MujocoError(f"model {model.name!r}: only the two-link, planar-N and URDF arms "
                          "have a MuJoCo form")
    if np.any(np.asarray(m) <= 0) or np.any(np.asarray(I) <= 0):
        raise MujocoError(f"model {model.name!r}: link masses {np.asarray(m)} and inertias "
                          f"{np.asarray(I)} must be positive")
    return np.asarray(lengths, float), m, c, I, damping


def planar_mjcf(model) -> str:
    """The MJCF of the paper's 2-link arm or a planar arm (``model.name`` "two-link" or
    "planar-N"): hinges about z in the x-y plane, link i's frame at its joint with x along
    the link, gravity along −y (``g`` of the model)."""
    g = float({str(k): v for k, v in model.constants.items()}.get("g", 9.81))
    lengths, m, c, I, damping = _planar_links(model)
    f = repr
    body, close = [], []
    for i in range(model.n):
        pos = "0 0 0" if i == 0 else f"{f(float(lengths[i - 1]))} 0 0"
        # only the moment about z acts in the plane; the three equal moments satisfy
        # MuJoCo's triangle inequality without changing the dynamics
        body.append(f'{"  " * (i + 2)}<body name="link{i + 1}" pos="{pos}">\n'
                    f'{"  " * (i + 3)}<joint name="joint{i + 1}" type="hinge" axis="0 0 1" '
                    f'damping="{f(float(damping[i]))}"/>\n'
                    f'{"  " * (i + 3)}<inertial pos="{f(float(c[i]))} 0 0" '
                    f'mass="{f(float(m[i]))}" diaginertia="{f(float(I[i]))} '
                    f'{f(float(I[i]))} {f(float(I[i]))}"/>\n')
        close.append(f'{"  " * (i + 2)}</body>\n')
    return (f'<mujoco model="{model.name}">\n'
            f'  <compiler angle="radian" balanceinertia="false"/>\n'
            f'  <option gravity="0 {f(-g)} 0"/>\n'
            f'  <worldbody>\n{"".join(body)}{"".join(reversed(close))}  </worldbody>\n'
            f'</mujoco>\n')


def urdf_mjcf(path, joint_names) -> tuple[str, dict]:
    """The URDF at ``path`` as MuJoCo reads it: visuals and collisions removed, every
    movable joint not in ``joint_names`` made fixed (locked at 0, as ivdrem locks it at its
    neutral position), MuJoCo's compiler told to keep links and inertias as written.
    Returns (xml text, what was changed)."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise MujocoError(f"{path}: cannot be read as a URDF ({exc})") from None
    removed = 0
    for link in root.iter("link"):
        for tag in ("visual", "collision"):
            for el in link.findall(tag):
                link.remove(el)
                removed += 1
    locked, dynamics, chain = [], {}, set(joint_names)
    for j in root.findall("joint"):
        name = j.get("name")
        if j.get("type") != "fixed" and name not in chain:
            locked.append(name)
            j.set("type", "fixed")
            for tag in ("limit", "dynamics", "mimic", "calibration", "safety_controller"):
                for el in j.findall(tag):
                    j.remove(el)
        elif name in chain and j.find("dynamics") is not None:
            d = j.find("dynamics")
            dynamics[name] = {k: float(d.get(k, 0.0)) for k in ("damping", "friction")}
    missing = chain - {j.get("name") for j in root.findall("joint")}
    if missing:
        raise MujocoError(f"{path}: no joint {sorted(missing)} (the model's joints)")
    for el in root.findall("mujoco"):
        root.remove(el)
    mj = ET.SubElement(root, "mujoco")
    ET.SubElement(mj, "compiler", discardvisual="true", fusestatic="false",
                  balanceinertia="false")
    return ET.tostring(root, encoding="unicode"), dict(
        removed_visual_collision=removed, locked_joints=locked, urdf_dynamics=dynamics)


# ----------------------------------------------------------------------------- plant
class MujocoPlant:
    """An arm in MuJoCo, stepped at the controller's sample h (``substeps`` MuJoCo steps of
    h/substeps each), the torque τ + τ_d held over the sample (``qfrc_applied``).

    ``model`` is ivdrem's model of the arm, ``mj`` the MjModel, ``data`` its MjData,
    ``report`` what MuJoCo made of the arm, ``check`` the load check's numbers,
    ``theta`` the true θ (``theta_at(t)``: with the payload once grasped), ``warnings``
    MuJoCo's warnings while the plant stepped (:meth:`warnings_kept`)."""

    def __init__(self, model, mj, report, *, h, substeps, integrator, payload):
        mujoco = _mujoco()
        self._mujoco = mujoco
        self.model, self.mj, self.report = model, mj, report
        self.n = model.n
        self.h, self.substeps, self.integrator = float(h), int(substeps), integrator
        self.data = mujoco.MjData(mj)
        self.payload = payload
        self.theta = np.asarray(model.theta_values, float)
        self.theta_payload = self.theta
        self._payload_body = None
        self._payload_on = None
        self.check = None
        self._M = np.zeros((self.n, self.n))
        self.warnings = []
        self._previous_handler = None

    @contextmanager
    def warnings_kept(self):
        """MuJoCo's warnings (an unstable simulation, a bad state) go to ``self.warnings``
        while the block runs, instead of MuJoCo's default handler, which prints them and
        appends them to MUJOCO_LOG.TXT in the working directory (the user's folder); a
        handler the user installed (``mujoco.set_mju_user_warning``) still gets them, and
        is put back afterwards.  A diverging plant's error quotes the last one."""
        mujoco = self._mujoco
        previous = mujoco.get_mju_user_warning()
        if getattr(previous, "__self__", None) is self:     # already kept (nested)
            yield
            return
        self._previous_handler = previous
        mujoco.set_mju_user_warning(self._keep_warning)
        try:
            yield
        finally:
            mujoco.set_mju_user_warning(previous)

    def _keep_warning(self, message):
        self.warnings.append(str(message))
        if self._previous_handler is not None:
            self._previous_handler(message)

    # -- state ------------------------------------------------------------------
    def reset(self, q0, dq0=None):
        mujoco = self._mujoco
        mujoco.mj_resetData(self.mj, self.data)
        self.data.qpos[:] = np.asarray(q0, float)
        self.data.qvel[:] = 0.0 if dq0 is None else np.asarray(dq0, float)
        if self.payload is not None:
            self._set_payload(self.payload.at <= 0.0)
        mujoco.mj_forward(self.mj, self.data)

    @property
    def q(self):
        return self.data.qpos.copy()

    @property
    def dq(self):
        return self.data.qvel.copy()

    @property
    def t(self):
        return float(self.data.time)

    def step(self, tau):
        """Advance one sample h with the generalised force ``tau`` held (torque and
        disturbance), grasping the payload at its time."""
        self.data.qfrc_applied[:] = tau
        with self.warnings_kept():
            self.advance()

    def advance(self):
        """Advance one sample h with the generalised force already in ``data.qfrc_applied``
        (the loop writes it there without a copy, inside :meth:`warnings_kept`)."""
        d = self.data
        if self._payload_on is False and d.time >= self.payload.at - 0.5 * self.h:
            self._set_payload(True)
        before = d.time
        for _ in range(self.substeps):
            self._mujoco.mj_step(self.mj, d)
        # MuJoCo answers a non-finite or huge position, velocity or acceleration by
        # resetting the data (time back to 0) and counting a warning: a diverged run would
        # go on from rest
        if not d.time > before:
            said = f"; MuJoCo: {self.warnings[-1]}" if self.warnings else ""
            raise FloatingPointError(
                f"the MuJoCo plant diverged near t = {before:g} s (a non-finite or too "
                f"large state; integrator {self.integrator}, step "
                f"{self.mj.opt.timestep:g} s{said}): a smaller step (substeps) or an "
                "implicit integrator may hold it")

    def theta_at(self, t):
        """The true θ at t (in ivdrem's parameters): with the payload once grasped."""
        if self.payload is not None and t >= self.payload.at - 0.5 * self.h:
            return self.theta_payload
        return self.theta

    # -- the payload --------------------------------------------------------------
    def _set_payload(self, on):
        b, p = self._payload_body, self.payload
        self.mj.body_mass[b] = p.mass if on else 0.0
        self.mj.body_inertia[b] = np.asarray(p.inertia, float) if on else 0.0
        self._payload_on = bool(on)

    # -- dynamics at a state --------------------------------------------------------
    def dynamics(self, q, dq):
        """(M(q), C(q, q̇)q̇ + G(q), passive forces) from MuJoCo at (q, q̇); the state of
        the run is kept."""
        mujoco, m = self._mujoco, self.mj
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = q, dq
        mujoco.mj_forward(m, d)
        M = np.zeros((self.n, self.n))
        mujoco.mj_fullM(m, d, M)
        return M, d.qfrc_bias.copy(), d.qfrc_passive.copy()


def _states(model, count, seed):
    """``count`` random (q, q̇): q uniform within the joint limits (±π where none),
    q̇ uniform in ±2 rad/s (within the velocity limits)."""
    rng = np.random.default_rng(seed)
    lim = np.asarray(model.position_limits, float)
    lo = np.where(np.isfinite(lim[:, 0]), lim[:, 0], -np.pi)
    hi = np.where(np.isfinite(lim[:, 1]), lim[:, 1], np.pi)
    vmax = np.minimum(2.0, np.asarray(model.velocity_limits, float))
    for _ in range(count):
        yield rng.uniform(lo, hi), rng.uniform(-vmax, vmax)


def check_model(plant, model=None, *, states=200, tol=LOAD_TOL, seed=0):
    """Compare the plant's M(q) and bias forces C(q, q̇)q̇ + G(q) with ``model``'s (default
    the plant's own) at ``states`` random states: the largest difference of each over the
    states relative to its largest entry over the states (a state where the forces nearly
    cancel does not inflate it).  Returns the numbers; raises :class:`MujocoError` with
    them and the likely cause when either exceeds ``tol``."""
    model = plant.model if model is None else model
    if model.n != plant.n:
        raise MujocoError(f"the MuJoCo arm has {plant.n} joints, ivdrem's model {model.n}")
    fn, th = model.functions, np.asarray(model.theta_values, float)
    n = model.n
    Mi, Ci, Gi = np.zeros((n, n)), np.zeros((n, n)), np.zeros(n)
    dM = dB = dG = 0.0
    sM = sB = sG = 1e-300
    for q, dq in _states(model, states, seed):
        M, bias, _ = plant.dynamics(q, dq)
        fn.M(q, th, Mi)
        fn.C(q, dq, th, Ci)
        fn.G(q, th, Gi)
        b = Ci @ dq + Gi
        _, g0, _ = plant.dynamics(q, np.zeros(n))
        dM, sM = max(dM, np.abs(M - Mi).max()), max(sM, np.abs(Mi).max())
        dB, sB = max(dB, np.abs(bias - b).max()), max(sB, np.abs(b).max())
        dG, sG = max(dG, np.abs(g0 - Gi).max()), max(sG, np.abs(Gi).max())
    eM, eB, eG = dM / sM, dB / sB, dG / sG
    result = dict(states=states, M=eM, bias=eB, gravity=eG, tol=tol)
    if max(eM, eB) > tol:
        if eM > tol:
            cause = ("the inertias differ: " + (plant.report.get("inertia_changes")
                     or "MuJoCo's link masses and inertias are those of the file, so the "
                        "chain (joint placements, axes, locked joints) differs"))
        elif eG > tol:
            cause = (f"gravity differs (MuJoCo {np.asarray(plant.mj.opt.gravity).tolist()}, "
                     f"ivdrem's model {np.asarray(getattr(model, 'gravity', [np.nan]))}"
                     f".tolist())")
        else:
            cause = "the Coriolis and centrifugal forces differ"
        raise MujocoError(
            f"MuJoCo's {model.name} differs from ivdrem's model beyond {tol:g} (relative, "
            f"{states} random states): M {eM:.3g}, bias forces {eB:.3g} (gravity alone "
            f"{eG:.3g}); cause: {cause}")
    return result


def _inertia_changes(root, mj, mujoco):
    """URDF links whose mass or principal inertias MuJoCo holds differently (text)."""
    out = []
    for link in root.iter("link"):
        el = link.find("inertial")
        name = link.get("name")
        bid = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, name)
        if el is None or bid < 0:
            continue
        mass = float(el.find("mass").get("value")) if el.find("mass") is not None else 0.0
        ie = el.find("inertia")
        if ie is None:
            continue
        g = {k: float(ie.get(k, 0.0)) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
        Iu = np.array([[g["ixx"], g["ixy"], g["ixz"]], [g["ixy"], g["iyy"], g["iyz"]],
                       [g["ixz"], g["iyz"], g["izz"]]])
        ev = np.sort(np.linalg.eigvalsh(Iu))
        mi = np.sort(np.asarray(mj.body_inertia[bid], float))
        scale = max(np.abs(ev).max(), 1e-300)
        if abs(mj.body_mass[bid] - mass) > 1e-12 * max(mass, 1.0) or \
                np.abs(mi - ev).max() > 1e-9 * scale:
            out.append(f"link {name!r}: mass {mass:g} -> {mj.body_mass[bid]:g} kg, "
                       f"principal inertias {ev.tolist()} -> {mi.tolist()}")
    return "; ".join(out)


def _resolve_model(model):
    if isinstance(model, str):
        from ..models import get_model
        return get_model(model)
    return model


def _urdf_path(model, urdf):
    if urdf is not None:
        return Path(urdf)
    from ..models.urdf import ARM_FILES, arm_urdf
    if model.name in ARM_FILES:
        return arm_urdf(model.name)
    return Path(model.urdf)


def load(model="two-link", *, urdf=None, h=None, integrator="implicit", substeps=1,
         joint_friction=False, payload=None, states=200, tol=LOAD_TOL, seed=0):
    """The arm of ``model`` (an ivdrem model or its name: "two-link", "planar-N", a named
    arm) as a :class:`MujocoPlant` stepping at h, checked against the model at load.

    Parameters
    ----------
    urdf : path, optional
        The URDF of a URDF arm (default: the named arm's file, else ``model.urdf``).
    h, substeps : float, int
        The sample (the controller's h; default :func:`ivdrem.controller.loop.default_period`,
        the default configuration's 1 ms) and the MuJoCo steps per sample.
    integrator : "implicit" (default), "implicitfast", "euler" or "rk4"
    joint_friction : bool
        Keep the URDF's ``<dynamics damping friction>`` in the plant (MuJoCo's joint
        damping and ``frictionloss``); default: set to 0 (both reported).
    payload : Payload, optional
        A load on the last link; ``plant.theta_payload`` is the true θ with it.
    states, tol, seed : the load check (:func:`check_model`); ``states = 0`` skips it.
    """
    mujoco = _mujoco()
    model = _resolve_model(model)
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {', '.join(INTEGRATORS)}, got "
                         f"{integrator!r}")
    if h is None:      # the controller's period by default
        from ..controller.loop import default_period
        h = default_period()
    if not (math.isfinite(h) and h > 0):
        raise ValueError(f"h must be a positive number of seconds, got {h!r}")
    if int(substeps) != substeps or substeps < 1:
        raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
    if payload is not None and not isinstance(payload, Payload):
        raise ValueError(f"payload must be an ivdrem.plants.mujoco.Payload, got {payload!r}")
    from ..models.urdf import RigidBodyModel
    root = None
    if isinstance(model, RigidBodyModel):
        path = _urdf_path(model, urdf)
        xml, report = urdf_mjcf(path, model.joint_names)
        root = ET.fromstring(xml)
        report["source"] = str(path)
        # the payload's body: the child link of the chain's last joint
        last_body = next((j.find("child").get("link") for j in root.findall("joint")
                          if j.get("name") == model.joint_names[-1]), None)
    else:
        xml = planar_mjcf(model)
        report = dict(source="MJCF written from the model's θ", locked_joints=[],
                      removed_visual_collision=0, urdf_dynamics={})
        last_body = f"link{model.n}"
    try:
        spec = mujoco.MjSpec.from_string(xml)
        if payload is not None:
            parent = spec.body(last_body) if last_body else None
            if parent is None:
                raise MujocoError(f"no body {last_body!r} to carry the payload")
            pb = parent.add_body(name="ivdrem_payload", pos=list(map(float, payload.com)))
            pb.ipos = [0.0, 0.0, 0.0]           # the centre of mass at the body's origin
            pb.iquat = [1.0, 0.0, 0.0, 0.0]
            pb.mass = float(payload.mass)
            pb.inertia = [float(v) for v in payload.inertia]
            pb.explicitinertial = True
        mj = spec.compile()
    except ValueError as exc:    # MuJoCo's compiler (mujoco.FatalError is a ValueError? no)
        raise MujocoError(f"MuJoCo refused the arm of {model.name}: {exc}") from None
    except Exception as exc:     # mujoco's own error types
        raise MujocoError(f"MuJoCo refused the arm of {model.name}: {exc}") from None
    if mj.nv != model.n or mj.nq != model.n:
        raise MujocoError(f"MuJoCo's arm has {mj.nv} degrees of freedom, ivdrem's model "
                          f"{model.n}")
    names = [mj.joint(i).name for i in range(mj.njnt)]
    want = list(getattr(model, "joint_names", names))
    if isinstance(model, RigidBodyModel) and names != want:
        raise MujocoError(f"MuJoCo's joints {names} are not ivdrem's {want} (in order)")
    # what MuJoCo made of it
    report["damping"] = mj.dof_damping.tolist()
    report["frictionloss"] = mj.dof_frictionloss.tolist()
    report["armature"] = mj.dof_armature.tolist()
    report["joint_limits_in_file"] = bool(np.any(mj.jnt_limited))
    report["welded_bodies"] = [mj.body(i).name for i in range(1, mj.nbody)
                               if mj.body_dofnum[i] == 0 and mj.body(i).name != "ivdrem_payload"]
    report["inertia_changes"] = (_inertia_changes(root, mj, mujoco) if root is not None
                                 else "")
    planar_damping = not isinstance(model, RigidBodyModel)
    if not joint_friction and not planar_damping:
        mj.dof_damping[:] = 0.0
        mj.dof_frictionloss[:] = 0.0
    report["joint_friction_in_plant"] = bool(joint_friction or planar_damping)
    mj.jnt_limited[:] = 0                 # the reference stays inside the limits
    mj.opt.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{integrator.upper()}")
    mj.opt.timestep = float(h) / int(substeps)
    plant = MujocoPlant(model, mj, report, h=h, substeps=int(substeps),
                        integrator=integrator, payload=payload)
    if payload is not None:
        plant._payload_body = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, "ivdrem_payload")
        plant.theta_payload = _fit_theta(plant, states=max(states, 4 * model.ntheta),
                                         seed=seed)
        plant._set_payload(False)         # M and bias of the arm as the file has it
    if states:
        plant.check = check_model(plant, states=states, tol=tol, seed=seed)
    plant.reset(np.zeros(model.n))
    return plant


def _fit_theta(plant, *, states, seed):
    """The true θ with the payload: θ + δ, δ the least-squares solution of
    Φ_rigid(q, q̇, q̇, q̈) δ = ΔM q̈ + Δbias (the payload's change of MuJoCo's M and bias at
    random states; the friction columns are left as they are).  A payload on the last link
    changes only that link's standard parameters, so it is exact (residual checked)."""
    model = plant.model
    n, nth = model.n, model.ntheta
    fn = model.functions
    rng = np.random.default_rng(seed + 1)
    rows, rhs = [], []
    Y, F = np.zeros((n, nth)), np.zeros((n, nth))
    for q, dq in _states(model, states, seed + 1):
        ddq = rng.uniform(-2.0, 2.0, n)
        plant._set_payload(False)
        M0, b0, _ = plant.dynamics(q, dq)
        plant._set_payload(True)
        M1, b1, _ = plant.dynamics(q, dq)
        fn.Phi(q, dq, dq, ddq, Y)
        fn.Phi_F(dq, F)
        Y[:, np.any(F != 0.0, axis=0)] = 0.0
        rows.append(Y.copy())
        rhs.append((M1 - M0) @ ddq + (b1 - b0))
    A, b = np.vstack(rows), np.concatenate(rhs)
    delta, *_ = np.linalg.lstsq(A, b, rcond=None)
    res = np.linalg.norm(A @ delta - b) / max(np.linalg.norm(b), 1e-300)
    if res > 1e-8:
        raise MujocoError(f"the payload's forces are not those of ivdrem's model's parameters "
                          f"(least-squares residual {res:.3g})")
    return plant.theta + delta


# ----------------------------------------------------------------------------- the loop
def controller_kwargs(experiment, law):
    """The sampled controller's arguments and the run's (q0, dq0, disturbance) of
    ``experiment`` (an :class:`~ivdrem.experiments.experiment.Experiment`, or a
    configuration: its Experiment is made): the law's arguments as the experiment resolved
    them once (``LawSetup.configured``) without the continuous loop's own keys, the
    reference as the configuration's table (a sinusoid or the Fourier series of
    docs/experiment.md)."""
    from ..experiments.experiment import Experiment
    experiment = Experiment.of(experiment)
    kw = dict(experiment.law(law).configured)
    kw.update(kw.pop("gains"))     # the sampled controller takes the law's gains by name
    run = dict(q0=kw.pop("q0"), dq0=kw.pop("dq0"), disturbance=kw.pop("disturbance"))
    kw.pop("theta", None)
    tr = experiment.config["trajectory"]
    if tr.get("kind", "sinusoid") == "fourier":
        kw["trajectory"] = dict(kind="fourier", omega_f=float(tr["omega_f"]),
                                a=np.asarray(tr["a"], float), b=np.asarray(tr["b"], float),
                                offset=np.asarray(tr["offset"], float))
    G = np.asarray(kw.pop("Gamma"), float)
    kw["Gamma"] = np.diag(G) if G.ndim == 2 else G
    return kw, run


def _signal_labels(name, size):
    return [f"{name}[{i}]" for i in range(size)]


def closed_loop(plant, t_end, law="iv-drem", *, controller=None, imperfections=None,
                disturbance=None, q0=None, dq0=None, every=100, progress=None, **gains):
    """The sampled controller closed around the MuJoCo ``plant`` for ``t_end`` seconds.

    Per sample t_k = k h: the plant's q(t_k), q̇(t_k) pass the robot's sensors
    (``imperfections``, :class:`ivdrem.plants.sensing.Imperfections`; default none) to the
    controller, whose torque (``delay = 1``: the previous one) passes the robot's actuator
    limits and is held, with the disturbance τ_d(t_k), over [t_k, t_k+1] while MuJoCo
    integrates (``plant.substeps`` steps).

    ``controller``: anything with ``step(t, q, dq) -> tau``, ``h``, ``n``, ``theta_hat``,
    ``tau_d_hat`` (default: the generated C library,
    :class:`~ivdrem.controller.clib.CController` of ``plant.model`` and ``law`` with
    ``gains``, at the plant's h).  ``disturbance``: sinusoids as the paper's (default its
    τ_d for two joints, none otherwise).  ``q0``, ``dq0``: the start (default the paper's
    q(0) for two joints, the reference's q_d(0) otherwise; at rest).

    Returns a python-control ``TimeResponseData`` sampled every ``every`` samples and at
    t_end, outputs (named, ``name[i]``): q, dq (the plant's), q_m, dq_m (measured), q_d
    (the reference), tau (applied), tau_d, theta_hat = θ̂(t_k), tau_d_hat, theta (the true θ,
    with the payload once grasped); ``response.costs`` holds the wall time per sample of
    the plant, of the controller and of the whole sample (µs; the run's set-up left out),
    and the CPU time of this thread per sample (``loop_cpu_us``: on a loaded machine the
    wall times include the time the process waited).
    """
    import control as ct
    from ..controller.loop import PAPER_DISTURBANCE, disturbance_at, paper_q0
    from ..controller.sampled import SampledController
    from .._progress import want_progress
    model, n = plant.model, plant.n
    if controller is None:
        from ..controller.clib import CController
        gains.setdefault("h", plant.h)
        reference = SampledController(model, law, **gains)
        try:
            controller = CController(model, law, flags=CONTROLLER_FLAGS, **gains)
        except (AttributeError, NotImplementedError, TypeError) as exc:
            raise ValueError(f"the sampled controller's C library has no form for "
                             f"{model.name!r} yet ({type(exc).__name__}: {exc}); pass a "
                             "controller= with step(t, q, dq) -> tau") from None
    else:
        reference = None
    h = float(controller.h)
    if abs(h - plant.h) > 1e-15 * max(1.0, h):
        raise ValueError(f"the controller's h = {h:g} s is not the plant's sample "
                         f"{plant.h:g} s (load(..., h=...))")
    N = int(round(t_end / h))
    if N < 1 or abs(N * h - t_end) > 1e-9 * max(1.0, t_end):
        raise ValueError(f"t_end = {t_end!r} must be a whole number of samples h = {h:g}")
    if disturbance is None:
        disturbance = PAPER_DISTURBANCE if n == 2 else dict(
            amplitude=np.zeros(n), omega=np.zeros(n), phase=np.zeros(n), offset=np.zeros(n))
    disturbance = {k: np.asarray(v, float) for k, v in disturbance.items()}   # once
    if q0 is None:
        q0 = paper_q0() if n == 2 else (reference.reference(0.0)[0] if reference is not None
                                      else np.zeros(n))
    q0 = np.asarray(q0, float)
    dq0 = np.zeros(n) if dq0 is None else np.asarray(dq0, float)
    if q0.shape != (n,) or dq0.shape != (n,):
        raise ValueError(f"q0 and dq0 must have {n} entries")
    every = max(1, int(every))
    delay = int(getattr(controller, "delay", 0))
    plant.reset(q0, dq0)
    robot = None if imperfections is None else imperfections.start(n, h, q0, dq0)
    nth = len(controller.theta_hat)
    names = ["q", "dq", "q_m", "dq_m", "q_d", "e", "r", "tau", "tau_d", "theta_hat",
             "tau_d_hat", "theta", "mu"]
    sizes = dict(theta_hat=nth, theta=nth, mu=1)
    rows = (N // every) + 1 + (N % every != 0)
    rec = {k: np.zeros((rows, sizes.get(k, n))) for k in names}
    times = np.zeros(rows)
    bar = None
    if want_progress(progress) and N >= 20000:
        from tqdm import tqdm
        bar = tqdm(total=N, unit="sample", desc=f"{model.name} in MuJoCo, {law}",
                   leave=False, mininterval=0.5)
    # Per sample, nothing is allocated and the C controller is called once through ctypes:
    # q, q̇ are read in place from MuJoCo's data (copied only for the sensors, which keep
    # them), the torque goes to one of two preallocated buffers (the previous one is the
    # command of a one-sample delay), τ + τ_d is summed into MuJoCo's qfrc_applied, and
    # τ_d(t_k) is evaluated in a preallocated buffer by the same operations as
    # disturbance_at (so the numbers are those of the earlier loop, bit for bit).
    d = plant.data
    qpos, qvel, force = d.qpos, d.qvel, d.qfrc_applied
    amp, om, ph, off = (disturbance[k] for k in ("amplitude", "omega", "phase", "offset"))
    tau_d = np.zeros(n)
    cmd = (np.zeros(n), np.zeros(n))
    c_step = None
    if getattr(controller, "lib", None) is not None and hasattr(controller, "_c"):
        import ctypes
        dp = ctypes.POINTER(ctypes.c_double)
        c_step, c_ptr = controller.lib.ivc_step, controller._c
        qin, dqin = np.zeros(n), np.zeros(n)
        p_q, p_dq = (qpos.ctypes.data_as(dp), qvel.ctypes.data_as(dp)) if robot is None \
            else (qin.ctypes.data_as(dp), dqin.ctypes.data_as(dp))
        p_tau = [c.ctypes.data_as(dp) for c in cmd]
    t_plant = t_ctl = 0.0
    clock = time.perf_counter
    r = 0
    with plant.warnings_kept():           # not MUJOCO_LOG.TXT in the user's folder
        start, cpu_start = clock(), time.thread_time()
        for k in range(N + 1):
            t = k * h
            if robot is None:
                qm, dqm = qpos, qvel
            else:
                qm, dqm = robot.measure(qpos.copy(), qvel.copy())
            keep = k == N or k % every == 0
            if keep:
                rec["theta_hat"][r] = controller.theta_hat
            now = k & 1
            c0 = clock()
            if c_step is not None:
                if robot is not None:
                    qin[:] = qm
                    dqin[:] = dqm
                status = c_step(c_ptr, t, p_q, p_dq, p_tau[now])
                if status != 0:                      # as CController.step says it
                    from ..controller.clib import CControllerError
                    raise CControllerError(f"ivc_step: {controller.lib.ivc_message(c_ptr).decode()}"
                                           f" (status {status})")
                tau = cmd[now]
            else:
                tau = cmd[now]
                tau[:] = controller.step(t, qm, dqm)
            t_ctl += clock() - c0
            command = tau if delay == 0 else cmd[1 - now]      # delay 1: the previous torque
            applied = command if robot is None else robot.actuate(command)
            np.multiply(om, t, out=tau_d)                      # disturbance_at(t, disturbance)
            np.add(tau_d, ph, out=tau_d)
            np.sin(tau_d, out=tau_d)
            np.multiply(amp, tau_d, out=tau_d)
            np.add(tau_d, off, out=tau_d)
            if keep:
                times[r] = t
                for name, v in (("q", qpos), ("dq", qvel), ("q_m", qm), ("dq_m", dqm),
                                ("tau", applied), ("tau_d", tau_d),
                                ("tau_d_hat", controller.tau_d_hat), ("theta", plant.theta_at(t))):
                    rec[name][r] = v
                if reference is not None:
                    qd, dqd, _ = reference.reference(t)
                    rec["q_d"][r] = qd
                    rec["e"][r] = qd - qpos
                    rec["r"][r] = (dqd - qvel) + reference.alpha * (qd - qpos)   # r of (9)
                    rec["mu"][r] = reference.mu(t)
                r += 1
            if k == N:
                break
            c0 = clock()
            np.add(applied, tau_d, out=force)
            plant.advance()
            t_plant += clock() - c0
            if bar is not None and k % 1000 == 0:
                bar.update(1000)
    wall, cpu = clock() - start, time.thread_time() - cpu_start
    if bar is not None:
        bar.close()
    labels = [lab for name in names
              for lab in ([name] if name == "mu" else
                          _signal_labels(name, rec[name].shape[1]))]
    outputs = np.vstack([rec[name].T for name in names])
    resp = ct.TimeResponseData(times, outputs, output_labels=labels, issiso=False,
                               title=f"{model.name} in MuJoCo, {law}", sysname="mujoco_loop")
    resp.costs = dict(plant_us=1e6 * t_plant / max(N, 1), controller_us=1e6 * t_ctl / max(N, 1),
                      loop_us=1e6 * wall / max(N, 1), loop_cpu_us=1e6 * cpu / max(N, 1),
                      samples=N)
    resp.law = law
    return resp
