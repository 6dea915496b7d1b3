"""Configuration of the paper experiment: embedded default, loading, validation.

The default configuration (the paper experiment) is the package data file
``ivdrem/experiments/default.toml``.  :func:`read_config` deep-merges a user TOML
file (and optional overrides) over it and checks every key: data, no model built, the keys
that follow the model left out.  :func:`resolve_config` (``Experiment.from_config``) builds
the model once, fills those keys (the real-arm reference designed once) and checks the
whole against that model, *before* anything is simulated.  ``load_config`` (both) is a
deprecated alias: the commands and the library take the
:class:`~ivdrem.experiments.experiment.Experiment` of the data instead.
Every problem is reported as a :class:`ConfigError` naming the key.

:func:`closed_loop_kwargs` maps a validated configuration to the arguments of
``ivdrem.diagrams.closed_loop(law, model, **kwargs)`` (the loop's keywords and the law's
``gains``, :func:`law_gains`), :func:`solver_kwargs` to those
of the simulator.
"""
from __future__ import annotations

import copy
import difflib
import hashlib
import functools
import math
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .._config_keys import POSITIVE, Key, in_range, magnitude
from .._config_file import ConfigError, read_toml  # noqa: F401 - read without the library (ivdrem.cli)
from ..laws import LAWS as _LAW_REGISTRY, get_law, law_names
from ..blocks.control_law import DESIGNS, INJECTIONS, inertia_scaled_gain

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = [
    "ConfigError",
    "LAWS",
    "SOLVER_METHODS",
    "OBSERVER_VARIANTS",
    "default_config",
    "read_config",
    "resolve_config",
    "load_config",
    "validate_config",
    "model_dims",
    "closed_loop_kwargs",
    "law_gains",
    "solver_kwargs",
    "dump_toml",
    "schema",
]

#: Adaptation laws known to the closed-loop diagrams (the registry ``ivdrem.laws``;
#: ``experiment.laws = "all"`` runs every registered law).  ``LAWS`` is read from the
#: registry on every access (module ``__getattr__`` below), so a law registered later is in it.


def __getattr__(name):
    if name == "LAWS":
        return law_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: Integration methods of ivdrem's simulator.
from ..sim.simulator import METHODS as SOLVER_METHODS  # noqa: E402  (one source of truth)
from ..sim.methods import method_info  # noqa: E402
#: Variants of the Φ_Mf filter gain (erratum E1).
OBSERVER_VARIANTS = ("corrected", "literal")


# --------------------------------------------------------------------------- schema
#: frequencies of the reference and the disturbance: each period needs steps of its own,
#: so 1e6 rad/s is already about 5e7 steps over the paper's 300 s (docs/experiment.md)
_OMEGA_MAX = 1e4

#: The sections every law's run reads, their keys and checks (:class:`ivdrem.laws.Key`).
#: Each law's own section ([iv_drem], ...) is its registry entry's (``Law.keys``, or its
#: numeric ``defaults``): :func:`schema` places those after [filters].
SECTIONS: dict[str, dict[str, Key]] = {
    "experiment": {
        "t_end": Key("float", **POSITIVE),
        "laws": Key("strlist"),  # checked against the law registry at validation
        # lower bounds of ivdrem.sim.guards (DT_OUT_MIN, H_MAX_MIN), kept equal by a test
        "dt_out": Key("float", check=lambda x: x >= 1e-6, requirement="> 0 (at least 1e-06 s)"),
    },
    "model": {
        "name": Key("str"),
        "theta": Key("vec", "ntheta", **magnitude(1e6, "SI units: kg, kg m, kg m^2")),
        "g": Key("float", **magnitude(1e3, "m/s^2")),
    },
    "initial": {
        "q0": Key("vec", "n", **magnitude(1e3, "rad or m")),
        "dq0": Key("vec", "n", **magnitude(1e3, "rad/s or m/s")),
        "theta_hat0": Key("vec", "ntheta", **magnitude(1e6, "as model.theta")),
    },
    "controller": {
        "alpha": Key("float", **in_range(0, 1e6, open_lo=True)),
        "K": Key("vec", "n", **in_range(0, 1e6, open_lo=True)),
        "delta_mu": Key("float", check=lambda x: 0 < x < 1, requirement="in (0, 1)"),
        "Gamma": Key("float_or_vec", "ntheta", **in_range(0, 1e6, open_lo=True)),
        "mu0": Key("float", **in_range(0, 1e6)),
        "mu1": Key("float", **in_range(1e-6, 1e6, "the observer divides by mu(0) = mu1")),
        "observer_variant": Key("str", choices=OBSERVER_VARIANTS),
    },
    "filters": {
        "l": Key("float", **in_range(0, 1e6, open_lo=True)),
    },
    "trajectory": {
        "amplitude": Key("vec", "n", **magnitude(1e6)),
        "omega": Key("vec", "n", **magnitude(_OMEGA_MAX, "rad/s")),
        "phase": Key("vec", "n", **magnitude(1e3, "rad")),
        "offset": Key("vec", "n", **magnitude(1e6)),
    },
    "disturbance": {
        "amplitude": Key("vec", "n", **magnitude(1e6)),
        "omega": Key("vec", "n", **magnitude(_OMEGA_MAX, "rad/s")),
        "phase": Key("vec", "n", **magnitude(1e3, "rad")),
        "offset": Key("vec", "n", **magnitude(1e6)),
    },
    "solver": {
        "method": Key("str", choices=SOLVER_METHODS),
        "rtol": Key("float", **in_range(1e-12, 0.5, "a relative tolerance")),
        "atol": Key("float", **in_range(1e-14, 1.0)),
        "h": Key("float", **in_range(1e-9, 1e3, "the initial or fixed step, s")),
        "h_max": Key("float", check=lambda x: 1e-6 <= x <= 1e6,
                      requirement="> 0 (at least 1e-06 s) and <= 1e+06 s"),
    },
}

#: Friction options of a URDF model (``ivdrem.models.from_urdf(friction=...)``).
FRICTION = ("none", "viscous", "coulomb", "viscous+coulomb")
#: Kinds of reference trajectory and the keys of [trajectory] each one uses.
TRAJECTORY_KINDS = {
    "sinusoid": ("amplitude", "omega", "phase", "offset"),   # the paper's (no `kind` key)
    "fourier": ("kind", "omega_f", "a", "b", "offset"),      # docs/experiment.md
}

#: Keys a section may hold beyond :data:`SECTIONS`' (none of them in the paper's
#: configuration): the model from a URDF file and its options, the Fourier reference.
OPTIONAL: dict[str, dict[str, Key]] = {
    "experiment": {
        # Python files (relative to the configuration file) or module names that register
        # the user's own laws (ivdrem.laws.register_law); imported before the laws are read
        "plugins": Key("names"),
    },
    "controller": {
        # the feedback of (9): "paper" or "inertia-scaled" (docs/controller.md); K stays the
        # joint gain (N m s), the inertia-scaled loop's K_i / M̂_ii(q0)
        "design": Key("str", choices=DESIGNS),
        # the observer's injection of (8) at theta_hat ("estimate", the paper's) or at the
        # model's nominal parameters ("nominal", the inertia-scaled design's default)
        "injection": Key("str", choices=INJECTIONS),
    },
    "model": {
        "urdf": Key("str"),            # a path, relative to the configuration file
        "friction": Key("str", choices=FRICTION),
        "joints": Key("names"),
    },
    "trajectory": {
        "kind": Key("str", choices=tuple(TRAJECTORY_KINDS)),
        "omega_f": Key("float", **in_range(0, _OMEGA_MAX, "rad/s", open_lo=True)),
        "a": Key("mat", "n"),
        "b": Key("mat", "n"),
    },
}


# --------------------------------------------------------------------------- the model
def _model_names() -> list[str]:
    """The names ``ivdrem.models.get_model`` accepts (its own list)."""
    from ..models import model_names
    return list(model_names())


@functools.lru_cache(maxsize=16)
def _build(name, urdf, stamp, g, friction, joints):
    from .. import models
    opts = {}
    if friction is not None:
        opts["friction"] = None if friction == "none" else friction
    if joints is not None:
        opts["joints"] = list(joints)
    if urdf is not None:
        if g is not None:
            opts["gravity"] = g
        try:
            return models.from_urdf(urdf, **opts)
        except (ValueError, OSError, ImportError) as exc:
            key = "model.joints" if joints is not None and "joint" in str(exc) else "model.urdf"
            where = "" if str(urdf) in str(exc) else f" ({urdf})"
            raise ConfigError(f"config key '{key}'{where}: {exc}") from None
    if g is not None:
        opts["g"] = g
    try:
        return models.get_model(name, **opts)
    except TypeError as exc:          # an option this model does not take
        given = ", ".join(f"model.{k}" for k in sorted(opts) if k != "g")
        raise ConfigError(f"config section [model]: model {name!r} does not take "
                          f"{given or 'model.g'}: {exc}") from None
    except ValueError as exc:
        names = _model_names()
        if not any(str(name).lower() == n.lower() for n in names) and "unknown model" in str(exc):
            raise ConfigError(f"config key 'model.name' = {name!r} is not a known model"
                              + _suggest(str(name), names) + "; valid: "
                              + ", ".join(names)) from None
        raise ConfigError(f"config key 'model.name' = {name!r}: {exc}") from None


def model_from_config(config: Mapping):
    """The robot model of a configuration's [model] section: ``name`` (any name of
    ``ivdrem.models.get_model``) or ``urdf`` (a file; made absolute by :func:`read_config`),
    with ``g`` and the URDF options ``friction`` and ``joints``.  Built once per process
    and options (a URDF file also by its modification time).  Raises :class:`ConfigError`
    naming the key."""
    m = config["model"]
    urdf = m.get("urdf")
    stamp = None
    if urdf is not None:
        p = Path(urdf)
        if not p.is_file():
            raise ConfigError(f"config key 'model.urdf': file '{p}' not found"
                              + (" (a directory)" if p.is_dir() else ""))
        stamp = p.stat().st_mtime_ns
    elif not isinstance(m.get("name"), str):
        raise ConfigError(f"config key 'model.name' must be a string, got {m.get('name')!r}")
    joints = m.get("joints")
    g = m.get("g")
    from .._progress import preparing
    # a large symbolic arm (planar-20) builds in sympy for minutes the first time: said
    with preparing(f"building the model {urdf or m.get('name')} (the first time; sympy or "
                   "Pinocchio)", only_if_slow=True):
        return _build(m.get("name"), None if urdf is None else str(urdf), stamp,
                      None if g is None else float(g), m.get("friction"),
                      None if joints is None else tuple(joints))


def model_label(config: Mapping) -> str:
    """The model of a configuration in words: its name, or the URDF file."""
    m = config["model"]
    return f"URDF {m['urdf']}" if "urdf" in m else str(m["name"])


def model_dims(config_or_name) -> tuple[int, int]:
    """(n, nθ) of the configured model (a configuration, its [model] table or a name)."""
    if isinstance(config_or_name, str):
        config_or_name = {"model": {"name": config_or_name}}
    elif "model" not in config_or_name:
        config_or_name = {"model": config_or_name}
    model = model_from_config(config_or_name)
    return int(model.n), int(model.ntheta)


#: Keys whose default follows the model when the configuration names a model other than
#: the paper's arm and does not set them: zeros, the paper's per-joint gain and the model's
#: own parameter values.  A law's keys follow the model by their ``Key.follow`` (the
#: registry's: θ* = 0, gamma = "auto", the mixing that works at this robot's size).
MODEL_FOLLOWING = {
    ("model", "theta"): lambda m: [float(v) for v in m.theta_values],
    ("initial", "dq0"): lambda m: [0.0] * m.n,
    ("initial", "theta_hat0"): lambda m: [0.0] * m.ntheta,
    ("controller", "K"): lambda m: [2.0] * m.n,
}
#: Keys whose default follows the Fourier reference (the real-arm experiment of
#: docs/experiment.md, :mod:`ivdrem.diagrams.arm_reference`): q(0) on the reference, the
#: disturbance scaled to the arm, gains per joint, the windows T of (15a) and (35).  Each gets (model, config, a memo
#: shared by one filling).
ARM_FOLLOWING = {
    ("initial", "q0"): lambda m, c, memo: _memo(memo, "x0", lambda: _arm().initial_state(c["trajectory"]))[0],
    ("initial", "dq0"): lambda m, c, memo: _memo(memo, "x0", lambda: _arm().initial_state(c["trajectory"]))[1],
    ("controller", "K"): lambda m, c, memo: _arm().design_gains(m, c["initial"]["q0"], c["model"]["theta"]),
    **{("disturbance", k): (lambda k: lambda m, c, memo: _memo(memo, "tau_d", lambda: _arm().design_disturbance(
        m, c["trajectory"], c["model"]["theta"]))[k])(k) for k in ("amplitude", "omega", "phase", "offset")},
    # after the disturbance: a common period of reference and disturbance (None: the law's T)
    **{(section, "T"): lambda m, c, memo: _memo(memo, "T", lambda: _arm().design_window(
        c["trajectory"], c["disturbance"])) for section in ("iv_drem", "composite_learning")},
}


def _memo(memo: dict, key: str, fn):
    if key not in memo:
        memo[key] = fn()
    return memo[key]


#: The model the embedded default is written for.
DEFAULT_MODEL = "two-link"


def _arm():
    from ..diagrams import arm_reference
    return arm_reference


def _user_traj_keys(user_set: set) -> set:
    return {k for s, k in user_set if s == "trajectory"}


def _following_keys() -> set:
    """Every (section, key) that may follow the model: MODEL_FOLLOWING, the laws'
    ``Key.follow``, the Fourier reference's keys and ARM_FOLLOWING."""
    laws = {(section, key) for section, keys in _law_tables().items()
            for key, (spec, _) in keys.items() if spec.follow is not None}
    return (set(MODEL_FOLLOWING) | laws | set(ARM_FOLLOWING)
            | {("trajectory", k) for k in TRAJECTORY_KINDS["fourier"] if k != "kind"})


def _leave_following(cfg: dict, user_set: set) -> set:
    """The data half of following the model (no model built): for a model other than the
    paper's arm, the keys of MODEL_FOLLOWING and the laws' ``Key.follow`` the user did not
    set are taken out; with no [trajectory] key set for such a model (or ``trajectory.kind
    = "fourier"``) the reference is the real-arm experiment's (kind "fourier") and its keys
    and ARM_FOLLOWING's the user did not set are taken out too.  Returns the keys taken
    out: :func:`resolve_config` fills them from the model."""
    mcfg = cfg["model"]
    is_default = "urdf" not in mcfg and mcfg.get("name") == DEFAULT_MODEL
    user_traj = _user_traj_keys(user_set)
    fourier = cfg["trajectory"].get("kind") == "fourier" or (not is_default and not user_traj)
    out: set = set()
    if not is_default:
        laws = {(section, key) for section, keys in _law_tables().items()
                for key, (spec, _) in keys.items() if spec.follow is not None}
        out |= (set(MODEL_FOLLOWING) | laws) - user_set
    if fourier:
        cfg["trajectory"]["kind"] = "fourier"
        out |= ({("trajectory", k) for k in TRAJECTORY_KINDS["fourier"] if k != "kind"}
                | set(ARM_FOLLOWING)) - user_set
    for section, key in out:
        cfg[section].pop(key, None)
    return out


def _follow_model(cfg: dict, model) -> None:
    """Fill the keys :func:`_leave_following` took out (those absent from `cfg`) from the
    built `model`: MODEL_FOLLOWING and the laws' ``Key.follow`` for a model other than the
    paper's arm; for the Fourier reference, the real-arm experiment's reference (designed
    once) and ARM_FOLLOWING.  A key still absent after it (a design that needs numbers of
    other shapes, a window T the design leaves to the law) takes the default's value."""
    missing = {(s, k) for s, k in _following_keys() if k not in cfg.get(s, {})}
    if not missing:
        return
    mcfg = cfg["model"]
    is_default = "urdf" not in mcfg and mcfg.get("name") == DEFAULT_MODEL
    fourier = cfg["trajectory"].get("kind") == "fourier"
    if not is_default:
        laws = {(section, key): spec.follow for section, keys in _law_tables().items()
                for key, (spec, _) in keys.items() if spec.follow is not None}
        for (section, key), fn in {**MODEL_FOLLOWING, **laws}.items():
            if (section, key) in missing:
                cfg[section][key] = fn(model)
    if fourier:
        design = None
        for key in TRAJECTORY_KINDS["fourier"]:
            if ("trajectory", key) in missing:
                design = _arm().design_trajectory(model) if design is None else design
                cfg["trajectory"][key] = design[key]
        _follow_arm(cfg, model, missing)
    base = default_config()
    for section, key in missing:
        if key not in cfg[section] and key in base[section]:
            cfg[section][key] = base[section][key]


def _follow_arm(cfg: dict, model, missing: set) -> None:
    tr = cfg["trajectory"]
    try:   # needs numbers of the right shapes: otherwise validation names the key
        a, b = np.asarray(tr["a"], float), np.asarray(tr["b"], float)
        if a.shape != b.shape or a.ndim != 2 or a.shape[0] != model.n or \
                np.shape(tr["offset"]) != (model.n,):
            return
        memo: dict = {}
        for (section, key), fn in ARM_FOLLOWING.items():
            if (section, key) in missing:
                value = fn(model, cfg, memo)
                if value is not None:
                    cfg[section][key] = value
    except (TypeError, ValueError, IndexError, KeyError):
        pass


def _settle_variants(cfg: dict, user_set: set) -> None:
    """One [model] source (name or urdf) and one kind of [trajectory]: the default's keys
    of the other variant go, the user's are checked."""
    if ("model", "urdf") in user_set:
        if ("model", "name") in user_set:
            raise ConfigError("config keys 'model.name' and 'model.urdf' are both set: "
                              "give one (a model name, or a URDF file)")
        cfg["model"].pop("name", None)
    traj = cfg["trajectory"]
    kind = traj.get("kind", "sinusoid")
    if kind not in TRAJECTORY_KINDS:
        return            # validation names the bad kind
    own = set(TRAJECTORY_KINDS[kind]) | {"kind"}
    for key in list(traj):
        if key not in own:
            if ("trajectory", key) in user_set:
                raise ConfigError(
                    f"config key 'trajectory.{key}' is not a key of trajectory.kind = "
                    f"{kind!r}; its keys: " + ", ".join(k for k in TRAJECTORY_KINDS[kind] if k != "kind"))
            del traj[key]


def _resolve_plugins(user: Mapping, base: Path | None) -> None:
    """Relative ``experiment.plugins`` files are relative to the configuration file (`base`
    its directory), or to the caller's directory for overrides; module names stay."""
    e = user.get("experiment")
    if not isinstance(e, Mapping) or not isinstance(e.get("plugins"), list):
        return
    from .._paths import user_path
    out = []
    for item in e["plugins"]:
        if isinstance(item, str) and item.endswith(".py"):
            q = Path(item).expanduser()
            if base is not None and not q.is_absolute():
                q = base / q
            item = str(user_path(q))
        out.append(item)
    e["plugins"] = out


_LOADED_PLUGINS: dict = {}


def load_plugins(cfg: Mapping, where: str = "configuration") -> None:
    """Import the modules ``experiment.plugins`` names (each once per process), so that the
    laws they register exist before the configuration reads ``experiment.laws``.  A Dask
    worker validating a study's configuration imports them the same way."""
    e = cfg.get("experiment") if isinstance(cfg, Mapping) else None
    items = e.get("plugins") if isinstance(e, Mapping) else None
    if items is None:
        return
    if not isinstance(items, list) or not all(isinstance(i, str) and i for i in items):
        raise ConfigError(f"config key 'experiment.plugins' ({where}) must be a list of Python "
                          f"files or module names, got {items!r}")
    import importlib
    from ..compile_cache import import_path
    for item in items:
        if item in _LOADED_PLUGINS:
            continue
        try:
            if item.endswith(".py"):
                q = Path(item)
                if not q.is_file():
                    raise ConfigError(f"config key 'experiment.plugins' ({where}): file '{q}' "
                                      "not found")
                name = "ivdrem_plugin_" + hashlib.sha256(str(q).encode()).hexdigest()[:12]
                module = import_path(name, q)
            else:
                module = importlib.import_module(item)
        except ConfigError:
            raise
        except Exception as exc:
            raise ConfigError(f"config key 'experiment.plugins' ({where}): importing {item!r} "
                              f"failed: {type(exc).__name__}: {exc}") from None
        _LOADED_PLUGINS[item] = module


def _resolve_urdf(user: Mapping, base: Path | None) -> None:
    """A relative ``model.urdf`` is relative to the configuration file (`base` its
    directory), or to the caller's directory for overrides."""
    m = user.get("model")
    if isinstance(m, Mapping) and isinstance(m.get("urdf"), str):
        from .._paths import user_path
        p = Path(m["urdf"]).expanduser()
        if base is not None and not p.is_absolute():
            p = base / p
        m["urdf"] = str(user_path(p))          # absolute, normalised


# --------------------------------------------------------------------------- loading
def default_config() -> dict:
    """A fresh copy of the embedded default configuration: the sections of default.toml
    and, from the law registry, the default gains of every registered law that has a
    section of its own (:func:`_law_sections`), in the order of :func:`schema`."""
    raw, laws = _default_raw(), _law_sections()
    return {s: copy.deepcopy(laws[s] if s in laws else raw[s]) for s in schema()}


_DEFAULT_CACHE: dict | None = None


def _default_raw() -> dict:
    global _DEFAULT_CACHE
    if _DEFAULT_CACHE is None:
        text = resources.files("ivdrem.experiments").joinpath("default.toml").read_text("utf-8")
        # the base every configuration is merged over: the paper's 2-link arm is built
        # (and the default checked against it) only by a configuration that uses it
        _DEFAULT_CACHE = validate_config(tomllib.loads(text), with_model=False)
    return _DEFAULT_CACHE


def read_config(path: str | Path | None = None, overrides: Mapping | None = None) -> dict:
    """The experiment configuration as data: nothing built, nothing designed.

    The user TOML file at ``path`` (if any) and then ``overrides`` (a nested mapping
    ``{"experiment": {"t_end": 10.0}}`` or dotted keys ``{"experiment.t_end": 10.0}``)
    are merged key by key over the embedded default and checked key by key (types,
    ranges, choices, unknown sections and keys); returned as a plain dict (floats as
    ``float``, vectors as lists of ``float``).  The keys that follow the model (a model
    other than the paper's arm, the real-arm reference of docs/experiment.md) and that the
    user did not set are absent: :func:`resolve_config` (``Experiment.from_config``) fills
    them from the model it builds, and checks what needs it (vector lengths, joint limits).
    Raises :class:`ConfigError` for any invalid or unknown entry.
    """
    user = over = None
    if path is not None:
        p = Path(path)
        user, _ = read_toml(p)
        _resolve_urdf(user, p.resolve().parent)
        _resolve_plugins(user, p.resolve().parent)
        load_plugins(user, where=str(p))       # a user law's section joins the default
    if overrides:
        over = _undot(overrides)
        _resolve_urdf(over, None)
        _resolve_plugins(over, None)
        load_plugins(over, where="overrides")
    cfg = default_config()
    user_set: set = set()
    if user is not None:
        _merge(cfg, user, where=str(p), user_set=user_set)
    if over is not None:
        _merge(cfg, over, where="overrides", user_set=user_set)
    _settle_variants(cfg, user_set)
    following = _leave_following(cfg, user_set)
    _settle_variants(cfg, user_set)
    return validate_config(cfg, with_model=False, following=following)


def resolve_config(data: Mapping, model=None) -> tuple[dict, object]:
    """(configuration, model) of configuration data (:func:`read_config`): the model built
    once (or `model`, already built for it), the keys that follow it filled (the real-arm
    reference designed once), and the whole checked against it.  A complete configuration
    comes back equal.  Raises :class:`ConfigError`."""
    cfg = copy.deepcopy({s: dict(t) for s, t in data.items()})
    model = model_from_config(cfg) if model is None else model
    _follow_model(cfg, model)
    return validate_config(cfg, model=model), model


def load_config(path: str | Path | None = None, overrides: Mapping | None = None) -> dict:
    """Deprecated: ``Experiment.from_config(read_config(path, overrides)).config`` (the
    :class:`~ivdrem.experiments.experiment.Experiment` keeps the model it built); warns."""
    import warnings
    warnings.warn("ivdrem.experiments.config.load_config is deprecated: read the data with "
                  "read_config(path, overrides) and resolve it once with "
                  "Experiment.from_config(data) (docs/experiment.md)",
                  DeprecationWarning, stacklevel=2)
    return resolve_config(read_config(path, overrides))[0]


def _check_reference_limits(config: Mapping, model=None) -> None:
    """The configured reference stays inside the model's position and velocity limits
    over the run (models without limits pass); a ConfigError names joint and time."""
    model = model_from_config(config) if model is None else model
    if not any(hasattr(model, a) for a in ("position_limits", "velocity_limits")):
        return
    try:
        _arm().check_limits(model, config["trajectory"], float(config["experiment"]["t_end"]))
    except _arm().LimitError as exc:
        raise ConfigError(f"config section [trajectory]: {exc}") from None


def _undot(overrides: Mapping) -> dict:
    out: dict = {}
    for key, value in overrides.items():
        if isinstance(key, str) and "." in key:
            section, _, name = key.partition(".")
            out.setdefault(section, {})
            if not isinstance(out[section], dict):
                raise ConfigError(f"override '{key}' conflicts with override '{section}'")
            out[section][name] = value
        elif isinstance(value, Mapping):
            out.setdefault(key, {})
            out[key].update(value)
        else:
            raise ConfigError(
                f"override {key!r} must be a section table or a dotted key 'section.key'"
            )
    return out


def _merge(cfg: dict, user: Mapping, where: str, user_set: set | None = None) -> None:
    for section, table in user.items():
        _check_section(section)
        if not isinstance(table, Mapping):
            raise ConfigError(
                f"config section '{section}' must be a table ([{section}]), "
                f"got {type(table).__name__} (in {where})"
            )
        for key, value in table.items():
            _check_key(section, key)
            cfg[section][key] = copy.deepcopy(value)
            if user_set is not None:
                user_set.add((section, key))


def _suggest(word: str, valid, prefix=" (did you mean ", suffix="?)") -> str:
    close = difflib.get_close_matches(word, list(valid), n=1, cutoff=0.5)
    if not close:
        # case-insensitive second chance ("kp" vs "K")
        lower = {v.lower(): v for v in valid}
        close = [lower[c] for c in difflib.get_close_matches(word.lower(), list(lower), n=1, cutoff=0.5)]
    return f"{prefix}'{close[0]}'{suffix}" if close else ""


def _law_key(value) -> Key:
    """Schema entry of a registered law's gain, from its default: a number or a vector."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return Key("vec")
    return Key("float")


def _config_value(value):
    """A law's default as the configuration holds it: a vector as a list of floats."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return [float(v) for v in np.asarray(value, float).ravel()]
    return value


def _law_tables() -> dict:
    """{section: {key: (spec, default)}} of the registered laws' own tables, in registry
    order; a section shared by several laws ([iv_drem]) is its first law's, and one named
    like a section of :data:`SECTIONS` is not the law's to define.  A law added
    with ``register_law(Law(..., section="my_law", defaults=..., keys=...))`` is configured
    in its table [my_law] like a built-in law: a gain it declares in ``keys`` has that
    type, range and default; any other numeric default is a number or a vector."""
    out: dict = {}
    for law in _LAW_REGISTRY.values():
        if not law.section or law.section in out or law.section in SECTIONS:
            continue
        declared = law.keys or {}
        table = {}
        for k, v in law.defaults.items():
            if k in declared:
                spec = declared[k]
                table[k] = (spec, _config_value(v if spec.default is None else spec.default))
            elif v is not None and not isinstance(v, (str, bool)):
                table[k] = (_law_key(v), _config_value(v))
        for k, spec in declared.items():
            if k not in table:
                table[k] = (spec, _config_value(spec.default))
        out[law.section] = table
    return out


def _law_sections() -> dict:
    """{section: {key: default}} of the registered laws' own tables (:func:`_law_tables`)."""
    return {s: {k: d for k, (_, d) in keys.items()} for s, keys in _law_tables().items()}


#: The laws' own sections follow the loop's shared gains ([controller], [filters]) and
#: precede its signals ([trajectory], [disturbance]) and the solver.
_LAWS_AFTER = "filters"


def schema() -> dict:
    """The configuration's sections and keys: :data:`SECTIONS` with, after [filters], one
    section per registered law that has its own (:func:`_law_tables`)."""
    laws = {s: {k: spec for k, (spec, _) in keys.items()} for s, keys in _law_tables().items()}
    out: dict = {}
    for section, keys in SECTIONS.items():
        out[section] = keys
        if section == _LAWS_AFTER:
            out.update(laws)
    return out


def _check_section(section: str) -> None:
    sch = schema()
    if section not in sch:
        raise ConfigError(
            f"config section '{section}' is not known"
            + _suggest(section, sch)
            + "; valid sections: "
            + ", ".join(sch)
        )


def _check_key(section: str, key: str) -> None:
    valid = {**schema()[section], **OPTIONAL.get(section, {})}
    if key not in valid:
        full = [f"{section}.{k}" for k in valid]
        raise ConfigError(
            f"config key '{section}.{key}' is not known"
            + _suggest(f"{section}.{key}", full)
            + f"; valid keys in [{section}]: "
            + ", ".join(valid)
        )


# --------------------------------------------------------------------------- validation
def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(
            f"config key '{name}' must be a number, got {type(value).__name__} {value!r}"
        )
    x = float(value)
    if not math.isfinite(x):
        raise ConfigError(f"config key '{name}' must be finite, got {value!r}")
    return x


def _section_keys(section: str, table: Mapping, keys: Mapping) -> dict:
    """{key: spec} a section must (:func:`schema`, per variant) and may (OPTIONAL) hold."""
    extra = OPTIONAL.get(section, {})
    if section == "model" and "urdf" in table:
        if "name" in table:
            raise ConfigError("config keys 'model.name' and 'model.urdf' are both set: "
                              "give one (a model name, or a URDF file)")
        keys = {k: v for k, v in keys.items() if k != "name"}
    if section == "trajectory":
        kind = _validate_value("trajectory.kind", extra["kind"], table.get("kind", "sinusoid"))
        want = TRAJECTORY_KINDS[kind]
        every = {**keys, **extra}
        for key in table:
            if key not in want and key != "kind":
                raise ConfigError(
                    f"config key 'trajectory.{key}' is not a key of trajectory.kind = "
                    f"{kind!r}; its keys: " + ", ".join(k for k in want if k != "kind"))
        keys = {k: every[k] for k in want if k != "kind"}
    return {**keys, **{k: v for k, v in extra.items() if k in table and k not in keys}}


def validate_config(cfg: Mapping, *, with_model: bool = True, following=frozenset(),
                    model=None) -> dict:
    """Check a complete configuration dict; return a normalized deep copy.

    Every section and key of :data:`SECTIONS` must be present (use :func:`read_config`
    to fill missing ones from the default); a law's own section takes the registry's
    defaults for the keys it lacks; the keys of :data:`OPTIONAL` may be.  The
    reference must stay inside the model's joint limits over the run.
    Raises :class:`ConfigError`.

    ``with_model=False`` leaves out what needs the model built (vector lengths against
    n and nθ, the joint limits): the embedded default read as the base of another
    model's configuration, which :func:`resolve_config` validates whole once merged.
    ``following`` (with ``with_model=False``): the (section, key) left absent to follow
    the model (:func:`read_config`), neither required nor filled.  ``model``: the model
    of `cfg`, already built (:func:`resolve_config`); default :func:`model_from_config`.
    """
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"configuration must be a table, got {type(cfg).__name__}")
    load_plugins(cfg)          # (a study's worker) the user's laws before they are read
    out: dict = {}
    for section in cfg:
        _check_section(section)
        if not isinstance(cfg[section], Mapping):
            raise ConfigError(f"config section '{section}' must be a table ([{section}])")
        for key in cfg[section]:
            _check_key(section, key)
    sch = schema()
    law_defaults = _law_sections()
    specs: dict = {}
    for section, keys in sch.items():
        if section in law_defaults:       # a registered law's own table: defaults fill gaps
            gaps = {k: v for k, v in law_defaults[section].items() if (section, k) not in following}
            cfg = {**cfg, section: {**gaps, **cfg.get(section, {})}}
        if section not in cfg:
            raise ConfigError(f"config section '{section}' is missing")
        out[section] = {}
        specs[section] = _section_keys(section, cfg[section], keys)
        for key, spec in specs[section].items():
            if key not in cfg[section] and (section, key) in following and not with_model:
                continue
            if key not in cfg[section]:
                raise ConfigError(f"config key '{section}.{key}' is missing")
            out[section][key] = _validate_value(f"{section}.{key}", spec, cfg[section][key])

    if not with_model:
        return out
    if model is None:
        n, ntheta = model_dims(out)
    else:
        n, ntheta = int(model.n), int(model.ntheta)
    dims = {"n": n, "ntheta": ntheta}
    label = model_label(out)
    for section, keys in specs.items():
        for key, spec in keys.items():
            value = out[section][key]
            if spec.length is None or not isinstance(value, list):
                continue
            want = dims[spec.length]
            if len(value) != want:
                what = "n" if spec.length == "n" else "nθ"
                rows = " rows" if spec.kind == "mat" else " entries"
                raise ConfigError(
                    f"config key '{section}.{key}' must have {want}{rows} "
                    f"(model '{label}' has {what} = {want}), got {len(value)}"
                )
    tr = out["trajectory"]
    if "a" in tr and len(tr["a"][0]) != len(tr["b"][0]):
        raise ConfigError(f"config keys 'trajectory.a' and 'trajectory.b' must have the same "
                          f"number of harmonics (columns), got {len(tr['a'][0])} and {len(tr['b'][0])}")
    exp = out["experiment"]
    if exp["dt_out"] > exp["t_end"]:
        raise ConfigError(
            f"config key 'experiment.dt_out' = {exp['dt_out']} exceeds experiment.t_end = {exp['t_end']}"
        )
    if len(set(exp["laws"])) != len(exp["laws"]):
        raise ConfigError(f"config key 'experiment.laws' lists a law twice: {exp['laws']}")
    _check_reference_limits(out, model)
    _check_step_bounds(out)
    return out


def _check_step_bounds(cfg: Mapping) -> None:
    """A fixed-step method's solver.h must fit under solver.h_max and, for a law with a
    sliding window, under half its T (eq. 14; :func:`solver_kwargs`), or the simulator
    refuses the run after the model is built.  (An adaptive method's h is only its first
    step: :func:`solver_kwargs` holds it to the same bound.)"""
    s = cfg["solver"]
    if method_info(s["method"]).adaptive:
        return
    if s["h"] > s["h_max"]:
        raise ConfigError(f"config key 'solver.h' = {s['h']:g} s (the fixed step of "
                          f"{s['method']}) exceeds solver.h_max = {s['h_max']:g} s: lower "
                          "solver.h or raise solver.h_max")
    for law in cfg["experiment"]["laws"]:
        bound = solver_kwargs(cfg, law)["h_max"]
        if s["h"] > bound:
            # a bound below h_max comes from a window T, which only a law's config names
            where = get_law(law).config["T"]
            raise ConfigError(
                f"config key 'solver.h' = {s['h']:g} s (the fixed step of {s['method']}) "
                f"exceeds {bound:g} s, half the sliding window {where} of law {law!r} (a "
                f"step must not reach past the window's delay, eq. (14)): lower solver.h "
                f"or lengthen {where}")


def _validate_value(name: str, spec: Key, value: Any):
    if spec.kind == "str":
        if not isinstance(value, str):
            raise ConfigError(f"config key '{name}' must be a string, got {type(value).__name__} {value!r}")
        if spec.choices is not None and value not in spec.choices:
            raise ConfigError(
                f"config key '{name}' = {value!r} is not valid" + _suggest(value, spec.choices)
                + "; valid: " + ", ".join(repr(c) for c in spec.choices)
            )
        return value
    if spec.kind == "names":
        if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"config key '{name}' must be a non-empty list of names, got {value!r}")
        if len(set(value)) != len(value):
            raise ConfigError(f"config key '{name}' lists a name twice: {value}")
        return list(value)
    if spec.kind == "mat":
        if (not isinstance(value, list) or not value
                or not all(isinstance(r, list) and r for r in value)):
            raise ConfigError(f"config key '{name}' must be a list of rows (one per joint), "
                              f"each a non-empty list of numbers, got {value!r}")
        rows = [[_number(f"{name}[{i}][{j}]", v) for j, v in enumerate(r)] for i, r in enumerate(value)]
        if len({len(r) for r in rows}) != 1:
            raise ConfigError(f"config key '{name}': every row must have the same length, "
                              f"got lengths {[len(r) for r in rows]}")
        return rows
    if spec.kind == "strlist":
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"config key '{name}' must be a list of strings, got {value!r}")
        if not value:
            raise ConfigError(f"config key '{name}' must name at least one law")
        choices = spec.choices if spec.choices is not None else law_names()
        if value == ["all"]:
            return list(choices)
        for v in value:
            if v not in choices:
                raise ConfigError(
                    f"config key '{name}': law {v!r} is not known" + _suggest(v, choices)
                    + "; valid laws: " + ", ".join(repr(c) for c in choices) + ", or 'all'"
                )
        return list(value)
    if spec.kind == "float_or_auto" and isinstance(value, str):
        if value != "auto":
            raise ConfigError(f"config key '{name}' must be a number or \"auto\", got {value!r}")
        return value
    if spec.kind in ("float", "float_or_auto") or (spec.kind == "float_or_vec" and not isinstance(value, list)):
        x = _number(name, value)
        if spec.check is not None and not spec.check(x):
            raise ConfigError(f"config key '{name}' must be {spec.requirement}, got {value!r}")
        return x
    if spec.kind in ("vec", "float_or_vec"):
        if not isinstance(value, list):
            raise ConfigError(
                f"config key '{name}' must be a list of numbers, got {type(value).__name__} {value!r}"
            )
        xs = [_number(f"{name}[{i}]", v) for i, v in enumerate(value)]
        if not xs:
            raise ConfigError(f"config key '{name}' must not be empty")
        if spec.check is not None:
            for i, x in enumerate(xs):
                if not spec.check(x):
                    raise ConfigError(
                        f"config key '{name}' entries must be {spec.requirement}, "
                        f"got {name}[{i}] = {value[i]!r}"
                    )
        return xs
    raise AssertionError(spec.kind)  # pragma: no cover


# --------------------------------------------------------------------------- mapping
_TRAJ_KEYS = ("amplitude", "omega", "phase", "offset")


def law_gains(config: Mapping, law: str) -> dict:
    """The gains of `law` in `config`, by the names its registry entry declares
    (``ivdrem.laws``): the configuration keys ``Law.config`` names ("iv-drem" and "drem":
    T, p, F0, gamma, mixing of [iv_drem]; "composite-learning": T, gamma, epsilon of
    [composite_learning]; "sigma-modification": sigma, theta_star; "none": nothing), or for
    a user's law its defaults over-written by its own section.  ``closed_loop``'s
    ``gains``."""
    names = law_names()
    if law not in names:
        raise ConfigError(f"law {law!r} is not known" + _suggest(law, names) + "; valid laws: " + ", ".join(names))
    spec = get_law(law)
    if spec.config is not None:      # the configuration keys the law's registry entry names
        return {name: _argument(config[key.split(".")[0]][key.split(".")[1]])
                for name, key in spec.config.items()}
    # a user law (ivdrem.laws.register_law): its registry defaults, overridden by its own
    # configuration table if it has one
    table = config.get(spec.section, {}) if spec.section else {}
    return {k: (_argument(table[k]) if k in table else v) for k, v in spec.defaults.items()}


def closed_loop_kwargs(config: Mapping, law: str, model=None) -> dict:
    """The arguments of ``ivdrem.diagrams.closed_loop(law, model, **kwargs)`` for `config`
    (`model`: its model, already built; default :func:`model_from_config`, read only by
    the inertia-scaled design).  An :class:`~ivdrem.experiments.experiment.Experiment`
    calls it once per law (``LawSetup.configured``).

    The loop's own keywords: alpha, K (n×n; with ``design = "inertia-scaled"`` the joint
    gains over M̂_ii(q0), in 1/s), design and injection (when configured), delta_mu, Gamma
    (nθ×nθ), mu0, mu1, observer_variant, l, theta_hat0, q0, dq0, theta, trajectory,
    disturbance; and ``gains``, the law's (:func:`law_gains`).
    """
    gains = law_gains(config, law)
    c = config
    ctl = c["controller"]
    theta = np.asarray(c["model"]["theta"], dtype=float)
    ntheta = theta.size
    gam = ctl["Gamma"]
    if isinstance(gam, (list, tuple, np.ndarray)):
        Gamma = np.diag(np.asarray(gam, dtype=float))
    else:
        Gamma = float(gam) * np.eye(ntheta)
    kw: dict[str, Any] = {
        "alpha": float(ctl["alpha"]),
        "K": np.diag(np.asarray(ctl["K"], dtype=float)),
        "delta_mu": float(ctl["delta_mu"]),
        "Gamma": Gamma,
        "mu0": float(ctl["mu0"]),
        "mu1": float(ctl["mu1"]),
        "observer_variant": ctl["observer_variant"],
        "l": float(c["filters"]["l"]),
        "gains": gains,
    }
    kw.update(
        theta_hat0=np.asarray(c["initial"]["theta_hat0"], dtype=float),
        q0=np.asarray(c["initial"]["q0"], dtype=float),
        dq0=np.asarray(c["initial"]["dq0"], dtype=float),
        theta=theta,
        trajectory=_trajectory(c["trajectory"], len(c["initial"]["q0"])),
        disturbance={k: np.asarray(c["disturbance"][k], dtype=float) for k in _TRAJ_KEYS},
    )
    if "injection" in ctl:
        kw["injection"] = ctl["injection"]
    if "design" in ctl:
        kw["design"] = ctl["design"]
        if ctl["design"] == "inertia-scaled":     # K in 1/s: the joint gain over M̂_ii(q0)
            kw["K"] = np.diag(inertia_scaled_gain(model_from_config(c) if model is None
                                                  else model, ctl["K"], kw["q0"],
                                                  theta))
    return kw


def _argument(value):
    """A configuration value as closed_loop takes it: a vector as an array, a number as a
    float, a string ("auto", a mixing's name) as it is."""
    if isinstance(value, str):
        return value
    if isinstance(value, list):
        return np.asarray(value, dtype=float)
    return float(value)


def _trajectory(table: Mapping, n: int):
    """closed_loop's `trajectory`: the sinusoid's parameters, or the Fourier block."""
    if table.get("kind", "sinusoid") == "fourier":
        from ..blocks.sources import fourier_trajectory
        return fourier_trajectory(n, float(table["omega_f"]), np.asarray(table["a"], float),
                                  np.asarray(table["b"], float),
                                  np.asarray(table["offset"], float))
    return {k: np.asarray(table[k], dtype=float) for k in _TRAJ_KEYS}


def solver_kwargs(config: Mapping, law: str | None = None) -> dict:
    """Keyword arguments of the simulator: method, rtol, atol, h, h_max.

    With `law` given, ``h_max`` is also held to half the law's sliding window T (eq. 14):
    a step must not read the window's delay history beyond t (docs/simulation.md).  The
    paper's h_max = 5 s and T = 20 s are unchanged by it; a study that shortens T to 5 s
    runs with h_max = 2.5 s instead of being refused.
    """
    s = config["solver"]
    h_max = float(s["h_max"])
    if law is not None:
        window = law_gains(config, law).get("T")
        if window is not None:
            h_max = min(h_max, float(window) / 2)
    return {
        "method": s["method"],
        "rtol": float(s["rtol"]),
        "atol": float(s["atol"]),
        # an adaptive method's h is its first step: held under the step bound
        "h": float(s["h"]) if not method_info(s["method"]).adaptive
        else min(float(s["h"]), h_max),
        "h_max": h_max,
    }


# --------------------------------------------------------------------------- writing
def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (int, float, np.floating, np.integer)):
        return repr(float(v))
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def dump_toml(config: Mapping) -> str:
    """TOML text of a configuration; :func:`read_config` of it, resolved, gives the same dict."""
    lines = []
    for section, table in config.items():
        lines.append(f"[{section}]")
        for key, value in table.items():
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)
