"""Robot arms from URDF files: :func:`from_urdf`, the named arms (:func:`arm`) and their model
class :class:`RigidBodyModel` (docs/models.md).

The URDF is parsed by Pinocchio (``pin.buildModelFromUrdf``; joints not on the chosen chain
are locked at their neutral position by ``pin.buildReducedModel``, fixed joints merged into
their parent link); ivdrem takes from it the joint placements, axes, types, limits and the
links' inertias, and evaluates the dynamics with its own recursive kernels
(:mod:`ivdrem.models.rigid_body`), whose code is the model's ``source(prefix)``.

Parameters.  Per link (joint frame ``j``) the 10 standard parameters of Pinocchio's
``Inertia.toDynamicParameters``, named ``m{i}, mx{i}, my{i}, mz{i}, Ixx{i}, Ixy{i}, Iyy{i},
Ixz{i}, Iyz{i}, Izz{i}`` (``i`` = 1-based joint index), then, if asked, the viscous
friction ``fv{i}`` (``F_i = fv_i dq_i``), the Coulomb friction ``fc{i}`` (``F_i = fc_i
tanh(dq_i / w)``, a smooth sign of width ``w = friction_width``, default 0.01 rad/s) and the
armature (rotor inertia) ``Ia{i}`` (``M_ii += Ia_i``).  With ``base=True`` (the default) the
model's ``theta`` is the minimal identifiable set: the standard regressor stacked at random
states (Pinocchio's ``computeJointTorqueRegressor``) is factored by QR with column pivoting;
its rank is the number of diagonal entries of R above ``RANK_RTOL`` times the first, the
base regressor is the pivot's independent columns and ``theta_base = theta_1 + R11^-1 R12
theta_2`` (Gautier 1990).  ``model.base_matrix`` is that ``K`` (``theta_base = K
theta_standard``), ``model.parameter_table()`` lists what every base parameter groups.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import json
import math
import sysconfig
import xml.etree.ElementTree as ET
from functools import cached_property
from pathlib import Path

import numpy as np

from .base import C_FUNCTION_ARGS, FUNCTION_NAMES, SINGULAR_INERTIA_MESSAGE, RobotModel
from . import rigid_body

__all__ = ["from_urdf", "arm", "ARM_NAMES", "RigidBodyModel", "URDFError", "RANK_RTOL",
           "DEFAULT_FRICTION_WIDTH"]

#: Version of the generated rigid-body code and of the cached build; part of the key.
RIGID_BODY_CODEGEN_VERSION = "3"

#: Relative rank tolerance of the pivoted QR: |R_kk| > RANK_RTOL |R_00| counts.
RANK_RTOL = 1e-10

#: Width w (rad/s, m/s) of the smooth Coulomb sign tanh(dq / w).
DEFAULT_FRICTION_WIDTH = 0.01

_LINK_PARAMS = ("m", "mx", "my", "mz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")
_LINK_UNITS = ("kg", "kg.m", "kg.m", "kg.m", "kg.m2", "kg.m2", "kg.m2", "kg.m2", "kg.m2",
               "kg.m2")


class URDFError(ValueError):
    """A URDF file that cannot be made a model; the message names the file and the joint or
    link at fault."""


# ----------------------------------------------------------------------------- named arms
#: arm name -> (package, path inside its data directory, joints of the chain or None)
ARM_FILES = {
    "panda": ("example-robot-data", "panda_description/urdf/panda.urdf",
              tuple(f"panda_joint{i}" for i in range(1, 8))),
    "ur5": ("example-robot-data", "ur_description/urdf/ur5_robot.urdf", None),
    "xarm7": ("example-robot-data", "xarm_description/urdf/xarm7.urdf", None),
    "iiwa": ("pybullet", "kuka_iiwa/model.urdf", None),
}
#: Names of the arms :func:`arm` knows (their URDF files come with the ``arms`` extra).
ARM_NAMES = tuple(ARM_FILES)


def _data_dir(package):
    if package == "pybullet":
        try:
            import pybullet_data
        except ImportError:
            return None
        return Path(pybullet_data.getDataPath())
    # example-robot-data ships no Python module: its files are in the cmeel prefix
    cand = Path(sysconfig.get_paths()["purelib"]) / "cmeel.prefix/share/example-robot-data/robots"
    if cand.is_dir():
        return cand
    try:
        dist = importlib.metadata.distribution(package)
    except importlib.metadata.PackageNotFoundError:
        return None
    for f in dist.files or ():
        s = str(f)
        if s.endswith("example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"):
            return Path(dist.locate_file(f)).parents[2]
    return None


def arm_urdf(name):
    """Path of the URDF file of a named arm (see :data:`ARM_NAMES`)."""
    key = str(name).strip().lower()
    if key not in ARM_FILES:
        raise ValueError(f"unknown arm {name!r}; valid names: {', '.join(ARM_NAMES)}")
    package, rel, _ = ARM_FILES[key]
    d = _data_dir(package)
    if d is None or not (d / rel).is_file():
        raise ImportError(f"arm {key!r} needs the URDF files of the package {package!r}, which "
                          "is not installed: pip install 'ivdrem[arms]'")
    return d / rel


def arm(name, **options):
    """A named arm: ``"panda"`` (Franka Emika Panda, 7 DoF, fingers locked), ``"ur5"``
    (Universal Robots UR5, 6), ``"xarm7"`` (UFactory xArm7, 7) from example-robot-data,
    ``"iiwa"`` (KUKA LBR iiwa 14, 7) from pybullet's data; ``options`` as for
    :func:`from_urdf`."""
    key = str(name).strip().lower()
    path = arm_urdf(key)
    options.setdefault("joints", ARM_FILES[key][2])
    options.setdefault("name", key)
    return from_urdf(path, **options)


# ----------------------------------------------------------------------------- parsing
def _fail(path, msg):
    raise URDFError(f"{path}: {msg}")


def _check_urdf_text(path, text):
    """Errors a URDF can have that Pinocchio would report badly or not at all."""
    xacro = "is an unexpanded xacro file; expand it first (xacro FILE > FILE.urdf)"
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        if "xacro:" in text:
            _fail(path, xacro)
        _fail(path, f"is not a URDF file (not valid XML: {exc})")
    # a file expanded by xacro keeps the namespace declaration, but no xacro element and
    # no ${...} / $(...) substitution
    for el in root.iter():
        if el.tag.startswith("{") and "xacro" in el.tag or any(
                "${" in v or "$(" in v for v in el.attrib.values()):
            _fail(path, xacro)
    if root.tag != "robot":
        _fail(path, f"is not a URDF file (its root element is <{root.tag}>, not <robot>)")
    links = {ln.get("name"): ln for ln in root.findall("link")}
    joints = root.findall("joint")
    if not links:
        _fail(path, "has no <link>")
    parents_of = {}
    for j in joints:
        jn, jt = j.get("name"), j.get("type")
        if jt in ("floating", "planar"):
            _fail(path, f"joint {jn!r} is of type {jt!r} (a floating base or planar joint); "
                  "ivdrem models fixed-base arms of revolute, continuous and prismatic joints")
        ch = j.find("child")
        if ch is not None:
            parents_of.setdefault(ch.get("link"), []).append(jn)
    for ln, js in parents_of.items():
        if len(js) > 1:
            _fail(path, f"link {ln!r} is the child of several joints ({', '.join(js)}): a "
                  "closed chain, which ivdrem does not model")
    # names: two links or two joints of one name make the file ambiguous (refused); a link
    # and a joint of one name (example-robot-data's SO-100: "gripper") are told apart by
    # their kind where the model is built (_parse)
    for kind, elements in (("link", root.findall("link")), ("joint", joints)):
        seen = set()
        for el in elements:
            name = el.get("name")
            if name is None or not name.strip():
                _fail(path, f"a <{kind}> has no name")
            if name in seen:
                _fail(path, f"two <{kind}> elements are named {name!r}; {kind} names must "
                      "be unique")
            seen.add(name)
    return root


def _numbers(path, where, text, count):
    """`count` finite numbers of the attribute text `text` (of `where`), or a URDFError."""
    try:
        vals = [float(v) for v in str(text).split()]
    except ValueError:
        vals = []
    if len(vals) != count or not all(math.isfinite(v) for v in vals):
        _fail(path, f"{where} must be {count} finite number{'s' if count > 1 else ''}, "
              f"got {text!r}")
    return vals


def _number(path, where, text):
    return _numbers(path, where, text, 1)[0]


#: relative tolerance of the inertia checks (principal moments of URDF files exported
#: from CAD are rounded to a few digits: a thin disc's I_zz = I_xx + I_yy may come out a
#: few units of the last digit above the sum)
INERTIA_RTOL = 1e-6


def _check_inertial(path, link_name, inertial):
    """A physically possible <inertial>: a finite mass >= 0 (0 only for a frame without
    inertia, a tool flange), and a rotational inertia about
    the centre of mass whose principal moments are >= 0 (positive semi-definite: a point
    mass, I = 0, is allowed) and satisfy the triangle inequality I_1 + I_2 >= I_3 (no body
    has a principal moment above the sum of the other two)."""
    where = f"link {link_name!r}"
    mass = inertial.find("mass")
    if mass is None or mass.get("value") is None:
        _fail(path, f"{where}: its <inertial> has no <mass value=...>")
    m = _number(path, f"{where}: mass", mass.get("value"))
    if m < 0:
        _fail(path, f"{where}: mass {m:g} kg; a mass is >= 0")
    origin = inertial.find("origin")
    if origin is not None:
        for attr in ("xyz", "rpy"):
            if origin.get(attr) is not None:
                _numbers(path, f"{where}: <inertial><origin {attr}>", origin.get(attr), 3)
    el = inertial.find("inertia")
    if el is None:
        _fail(path, f"{where}: its <inertial> has no <inertia>")
    comp = {}
    for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"):
        comp[k] = 0.0 if el.get(k) is None else _number(path, f"{where}: inertia {k}", el.get(k))
    inertia = np.array([[comp["ixx"], comp["ixy"], comp["ixz"]],
                        [comp["ixy"], comp["iyy"], comp["iyz"]],
                        [comp["ixz"], comp["iyz"], comp["izz"]]])
    lam = np.linalg.eigvalsh(inertia)
    scale = max(float(np.sum(np.abs(lam))), 1e-300)
    text = ", ".join(f"{k}={comp[k]:g}" for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz"))
    if m == 0 and np.any(inertia != 0):   # a massless frame (a tool flange) has none
        _fail(path, f"{where}: mass 0 kg with a rotational inertia ({text}); a body "
              "without mass has none")
    if lam[0] < -INERTIA_RTOL * scale:
        _fail(path, f"{where}: its rotational inertia ({text}) is not positive "
              f"semi-definite (principal moment {lam[0]:.4g} kg m^2 < 0): no body has it")
    if lam[0] + lam[1] < lam[2] - INERTIA_RTOL * scale:
        _fail(path, f"{where}: its principal moments {lam[0]:.4g}, {lam[1]:.4g}, "
              f"{lam[2]:.4g} kg m^2 ({text}) break the triangle inequality "
              f"I1 + I2 >= I3 that every body's inertia satisfies")


def _check_chain(path, root, chain):
    """The joints of `chain` and every link they move, from the URDF's text, before any
    model is built: limits (lower <= upper), a nonzero finite axis, and a physically
    possible inertia for each moving link that has one (links fixed to a moving one and
    the links of locked joints are part of it)."""
    by_name = {j.get("name"): j for j in root.findall("joint")}
    for jn in chain:
        j = by_name.get(jn)
        if j is None:
            continue
        axis = j.find("axis")
        if axis is not None and axis.get("xyz") is not None:
            xyz = _numbers(path, f"joint {jn!r}: axis xyz", axis.get("xyz"), 3)
            if not any(xyz):
                _fail(path, f"joint {jn!r}: its axis is xyz=\"0 0 0\" (no direction); give "
                      "the unit vector it turns or slides along")
        limit = j.find("limit")
        if limit is not None and j.get("type") in ("revolute", "prismatic"):
            lo, hi = (None if limit.get(k) is None else
                      _number(path, f"joint {jn!r}: limit {k}", limit.get(k))
                      for k in ("lower", "upper"))
            if lo is not None and hi is not None and lo > hi:
                _fail(path, f"joint {jn!r}: limit lower={lo:g} is above upper={hi:g}")
            for k in ("velocity", "effort"):
                if limit.get(k) is not None:
                    v = _number(path, f"joint {jn!r}: limit {k}", limit.get(k))
                    if v < 0:
                        _fail(path, f"joint {jn!r}: limit {k}={v:g} is negative")
    # every link below the first joint of the chain moves with the arm
    children = {}
    for j in root.findall("joint"):
        p, c = j.find("parent"), j.find("child")
        if p is not None and c is not None:
            children.setdefault(p.get("link"), []).append(c.get("link"))
    first = by_name.get(chain[0]) if chain else None
    start = first.find("child").get("link") if first is not None and \
        first.find("child") is not None else None
    links = {ln.get("name"): ln for ln in root.findall("link")}
    todo, moving = [start] if start is not None else [], []
    while todo:
        name = todo.pop()
        if name in moving:
            continue
        moving.append(name)
        todo.extend(children.get(name, []))
    for name in moving:
        el = links.get(name)
        if el is not None and el.find("inertial") is not None:
            _check_inertial(path, name, el.find("inertial"))


def _link_has_inertia(root, link, seen=None):
    """True if ``link`` or a link fixed to it (merged into it) has an <inertial>."""
    el = root.find(f"link[@name='{link}']")
    if el is not None and el.find("inertial") is not None:
        return True
    for j in root.findall("joint"):
        if j.get("type") == "fixed" and j.find("parent").get("link") == link:
            if _link_has_inertia(root, j.find("child").get("link")):
                return True
    return False


def _pinocchio():
    try:
        import pinocchio
    except ImportError:
        raise ImportError("URDF models need Pinocchio (the PyPI package 'pin'): "
                          "pip install 'ivdrem[urdf]'") from None
    return pinocchio


def _untie_frame_names(pin, model):
    """A link named as a joint (example-robot-data's SO-100: "gripper"): Pinocchio's frame
    lookups by name, buildReducedModel's among them, would find both ("Several frames
    match the filter"); the link's frames get the suffix ``#link``."""
    joint_names = set(model.names)
    for frame in model.frames:
        if frame.type != pin.FrameType.JOINT and frame.name in joint_names:
            frame.name = f"{frame.name}#link"
    return model


def _chain_model(path, locked):
    """Pinocchio's model of the URDF at `path` with the joints `locked` (names) locked at
    their neutral position: the chain a RigidBodyModel describes."""
    pin = _pinocchio()
    full = _untie_frame_names(pin, pin.buildModelFromUrdf(str(path)))
    lock = [full.getJointId(j) for j in locked]
    return pin.buildReducedModel(full, lock, pin.neutral(full)) if lock else full


def _parse(path, joints, gravity, friction, friction_width, armature):
    """The chain data of the URDF at ``path`` (a dict; see :class:`RigidBodyModel`)."""
    pin = _pinocchio()

    path = Path(path)
    if not path.exists():
        raise URDFError(f"URDF file {path} does not exist")
    if not path.is_file():
        raise URDFError(f"URDF path {path} is not a file")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise URDFError(f"{path}: cannot be read as a URDF text file ({exc})") from None
    root = _check_urdf_text(path, text)
    try:
        full = pin.buildModelFromUrdf(str(path))
    except Exception as exc:  # Pinocchio raises ValueError/RuntimeError/IOError
        _fail(path, f"Pinocchio cannot parse it: {exc}")
    names = [full.names[i] for i in range(1, full.njoints)]
    if not names:
        _fail(path, "has no revolute, continuous or prismatic joint")
    _untie_frame_names(pin, full)
    xml_joints = {j.get("name"): j for j in root.findall("joint")}
    if joints is None:
        # the actuated joints must form one chain from the root
        for i in range(1, full.njoints):
            kids = [full.names[k] for k in range(1, full.njoints) if full.parents[k] == i]
            if len(kids) > 1:
                _fail(path, f"its actuated joints branch after joint {full.names[i]!r} "
                      f"(into {', '.join(kids)}); pass joints=[...] to choose the chain")
        chain = names
    else:
        if isinstance(joints, str):
            joints = [joints]
        chain = [str(j) for j in joints]
        if not chain:
            raise ValueError("joints must name at least one joint")
        unknown = [j for j in chain if j not in names]
        if unknown:
            fixed = [j for j in unknown if j in xml_joints]
            what = (f"joint {unknown[0]!r} is not a movable joint of the URDF" if fixed
                    else f"joint {unknown[0]!r} is not in the URDF")
            _fail(path, f"{what}; its revolute, continuous and prismatic joints: "
                  + ", ".join(names))
        if len(set(chain)) != len(chain):
            raise ValueError(f"joints lists a joint twice: {chain}")
        ids = [full.getJointId(j) for j in chain]
        for k, jid in enumerate(ids):
            # the nearest chosen ancestor must be the previous joint of the list
            a = full.parents[jid]
            while a > 0 and a not in ids:
                a = full.parents[a]
            want = ids[k - 1] if k else 0
            if a != want:
                _fail(path, f"the joints given do not form a chain from the root: joint "
                      f"{chain[k]!r} does not follow "
                      + (f"{chain[k - 1]!r}" if k else "the root"))
    for jn in chain:
        mim = xml_joints.get(jn)
        if mim is not None and mim.find("mimic") is not None:
            _fail(path, f"joint {jn!r} is a mimic joint (it copies "
                  f"{mim.find('mimic').get('joint')!r}); lock it or leave it out of joints")
        child = mim.find("child").get("link") if mim is not None else None
        if child is not None and not _link_has_inertia(root, child):
            _fail(path, f"link {child!r} (moved by joint {jn!r}) has no <inertial>: its mass "
                  "and inertia are unknown")
    _check_chain(path, root, chain)        # limits, axes, inertias: before any model
    lock = [full.getJointId(j) for j in names if j not in chain]
    model = (pin.buildReducedModel(full, lock, pin.neutral(full)) if lock else full)
    n = model.njoints - 1
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    jtype, axis, Rp, pp, parent, continuous = [], [], [], [], [], []
    lower, upper = [], []
    for i in range(1, model.njoints):
        sn = model.joints[i].shortname()
        S = np.asarray(data.joints[i].S, float).reshape(6)
        if sn.startswith("JointModelR") and "Universal" not in sn:
            jtype.append(0)
            u = S[3:6]
        elif sn.startswith("JointModelP") and "Planar" not in sn:
            jtype.append(1)
            u = S[0:3]
        else:
            _fail(path, f"joint {model.names[i]!r} is of Pinocchio type {sn}; ivdrem models "
                  "revolute, continuous and prismatic joints")
        if not (np.all(np.isfinite(u)) and np.linalg.norm(u) > 0):
            _fail(path, f"joint {model.names[i]!r}: its axis has no direction ({u.tolist()})")
        axis.append(u / np.linalg.norm(u))
        M0 = model.jointPlacements[i]
        Rp.append(np.asarray(M0.rotation, float))
        pp.append(np.asarray(M0.translation, float))
        parent.append(int(model.parents[i]) - 1)
        iq = model.joints[i].idx_q
        cont = model.joints[i].nq == 2
        continuous.append(cont)
        lo = -math.inf if cont else float(model.lowerPositionLimit[iq])
        hi = math.inf if cont else float(model.upperPositionLimit[iq])
        lower.append(lo if abs(lo) < 1e300 else -math.inf)
        upper.append(hi if abs(hi) < 1e300 else math.inf)
    vel = [float(x) if 0 < x < 1e300 else math.inf for x in model.velocityLimit]
    eff = [float(x) if 0 < x < 1e300 else math.inf for x in model.effortLimit]
    link_params = np.concatenate([np.asarray(model.inertias[i].toDynamicParameters(), float)
                                  for i in range(1, model.njoints)])
    # gravity: a magnitude along -z of the URDF's world, or a vector
    g = np.asarray(gravity, float).reshape(-1)
    if g.size == 1:
        g = np.array([0.0, 0.0, -float(g[0])])
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ValueError(f"gravity must be a finite number (magnitude along -z) or 3-vector, "
                         f"got {gravity!r}")
    # friction and armature
    fv_vals = fc_vals = None
    if friction is None:
        kinds = ()
    elif isinstance(friction, str):
        kinds = {"viscous": ("viscous",), "viscous+coulomb": ("viscous", "coulomb"),
                 "coulomb": ("coulomb",)}.get(friction.strip().lower())
        if kinds is None:
            raise ValueError(f"friction must be None, 'viscous', 'coulomb' or "
                             f"'viscous+coulomb', or a dict of values, got {friction!r}")
        fv_vals = np.asarray(model.damping, float) if "viscous" in kinds else None
        fc_vals = np.asarray(model.friction, float) if "coulomb" in kinds else None
    elif isinstance(friction, dict):
        bad = set(friction) - {"viscous", "coulomb"}
        if bad:
            raise ValueError(f"friction dict keys must be 'viscous' and/or 'coulomb', got "
                             f"{sorted(bad)}")
        kinds = tuple(k for k in ("viscous", "coulomb") if k in friction)

        def vals(k):
            v = np.broadcast_to(np.asarray(friction[k], float).reshape(-1), (n,)) \
                if np.size(friction[k]) in (1, n) else None
            if v is None or not np.all(np.isfinite(v)):
                raise ValueError(f"friction[{k!r}] must be a number or {n} finite numbers, "
                                 f"got {friction[k]!r}")
            return np.array(v, float)
        fv_vals = vals("viscous") if "viscous" in kinds else None
        fc_vals = vals("coulomb") if "coulomb" in kinds else None
    else:
        raise ValueError(f"friction must be None, a string or a dict, got {friction!r}")
    w = float(friction_width)
    if not (math.isfinite(w) and w > 0):
        raise ValueError(f"friction_width must be a positive finite number, got {friction_width!r}")
    if isinstance(armature, bool) or armature is None:
        arm_vals = np.asarray(model.armature, float) if armature else None
    else:
        arm_vals = np.broadcast_to(np.asarray(armature, float).reshape(-1), (n,)).copy()
    theta = [link_params]
    if fv_vals is not None:
        theta.append(fv_vals)
    if fc_vals is not None:
        theta.append(fc_vals)
    if arm_vals is not None:
        theta.append(arm_vals)
    return dict(
        joint_names=[model.names[i] for i in range(1, model.njoints)],
        # the joint's own frame: a link may bear a joint's name (the SO-100's "gripper")
        link_names=[model.frames[model.getFrameId(model.names[i], pin.FrameType.JOINT)].name
                    for i in range(1, model.njoints)],
        parent=parent, jtype=jtype, axis=np.array(axis).tolist(), Rp=np.array(Rp).tolist(),
        pp=np.array(pp).tolist(), continuous=continuous, gravity=g.tolist(),
        lower=lower, upper=upper, velocity=vel, effort=eff,
        viscous=fv_vals is not None, coulomb=fc_vals is not None, armature=arm_vals is not None,
        friction_width=w, theta_standard=np.concatenate(theta).tolist(),
        locked=[full.names[j] for j in lock], urdf=str(path.resolve()))


def _pin_configuration(chain, q):
    """Pinocchio's q of the angles/positions q (continuous joints as (cos, sin))."""
    out = []
    for qi, cont in zip(q, chain["continuous"]):
        out += [math.cos(qi), math.sin(qi)] if cont else [qi]
    return np.array(out)


def _standard_names(chain):
    n = len(chain["parent"])
    names = [f"{p}{i + 1}" for i in range(n) for p in _LINK_PARAMS]
    units = [u for _ in range(n) for u in _LINK_UNITS]
    pris = [t == 1 for t in chain["jtype"]]
    if chain["viscous"]:
        names += [f"fv{i + 1}" for i in range(n)]
        units += ["N.s/m" if pris[i] else "N.m.s/rad" for i in range(n)]
    if chain["coulomb"]:
        names += [f"fc{i + 1}" for i in range(n)]
        units += ["N" if pris[i] else "N.m" for i in range(n)]
    if chain["armature"]:
        names += [f"Ia{i + 1}" for i in range(n)]
        units += ["kg" if pris[i] else "kg.m2" for i in range(n)]
    return names, units


def _stacked_regressor(pmodel, chain, rng, nstates):
    """The standard regressor (links by Pinocchio, then friction, armature) at random states."""
    import pinocchio as pin
    data = pmodel.createData()
    n = len(chain["parent"])
    lo = np.where(np.isfinite(chain["lower"]), chain["lower"], -math.pi)
    hi = np.where(np.isfinite(chain["upper"]), chain["upper"], math.pi)
    w = chain["friction_width"]
    rows = []
    for _ in range(nstates):
        q = rng.uniform(lo, hi)
        v = rng.standard_normal(n)
        a = rng.standard_normal(n)
        Y = np.array(pin.computeJointTorqueRegressor(pmodel, data, _pin_configuration(chain, q),
                                                     v, a))
        extra = []
        if chain["viscous"]:
            extra.append(np.diag(v))
        if chain["coulomb"]:
            extra.append(np.diag(np.tanh(v / w)))
        if chain["armature"]:
            extra.append(np.diag(a))
        rows.append(np.hstack([Y] + extra))
    return np.vstack(rows)


def _base_parameters(W, rtol=RANK_RTOL):
    """(independent columns ascending, K (r x ns)) of the stacked regressor W by pivoted QR:
    theta_base = K theta_standard, base regressor = W[:, columns]."""
    import scipy.linalg as sl
    ns = W.shape[1]
    _, R, piv = sl.qr(W, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    r = int(np.sum(d > rtol * d[0])) if d.size and d[0] > 0 else 0
    if r == 0:
        raise ValueError("the regressor is zero: no parameter is identifiable")
    beta = sl.solve_triangular(R[:r, :r], R[:r, r:]) if r < ns else np.zeros((r, 0))
    # round-off of exact zeros (|beta| ~ 1e-20) out of the parameter table; a coefficient
    # this small changes Y theta by less than the rounding of Y itself
    beta[np.abs(beta) < 1e-13] = 0.0
    order = np.argsort(piv[:r])
    cols = piv[:r][order]
    K = np.zeros((r, ns))
    K[np.arange(r), cols] = 1.0
    K[:, piv[r:]] = beta[order]
    return cols, K


def _build(path, joints, gravity, friction, friction_width, armature, base):
    pin = _pinocchio()
    chain = _parse(path, joints, gravity, friction, friction_width, armature)
    std_names, std_units = _standard_names(chain)
    ns = len(std_names)
    theta_std = np.asarray(chain["theta_standard"])
    if base:
        pmodel = _chain_model(chain["urdf"], chain["locked"])
        pmodel.gravity.linear = np.asarray(chain["gravity"])
        n = len(chain["parent"])
        rng = np.random.default_rng(20260)
        W = _stacked_regressor(pmodel, chain, rng, max(40, -(-4 * ns // n)))
        cols, K = _base_parameters(W)
    else:
        cols, K = np.arange(ns), np.eye(ns)
    chain.update(base_columns=cols.tolist(), base_matrix=K.tolist(), base=bool(base))
    return chain


def _cache_file(text, options):
    from ..compile_cache import cache_dir
    try:    # the installed version, without importing Pinocchio (a cached load needs none)
        pin_version = importlib.metadata.version("pin")
    except importlib.metadata.PackageNotFoundError:
        pin_version = _pinocchio().__version__
    h = hashlib.sha256()
    for part in (text, repr(options), pin_version, RIGID_BODY_CODEGEN_VERSION):
        h.update(part.encode())
        h.update(b"\0")
    return cache_dir() / "urdf" / f"{h.hexdigest()[:24]}.json"


def from_urdf(path, *, base=True, friction=None, joints=None, gravity=9.81, armature=False,
              friction_width=DEFAULT_FRICTION_WIDTH, name=None, cache=True):
    """A model of the serial arm in the URDF file ``path`` (docs/models.md).

    Parameters
    ----------
    path : path-like
        The URDF file (not xacro).  Parsed by Pinocchio.
    base : bool
        ``True``: theta is the minimal identifiable set (base parameters); ``False``: the
        standard parameters (10 per link, and friction, armature), not all identifiable.
    friction : None, "viscous", "coulomb", "viscous+coulomb" or dict
        Friction terms per joint; a string takes the URDF's ``<dynamics damping friction>``
        as true values, a dict ``{"viscous": ..., "coulomb": ...}`` gives them.
    joints : list of str, optional
        The chain's joints, root first (default: every movable joint, which must form one
        chain); the others are locked at their neutral position.
    gravity : float or 3-vector
        Magnitude along -z of the URDF's world frame (default 9.81), or the vector.
    armature : bool or array_like
        Rotor inertia per joint (``True``: the values of Pinocchio's model, 0 unless given).
    friction_width : float
        Width ``w`` of the smooth Coulomb sign ``tanh(dq / w)``.
    name : str, optional
        Model name (default: the URDF's robot name).
    cache : bool
        Reuse a build of the same file content and options from ivdrem's cache directory.
    """
    path = Path(path)
    options = dict(base=bool(base), friction=friction, joints=None if joints is None
                   else list(joints) if not isinstance(joints, str) else [joints],
                   gravity=np.asarray(gravity, float).tolist(), armature=armature
                   if isinstance(armature, bool) else np.asarray(armature, float).tolist(),
                   friction_width=float(friction_width))
    cfile = None
    if cache and path.is_file():
        try:
            cfile = _cache_file(path.read_text(), options)
        except (OSError, UnicodeDecodeError):
            cfile = None
    chain = None
    if cfile is not None and cfile.is_file():
        try:
            chain = json.loads(cfile.read_text())
        except (OSError, ValueError):
            chain = None
        if chain is not None:   # the checks of the text hold for a cached build too (an
            # older ivdrem cached files they refuse); XML only, no Pinocchio
            _check_chain(path, _check_urdf_text(path, path.read_text()), chain["joint_names"])
            # the entry is keyed by the file's content, not its place: the same text read
            # from elsewhere (another environment's copy, the first one deleted) is this file
            chain["urdf"] = str(path.resolve())
    if chain is None:
        chain = _build(path, options["joints"], gravity, friction, friction_width, armature,
                       base)
        if cfile is not None:
            from .._atomic import write_text_atomic
            try:
                cfile.parent.mkdir(parents=True, exist_ok=True)
                write_text_atomic(cfile, json.dumps(chain))
            except OSError:
                pass
    if name is None:
        try:
            name = ET.fromstring(path.read_text()).get("name") or path.stem
        except (OSError, ET.ParseError):
            name = path.stem
    return RigidBodyModel(name, chain)


# ----------------------------------------------------------------------------- model
def _kernels_hash():
    from .base import kernels_digest
    return kernels_digest()


def _array_literal(a, dtype):
    a = np.asarray(a, dtype=dtype)
    body = json.dumps(a.tolist()) if a.size else "[]"
    body = body.replace("Infinity", "np.inf")
    if dtype is float:
        return f"np.array({body}, dtype=np.float64).reshape({a.shape})"
    return f"np.array({body}, dtype=np.int64).reshape({a.shape})"


#: A URDF model's functions: the workspaces each one needs and its kernel's arguments
#: (rigid_body._rb_<name>), the same in its Python source and its C face
_GLUE = {
    "Phi_M": (("Y",), "q, a, {chain}, {base}, {fric}, Y"),
    "Phi_C": (("Y",), "q, dq, v, {chain}, {base}, {fric}, Y"),
    "Phi_dM": (("Y", "dY"), "q, dq, a, {chain}, {base}, {fric}, Y, dY"),
    "Phi_G": (("Y",), "q, {chain}, {base}, {fric}, Y"),
    "Phi_F": (("Y",), "dq, {base}, {fv}, {fc}, {width}, Y"),
    "Phi": (("Y",), "q, dq, v, dv, {chain}, {base}, {fric}, Y"),
    "M": (("pi",), "q, theta, {chain5}, {base}, {ia}, pi"),
    "C": (("pi",), "q, dq, theta, {chain}, {base}, pi"),
    "G": (("pi",), "q, theta, {chain}, {base}, pi"),
    "F": (("pi",), "dq, theta, {base}, {fv}, {fc}, {width}, pi"),
    "forward_dynamics": (("pi",), "q, dq, tau, theta, {chain}, {base}, {fric}, pi"),
}
#: the regressors' derivatives (rigid_body._rb_<name>_jac): out (n, ntheta, k n), the
#: derivative by argument k's entry m in column k n + m; the Python source and the compiled
#: engine's C library (``RigidBodyModel.engine_c_source``) call the same kernels
_JAC_GLUE = {
    "Phi_M_jac": (("Y", "dY"), "q, a, {chain}, {base}, {fric}, Y, dY", ("q", "a"), 2),
    "Phi_C_jac": (("Y", "dY"), "q, dq, v, {chain}, {base}, {fric}, Y, dY", ("q", "dq", "v"), 3),
    "Phi_dM_jac": (("Y", "dY"), "q, dq, a, {chain}, {base}, {fric}, Y, dY", ("q", "dq", "a"), 3),
    "Phi_G_jac": (("Y", "dY"), "q, {chain}, {base}, {fric}, Y, dY", ("q",), 1),
    "Phi_F_jac": (("Y",), "dq, {base}, {fv}, {fc}, {width}, Y", ("dq",), 1),
    "Phi_jac": (("Y", "dY"), "q, dq, v, dv, {chain}, {base}, {fric}, Y, dY",
                ("q", "dq", "v", "dv"), 4),
}
_GLUE_DOCS = {
    "Phi_M": "Phi_M^T(q, a) = d(M a)/dtheta; out ({n}, {nb})",
    "Phi_C": "Phi_C^T(q, dq, v) = d(C v)/dtheta; out ({n}, {nb})",
    "Phi_dM": "Phi_dM^T(q, dq, a) = d(Mdot a)/dtheta (forward-mode along dq); out ({n}, {nb})",
    "Phi_G": "Phi_G^T(q) = dG/dtheta; out ({n}, {nb})",
    "Phi_F": "Phi_F^T(dq) = dF/dtheta; out ({n}, {nb})",
    "Phi": "Phi^T(q, dq, v, dv) = Phi_M^T(q,dv)+Phi_C^T(q,dq,v)+Phi_F^T+Phi_G^T; out ({n}, {nb})",
    "M": "inertia matrix M(q); out ({n}, {n})",
    "C": "Coriolis matrix C(q, dq) (Christoffel); out ({n}, {n})",
    "G": "gravity G(q); out ({n},)",
    "F": "friction F(dq); out ({n},)",
    "forward_dynamics": "qdd solving M(q) qdd = tau - C(q,dq) dq - F(dq) - G(q) (Cholesky); "
                        "out ({n},)",
}


class RigidBodyModel(RobotModel):
    """An arm of rigid links from a URDF: the same interface as
    :class:`~ivdrem.models.EulerLagrangeModel` (``source(prefix)`` defines the same
    functions), its code the recursive kernels of :mod:`ivdrem.models.rigid_body` over
    constant arrays of the chain.  Made by :func:`from_urdf` / :func:`arm`.

    Attributes besides the common ones: ``joint_names``, ``link_names``,
    ``position_limits`` (n, 2; +-inf where none), ``velocity_limits``, ``effort_limits``
    (n; inf where none), ``standard_names``, ``theta_standard`` (the URDF's values),
    ``base_matrix`` K (``theta = K theta_standard``), ``base_columns``, ``parameter_units``
    ({name: unit}), ``gravity``, ``friction_width``, ``urdf`` (the file).
    """

    def __init__(self, name, chain):
        self.name = str(name)
        self._chain = chain
        self.n = len(chain["parent"])
        self.joint_names = list(chain["joint_names"])
        self.link_names = list(chain["link_names"])
        self.position_limits = np.column_stack([chain["lower"], chain["upper"]])
        self.velocity_limits = np.asarray(chain["velocity"], float)
        self.effort_limits = np.asarray(chain["effort"], float)
        for a in (self.position_limits, self.velocity_limits, self.effort_limits):
            a.setflags(write=False)
        self.gravity = np.asarray(chain["gravity"], float)
        self.friction_width = float(chain["friction_width"])
        self.urdf = chain["urdf"]
        self.standard_names, std_units = _standard_names(chain)
        self.theta_standard = np.asarray(chain["theta_standard"], float)
        self.base_columns = np.asarray(chain["base_columns"], dtype=np.int64)
        self.base_matrix = np.asarray(chain["base_matrix"], float)
        self.ntheta = len(self.base_columns)
        self.nstandard = len(self.standard_names)
        names, units = [], {}
        for b, c in enumerate(self.base_columns):
            grouped = np.count_nonzero(self.base_matrix[b]) > 1
            nm = self.standard_names[c] + ("R" if grouped and chain["base"] else "")
            names.append(nm)
            units[nm] = std_units[c]
        self.theta_names = names
        self.parameter_units = units
        tv = self.base_matrix @ self.theta_standard
        tv.setflags(write=False)
        self.theta_values = tv
        self._source_cache = {}

    def __repr__(self):
        return f"RigidBodyModel({self.name!r}, n={self.n}, ntheta={self.ntheta})"

    def __reduce__(self):
        # the chain's data is the whole model (a worker process rebuilds the rest)
        return (RigidBodyModel, (self.name, self._chain))

    # ------------------------------------------------------------------ parameters
    def parameter_table(self):
        """Rows ``(name, value, unit, [(coefficient, standard name), ...])``: what every
        parameter of theta groups (theta_b = sum coefficient * theta_standard)."""
        rows = []
        for b, nm in enumerate(self.theta_names):
            terms = [(float(self.base_matrix[b, k]), self.standard_names[k])
                     for k in np.flatnonzero(self.base_matrix[b])]
            rows.append((nm, float(self.theta_values[b]), self.parameter_units[nm], terms))
        return rows

    def parameter_table_text(self):
        """The parameter table as aligned text lines."""
        out = [f"{'parameter':<10} {'value':>14}  {'unit':<10} groups"]
        for nm, val, unit, terms in self.parameter_table():
            g = " + ".join(s if c == 1.0 else f"{c:.6g} {s}" for c, s in terms)
            out.append(f"{nm:<10} {val:>14.8g}  {unit:<10} {g}")
        return "\n".join(out)

    def pinocchio_model(self):
        """The Pinocchio model of the same chain (the reference the tests check against)."""
        m = _chain_model(self.urdf, self._chain["locked"])
        m.gravity.linear = self.gravity
        return m

    def pinocchio_configuration(self, q):
        """Pinocchio's configuration vector of q (continuous joints as cos, sin)."""
        return _pin_configuration(self._chain, q)

    # ------------------------------------------------------------------ identity
    @cached_property
    def key(self) -> str:
        """sha256 hex digest of the generated code (which holds all the chain's data)."""
        return hashlib.sha256(("ivdrem.models.RigidBodyModel\n" + RIGID_BODY_CODEGEN_VERSION
                               + "\n" + self.source("")).encode()).hexdigest()

    # ------------------------------------------------------------------ code
    def source(self, prefix: str = "") -> str:
        """Python source defining the model's functions (same names and signatures as
        :class:`~ivdrem.models.EulerLagrangeModel`'s), prefixed with ``prefix``: constant
        arrays of the chain, the kernels of :mod:`ivdrem.models.rigid_body` and thin
        functions calling them.  Needs ``import math`` and ``import numpy as np``;
        numba-nopython compilable."""
        return self._memo_source(prefix, self._generate)

    def _generate(self, P):
        c = self._chain
        n, ns, nb = self.n, self.nstandard, self.ntheta
        K = f"{P}_RB_"
        consts = [
            f"# chain of {self.name}: {', '.join(self.joint_names)}",
            f"{K}PARENT = {_array_literal(c['parent'], int)}",
            f"{K}JTYPE = {_array_literal(c['jtype'], int)}",
            f"{K}AXIS = {_array_literal(c['axis'], float)}",
            f"{K}RP = {_array_literal(c['Rp'], float)}",
            f"{K}PP = {_array_literal(c['pp'], float)}",
            f"{K}GRAV = {_array_literal(c['gravity'], float)}",
            f"{K}BASE = {_array_literal(self.base_columns, int)}",
        ]
        # the kernels: compiled once for all models (ivdrem.models._rigid_body_jit); the
        # plain-Python path (``python_functions``) binds the name to rigid_body instead
        kmod = f"{P}_rbk"
        # numba's cache of these functions holds the kernels' machine code too: the
        # kernels' own hash in the source renames the module when they change
        imports = (f"# kernels: ivdrem.models.rigid_body {_kernels_hash()}\n"
                   f"import ivdrem.models._rigid_body_jit as {kmod}")
        chain_args = f"{K}PARENT, {K}JTYPE, {K}AXIS, {K}RP, {K}PP, {K}GRAV"
        k_ = f"{kmod}._rb_"
        glue = []
        for name, (work, args) in _GLUE.items():
            doc = _GLUE_DOCS[name].format(n=n, nb=nb)
            alloc = "".join(f"    {w} = np.empty({({'pi': (ns,)}.get(w, (n, ns)))!r})\n"
                            for w in work)
            call = f"{k_}{name}({args.format(**self._glue_args(K, chain_args))}, out)"
            if name == "forward_dynamics":
                call = (f"if {call} != 0:\n"
                        f"        raise ValueError({SINGULAR_INERTIA_MESSAGE!r})")
            glue.append(f"def {P}{name}({', '.join(C_FUNCTION_ARGS[name][:-1])}, out):\n"
                        f'    """{doc}"""\n{alloc}    {call}\n    return None\n')
        for name, (work, args, vec, k) in _JAC_GLUE.items():
            alloc = "".join(f"    {w} = np.empty({(n, ns)!r})\n" for w in work)
            call = f"{k_}{name}({args.format(**self._glue_args(K, chain_args))}, out)"
            glue.append(f"def {P}{name}({', '.join(vec)}, out):\n"
                        f'    """d{name[:-4]}[i, j]/d({", ".join(vec)})[c], c = arg * {n} + entry;'
                        f' out ({n}, {nb}, {k * n})"""\n{alloc}    {call}\n    return None\n')
        t = "\n\n".join(glue)
        return imports + "\n" + "\n".join(consts) + "\n\n\n" + t

    def _offsets(self):
        """Columns of the viscous, Coulomb friction and armature parameters in the standard
        vector (-1: none)."""
        c, n = self._chain, self.n
        nl = 10 * n
        fv = nl if c["viscous"] else -1
        fc = nl + (n if c["viscous"] else 0) if c["coulomb"] else -1
        ia = nl + (n if c["viscous"] else 0) + (n if c["coulomb"] else 0) if c["armature"] else -1
        return fv, fc, ia

    def _glue_args(self, K, chain_args):
        fv, fc, ia = self._offsets()
        width = repr(self.friction_width)
        return dict(chain=chain_args, chain5=chain_args.rsplit(",", 1)[0], base=f"{K}BASE",
                    fric=f"{fv}, {fc}, {ia}, {width}", fv=fv, fc=fc, ia=ia, width=width)

    def _c_body(self, prefix):
        """The C face's body: the chain's constant arrays, the kernels of
        ivdrem.models.rigid_body printed to C, and the functions calling them."""
        from ._c_printer import c_double, print_kernels
        c = self._chain
        P = prefix.upper()
        K = f"{prefix}"

        def arr(values, ctype):
            a = np.asarray(values, dtype=float if ctype == "double" else np.int64).reshape(-1)
            if ctype == "double":
                body = ", ".join(c_double(v) for v in a)
            else:
                body = ", ".join(str(int(v)) for v in a)
            return f"{{{body}}}"

        consts = "\n".join([
            f"#ifndef {P}NSTD\n#define {P}NSTD {self.nstandard}\n#endif",
            f"/* the chain: {', '.join(self.joint_names)} */",
            f"static const int {K}PARENT[{P}N] = {arr(c['parent'], 'int')};",
            f"static const int {K}JTYPE[{P}N] = {arr(c['jtype'], 'int')};",
            f"static const double {K}AXIS[{P}N * 3] = {arr(c['axis'], 'double')};",
            f"static const double {K}RP[{P}N * 9] = {arr(c['Rp'], 'double')};",
            f"static const double {K}PP[{P}N * 3] = {arr(c['pp'], 'double')};",
            f"static const double {K}GRAV[3] = {arr(c['gravity'], 'double')};",
            "/* the base parameters: columns of the standard vector (docs/models.md) */",
            f"static const int {K}BASE[{P}NTHETA] = {arr(self.base_columns, 'int')};",
        ])
        chain_args = ", ".join(f"{K}{a}" for a in ("PARENT", "JTYPE", "AXIS", "RP", "PP",
                                                    "GRAV"))
        ga = self._glue_args(K, chain_args)
        from .rigid_body import C_CHOLESKY, C_KERNELS
        kernels = print_kernels([f for f in C_KERNELS if f not in C_CHOLESKY], prefix,
                                printed=C_CHOLESKY)
        from .base import _c_prototype
        glue = []
        for name, (work, args) in _GLUE.items():
            size = {"pi": f"{P}NSTD"}
            decl = "".join(f"    double {w}[{size.get(w, f'{P}N * {P}NSTD')}];\n" for w in work)
            call = f"{prefix}rb_{name}({args.format(**ga)}, {C_FUNCTION_ARGS[name][-1]})"
            if name == "forward_dynamics":
                call = "return " + call
            glue.append(f"{P}FN {_c_prototype(prefix, name)} {{\n{decl}    {call};\n}}\n")
        glue.append(f"{P}FN {_c_prototype(prefix, 'forward_dynamics_k')} {{\n"
                    f"    (void)k;  /* a URDF model has no constants */\n"
                    f"    return {prefix}forward_dynamics(q, dq, tau, theta, ddq);\n}}\n")
        return "\n" + consts + "\n\n" + kernels + "\n" + "\n".join(glue)

    def engine_c_source(self, prefix: str) -> str:
        """:meth:`c_source` and the regressors' derivatives ``<prefix>Phi_M_jac`` ...
        (``_JAC_GLUE``: out (n, nθ, k n) row major, the derivative by argument k's entry m
        in column k n + m): the C
        library the compiled engine and :attr:`functions` call
        (:mod:`ivdrem.models._c_engine`), printed from the same kernels as :meth:`source`."""
        from ._c_printer import print_kernels
        from .rigid_body import C_CHOLESKY, C_JAC_KERNELS, C_KERNELS
        prefix = self._check_c_prefix(prefix)
        P = prefix.upper()
        K = f"{prefix}"
        chain_args = ", ".join(f"{K}{a}" for a in ("PARENT", "JTYPE", "AXIS", "RP", "PP",
                                                    "GRAV"))
        ga = self._glue_args(K, chain_args)
        jac = print_kernels(C_JAC_KERNELS, prefix,
                            printed=[f for f in C_KERNELS if f not in C_CHOLESKY])
        glue = []
        for name, (work, args, vec, k) in _JAC_GLUE.items():
            decl = "".join(f"    double {w}[{P}N * {P}NSTD];\n" for w in work)
            sig = ", ".join([f"const double *{a}" for a in vec] + ["double *out"])
            glue.append(f"{P}FN void {prefix}{name}({sig}) {{\n{decl}"
                        f"    {prefix}rb_{name}({args.format(**ga)}, out);\n}}\n")
        sizes = "".join(f"#define {P}N{k} ({k} * {P}N)\n" for k in (2, 3, 4))
        return (self.c_source(prefix)
                + "\n/* The regressors' derivatives (the compiled engine's Jacobians). */\n"
                + sizes + "\n" + jac + "\n"
                + "\n".join(glue))

    @cached_property
    def functions(self):
        """The model's functions from Python: its C library through ctypes
        (:mod:`ivdrem.models._c_engine`), or without a C compiler the generated functions
        calling the numba-compiled rigid-body kernels (``ivdrem.models._rigid_body_jit``):
        the reference engine's path, and what the compiled engine's sparsity probe
        evaluates (all plain Python, one regressor costs milliseconds:
        :attr:`python_functions`)."""
        from . import _c_engine
        lib = _c_engine.load(self)
        if lib is not None:
            return _c_engine.python_functions(self, lib)
        return self._namespace(jit=False)

    @cached_property
    def numba_functions(self):
        """The generated functions calling the numba-compiled rigid-body kernels (the path
        without a C compiler; the C library's reference in tests/test_c_engine.py)."""
        return self._namespace(jit=False)

    def engine_source(self) -> str:
        """Python source of the compiled engine's model module: functions calling the
        model's C library (:func:`ivdrem.models._c_engine.numba_source`), or without a C
        compiler :meth:`source` (numba then compiles the rigid-body kernels)."""
        from . import _c_engine
        if _c_engine.load(self) is None:
            return self.source("")
        return _c_engine.numba_source(self)

    @cached_property
    def python_functions(self):
        """The generated functions and the kernels all as plain Python (no numba)."""
        ns = self._namespace(jit=False)
        for f in FUNCTION_NAMES:
            getattr(ns, f).__globals__["_rbk"] = rigid_body
        return ns

    @cached_property
    def jit_functions(self):
        """The generated functions compiled by numba, from the module the compiled engine
        uses (written to ivdrem's cache directory, machine code cached by numba)."""
        import types
        from ._jit_module import model_module
        mod = model_module(self)
        return types.SimpleNamespace(**{f: getattr(mod, f) for f in FUNCTION_NAMES})

