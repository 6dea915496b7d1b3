"""The sampled controller's parameter vector, declared once: one table of its entries (name,
size, unit, doc, tunable between steps, structural), from which the C library's header
(``IVC_P_<NAME>``, ``IVC_PAR_DEFAULTS``), the vector of a
:class:`~ivdrem.controller.sampled.SampledController`, the controller of a vector
(:class:`~ivdrem.controller.clib.CController.from_params`, an FMU's start values) and the
controller FMU's parameters are made.

A law's gains (``T``, ``p``, ``F0``, ``gamma``, ``sigma``, ``epsilon``, ``theta_star``) take
their unit and doc from the law registry (:func:`ivdrem.laws.gain_declaration`); the law
codes are the registry's (:func:`ivdrem.laws.law_codes`), the other codes the positions in
the enumerations the Python controller validates against.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..blocks._kernels import MIXING_VARIANTS
from ..blocks.control_law import DESIGNS, INJECTIONS
from ..laws import gain_declaration, law_codes
from .sampled import GRAVITY_OPTIONS, REFERENCE_HARMONICS

__all__ = ["Parameter", "PARAMETERS", "param_layout", "param_vector", "controller_arguments",
           "TUNABLE", "STRUCTURAL", "DESIGN_CODES", "GRAVITY_CODES", "MIXING_CODES",
           "INJECTION_CODES"]


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


def _gain(name, size="1", **kw):
    """A law's gain: unit and doc from the registry (tunable unless said otherwise)."""
    arg = _number(name) if size == "1" else _vector(name)
    return Parameter(name, size, lambda c: getattr(c, name), arg, doc=None,
                     tunable=kw.pop("tunable", True), **kw)


P = Parameter
#: the parameter vector, in order (the C library's IVC_P_<NAME> indices)
PARAMETERS = (
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
    _gain("T", tunable=False, structural=True),
    _gain("p"),
    _gain("F0"),
    _gain("gamma"),
    _gain("sigma"),
    _gain("epsilon"),
    _gain("theta_star", "ntheta"),
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

#: parameters a host may change between steps
TUNABLE = tuple(p.name for p in PARAMETERS if p.tunable)
#: parameters that fix the memory or the meaning of the state (set before ivc_init)
STRUCTURAL = tuple(p.name for p in PARAMETERS if p.structural)
#: the entries of a trajectory of each kind (ivdrem.controller.sampled)
_TRAJECTORY = {"sinusoid": ("amplitude", "omega", "phase", "offset"),
               "fourier": ("kind", "omega_f", "a", "b", "offset")}


def param_layout(model):
    """[(name, size, description)] of the flat parameter vector, in order."""
    return [(p.name, p.length(model.n, model.ntheta), p.declared()[1]) for p in PARAMETERS]


def param_vector(ctrl):
    """The flat parameter vector of a :class:`~ivdrem.controller.sampled.SampledController`."""
    out = []
    for p in PARAMETERS:
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
    total = sum(p.length(n, nth) for p in PARAMETERS)
    codes = law_codes()
    off = [p.name for p in PARAMETERS].index("law")
    at = sum(p.length(n, nth) for p in PARAMETERS[:off])
    if par.size != total or law not in codes or codes[law] != par[at]:
        raise ValueError(f"parameter vector of {par.size} entries (expected {total}) or "
                         f"law code does not match {law!r}")
    kwargs, trajectory, i = {}, {}, 0
    for p in PARAMETERS:
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
