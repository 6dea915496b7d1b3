"""The controller of the paper (eqs. 7-21) sampled every h seconds: the reference in Python.

One call ``step(t_k, q_k, dq_k) -> tau_k`` per sample ``t_k = k h``.  Everything the
controller computes at t_k uses the states at t_k (outputs first), then every state is
advanced over [t_k, t_k + h] with the sampled inputs held (zero-order hold):

* reference q_d(t) = A sin(w t + phi) + c generated inside (the paper's sinusoid);
* e = q_d - q, r = de + alpha e, v = dq_d + alpha e, dv = ddq_d + alpha de;
* Pi^T (8), the control law (9) tau = (K + delta_mu mu) r + Pi^T theta_hat - u_f, saturated
  at +-tau_max, and tau_d_hat (Section 4; docs/conventions.md); with ``injection =
  "nominal"`` the observer's injection mu (Phi_M^T(q, r) - Phi_Mf^T) theta is taken at
  theta_nominal and Pi^T is Pi_X^T = Phi^T - Phi_f^T (docs/controller.md, "The observer on
  the nominal inertia");
* the observer (7) (Phi_f, Phi_Mf with erratum E1, u_f), the regression filters (13) and the
  instrument (14) by their exact update (:func:`ivdrem.controller.discrete.filter_step`);
  xi and eta of (13) filter functions of q, dq, which move between samples: they take
  the exact update for an input linear between the samples (first-order hold), one sample
  late (xi(t_k) is advanced from t_k-1 when q_k arrives, before phi(t_k) uses it):
  x_f(t_k) = X_k - (X_k - X_k-1) w/h + d (x_f(t_k-1) - X_k-1), d = e^{-l h},
  w = (1 - d)/l.  A held input would lag by h/2, and phi = l (Phi_M - xi) + eta amplifies
  that lag by l (measured: theta_hat(4 s) 6 times closer to the continuous loop);
* the window (15a) on the samples (:class:`~ivdrem.controller.window.BlockWindow`), the
  averaging (15b) by its exact factor F(t)/F(t+h), the mixing (17) by
  :func:`ivdrem.blocks._kernels.mixing_values` ("paper" variant, erratum E4);
* the adaptation (11): theta_hat' = Gamma (Pi r + vartheta_c) with its inputs held is linear
  in theta_hat, theta_hat' = Gamma (b - a theta_hat) with a = gamma Delta^2 (IV-DREM, DREM,
  (21)), sigma (sigma-modification), 0 (none), so the exact update
  theta_hat+ = theta_hat + h phi1(-Gamma a h) Gamma (Pi r + vartheta_c(theta_hat)),
  phi1(z) = (e^z - 1)/z, is stable at any gain (Gamma diagonal).  Composite learning (35)
  (vartheta_c = gamma (Y_b(t_e) - Psi_b(t_e) theta_hat), a matrix gain) takes the explicit
  step (a = 0); its max-hold samples lambda_min of the symmetric part of Psi_b at every t_k
  and holds (Y_b, Psi_b) when it beats both the running maximum and epsilon (as the
  continuous max-hold block does on its 1 ms grid); with mix_every = m > 1 it samples at
  t_k, k a multiple of m, and decides at t_k + m h.

``mu(t) = min(mu0 t + mu1, mu_max)`` (docs/controller.md, "Saturating mu").

``delay`` is the sample at which the torque reaches the plant (docs/controller.md, "Where
the torque goes"): 0, tau_k is applied over [t_k, t_k+1] (Gauss-Seidel host); 1, tau_k is
applied over [t_k+1, t_k+2] (Jacobi host) and the filters of u = -tau (7) and z (13) see
the torque actually applied, tau_{k-1} (tau_{-1} = 0).

While the window fills (t < T) its integrand is 0 before t0 (docs/conventions.md), so Psi
is singular, Delta = 0 and the composite term of (21) is 0: a defined behaviour, no special
case.  Non-finite q, dq are refused with an error before any state changes; a non-finite
torque (a diverged loop) too.
"""
from __future__ import annotations

import math

import numpy as np

from .._default_config import paper_experiment
from ..blocks._kernels import MIXING_VARIANTS, mixing_values, start_weight
from ..blocks.control_law import DESIGNS, INJECTIONS, default_injection, inertia_scaled_gain
from ..blocks.mixing import DEFAULT_F_REL, DEFAULT_GUARD, start_of_term
from ..blocks.sources import fourier_series
from ..diagrams.gamma_auto import DEFAULT_RATE as GAMMA_RATE
from ..laws import get_law, sampled_gain_defaults, sampled_gains, sampled_laws, sampled_step
from .discrete import averaging_factor, mu_integral, mu_saturated
from .loop import default_period
from .window import BlockWindow

__all__ = ["SampledController", "SAMPLED_LAWS", "PAPER_TRAJECTORY", "phi1", "DESIGNS",
           "GRAVITY_OPTIONS", "REFERENCE_HARMONICS", "default_design", "default_mixing",
           "inertia_scaled_gains", "gain_budget", "GAIN_FLOOR", "GRADIENT_GAIN"]

# DESIGNS: the designs of the feedback of (9), one enumeration with the continuous
# control-law block (ivdrem.blocks.control_law; docs/controller.md, "Sampled designs")
#: who compensates gravity: the controller's law alone, or the robot ("robot": tau - g_hat)
GRAVITY_OPTIONS = ("controller", "robot")
#: harmonics per joint of a Fourier reference (the C library's fixed size; the real-arm
#: experiment's ivdrem.diagrams.arm_reference.HARMONICS)
REFERENCE_HARMONICS = 5


def _is_urdf_arm(model):
    from ..models.urdf import RigidBodyModel
    return isinstance(model, RigidBodyModel)


def default_design(model):
    """"paper" for the symbolic arms (the paper's 2-link, planar-N: the paper's (9) holds at
    1 kHz there), "inertia-scaled" for the URDF arms (docs/controller.md)."""
    return "inertia-scaled" if _is_urdf_arm(model) else "paper"


def default_mixing(model):
    """"paper" for the symbolic arms, "eigen" for the URDF arms (docs/mixing.md)."""
    return "eigen" if _is_urdf_arm(model) else "paper"

#: the laws the sampled controller implements: those the registry gives a sampled form
#: (ivdrem.laws.sampled_laws, in the order of their C codes)
SAMPLED_LAWS = sampled_laws()


#: The paper's reference trajectory (Section 4), as ivdrem.diagrams.closed_loop uses it: read
#: from the default configuration where it is written ([trajectory] of experiments/default.toml).
PAPER_TRAJECTORY = paper_experiment()["trajectory"]


def generic_trajectory(n):
    """A reference for an n-joint arm without the paper's: q_d,i = 0.3 sin((0.5 + 0.25 i) t)
    (tunable: the ``trajectory`` argument, the FMU's tr_* parameters)."""
    return dict(amplitude=[0.3] * n, omega=[0.5 + 0.25 * i for i in range(n)],
                phase=[0.0] * n, offset=[0.0] * n)


def phi1(z):
    """(e^z - 1)/z, 1 at z = 0 (accurate near 0 by expm1)."""
    return 1.0 if z == 0.0 else math.expm1(z) / z


def _vector(name, value, n):
    a = np.asarray(value, dtype=float)
    if a.ndim == 0:
        a = np.full(n, float(a))
    a = a.reshape(-1)
    if a.size != n:
        raise ValueError(f"{name} must have {n} entries, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a}")
    return a


#: the floor of the "inertia-scaled" design's K (1/s): a closed-loop bandwidth every joint
#: gets at least (docs/controller.md, "Sampled designs")
GAIN_FLOOR = 50.0


#: Γ of (11) for the "inertia-scaled" design on URDF arms at the robot's rate, with γ of
#: (21) at 0.5 / Γ (what γ = "auto" gives with "eigen", Δ ≈ 1: the composite term's rate
#: Γ γ Δ² kept): the gradient term Γ Π r alone moves θ̂ until the window is full (t < T),
#: and where it moves M(q, θ̂) along a light wrist the observer's injection μ M(q, θ̂) r of
#: (8) grows past the per-step budget (docs/controller.md, "Sampled designs")
GRADIENT_GAIN = 1e-3


def gain_budget(delay):
    """The per-step loop gain g = h (K_i + (1 + δ_μ) μ_max) the "inertia-scaled" design
    allows: half the limit of the discrete loop, z - 1 + g = 0 (delay 0: |1 - g| < 1, g < 2)
    and z² - z + g = 0 (delay 1, the torque held one sample: g < 1)."""
    return 1.0 if int(delay) == 0 else 0.5


def inertia_scaled_gains(model, K, q0, h, *, delta_mu=0.8, mu_max=135.0, delay=1,
                         floor=GAIN_FLOOR, budget=None, theta=None):
    """The "inertia-scaled" design's K (1/s) from joint gains K (N m s/rad, e.g.
    ivdrem.diagrams.arm_reference.design_gains): K_i / M_ii(q0) (the paper's feedback at q0 on the
    diagonal), at least ``floor`` (a uniform bandwidth on the heavy joints, where
    K_i / M_ii is ~2 1/s), at most the cap

        h (K_i + δ_μ μ_max + μ_max) <= budget        (default :func:`gain_budget` (delay)),

    the per-step gain of the sampled loop on joint i with the nominal inertia: the feedback
    M̂(K + δ_μ μ) r of (9) and the observer's injection μ Φ_Mᵀ(q, r) θ̂ ≈ μ M r of (8) with
    θ̂ = θ (docs/controller.md, "Sampled designs").  ``delay``: 1 for the controller FMU
    (its torque is applied one sample late), 0 for a host that applies τ_k at once.  The
    cap wins over the floor; a cap <= 0 is refused naming h and μ_max."""
    budget = gain_budget(delay) if budget is None else float(budget)
    cap = budget / h - (1.0 + delta_mu) * mu_max
    if not cap > 0:
        raise ValueError(f"h (1 + delta_mu) mu_max = {h * (1 + delta_mu) * mu_max:.3g} leaves "
                         f"no room for K below the per-step budget {budget:g} (delay "
                         f"{int(delay)}): lower mu_max or h")
    return np.minimum(np.maximum(inertia_scaled_gain(model, K, q0, theta), floor), cap)


def _declared_gain(name, key, value, n, ntheta):
    """A gain of a law's registry declaration (:class:`~ivdrem.laws.Key`): a finite number,
    or a vector of the Key's length, each number within the Key's check."""
    if key.kind == "vec":
        a = _vector(name, value, {"n": n, "ntheta": ntheta}[key.length])
    else:
        try:
            a = np.array([float(value)])
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number, got {value!r}") from None
        if not np.isfinite(a[0]):
            raise ValueError(f"{name} must be finite, got {value!r}")
    if key.check is not None and not all(key.check(float(x)) for x in a):
        raise ValueError(f"{name} must be {key.requirement}, got {value!r}")
    return a if key.kind == "vec" else float(a[0])


def _limit(name, value, n):
    """A per-joint limit: a number or n numbers, each > 0 (inf: none)."""
    a = np.asarray(value, dtype=float)
    a = np.full(n, float(a)) if a.ndim == 0 else a.reshape(-1)
    if a.size != n:
        raise ValueError(f"{name} must be a number or {n} numbers, got {a.size}")
    if not np.all(a > 0):          # NaN fails too
        raise ValueError(f"{name} must be > 0 (inf: no limit), got {a}")
    return a


def _matrix(name, value, n, *, pd=False):
    a = np.asarray(value, dtype=float)
    if a.ndim == 0:
        a = float(a) * np.eye(n)
    elif a.ndim == 1:
        a = np.diag(_vector(name, a, n))
    if a.shape != (n, n) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite {n} x {n} matrix (or a scalar or diagonal)")
    if pd and (not np.allclose(a, a.T) or np.linalg.eigvalsh(0.5 * (a + a.T)).min() <= 0):
        raise ValueError(f"{name} must be symmetric positive definite")
    return a


def _positive(name, value, *, allow_inf=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not (v > 0) or (math.isinf(v) and not allow_inf) or math.isnan(v):
        raise ValueError(f"{name} must be > 0" + ("" if allow_inf else " and finite")
                         + f", got {value!r}")
    return v


class SampledController:
    """The paper's controller at a fixed step h for ``model`` (an EulerLagrangeModel).

    Parameters are those of :func:`ivdrem.diagrams.closed_loop` (the paper's experiment by
    default) plus ``h``, ``mu_max``, ``tau_max`` (torque saturation, default none),
    ``delay`` (0 or 1) and ``block`` (samples per block sum of the window).  ``Gamma``:
    scalar or diagonal (the exact update of (11) above needs a diagonal gain).

    The laws' gains: the keywords ``T`` ... ``epsilon`` the step reads, and any other gain a
    law with a sampled form declares in the registry (``**gains``, e.g. a registered law's
    own ``kappa``): each defaults to the law's registry value and is kept in ``gains``
    with the others, the parameter vector's entries (:mod:`ivdrem.controller.parameters`).
    A law that runs another's step (``sampled_as`` in its entry) runs that step.

    Real arms (docs/controller.md, "Sampled designs" and "The robot's contract"):

    * ``design``: "paper" (the feedback (K + delta_mu mu) r of (9)) or "inertia-scaled"
      (M(q, theta_nominal)(K + delta_mu mu) r, K in 1/s): default :func:`default_design`;
    * ``mixing``: "paper", "eigen" or "channel" (docs/mixing.md; default
      :func:`default_mixing`), with ``f_rel`` ("eigen") and ``guard`` ("channel"); the
      scale-free variants switch the composite term on at t = T (ramp 0.1 T), as the
      continuous loop does, and take ``gamma`` = 0.5 / max(Gamma) unless given (the rule
      of gamma "auto" with Delta = 1: 50 at Gamma = 0.01; the paper's mixing keeps the
      law's registry value); ``mix_every``: the mixing (17) every m samples (multi-rate; the
      filters, the window and theta_hat's update run at every sample): with m > 1 the
      mixing of (Y, Psi)(t_k), k a multiple of m, is held over [t_k + m h, t_k + 2 m h)
      (one period late: the C library spreads its work over the m samples between);
      composite learning: its max-hold samples lambda_min(Psi_b(t_k)) every m samples and
      decides at t_k + m h;
    * ``trajectory``: the paper's sinusoid (amplitude, omega, phase, offset) or a Fourier
      reference {"kind": "fourier", "omega_f", "a", "b", "offset"} of at most
      REFERENCE_HARMONICS harmonics (ivdrem.diagrams.arm_reference.design_trajectory);
    * ``gravity``: "controller", or "robot" (the robot adds its own g(q): tau - g_hat(q)
      is commanded, g_hat = G(q, theta_nominal)); ``theta_nominal``: default the model's
      theta_values (the URDF's);
    * ``tau_max``, ``tau_rate_max``: per-joint limits of the command (N m, N m/s; a number
      or n numbers; inf: none); ``first_zero``: the command of t = 0 is 0;
    * ``injection``: the parameters of the observer's injection mu (Phi_M^T(q, r) -
      Phi_Mf^T) theta in (8)-(9): "estimate" (theta_hat, the paper's) or "nominal"
      (theta_nominal, the adaptation then reads Pi_X^T = Phi^T - Phi_f^T); default
      :func:`ivdrem.blocks.control_law.default_injection` of the design ("nominal" for
      "inertia-scaled"; docs/controller.md, "The observer on the nominal inertia").
    """

    def __init__(self, model=None, law="iv-drem", *, h=None, alpha=1.0, K=2.0,
                 delta_mu=0.8, Gamma=0.01, mu0=1.0, mu1=15.0, mu_max=135.0,
                 observer_variant="corrected", l=50.0, T=None, p=None, F0=None, gamma=None,
                 sigma=None, theta_star=None, epsilon=None, theta_hat0=None, trajectory=None,
                 tau_max=math.inf, delay=0, block=10, design=None, mixing=None, mix_every=1,
                 f_rel=DEFAULT_F_REL, guard=DEFAULT_GUARD, gravity="controller",
                 theta_nominal=None, tau_rate_max=math.inf, first_zero=False, injection=None,
                 **gains):
        if model is None:
            from ..models import two_link
            model = two_link()
        if law not in sampled_laws():
            raise ValueError(f"law {law!r} has no sampled form; choose one of "
                             f"{', '.join(sampled_laws())}")
        if observer_variant not in ("corrected", "literal"):
            raise ValueError(f"observer_variant must be 'corrected' or 'literal', "
                             f"got {observer_variant!r}")
        if delay not in (0, 1):
            raise ValueError(f"delay must be 0 or 1 (samples), got {delay!r}")
        # the law's own gains default to its entry of the registry ivdrem.laws; the
        # parameter vector holds every sampled law's gains, the others at their registry
        # defaults (ivdrem.laws.sampled_gain_defaults); the step is the law's own or the
        # one it names (sampled_as): its window, max-hold and instrument
        declared = sampled_gains()
        unknown = sorted(set(gains) - set(declared))
        if unknown:
            raise TypeError(f"SampledController got unexpected keyword argument(s) "
                            f"{', '.join(map(repr, unknown))}; the gains of the laws with a "
                            f"sampled form: {', '.join(declared)}")
        own = get_law(law)
        self.step_law = sampled_step(law)
        spec = get_law(self.step_law)
        # the gains the steps below read (theta_star apart: the model's theta by default)
        read = dict(T=T, p=p, F0=F0, gamma=gamma, sigma=sigma, epsilon=epsilon)
        given = {**read, **gains}
        defaults = sampled_gain_defaults()
        defaults.update({k: v for k, v in own.defaults.items() if k in defaults})
        d = {k: defaults.get(k) if given.get(k) is None else given[k] for k in declared}
        T, p, F0, gamma, sigma, epsilon = (d[k] for k in read)
        n, nth = model.n, model.ntheta
        # the other declared gains: no step of this class reads them (a law that adds a
        # gain to another's step), the parameter vector carries them
        other = {k: _declared_gain(k, declared[k], d[k], n, nth) for k in declared
                 if k not in read and k != "theta_star"}
        self.model, self.law, self.n, self.ntheta = model, law, n, nth
        self.fn = model.jit_functions
        self.h = _positive("h", default_period() if h is None else h)
        self.alpha = float(alpha)
        self.K = _matrix("K", K, n, pd=True)
        if not 0.0 < float(delta_mu) < 1.0:
            raise ValueError(f"delta_mu must lie in (0, 1), got {delta_mu!r}")
        self.delta_mu = float(delta_mu)
        G = np.asarray(Gamma, dtype=float)
        if G.ndim == 2:
            if np.any(G != np.diag(np.diag(G))):
                raise ValueError("Gamma must be a scalar or diagonal for the exact update "
                                 "of (11) (see ivdrem.controller.sampled)")
            G = np.diag(G)
        self.Gamma = _vector("Gamma", G, nth)
        if np.any(self.Gamma <= 0):
            raise ValueError(f"Gamma must be positive, got {self.Gamma}")
        if not float(mu0) >= 0:
            raise ValueError(f"mu0 must be >= 0, got {mu0!r}")
        self.mu0, self.mu1 = float(mu0), _positive("mu1", mu1)
        self.mu_max = _positive("mu_max", mu_max, allow_inf=True)
        if self.mu_max < self.mu1:
            raise ValueError(f"mu_max = {mu_max} must be >= mu1 = {mu1}")
        self.corrected = observer_variant == "corrected"
        self.l = _positive("l", l)
        self.tau_max = _limit("tau_max", tau_max, n)
        self.tau_rate_max = _limit("tau_rate_max", tau_rate_max, n)
        self.first_zero = bool(first_zero)
        self.design = default_design(model) if design is None else design
        if self.design not in DESIGNS:
            raise ValueError(f"design = {design!r} is not a sampled design; choose one of "
                             f"{', '.join(map(repr, DESIGNS))}")
        if gravity not in GRAVITY_OPTIONS:
            raise ValueError(f"gravity = {gravity!r} is not an option; choose 'controller' "
                             f"(the law's torque is commanded) or 'robot' (the robot adds its "
                             f"own gravity model: tau - g_hat(q) is commanded)")
        self.gravity = gravity
        self.injection = default_injection(self.design) if injection is None else injection
        if self.injection not in INJECTIONS:
            raise ValueError(f"injection = {injection!r} is not an option; choose 'estimate' "
                             f"(the observer's injection of (8) at theta_hat, the paper's) or "
                             f"'nominal' (at theta_nominal)")
        self.mixing = default_mixing(model) if mixing is None else mixing
        if self.mixing not in MIXING_VARIANTS:
            raise ValueError(f"mixing = {mixing!r} is not a variant; choose one of "
                             f"{', '.join(map(repr, MIXING_VARIANTS))}")
        self.mix_code = MIXING_VARIANTS.index(self.mixing)
        self.mix_every = int(mix_every)
        if self.mix_every != mix_every or self.mix_every < 1:
            raise ValueError(f"mix_every must be a whole number >= 1, got {mix_every!r}")
        self.f_rel = _positive("f_rel", f_rel)
        self.guard = _positive("guard", guard)
        tn = model.theta_values if theta_nominal is None else theta_nominal
        if tn is None and (self.design != "paper" or gravity == "robot"
                           or self.injection == "nominal"):
            raise ValueError(f"design {self.design!r}, gravity 'robot' and injection "
                             f"'nominal' need the nominal "
                             f"parameters theta_nominal (model {model.name!r} has none)")
        self.theta_nominal = _vector("theta_nominal", tn if tn is not None else np.zeros(nth),
                                     nth)
        self.delay = int(delay)
        self.uses_window = spec.windowed
        self.averaged = not spec.max_hold
        self.epsilon = _positive("epsilon", epsilon)
        self.instrument = spec.instrument == "zeta"
        self.T, self.p, self.F0 = _positive("T", T), float(p), _positive("F0", F0)
        if self.p < 1:
            raise ValueError(f"p must be >= 1, got {p!r}")
        if given["gamma"] is None and self.averaged and self.mixing != "paper":
            # the scale-free mixings keep Delta near 1 (docs/mixing.md), where the rule of
            # gamma "auto" (ivdrem.diagrams.gamma_auto) gives rate / (lambda_max(Gamma)
            # mean Delta^2) = rate / max(Gamma); the registry's 1e10 is the paper's
            # mixing's, whose Delta is tiny
            gamma = GAMMA_RATE / float(np.max(self.Gamma))
        self.gamma = _positive("gamma", gamma)
        self.sigma = _positive("sigma", sigma)
        ts = model.theta_values if theta_star is None else theta_star
        self.theta_star = _vector("theta_star", ts if ts is not None else np.zeros(nth), nth)
        # every declared gain, as the parameter vector holds it
        self.gains = {k: other[k] if k in other else getattr(self, k) for k in declared}
        self.theta_hat0 = (np.zeros(nth) if theta_hat0 is None
                           else _vector("theta_hat0", theta_hat0, nth))
        if trajectory is None:
            trajectory = paper_experiment()["trajectory"] if n == 2 else generic_trajectory(n)
        self._set_trajectory(trajectory)
        self.block = int(block)
        self.m = nth + nth * nth
        if self.uses_window:
            BlockWindow(self.m, self.T, self.h, block=self.block)   # checks T / h early
        # the composite term's start (docs/mixing.md): t = 0 for "paper", T for the others
        self.t_on, self.t_ramp = (start_of_term(self.mixing, self.T) if self.averaged
                                  else (0.0, 0.0))
        # work buffers (preallocated; the step allocates only small temporaries)
        z = lambda *s: np.zeros(s)  # noqa: E731
        self._A, self._B, self._C = z(n, nth), z(n, nth), z(n, nth)
        self._Pi, self._PM, self._E = z(n, nth), z(n, nth), z(n, nth)
        self._F = [z(n, nth) for _ in range(4)]
        self._Delta, self._calY, self._logD = z(nth), z(nth), z(nth)
        self._Mx = z(n, nth)
        self.reset()

    def _set_trajectory(self, tr):
        n, H = self.n, REFERENCE_HARMONICS
        self.fourier = tr.get("kind", "sinusoid") == "fourier"
        if self.fourier:
            unknown = set(tr) - {"kind", "omega_f", "a", "b", "offset", "rank", "cond"}
            if unknown:
                raise ValueError(f"unknown Fourier trajectory parameter(s) {sorted(unknown)}")
            a = np.asarray(tr["a"], dtype=float)
            b = np.asarray(tr["b"], dtype=float)
            if a.ndim != 2 or a.shape != b.shape or a.shape[0] != n or a.shape[1] > H:
                raise ValueError(f"a Fourier trajectory's a and b must be {n} x H matrices "
                                 f"with H <= {H} harmonics, got {a.shape} and {b.shape}")
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
                raise ValueError("a Fourier trajectory's a and b must be finite")
            self.fr_a, self.fr_b = np.zeros((n, H)), np.zeros((n, H))
            self.fr_a[:, :a.shape[1]] = a
            self.fr_b[:, :b.shape[1]] = b
            self.fr_wf = _positive("trajectory omega_f", tr["omega_f"])
            self.tr_A = self.tr_w = self.tr_phi = np.zeros(n)
            self.tr_c = _vector("trajectory offset", tr.get("offset", 0.0), n)
            return
        unknown = set(tr) - {"kind", "amplitude", "omega", "phase", "offset"}
        if unknown:
            raise ValueError(f"unknown trajectory parameter(s) {sorted(unknown)}")
        self.tr_A = _vector("trajectory amplitude", tr["amplitude"], n)
        self.tr_w = _vector("trajectory omega", tr["omega"], n)
        self.tr_phi = _vector("trajectory phase", tr.get("phase", 0.0), n)
        self.tr_c = _vector("trajectory offset", tr.get("offset", 0.0), n)
        self.fr_wf, self.fr_a, self.fr_b = 0.0, np.zeros((n, H)), np.zeros((n, H))

    # ------------------------------------------------------------------ state
    def reset(self):
        n, nth = self.n, self.ntheta
        self.k = 0
        self.Phi_f = np.zeros((n, nth))
        self.Phi_Mf = np.zeros((n, nth))
        self.u_f = np.zeros(n)
        self.theta_hat = self.theta_hat0.copy()
        self.zf = np.zeros(n)
        self.xi = np.zeros((n, nth))
        self.eta = np.zeros((n, nth))
        self.X_xi = np.zeros((n, nth))    # inputs of xi, eta at the previous sample
        self.X_eta = np.zeros((n, nth))
        self.zeta = np.zeros((n, nth))
        self.Yavg = np.zeros(self.m)
        self.tau_prev = np.zeros(n)      # torque applied over the current sample (delay 1)
        self.tau = np.zeros(n)           # the command tau_k (what the robot receives)
        self.tau_d_hat = np.zeros(n)
        self.Delta = 0.0
        self.D_held = np.zeros(nth)       # the mixing (17) in use
        self.calY_held = np.zeros(nth)
        self.D_next = np.zeros(nth)       # multi-rate: the mixing applied at the next period
        self.calY_next = np.zeros(nth)
        self.q_d = np.zeros(n)            # the reference at the last sample
        self.dq_d = np.zeros(n)
        self.held = np.zeros(self.m)      # composite learning: (Y_b, Psi_b) at t_e
        self.lambda_min_held = 0.0
        self.held_next = np.zeros(self.m)  # multi-rate: the candidate decided next period
        self.lambda_min_next = 0.0
        self.window = (BlockWindow(self.m, self.T, self.h, block=self.block)
                       if self.uses_window else None)

    _STATE = ("k", "Phi_f", "Phi_Mf", "u_f", "theta_hat", "zf", "xi", "eta", "X_xi", "X_eta",
              "zeta", "Yavg",
              "tau_prev", "tau", "tau_d_hat", "Delta", "held", "lambda_min_held", "held_next",
              "lambda_min_next", "D_held",
              "calY_held", "D_next", "calY_next", "q_d", "dq_d")
    _WINDOW = ("ring", "pos", "P", "i", "S", "shadow", "nshadow", "g_prev")

    def state(self):
        """A copy of the whole state (window included), for :meth:`set_state`."""
        s = {k: np.copy(getattr(self, k)) for k in self._STATE}
        if self.window is not None:
            s["window"] = {k: (None if getattr(self.window, k) is None
                               else np.copy(getattr(self.window, k))) for k in self._WINDOW}
        return s

    def set_state(self, s):
        for k in self._STATE:
            v = np.copy(s[k])
            setattr(self, k, v if v.ndim else v.item())
        if self.window is not None:
            for k, v in s["window"].items():
                v = None if v is None else np.copy(v)
                setattr(self.window, k, v if v is None or v.ndim else v.item())

    # ------------------------------------------------------------------ step
    def reference(self, t):
        """(q_d, dq_d, ddq_d) at t: the sinusoid, or the Fourier series of
        :func:`ivdrem.blocks.sources.fourier_series`."""
        if self.fourier:
            q, dq, ddq = fourier_series(t, self.fr_wf, self.fr_a, self.fr_b, self.tr_c)
            return q[0], dq[0], ddq[0]
        arg = self.tr_w * t + self.tr_phi
        s, c = np.sin(arg), np.cos(arg)
        return (self.tr_A * s + self.tr_c, self.tr_A * self.tr_w * c,
                -self.tr_A * self.tr_w * self.tr_w * s)

    def last_reference(self):
        """(q_d, dq_d) of the last step (the C library's ivc_reference)."""
        return self.q_d.copy(), self.dq_d.copy()

    def feedback(self, q, r, mu):
        """The feedback term of (9): (K + delta_mu mu) r ("paper"), or
        M(q, theta_nominal)(K + delta_mu mu) r ("inertia-scaled"), M x = Phi_M^T(q, x) theta
        (Property 1)."""
        x = self.K @ r + self.delta_mu * mu * r
        if self.design == "paper":
            return x
        self.fn.Phi_M(q, x, self._Mx)
        return self._Mx @ self.theta_nominal

    def mu(self, t):
        return mu_saturated(t, self.mu0, self.mu1, self.mu_max)[0]

    def _max_hold_sample(self, y):
        """Composite learning's max-hold of (35) at t_k, the window's output y = (Y_b, Psi_b):
        (Y_b, Psi_b) is held when lambda_min of the symmetric part of Psi_b beats the running
        maximum and epsilon.  With mix_every = m > 1 the candidate of t_k (k a multiple of m)
        is decided at t_k + m h (the C library spreads its lambda_min over the m samples
        between, docs/controller.md, "Real arms: reference, mixing, multi-rate")."""
        m = self.mix_every
        if self.k % m:
            return
        if m > 1 and self.k > 0:            # the candidate of t_k - m h
            self._hold(self.lambda_min_next, self.held_next)
        nth = self.ntheta
        Pb = y[nth:].reshape(nth, nth)
        lam = np.linalg.eigvalsh(0.5 * (Pb + Pb.T))[0]
        if m == 1:
            self._hold(lam, y)
        else:
            self.lambda_min_next, self.held_next = lam, y.copy()

    def _hold(self, lam, y):
        if lam > self.lambda_min_held and lam > self.epsilon:
            self.lambda_min_held = lam
            self.held = y.copy()

    def step(self, t, q, dq):
        """tau_k for the sample (t_k, q_k, dq_k), t_k = k h (k counts the calls)."""
        h, fn, l = self.h, self.fn, self.l
        tk = self.k * h
        if not abs(t - tk) <= 1e-9 * max(1.0, abs(tk)):
            raise ValueError(f"step {self.k} must be at t = {tk!r} (fixed step h = {h}), "
                             f"got t = {t!r}")
        q = np.asarray(q, dtype=float)
        dq = np.asarray(dq, dtype=float)
        if q.shape != (self.n,) or dq.shape != (self.n,):
            raise ValueError(f"q and dq must have {self.n} entries, got {q.shape}, {dq.shape}")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(dq))):
            raise ValueError(f"non-finite measurement at t = {tk}: q = {q}, dq = {dq}")
        qd, dqd, ddqd = self.reference(tk)
        e, de = qd - q, dqd - dq
        r = de + self.alpha * e
        v = dqd + self.alpha * e
        dv = ddqd + self.alpha * de
        mu = self.mu(tk)
        A, B, C, PM, Pi = self._A, self._B, self._C, self._PM, self._Pi
        fn.Phi(q, dq, v, dv, A)
        fn.Phi_C(q, dq, r, B)
        fn.Phi_dM(q, dq, r, C)
        fn.Phi_M(q, r, PM)
        th = self.theta_hat
        inj = mu * (PM - self.Phi_Mf)       # the observer's injection: chi = inj theta (7)
        if self.injection == "estimate":
            obs = inj - self.Phi_f                            # Pi^T - Phi^T          (8)
            Pi[:] = obs + A
        else:
            # injection at theta_nominal: Pi_X^T = Phi^T - Phi_f^T is the regressor of
            # theta_tilde left in (10) (adaptation (11)), inj theta_nominal the nominal
            # momentum's injection (docs/controller.md, "The observer on the nominal inertia")
            Pi[:] = A - self.Phi_f
            chi = inj @ self.theta_nominal
        # composite term vartheta_c(theta_hat) = b_c - a theta_hat
        a = 0.0
        if not self.averaged:             # the max-hold of composite learning
            nth = self.ntheta
            Psi_h = self.held[nth:].reshape(nth, nth)
            theta_c = self.gamma * (self.held[:nth] - Psi_h @ th)                  # (35)
        elif self.uses_window:
            if self.k % self.mix_every == 0:
                # multi-rate (m > 1): the mixing of (Y, Psi)(t_k - m h) is held from t_k on,
                # the one of (Y, Psi)(t_k) from t_k + m h (the C library spreads its work
                # over the m samples between); single-rate: the mixing of t_k at t_k
                if self.mix_every > 1:
                    self.D_held[:] = self.D_next
                    self.calY_held[:] = self.calY_next
                mixing_values(self.mix_code, self.Yavg[:self.ntheta], self.Yavg[self.ntheta:],
                              self.f_rel, self.guard, self._Delta, self._calY,
                              self._logD)                                       # (17), E4
                D_out, calY_out = ((self.D_held, self.calY_held) if self.mix_every == 1
                                   else (self.D_next, self.calY_next))
                D_out[:] = self._Delta if self.mix_code == 2 else self._Delta[0]  # per channel
                calY_out[:] = self._calY
            D = self.D_held if self.mix_code == 2 else self.D_held[0]
            self.Delta = float(np.min(D)) if self.mix_code == 2 else D
            gw = self.gamma * start_weight(tk, self.t_on, self.t_ramp)
            theta_c = gw * D * (self.calY_held - D * th)                        # (21)
            a = gw * D * D
        elif self.step_law == "sigma-modification":
            theta_c = self.sigma * (self.theta_star - th)                       # E5
            a = self.sigma
        else:
            theta_c = np.zeros(self.ntheta)
        if self.injection == "estimate":
            tau = self.feedback(q, r, mu) + Pi @ th - self.u_f                  # (9)
            f_hat = obs @ th                              # f_hat + u_f of (7) at theta_hat
        else:
            tau = self.feedback(q, r, mu) + (Pi @ th + chi) - self.u_f          # (9)
            f_hat = chi - self.Phi_f @ th
        # the command: the robot's gravity taken out, the limits, the first command
        F4 = self._F[3]
        g_hat = None
        if self.gravity == "robot":
            self.fn.Phi_G(q, F4)
            g_hat = F4 @ self.theta_nominal
            tau = tau - g_hat
        if np.any(self.tau_max < math.inf):
            tau = np.clip(tau, -self.tau_max, self.tau_max)
        if self.k == 0 and self.first_zero:
            tau = np.zeros(self.n)
        elif self.k > 0 and np.any(self.tau_rate_max < math.inf):
            step = h * self.tau_rate_max
            tau = np.clip(tau, self.tau - step, self.tau + step)
        if not np.all(np.isfinite(tau)):
            raise FloatingPointError(f"non-finite torque at t = {tk}: the loop diverged")
        self.tau_d_hat = -f_hat + self.u_f                                      # Section 4
        # the torque acting on the arm (the robot adds g_hat), which the filters see
        acting = tau if g_hat is None else tau + g_hat
        applied = acting if self.delay == 0 else (
            self.tau_prev if g_hat is None else self.tau + g_hat)
        # regression (13) at t_k: phi^T = l (Phi_M^T(q, dq) - xi) + eta
        E = self._E
        fn.Phi_M(q, dq, E)
        F1, F2, F3, F4 = self._F
        fn.Phi_C(q, dq, dq, F1)
        fn.Phi_dM(q, dq, dq, F2)
        fn.Phi_F(dq, F3)
        fn.Phi_G(q, F4)
        Xe = ((F1 - F2) + F3) + F4    # Phi_C^T(q,dq,dq) - Phi_dM^T(q,dq,dq) + Phi_F^T + Phi_G^T
        dl = math.exp(-l * h)
        if self.k > 0:                # xi, eta from t_k-1 to t_k, input linear between
            w = h * phi1(-l * h)      # (1 - d)/l
            for name, X, X0 in (("xi", E, self.X_xi), ("eta", Xe, self.X_eta)):
                sl = (X - X0) / h
                setattr(self, name, (X - sl * w) + dl * (getattr(self, name) - X0))
        self.X_xi = E.copy()
        self.X_eta = Xe
        phi = l * (E - self.xi) + self.eta
        if self.uses_window:
            inst = self.zeta if self.instrument else phi
            g = np.concatenate([inst.T @ self.zf, (inst.T @ phi).reshape(-1)])   # (15a)
            y = self.window.push(g)
            if not self.averaged:           # composite learning: max-hold of (Y_b, Psi_b)
                self._max_hold_sample(y)
        # ---- advance every state over [t_k, t_k + h], inputs held
        I = mu_integral(tk, h, self.mu0, self.mu1, self.mu_max)
        d1 = math.exp(-I)
        d2 = d1 * (mu / self.mu(tk + h)) if self.corrected else d1             # E1
        X = A - B + C                 # Phi^T(q,dq,v,dv) - Phi_C^T(q,dq,r) + Phi_dM^T(q,dq,r)
        self.Phi_f = X + d1 * (self.Phi_f - X)                                  # (7)
        self.Phi_Mf = PM + d2 * (self.Phi_Mf - PM)
        self.u_f = -applied + d1 * (self.u_f + applied)
        self.zf = applied + dl * (self.zf - applied)                            # (13)
        if self.instrument:
            fn.Phi(qd, dqd, dqd, ddqd, A)                                       # (14)
            self.zeta = A + dl * (self.zeta - A)
        if self.uses_window and self.averaged:
            f = averaging_factor(tk, h, self.p, self.F0)                        # (15b)
            self.Yavg = y + f * (self.Yavg - y)
        b = Pi.T @ r + theta_c                                                  # (11)
        if np.ndim(a):                # "channel": one rate per channel
            f1 = np.array([phi1(-gi * ai * h) for gi, ai in zip(self.Gamma, a)])
        else:
            f1 = np.array([phi1(-gi * a * h) for gi in self.Gamma])
        self.theta_hat = th + h * f1 * self.Gamma * b
        self.tau_prev = acting.copy()
        self.tau = tau
        self.q_d, self.dq_d = qd, dqd
        self.k += 1
        return tau.copy()
