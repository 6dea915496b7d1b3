"""The sampled controller's parameter vector, declared once: one table of its entries (name,
size, unit, doc, tunable between steps, structural), from which the C library's header
(``IVC_P_<NAME>``, ``IVC_PAR_DEFAULTS``), the vector of a
:class:`~ivdrem.controller.sampled.SampledController`, the controller of a vector
(:class:`~ivdrem.controller.clib.CController.from_params`, an FMU's start values) and the
controller FMU's parameters are made.

The laws' gains are not written here: their entries are made from the law registry each
time the table is read (:func:`ivdrem.laws.sampled_gains`: every numeric gain a law with a
sampled form declares, its size, unit, doc and whether it is structural from its
:class:`~ivdrem.laws.Key`), so a law registered later, with a gain of its own, has it in
the vector, the C header and the FMU without an edit here.  The law codes are the
registry's (:func:`ivdrem.laws.law_codes`), the other codes the positions in the
enumerations the Python controller validates against.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..blocks._kernels import MIXING_VARIANTS
from ..blocks.control_law import DESIGNS, INJECTIONS
from ..laws import gain_declaration, law_codes, sampled_gains
from .sampled import GRAVITY_OPTIONS, REFERENCE_HARMONICS

__all__ = ["Parameter", "PARAMETERS", "parameter_table", "param_layout", "param_vector",
           "controller_arguments", "TUNABLE", "STRUCTURAL", "DESIGN_CODES", "GRAVITY_CODES",
           "MIXING_CODES", "INJECTION_CODES"]


def _codes(names):
    return {name: i for i, name in enumerate(names)}


#: design name -> code of the parameter ``design`` (docs/controller.md, "Sampled designs")
DESIGN_CODES = _codes(DESIGNS)
#: gravity option -> code of the parameter ``gravity`` ("robot": the robot adds ĝ(q) itself)
GRAVITY_CODES = _codes(GRAVITY_OPTIONS)
#: mixing variant -> code of the parameter ``mixing`` (ivdrem.blocks._kernels.MIXING_VARIANTS)
MIXING_CODES = _codes(MIXING_VARIANTS)
#: the observer's injection -> code of the parameter ``injection``
INJECTION_CODES = _codes(INJECTIONS)


@dataclass(frozen=True)
class Parameter:
    """One entry of the parameter vector.

    ``size``: "1", "n", "ntheta", "n*n" or "n*H" (H = REFERENCE_HARMONICS); ``value(ctrl)``:
    its value(s) in a SampledController; ``argument(v, n)``: {SampledController keyword:
    value} of its entries ``v`` (None: read apart, the law); a keyword ``trajectory.X`` is
    entry X of the trajectory.  ``doc`` None: a law's gain, its unit and doc from the law
    registry; a function: the doc made when asked (the law codes, from the registry).  ``tunable``: a host may change it between steps; ``structural``: it fixes the
    memory or the meaning of the state (set before ivc_init); ``hidden`` in the FMU.
    """
    name: str
    size: str
    value: Callable[[Any], Any]
    argument: Callable[[np.ndarray, int], dict] | None
    doc: str | Callable[[], str] | None = None
    unit: str = ""
    tunable: bool = False
    structural: bool = False
    hidden: bool = False

    def length(self, n: int, ntheta: int) -> int:
        return {"1": 1, "n": n, "ntheta": ntheta, "n*n": n * n,
                "n*H": n * REFERENCE_HARMONICS}[self.size]

    def declared(self) -> tuple[str, str]:
        """(unit, doc): the table's, or for a law's gain the registry's."""
        if self.doc is None:
            return gain_declaration(self.name)
        return self.unit, self.doc() if callable(self.doc) else self.doc


def _number(key, cast=float):
    return lambda v, n: {key: cast(v[0])}


def _vector(key):
    return lambda v, n: {key: v.copy()}


def _code(key, codes):
    names = {c: name for name, c in codes.items()}
    return lambda v, n: {key: names[int(v[0])]}


def _gain(name, key):
    """A law's gain, from its registry declaration: a number, or a vector of the Key's
    length ("n" or "ntheta"); unit and doc from the registry; structural where the Key
    says it fixes the state's memory, tunable otherwise."""
    size = "1" if key.kind != "vec" else key.length
    if size not in ("1", "n", "ntheta"):
        raise ValueError(f"gain {name!r}: a vector gain of the sampled controller has "
                         f"length 'n' or 'ntheta', not {key.length!r}")
    arg = _number(name) if size == "1" else _vector(name)
    return Parameter(name, size, lambda c: c.gains[name], arg, doc=None,
                     tunable=not key.structural, structural=key.structural)


P = Parameter
#: the entries before the laws' gains
_HEAD = (
    P("h", "1", lambda c: c.h, _number("h"), "sample period (s)", unit="s", structural=True),
    P("alpha", "1", lambda c: c.alpha, _number("alpha"),
      "tracking error filter alpha: r = de + alpha e", tunable=True),
    P("K", "n*n", lambda c: c.K.reshape(-1), lambda v, n: {"K": v.reshape(n, n)},
      "feedback gain K (n x n, row major), control law (9)", tunable=True),
    P("delta_mu", "1", lambda c: c.delta_mu, _number("delta_mu"),
      "delta_mu in (0, 1), control law (9)", tunable=True),
    P("Gamma_diag", "ntheta", lambda c: c.Gamma, _vector("Gamma"),
      "adaptation gain Gamma (diagonal), (11)", tunable=True),
    P("mu0", "1", lambda c: c.mu0, _number("mu0"), "mu(t) = min(mu0 t + mu1, mu_max)",
      tunable=True),
    P("mu1", "1", lambda c: c.mu1, _number("mu1"), "mu(0) > 0", tunable=True),
    P("mu_max", "1", lambda c: c.mu_max, _number("mu_max"),
      "saturation of mu (docs/controller.md)", tunable=True),
    P("l", "1", lambda c: c.l, _number("l"), "filter gain l of (13), (14)", tunable=True),
)
#: the entries after the laws' gains
_TAIL = (
    P("theta_hat0", "ntheta", lambda c: c.theta_hat0, _vector("theta_hat0"),
      "initial estimate theta_hat(0)"),
    P("tau_max", "n", lambda c: c.tau_max, _vector("tau_max"),
      "torque limit |tau_i| <= tau_max_i of the command (N m; inf: none)", tunable=True),
    P("delay", "1", lambda c: c.delay, _number("delay", int),
      "0: tau_k applied over [t_k, t_k+1]; 1: over [t_k+1, t_k+2]", structural=True,
      hidden=True),
    P("block", "1", lambda c: c.block, _number("block", int),
      "samples per block sum of the window", structural=True),
    P("law", "1", lambda c: law_codes()[c.law], None,
      lambda: ", ".join(f"{code} {name}" for name, code in law_codes().items()),
      structural=True),
    P("corrected", "1", lambda c: 1.0 if c.corrected else 0.0,
      lambda v, n: {"observer_variant": "corrected" if v[0] else "literal"},
      "1: observer gain mu + dmu/mu for Phi_Mf (erratum E1); 0: mu", structural=True),
    P("tr_amplitude", "n", lambda c: c.tr_A, _vector("trajectory.amplitude"),
      "reference q_d = A sin(w t + phi) + c: A"),
    P("tr_omega", "n", lambda c: c.tr_w, _vector("trajectory.omega"), "reference: w (rad/s)"),
    P("tr_phase", "n", lambda c: c.tr_phi, _vector("trajectory.phase"), "reference: phi"),
    P("tr_offset", "n", lambda c: c.tr_c, _vector("trajectory.offset"),
      "reference: c (also the Fourier reference's offset)"),
    P("design", "1", lambda c: DESIGN_CODES[c.design], _code("design", DESIGN_CODES),
      "0 paper: feedback (K + delta_mu mu) r of (9); 1 inertia-scaled: "
      "M(q, theta_nominal)(K + delta_mu mu) r, K in 1/s", structural=True),
    P("mixing", "1", lambda c: MIXING_CODES[c.mixing], _code("mixing", MIXING_CODES),
      "mixing (17): 0 paper, 1 eigen, 2 channel (docs/mixing.md)", structural=True),
    P("mix_every", "1", lambda c: c.mix_every, _number("mix_every", int),
      "the mixing (17), or composite learning's max-hold of (35), every m samples "
      "(multi-rate, m > 1: held or decided one period later, its work spread over the "
      "period)", structural=True),
    P("f_rel", "1", lambda c: c.f_rel, _number("f_rel"), "eigen mixing: f0 = f_rel ||Psi||_F"),
    P("guard", "1", lambda c: c.guard, _number("guard"),
      "channel mixing: guard of the (i, i) cofactor"),
    P("gravity", "1", lambda c: GRAVITY_CODES[c.gravity], _code("gravity", GRAVITY_CODES),
      "0: the law's tau is commanded; 1 robot: tau - G(q, theta_nominal) (the robot adds "
      "its own gravity)", structural=True),
    P("theta_nominal", "ntheta", lambda c: c.theta_nominal, _vector("theta_nominal"),
      "nominal parameters (the URDF's): inertia-scaled design, gravity robot"),
    P("tau_rate_max", "n", lambda c: c.tau_rate_max, _vector("tau_rate_max"),
      "rate limit |tau_k,i - tau_k-1,i| <= h tau_rate_max_i (N m/s; inf: none)"),
    P("first_zero", "1", lambda c: 1.0 if c.first_zero else 0.0,
      lambda v, n: {"first_zero": bool(v[0])}, "1: the first command tau_0 is 0"),
    P("ref_kind", "1", lambda c: 1.0 if c.fourier else 0.0,
      lambda v, n: {"trajectory.kind": "fourier" if v[0] else "sinusoid"},
      "reference: 0 the sinusoid tr_*, 1 the Fourier series fr_*", structural=True),
    P("fr_omega_f", "1", lambda c: c.fr_wf, _number("trajectory.omega_f"),
      "Fourier reference: base frequency omega_f (rad/s)"),
    P("fr_a", "n*H", lambda c: c.fr_a.reshape(-1),
      lambda v, n: {"trajectory.a": v.reshape(n, -1)},
      "Fourier reference: a (n x H, row major): q_d,i = c_i + sum_l (a_il sin(l w t) - "
      "b_il cos(l w t))/(l w)"),
    P("fr_b", "n*H", lambda c: c.fr_b.reshape(-1),
      lambda v, n: {"trajectory.b": v.reshape(n, -1)},
      "Fourier reference: b (n x H, row major)"),
    P("injection", "1", lambda c: INJECTION_CODES[c.injection],
      _code("injection", INJECTION_CODES),
      "the observer's injection mu (Phi_M^T(q, r) - Phi_Mf^T) theta of (8) at 0 theta_hat "
      "(the paper's), 1 theta_nominal (adaptation (11) with Phi^T - Phi_f^T)"),
)
del P


def parameter_table() -> tuple:
    """The parameter vector's entries, in order (the C library's IVC_P_<NAME> indices):
    the controller's own, then every gain of the laws with a sampled form as the registry
    declares them now (:func:`ivdrem.laws.sampled_gains`), then the rest.  A gain whose
    name an entry of the table already has (e.g. the coded ``mixing``) is refused."""
    gains = tuple(_gain(name, key) for name, key in sampled_gains().items())
    table = _HEAD + gains + _TAIL
    own = {p.name for p in _HEAD + _TAIL}
    clash = sorted(own & {p.name for p in gains})
    if clash:
        raise ValueError(f"law gain(s) {clash} have the name of an entry of the sampled "
                         "controller's parameter table; rename the gain")
    return table


class _FromTable(Sequence):
    """A tuple read from :func:`parameter_table` each time it is used, so that it follows
    the law registry (a law registered after this module's import included)."""

    def __init__(self, pick):
        self._pick = pick

    def _now(self):
        return self._pick(parameter_table())

    def __getitem__(self, i):
        return self._now()[i]

    def __len__(self):
        return len(self._now())

    def __iter__(self):
        return iter(self._now())

    def __eq__(self, other):
        return tuple(self) == tuple(other)

    def __repr__(self):
        return repr(self._now())


#: the parameter vector, in order (the C library's IVC_P_<NAME> indices): the table as the
#: registry makes it when read (:func:`parameter_table`)
PARAMETERS = _FromTable(lambda table: table)
#: parameters a host may change between steps
TUNABLE = _FromTable(lambda table: tuple(p.name for p in table if p.tunable))
#: parameters that fix the memory or the meaning of the state (set before ivc_init)
STRUCTURAL = _FromTable(lambda table: tuple(p.name for p in table if p.structural))
#: the entries of a trajectory of each kind (ivdrem.controller.sampled)
_TRAJECTORY = {"sinusoid": ("amplitude", "omega", "phase", "offset"),
               "fourier": ("kind", "omega_f", "a", "b", "offset")}


def param_layout(model):
    """[(name, size, description)] of the flat parameter vector, in order."""
    return [(p.name, p.length(model.n, model.ntheta), p.declared()[1])
            for p in parameter_table()]


def param_vector(ctrl):
    """The flat parameter vector of a :class:`~ivdrem.controller.sampled.SampledController`."""
    out = []
    for p in parameter_table():
        v = np.atleast_1d(np.asarray(p.value(ctrl), dtype=float)).reshape(-1)
        assert v.size == p.length(ctrl.n, ctrl.ntheta), p.name
        out.extend(v.tolist())
    return np.array(out)


def controller_arguments(model, law, par) -> dict:
    """The keyword arguments of the SampledController (law `law`) whose parameter vector is
    `par` (ivdrem_controller.h's layout, e.g. a controller FMU's start values); a
    ValueError where its size or its law code does not match."""
    par = np.asarray(par, dtype=float).reshape(-1)
    n, nth = model.n, model.ntheta
    table = parameter_table()
    total = sum(p.length(n, nth) for p in table)
    codes = law_codes()
    off = [p.name for p in table].index("law")
    at = sum(p.length(n, nth) for p in table[:off])
    if par.size != total or law not in codes or codes[law] != par[at]:
        raise ValueError(f"parameter vector of {par.size} entries (expected {total}) or "
                         f"law code does not match {law!r}")
    kwargs, trajectory, i = {}, {}, 0
    for p in table:
        v = par[i:i + p.length(n, nth)]
        i += v.size
        for key, value in (p.argument(v, n) if p.argument else {}).items():
            if key.startswith("trajectory."):
                trajectory[key.split(".", 1)[1]] = value
            else:
                kwargs[key] = value
    kind = trajectory["kind"]
    kwargs["trajectory"] = {k: trajectory[k] for k in _TRAJECTORY[kind] if k != "kind"}
    if kind == "fourier":
        kwargs["trajectory"]["kind"] = kind
    return kwargs
