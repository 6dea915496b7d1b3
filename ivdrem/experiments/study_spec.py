"""Study files: an experiment configuration plus a ``[study]`` table of varied keys.

A study file is an ordinary configuration (any key of ``examples/paper.toml``, merged over
the embedded default, or over ``base = "other.toml"`` given relative to the study file)
with a ``[study]`` table (see docs/studies.md)::

    [study.grid]                      # cartesian product of the lists
    "iv_drem.T" = [5.0, 10.0, 20.0]
    "disturbance.amplitude[0]" = [5.0, 7.5]   # one element of a vector key

    [study.random]                    # `samples` draws, reproducible from `seed`
    samples = 50
    seed = 1
    "disturbance.omega" = [{uniform = [0.5, 3.0]}, {loguniform = [0.05, 0.5]}]
    "iv_drem.gamma" = {loguniform = [1e8, 1e12]}
    "initial.q0[1]" = {normal = [0.94, 0.1]}
    "controller.observer_variant" = {choice = ["corrected", "literal"]}

Every grid point is combined with every random sample (the same draws for every grid
point), and each of those *points* is run once per law of ``experiment.laws`` (which may
itself be a grid key): one run = one closed loop, one law.

:func:`expand_study` turns a study into its list of :class:`RunSpec`, each with a complete,
validated configuration (``experiment.laws`` = [its law]) and the hash of what it reads (:func:`config_hash`),
which identifies it for ``--resume``.  Every run is validated before anything is simulated; errors are
:class:`StudyError` naming the run and the key, with the message of ``ivdrem paper --config``.

Random draws: each (key, element) has its own stream, ``numpy.random.default_rng([seed,
crc32(key)])``, so adding or reordering keys leaves the draws of the others unchanged, and
the same seed gives the same runs on any machine (with the same numpy version).
"""
from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .config import (ConfigError, closed_loop_kwargs, read_config, read_toml, solver_kwargs,
                     validate_config)


__all__ = ["StudyError", "StudySpec", "RunSpec", "DISTRIBUTIONS", "read_study", "expand_study",
           "config_hash"]

#: distributions of [study.random] and their parameters
DISTRIBUTIONS = ("uniform", "loguniform", "normal", "choice")

#: the most runs one study may have: each is a configuration held in memory and a record
#: on disk, so a mistyped sample count is refused before it fills the memory
MAX_RUNS = 100_000

_INDEXED = re.compile(r"^([A-Za-z_][\w]*)\.([A-Za-z_][\w]*)(?:\[(\d+)\])?$")


class StudyError(ConfigError):
    """An invalid study (raised before any run starts)."""


@dataclass(frozen=True)
class Dist:
    kind: str
    args: tuple

    def sample(self, rng: np.random.Generator, n: int) -> list:
        if self.kind == "uniform":
            return [float(v) for v in rng.uniform(self.args[0], self.args[1], n)]
        if self.kind == "loguniform":
            lo, hi = math.log(self.args[0]), math.log(self.args[1])
            return [float(math.exp(v)) for v in rng.uniform(lo, hi, n)]
        if self.kind == "normal":
            return [float(v) for v in rng.normal(self.args[0], self.args[1], n)]
        idx = rng.integers(0, len(self.args), n)
        return [copy.deepcopy(self.args[int(i)]) for i in idx]

    def text(self) -> str:
        return f"{self.kind}({', '.join(json.dumps(a) for a in self.args)})"


@dataclass
class StudySpec:
    """A parsed study: base configuration, grid and random dimensions."""
    source: str  # path of the study file, or "<dict>"
    base: dict  # validated configuration every run starts from
    grid: dict  # dotted key -> list of values (file order)
    random: dict  # dotted key -> Dist, or list of (Dist | fixed number) for a vector key
    samples: int = 0
    seed: int | None = None
    text: str = ""  # the study definition as TOML-ish text, for the report
    raw: dict = field(default_factory=dict)
    #: the base's model, built once (its Experiment's): the runs that keep the base's
    #: [model] are checked against it and carry it to their Experiment (in this process)
    model: Any = field(default=None, repr=False, compare=False)


@dataclass
class RunSpec:
    """One run of a study: one closed loop, one law."""
    index: int  # position in the study (row order of the results)
    point: int  # grid point x random sample; runs of one point differ only by law
    law: str
    sample: int | None  # random sample index (None without [study.random])
    values: dict  # varied column -> value ("iv_drem.T": 10.0, "disturbance.omega[0]": 1.2)
    config: dict  # complete validated configuration, experiment.laws == [law]
    hash: str
    #: the run's model when it is the base's (built once, :attr:`StudySpec.model`), else None
    model: Any = field(default=None, repr=False, compare=False)

    @property
    def label(self) -> str:
        parts = [f"{k} = {_short(v)}" for k, v in self.values.items() if k != "law"]
        if self.sample is not None:
            parts.append(f"sample {self.sample}")
        return f"run {self.index} ({', '.join(parts + [self.law])})"


def _short(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return json.dumps(v) if not isinstance(v, str) else v


def config_hash(config: Mapping, law: str, model=None) -> str:
    """Hash of everything one law's run reads from a configuration (identifies the run).

    That is the closed loop's arguments (``closed_loop_kwargs``; `model`: the
    configuration's, already built), the solver's (``solver_kwargs``), the model and the
    horizon: two runs that differ only in keys their law does not read (composite learning
    and ``iv_drem.T``) have the same hash.
    """
    def plain(v):
        if isinstance(v, np.ndarray):
            return v.tolist()
        if isinstance(v, Mapping):
            return {str(k): plain(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        return v

    loop = closed_loop_kwargs(config, law, model)
    loop.update(loop.pop("gains"))      # by name beside the loop's: hashes of earlier studies
    if not isinstance(loop["trajectory"], Mapping):
        # a Fourier reference is a block in closed_loop's arguments: hashed as its table
        loop["trajectory"] = dict(config["trajectory"])
    what = {
        "law": law,
        "model": config["model"],
        "experiment": {k: v for k, v in config["experiment"].items() if k != "laws"},
        "closed_loop": plain(loop),
        "solver": plain(solver_kwargs(config, law)),
    }
    text = json.dumps(what, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


# --------------------------------------------------------------------------- reading
def read_study(source) -> StudySpec:
    """Parse a study file (path) or dict; check the [study] table and the base config."""
    if isinstance(source, Mapping):
        raw = copy.deepcopy(dict(source))
        where, folder, text = "<dict>", Path.cwd(), None
    else:
        path = Path(source)
        raw, text = read_toml(path, "study file", StudyError)
        where, folder = str(path), path.resolve().parent
    study = raw.pop("study", None)
    if not isinstance(study, Mapping):
        raise StudyError(f"{where}: no [study] table (a study needs [study.grid] and/or [study.random])")
    unknown = set(study) - {"grid", "random"}
    if unknown:
        raise StudyError(f"{where}: unknown entries in [study]: {', '.join(sorted(unknown))}; "
                         "valid: [study.grid], [study.random]")
    base_path = raw.pop("base", None)
    if base_path is not None:
        if not isinstance(base_path, str):
            raise StudyError(f"{where}: 'base' must be a file name (string), got {base_path!r}")
        base_path = Path(base_path)
        if not base_path.is_absolute():
            base_path = folder / base_path
    from .experiment import Experiment
    try:     # the base resolved once: its model built, the keys that follow it filled
        # (its laws are resolved by each run's own Experiment)
        experiment = Experiment.from_config(read_config(base_path, overrides=raw or None),
                                            laws=[])
    except ConfigError as exc:
        raise StudyError(f"{where}: {exc}") from None
    base = experiment.config
    grid = _flatten(study.get("grid", {}), stop_at_dist=False)
    rand = dict(study.get("random", {}))
    samples, seed = rand.pop("samples", None), rand.pop("seed", None)
    rand = _flatten(rand, stop_at_dist=True)
    if not grid and not rand:
        raise StudyError(f"{where}: [study] varies nothing: give [study.grid] and/or [study.random] keys")
    spec = StudySpec(source=where, base=base, grid={}, random={}, text=text or _dict_text(source),
                     raw=copy.deepcopy(dict(source)) if isinstance(source, Mapping) else {},
                     model=experiment.model)
    for key, values in grid.items():
        _check_key(base, key, f"[study.grid] key '{key}'")
        if not isinstance(values, list):
            raise StudyError(f"[study.grid] key '{key}' must be a list of values, got {values!r}")
        if not values:
            raise StudyError(f"[study.grid] key '{key}' is an empty list: give at least one value")
        seen = []
        for v in values:
            if v in seen:
                raise StudyError(f"[study.grid] key '{key}' lists {v!r} twice")
            seen.append(v)
        spec.grid[key] = list(values)
    if rand:
        if samples is None:
            raise StudyError("[study.random] needs 'samples' (the number of draws)")
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise StudyError(f"[study.random] 'samples' must be an integer >= 1, got {samples!r}")
        if samples > MAX_RUNS:
            raise StudyError(f"[study.random] 'samples' = {samples} exceeds {MAX_RUNS} (the most "
                             "runs a study may have); split it into several studies")
        if seed is None:
            raise StudyError("[study.random] needs 'seed' (an integer >= 0), so that the draws "
                             "can be repeated")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise StudyError(f"[study.random] 'seed' must be an integer >= 0, got {seed!r}")
        spec.samples, spec.seed = samples, seed
    elif samples is not None or seed is not None:
        raise StudyError("[study.random] gives 'samples'/'seed' but no key to draw")
    for key, value in rand.items():
        name = f"[study.random] key '{key}'"
        _check_key(base, key, name)
        if key in spec.grid:
            raise StudyError(f"{name} is also a [study.grid] key")
        if isinstance(value, list):
            if _INDEXED.match(key).group(3) is not None:
                raise StudyError(f"{name}: an element takes one distribution, not a list")
            current = _get(base, key)
            if not isinstance(current, list):
                raise StudyError(f"{name}: the key is a number, give one distribution, not a list")
            if len(value) != len(current):
                raise StudyError(f"{name} gives {len(value)} entries, the configuration has "
                                 f"{len(current)} (one distribution or number per element)")
            spec.random[key] = [_dist(f"{name}[{i}]", v) if isinstance(v, Mapping) else
                                _fixed(f"{name}[{i}]", v) for i, v in enumerate(value)]
        else:
            spec.random[key] = _dist(name, value)
    for key in spec.grid:
        for other in list(spec.grid) + list(spec.random):
            if other != key and _base_key(other) == key:
                raise StudyError(f"study key '{other}' sets an element of '{key}', which is varied whole")
    for key in spec.random:
        for other in spec.random:
            if other != key and _base_key(other) == key:
                raise StudyError(f"study key '{other}' sets an element of '{key}', which is varied whole")
    return spec


def _dict_text(source) -> str:
    if isinstance(source, Mapping):
        return json.dumps(source, indent=2, default=str)
    return ""


def _flatten(table, *, stop_at_dist: bool = True) -> dict:
    """{"iv_drem": {"T": [...]}} (TOML's bare dotted keys) -> {"iv_drem.T": [...]}.

    Quoted keys ("iv_drem.T") are taken as they are; a bare key is a section whose
    entries are its keys.  Values are never looked into (a distribution is a table).
    """
    out = {}
    if not isinstance(table, Mapping):
        raise StudyError(f"[study.grid] and [study.random] must be tables, got {table!r}")
    for key, value in table.items():
        key = str(key)
        if "." in key or not isinstance(value, Mapping) or _is_dist(value):
            out[key] = value
        else:
            for sub, v in value.items():
                out[f"{key}.{sub}"] = v
    return out


def _is_dist(value) -> bool:
    return isinstance(value, Mapping) and len(value) == 1 and next(iter(value)) in DISTRIBUTIONS


def _base_key(key: str) -> str:
    return key.split("[", 1)[0]


def _check_key(base: dict, key: str, name: str) -> None:
    m = _INDEXED.match(key)
    if not m:
        raise StudyError(f"{name} is not a configuration key: write 'section.key' or "
                         "'section.key[i]' (e.g. 'iv_drem.T', 'disturbance.omega[0]')")
    section, sub, idx = m.group(1), m.group(2), m.group(3)
    if section not in base or sub not in base[section]:
        probe = copy.deepcopy(base)
        probe.setdefault(section, {})
        if isinstance(probe[section], dict):
            probe[section][sub] = None
        try:
            validate_config(probe)
        except ConfigError as exc:
            raise StudyError(f"{name}: {exc}") from None
        raise StudyError(f"{name}: not a configuration key")  # pragma: no cover
    if idx is not None:
        current = base[section][sub]
        if not isinstance(current, list):
            raise StudyError(f"{name}: '{section}.{sub}' is not a vector, it has no element [{idx}]")
        if int(idx) >= len(current):
            raise StudyError(f"{name}: '{section}.{sub}' has {len(current)} entries, "
                             f"no element [{idx}]")


def _get(cfg: dict, key: str):
    m = _INDEXED.match(key)
    v = cfg[m.group(1)][m.group(2)]
    return v if m.group(3) is None else v[int(m.group(3))]


def _set(cfg: dict, key: str, value) -> None:
    m = _INDEXED.match(key)
    section, sub, idx = m.group(1), m.group(2), m.group(3)
    if idx is None:
        cfg[section][sub] = copy.deepcopy(value)
    else:
        vec = list(cfg[section][sub])
        vec[int(idx)] = value
        cfg[section][sub] = vec


def _number(name: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise StudyError(f"{name}: expected a finite number, got {v!r}")
    return float(v)


def _fixed(name: str, v):
    _number(name, v)
    return float(v)


def _dist(name: str, value) -> Dist:
    if not _is_dist(value):
        raise StudyError(f"{name} must be one distribution, e.g. {{uniform = [a, b]}}; "
                         f"known: {', '.join(DISTRIBUTIONS)}; got {value!r}")
    kind, args = next(iter(value.items()))
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise StudyError(f"{name}: choice needs a non-empty list of values, got {args!r}")
        return Dist(kind, tuple(args))
    if not isinstance(args, list) or len(args) != 2:
        raise StudyError(f"{name}: {kind} needs two numbers [{'m, s' if kind == 'normal' else 'a, b'}], "
                         f"got {args!r}")
    a, b = (_number(f"{name}: {kind}", x) for x in args)
    if kind in ("uniform", "loguniform") and not a < b:
        raise StudyError(f"{name}: {kind} = [a, b] needs a < b, got a = {a:g}, b = {b:g}")
    if kind == "loguniform" and a <= 0:
        raise StudyError(f"{name}: loguniform = [a, b] needs 0 < a, got a = {a:g}")
    if kind == "normal" and not b > 0:
        raise StudyError(f"{name}: normal = [m, s] needs a standard deviation s > 0, got s = {b:g}")
    return Dist(kind, (a, b))


# --------------------------------------------------------------------------- expansion
def _draws(spec: StudySpec) -> list[dict]:
    """The random samples: list of {column: value}, one per sample."""
    if not spec.random:
        return [{}]
    cols: dict[str, list] = {}
    for key, dist in spec.random.items():
        if isinstance(dist, list):
            for i, d in enumerate(dist):
                if isinstance(d, Dist):
                    col = f"{key}[{i}]"
                    cols[col] = d.sample(_rng(spec.seed, col), spec.samples)
        else:
            cols[key] = dist.sample(_rng(spec.seed, key), spec.samples)
    return [{c: v[s] for c, v in cols.items()} for s in range(spec.samples)]


def _rng(seed: int, column: str) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(column.encode("utf-8"))])


def _columns(key: str, value) -> dict:
    """Varied columns of one value: a vector of numbers becomes key[0], key[1], ..."""
    if key == "experiment.laws":
        return {}
    if isinstance(value, list) and value and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                  for v in value):
        return {f"{key}[{i}]": float(v) for i, v in enumerate(value)}
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return {key: float(value)}
    return {key: value}


def expand_study(spec: StudySpec) -> list[RunSpec]:
    """Every run of a study, validated, in a fixed order (grid points, then samples, then laws).

    Raises :class:`StudyError` naming the first invalid run and key.
    """
    runs: list[RunSpec] = []
    grid_keys = list(spec.grid)
    n_points = math.prod(len(spec.grid[k]) for k in grid_keys) * max(spec.samples, 1)
    n_laws = len(spec.base["experiment"]["laws"])
    if n_points * n_laws > MAX_RUNS:   # refused before any configuration is built
        sizes = " x ".join([str(len(spec.grid[k])) for k in grid_keys]
                           + ([f"{spec.samples} samples"] if spec.random else []))
        raise StudyError(f"the study has {n_points * n_laws} runs ({sizes} points x {n_laws} "
                         f"law(s)); at most {MAX_RUNS} are allowed: split it into several studies")
    points = list(itertools.product(*(spec.grid[k] for k in grid_keys))) if grid_keys else [()]
    samples = _draws(spec)
    point = 0
    for gvals in points:
        for s, draw in enumerate(samples):
            cfg = copy.deepcopy(spec.base)
            values: dict[str, Any] = {}
            assigned = list(zip(grid_keys, gvals)) + list(draw.items())
            for key, value in assigned:
                _set(cfg, key, value)
                values.update(_columns(key, value))
            sample = s if spec.random else None
            where = _point_label(point, assigned, sample)
            # a point that keeps the base's [model] has the base's model (built once)
            model = spec.model if cfg["model"] == spec.base["model"] else None
            try:
                cfg = validate_config(cfg, model=model)
            except ConfigError as exc:
                raise StudyError(f"{where}: {exc}") from None
            for law in cfg["experiment"]["laws"]:
                run_cfg = copy.deepcopy(cfg)
                run_cfg["experiment"]["laws"] = [law]
                h = config_hash(run_cfg, law, model)
                r = RunSpec(index=len(runs), point=point, law=law, sample=sample,
                            values=dict(values), config=run_cfg, hash=h, model=model)
                # runs with the same configuration (a law that does not read a varied
                # key, a repeated draw of `choice`) are simulated once and share a record
                runs.append(r)
            point += 1
    return runs


def _point_label(point: int, assigned, sample) -> str:
    parts = [f"{k} = {_short(v)}" for k, v in assigned]
    if sample is not None:
        parts.append(f"sample {sample}")
    return f"study point {point} ({', '.join(parts)})"
