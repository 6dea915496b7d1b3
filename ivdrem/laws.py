"""One registry of adaptation laws: the composite terms ϑ_c of the adaptation law (11).

A :class:`Law` says everything the rest of ivdrem needs about one composite term, in one
place:

* ``name``: the key used by ``closed_loop(law, ...)``, the configuration
  (``experiment.laws``) and the command line (``--laws``);
* ``build(ctx)``: the blocks that compute ``theta_c`` (and their outputs worth recording),
  given a :class:`LawContext` (model, sizes and the law's parameters);
* ``defaults``: the law's default gains (keyword arguments of ``build``);
* ``section``: the configuration table holding those gains (``[iv_drem]``, ...), made
  from the registry alone: its keys are the numeric ``defaults``, with the type, range
  and configuration default that ``keys`` declares for a gain (:class:`Key`), so a TOML
  file sets the law's gains in ``[section]`` and a built-in law is configured like a
  user's;
* ``color`` and ``label``: the law's colour and legend label in every figure;
* ``equation``, ``description``: what the report and the docs say about it;
* ``sampled_code``: the law's code in the sampled controller's C library where it has a
  sampled form of its own (its step in ``ivdrem/controller/ivdrem_controller.c``; the
  header's ``IVC_LAW_<NAME>`` macros are generated from these codes), None where it has
  none; ``sampled_as``: the name of a law whose sampled step this law runs (its code), for
  a law that adds gains to another's step.

A gain's declaration (:class:`Key`) gives its type, range, configuration default, unit,
doc and whether it fixes the state's memory (``structural``); the configuration's
sections, the sampled controller's list of laws, law codes and parameter table are read
from here (:func:`sampled_laws`, :func:`law_codes`, :func:`sampled_gains`).

:func:`register_law` adds a user's law; ``closed_loop``, the configuration and the
figures then know it (see docs/custom-law.md and examples/custom_law.py).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from . import blocks as block_library
from ._config_keys import Key, base_unit, in_range, magnitude
from .blocks._kernels import MIXING_VARIANTS as _VARIANTS
from .blocks.mixing import start_of_term

__all__ = ["Law", "LawContext", "LAWS", "register_law", "get_law", "law_names",
           "sampled_laws", "law_codes", "sampled_step", "sampled_gains",
           "sampled_gain_defaults", "gain_declaration",
           "mixed_regression_blocks", "MIXING_VARIANTS", "default_mixing", "is_paper_arm",
           "Key", "base_unit", "in_range", "magnitude"]


@dataclass
class LawContext:
    """What a law's ``build`` receives: the model, its sizes and the law's parameters.

    ``params`` holds the law's gains (its ``defaults`` overridden by the caller) and the
    loop's shared values ``l`` (filter gain of (13)).
    """
    model: object
    n: int
    ntheta: int
    params: dict


@dataclass(frozen=True)
class Law:
    """A law of the registry: how `closed_loop` builds its composite term ϑ_c, its gains
    and their configuration table, and how the figures show it.

    ``build(ctx)`` returns the blocks computing ``theta_c`` (and extra recorded outputs);
    ``label``, ``color`` and ``equation`` are used by the report; ``section`` and
    ``defaults`` make the law's table of the configuration.  Register one with
    :func:`register_law`.
    """
    name: str
    build: Callable[[LawContext], tuple]   # ctx -> (blocks, extra recorded outputs)
    label: str
    color: str
    equation: str = ""
    description: str = ""
    section: str | None = None             # configuration table of the gains
    defaults: dict = field(default_factory=dict)
    # {closed_loop keyword: configuration key "section.key"} that the law's run reads; None:
    # a user's law, whose gains are its section's keys (its defaults) passed in gains={...}
    config: dict | None = None
    # {key: Key} of `section`: a gain's type, range and default in the configuration; a
    # numeric default not declared here is checked as a number or a vector only
    keys: dict | None = None
    uses_delta: bool = False               # has the mixed regression (17): Delta, calY
    instrument: str | None = None          # recorded instrument signal (zeta or phi)
    linestyle: str = "-"                   # with the colour: five laws told apart in grey too
    # the law's code in the sampled controller (its C library's parameter ``law``); None: no
    # sampled form of its own.  A sampled form is C code of ivdrem_controller.c (ivc_step)
    # and its Python reference (SampledController.step): built-in laws only
    sampled_code: int | None = None
    # the name of a law whose sampled step this law runs (that law's code): the law's own
    # gains then ride in the controller's parameter vector, read by no step until one does
    sampled_as: str | None = None

    @property
    def windowed(self) -> bool:
        """The law keeps a sliding window T of (15a) (the sampled controller's block sums)."""
        return "T" in self.defaults

    @property
    def max_hold(self) -> bool:
        """A window without the mixing step (17): composite learning's max-hold of
        λ_min(Ψ_b) (35), in place of the averaging (15b)."""
        return self.windowed and not self.uses_delta


#: the registry, in report order
LAWS: dict[str, Law] = {}


def register_law(law: Law, *, replace: bool = False) -> Law:
    """Add ``law`` to the registry (``replace=True`` to redefine an existing name)."""
    if not isinstance(law, Law):
        raise TypeError(f"register_law expects an ivdrem.laws.Law, got {type(law).__name__}")
    if not law.name or not isinstance(law.name, str):
        raise ValueError("a law needs a non-empty string name")
    if law.name in LAWS and not replace:
        raise ValueError(f"law {law.name!r} is already registered (pass replace=True)")
    if law.sampled_as is not None:
        owner = LAWS.get(law.sampled_as)
        if law.sampled_code is not None or owner is None or owner.sampled_code is None:
            raise ValueError(f"law {law.name!r}: sampled_as {law.sampled_as!r} must name a "
                             "registered law with a sampled step of its own (sampled_code), "
                             "and then the law has no sampled_code; laws with a step: "
                             + ", ".join(n for n, o in LAWS.items() if o.sampled_code is not None))
    if law.sampled_code is not None:
        taken = {o.sampled_code: o.name for o in LAWS.values() if o.name != law.name}
        if not isinstance(law.sampled_code, int) or law.sampled_code < 0 \
                or law.sampled_code in taken:
            raise ValueError(f"law {law.name!r}: sampled_code {law.sampled_code!r} must be a "
                             "whole number >= 0 that no other law has"
                             + (f" ({taken[law.sampled_code]!r} has it)"
                                if law.sampled_code in taken else ""))
    if law.keys is not None:
        if not law.section:
            raise ValueError(f"law {law.name!r} declares keys but no section to hold them")
        for k, spec in law.keys.items():
            if not isinstance(spec, Key):
                raise TypeError(f"law {law.name!r}: key {k!r} must be an ivdrem.laws.Key, "
                                f"got {type(spec).__name__}")
            if spec.default is None and law.defaults.get(k) is None:
                raise ValueError(f"law {law.name!r}: key {k!r} of [{law.section}] has no "
                                 "default (in the law's defaults or the Key's default)")
    LAWS[law.name] = law
    return law


def get_law(name: str) -> Law:
    """The registered :class:`Law` called `name`; a ValueError names the known laws."""
    try:
        return LAWS[name]
    except KeyError:
        raise ValueError(f"unknown law {name!r}; choose one of {', '.join(LAWS)}") from None


def law_names() -> tuple[str, ...]:
    """Names of the registered laws, in registration order (the built-in five first)."""
    return tuple(LAWS)


def sampled_step(name: str) -> str:
    """The name of the law whose sampled step runs law `name`: its own where it has a
    ``sampled_code``, the law it names in ``sampled_as``; a ValueError where it has none."""
    law = get_law(name)
    if law.sampled_as is not None:
        return law.sampled_as
    if law.sampled_code is None:
        raise ValueError(f"law {name!r} has no sampled form; choose one of "
                         f"{', '.join(sampled_laws())}")
    return name


def sampled_laws() -> tuple[str, ...]:
    """Names of the laws with a sampled form (the sampled controller, its C library and
    FMU): their own step or another's (``sampled_as``), in the order of their codes."""
    return tuple(sorted((n for n, law in LAWS.items()
                         if law.sampled_code is not None or law.sampled_as in LAWS),
                        key=lambda n: LAWS[sampled_step(n)].sampled_code))


def law_codes() -> dict[str, int]:
    """{law name: code} of the laws with a sampled form (the C library's ``law``
    parameter and its ``IVC_LAW_<NAME>`` macros: name upper-cased, ``-`` as ``_``); a law
    that runs another's step (``sampled_as``) has that law's code."""
    return {n: LAWS[sampled_step(n)].sampled_code for n in sampled_laws()}


def gain_declaration(name: str) -> tuple[str, str]:
    """(unit, doc) of gain `name` as the laws with a sampled form declare it (:class:`Key`):
    their docs joined in code order where laws declare it differently (γ of (21) or (35));
    a ValueError where no such law declares it."""
    keys = [LAWS[n].keys[name] for n in sampled_laws() if name in (LAWS[n].keys or {})]
    if not keys:
        raise ValueError(f"no law with a sampled form declares the gain {name!r}")
    units = {k.unit for k in keys}
    if len(units) > 1:
        raise ValueError(f"the laws declare gain {name!r} in different units {sorted(units)}")
    docs = list(dict.fromkeys(k.doc for k in keys if k.doc))
    if len(docs) > 1:            # "gain gamma of (21)", "gain gamma of (35)": "... (21) or (35)"
        head = os.path.commonprefix(docs)
        head = head[:head.rfind(" ") + 1]
        return keys[0].unit, head + " or ".join(d[len(head):] for d in docs)
    return keys[0].unit, "".join(docs)


#: the kinds of a gain the sampled controller's parameter vector holds as numbers (a
#: choice, "str", is a coded entry of its own: the mixing)
NUMERIC_KINDS = ("float", "float_or_auto", "vec")


def sampled_gains() -> dict:
    """{gain: :class:`Key`} of every numeric gain a law with a sampled form declares, in
    code order (the first law's declaration where several declare it): the entries of the
    sampled controller's parameter vector that belong to the laws.  A law with a sampled
    form that leaves a gain undeclared (no ``keys`` entry: no unit, doc or size) is refused
    here, naming it."""
    out = {}
    for name in sampled_laws():
        law = LAWS[name]
        for k in law.defaults:
            key = (law.keys or {}).get(k)
            if key is None:
                raise ValueError(f"law {name!r} has a sampled form but does not declare its "
                                 f"gain {k!r} (keys={{{k!r}: Key(...)}}: kind, unit, doc)")
            if key.kind in NUMERIC_KINDS:
                out.setdefault(k, key)
    return out


def sampled_gain_defaults() -> dict:
    """Every gain of a law with a sampled form, at the first such law's default (in code
    order): the sampled controller's parameter vector holds them all, whichever law runs."""
    out = {}
    for name in sampled_laws():
        for k, v in LAWS[name].defaults.items():
            out.setdefault(k, v)
    return out


# --------------------------------------------------------------------------- built-in laws
def mixed_regression_blocks(ctx: LawContext, *, instrument: bool = True):
    """The blocks that produce the scalar regressions 𝒴_i = Δθ_i + 𝒲_i (17): regression
    filters (13), [instrument (14)], extension (15a) over a window T (``params["T"]``),
    averaging (15b) (``p``, ``F0``) and mixing (``mixing``: "paper", "eigen" or "channel",
    docs/mixing.md).  Outputs Delta (one, or one per channel), calY for a composite term
    to use; returns (blocks, recorded outputs).  A user law built on (17) starts here."""
    model, n, nth, p = ctx.model, ctx.n, ctx.ntheta, ctx.params
    m = nth + nth * nth
    blocks = [block_library.regression_filter(model, p["l"])]
    if instrument:
        blocks.append(block_library.instrument(model, p["l"]))
    blocks += [block_library.extension(n, nth, instrument=instrument),
               *block_library.windowed_integral(m, p["T"]),
               block_library.averaging(m, p["p"], p["F0"]),
               block_library.mixing(nth, p.get("mixing") or "paper")]
    # z, phi (and zeta) are recorded so that the diagnostics can form w = z - phi^T theta
    # (13), the excitation of (18) and the products of (19) offline
    outputs = ["Delta", "Delta_log10", "calY", "z", "phi"] + (["zeta"] if instrument else [])
    return blocks, outputs


def _drem_blocks(ctx: LawContext, *, iv: bool):
    """(17) and the composite term (21); one Δ_i and γ_i per channel for the "channel"
    mixing (docs/mixing.md)."""
    blocks, outputs = mixed_regression_blocks(ctx, instrument=iv)
    mixing = ctx.params.get("mixing") or "paper"
    t_on, t_ramp = start_of_term(mixing, ctx.params["T"])
    start = block_library.term_start(ctx.params.get("t_on", t_on),
                                     ctx.params.get("t_ramp", t_ramp))
    if mixing == "channel":
        term = block_library.drem_channel_term(ctx.ntheta, ctx.params["gamma"])
    else:
        term = block_library.drem_term(ctx.ntheta, ctx.params["gamma"])
    return blocks + [start, term], outputs


def _build_iv_drem(ctx):
    return _drem_blocks(ctx, iv=True)


def _build_drem(ctx):
    return _drem_blocks(ctx, iv=False)


def _build_composite_learning(ctx):
    model, n, nth, p = ctx.model, ctx.n, ctx.ntheta, ctx.params
    m = nth + nth * nth
    blocks = [block_library.regression_filter(model, p["l"]),
              block_library.extension(n, nth, instrument=False),
              *block_library.windowed_integral(m, p["T"]),
              block_library.max_hold(nth, nth, p["epsilon"]),
              block_library.composite_learning_term(nth, p["gamma"])]
    return blocks, ["lambda_min_held"]


def _build_sigma(ctx):
    ts = ctx.params.get("theta_star")
    if ts is None:
        ts = ctx.model.theta_values
    return [block_library.sigma_modification_term(ctx.ntheta, ctx.params["sigma"], ts)], []


def _build_none(ctx):
    return [block_library.zero_term(ctx.ntheta)], []


#: the gains of [iv_drem], shared by "iv-drem" and "drem": window T of (15a), averaging p,
#: F0 of (15b), γ of (21) (the paper's 1e10) and the mixing of (17) (docs/mixing.md)
_IV_DREM_DEFAULTS = dict(T=20.0, p=2.0, F0=1.0, gamma=1e10, mixing="paper")

#: the largest gain the configuration accepts: the paper's γ is 1e10; 1e300 overflows Δ·γ at
#: the first step
GAIN_MAX = 1e12
#: a sliding window T of (15a) or of composite learning's integrals: h_max follows T/2
_WINDOW = Key("float", **in_range(2e-6, 1e6, "h_max follows T/2, at least 1e-06 s"),
               unit="s", doc="window length T of (15a) (s)", structural=True)

#: the configuration keys of [iv_drem] with their ranges; on any arm but the paper's the
#: mixing and γ follow the model, as in closed_loop
_IV_DREM_KEYS = {
    "T": _WINDOW,
    "p": Key("float", check=lambda x: 1 <= x <= 1e3, requirement=">= 1 and <= 1000",
             doc="averaging F(t) = t^p + F0 (15b)"),
    "F0": Key("float", **in_range(0, GAIN_MAX, open_lo=True),
              doc="averaging F0 > 0 (erratum E3)"),
    # the paper's mixing on a large arm needs gamma of order 1/mean(Delta^2) (UR5: 9e119,
    # docs/mixing.md), so only the bound of gamma = "auto" applies
    "gamma": Key("float_or_auto", check=lambda x: 0 < x < 1e300,
                 requirement="> 0 and below 1e300 (the bound of gamma = 'auto')",
                 follow=lambda m: "auto", doc="gain gamma of the composite term (21)"),
    "mixing": Key("str", choices=_VARIANTS, follow=lambda m: default_mixing(m),
                  doc="mixing (17): paper, eigen or channel (docs/mixing.md)"),
}
#: [composite_learning]: window T, γ of (35) and the max-hold's threshold ε
_COMPOSITE_LEARNING_KEYS = {
    "T": _WINDOW,
    "gamma": Key("float", **in_range(0, GAIN_MAX, open_lo=True),
                 doc="gain gamma of the composite term (35)"),
    "epsilon": Key("float", **in_range(0, 1e6, open_lo=True),
                   doc="composite learning: threshold of lambda_min"),
}
#: [sigma_modification]: σ and θ* of ϑ_c = σ(θ* − θ̂) (erratum E5); the configuration's θ*
#: is a guess for the paper's arm (zeros on any other), closed_loop's the model's own θ
_SIGMA_MODIFICATION_KEYS = {
    "sigma": Key("float", **in_range(0, 1e6, "sigma = 0 is the law 'none'", open_lo=True),
                 doc="sigma-modification gain (erratum E5)"),
    "theta_star": Key("vec", "ntheta", **magnitude(1e6, "as model.theta"),
                      default=(1.0, 0.2, 0.3, 0.3, 1.0), follow=lambda m: [0.0] * m.ntheta,
                      doc="sigma-modification prior theta*"),
}


def _keys(section, names):
    return {name: f"{section}.{name}" for name in names}


_IV_DREM_CONFIG = _keys("iv_drem", _IV_DREM_KEYS)

for _law in (
    Law("iv-drem", _build_iv_drem, "IV-DREM, (11)+(21)", "#0072B2", "eqs. (11) + (21)",
        "proposed: instrumental-variables DREM, ζ from the reference trajectory (14)",
        section="iv_drem", defaults=dict(_IV_DREM_DEFAULTS), config=_IV_DREM_CONFIG,
        keys=_IV_DREM_KEYS, uses_delta=True, instrument="zeta", sampled_code=0),
    Law("composite-learning", _build_composite_learning, "composite learning, (35)", "#E69F00",
        "eq. (35)", "baseline of Pan & Yu: max-held window integrals of φ",
        section="composite_learning", defaults=dict(T=20.0, gamma=1.0, epsilon=1e-9),
        config=_keys("composite_learning", _COMPOSITE_LEARNING_KEYS),
        keys=_COMPOSITE_LEARNING_KEYS, sampled_code=1),
    Law("drem", _build_drem, "DREM without IV", "#009E73", "eqs. (11) + (21), ζ := φ",
        "DREM with the measured regressor φ in place of the instrument",
        section="iv_drem", defaults=dict(_IV_DREM_DEFAULTS), config=_IV_DREM_CONFIG,
        keys=_IV_DREM_KEYS, uses_delta=True, instrument="phi", linestyle="--",
        sampled_code=2),
    Law("sigma-modification", _build_sigma, "σ-modification", "#D55E00",
        "ϑ_c = σ(θ* − θ̂) (erratum E5)", "leakage toward a prior guess θ*",
        section="sigma_modification", defaults=dict(sigma=0.1, theta_star=None),
        config=_keys("sigma_modification", _SIGMA_MODIFICATION_KEYS),
        keys=_SIGMA_MODIFICATION_KEYS, linestyle="-.", sampled_code=3),
    Law("none", _build_none, "no composite term", "#000000", "ϑ_c = 0",
        "plain disturbance-rejection adaptive control", config={}, linestyle=":",
        sampled_code=4),
):
    register_law(_law)
del _law


#: the mixing variants of (17) (ivdrem.blocks.mixing, docs/mixing.md)
MIXING_VARIANTS = _VARIANTS
#: the paper's arm keeps the paper's mixing; every other arm gets this one by default
DEFAULT_MIXING_OTHER_ARMS = "eigen"


def is_paper_arm(model) -> bool:
    """The paper's 2-link arm (its experiment and γ = 1e10 are the paper's)."""
    return getattr(model, "name", None) == "two-link" and getattr(model, "n", None) == 2


def default_mixing(model) -> str:
    """The mixing of (17) that works at this model's size: the paper's for its own arm,
    DEFAULT_MIXING_OTHER_ARMS otherwise (measured in docs/mixing.md)."""
    return "paper" if is_paper_arm(model) else DEFAULT_MIXING_OTHER_ARMS


def arm_gain_rule(law: Law, model, gamma=None, mixing=None) -> tuple:
    """(gamma, mixing) of `law` on `model` as closed_loop takes them: on every arm but the
    paper's, a law with the mixing step (17) left at None gets the mixing that works at the
    arm's size and γ "auto" (γ of (21) from a calibration run, docs/mixing.md)."""
    if "mixing" in law.defaults and not is_paper_arm(model):
        mixing = default_mixing(model) if mixing is None else mixing
        gamma = "auto" if gamma is None and "gamma" in law.defaults else gamma
    return gamma, mixing


def resolve_params(law: Law, given: dict) -> dict:
    """The law's defaults overridden by the non-None entries of ``given``."""
    out = dict(law.defaults)
    for k, v in given.items():
        if v is not None:
            out[k] = v
    return out


def as_array(v):
    return None if v is None else np.asarray(v, dtype=float)
