"""The controller of the paper (eqs. 7-21) sampled every h seconds: the reference in Python.

One call ``step(t_k, q_k, dq_k) -> tau_k`` per sample ``t_k = k h``.  Everything the
controller computes at t_k uses the states at t_k (outputs first), then every state is
advanced over [t_k, t_k + h] with the sampled inputs held (zero-order hold):

* reference q_d(t) = A sin(w t + phi) + c generated inside (the paper's sinusoid);
* e = q_d - q, r = de + alpha e, v = dq_d + alpha e, dv = ddq_d + alpha de;
* Pi^T (8), the control law (9) tau = (K + delta_mu mu) r + Pi^T theta_hat - u_f, saturated
  at +-tau_max, and tau_d_hat (Section 4; docs/conventions.md);
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
  continuous max-hold block does on its 1 ms grid).

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

from ..blocks._kernels import mixing_values
from ..laws import get_law
from .discrete import averaging_factor, mu_integral, mu_saturated
from .window import BlockWindow

__all__ = ["SampledController", "SAMPLED_LAWS", "PAPER_TRAJECTORY", "phi1"]

#: the laws the sampled controller implements (names of ivdrem.laws)
SAMPLED_LAWS = ("iv-drem", "composite-learning", "drem", "sigma-modification", "none")

#: the paper's reference trajectory (Section 4), as ivdrem.diagrams.closed_loop uses it
PAPER_TRAJECTORY = dict(amplitude=[0.4 * np.pi, 0.3 * np.pi], omega=[2.0, 0.3],
                        phase=[0.0, np.pi / 2], offset=[0.2 * np.pi, 0.3 * np.pi])


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
    """

    def __init__(self, model=None, law="iv-drem", *, h=1e-3, alpha=1.0, K=2.0,
                 delta_mu=0.8, Gamma=0.01, mu0=1.0, mu1=15.0, mu_max=135.0,
                 observer_variant="corrected", l=50.0, T=None, p=None, F0=None, gamma=None,
                 sigma=None, theta_star=None, epsilon=None, theta_hat0=None, trajectory=None,
                 tau_max=math.inf, delay=0, block=10):
        if model is None:
            from ..models import two_link
            model = two_link()
        if law not in SAMPLED_LAWS:
            raise ValueError(f"law {law!r} has no sampled form; choose one of "
                             f"{', '.join(SAMPLED_LAWS)}")
        if observer_variant not in ("corrected", "literal"):
            raise ValueError(f"observer_variant must be 'corrected' or 'literal', "
                             f"got {observer_variant!r}")
        if delay not in (0, 1):
            raise ValueError(f"delay must be 0 or 1 (samples), got {delay!r}")
        # the law's own gains default to its entry of the registry ivdrem.laws
        given = dict(T=T, p=p, F0=F0, gamma=gamma, sigma=sigma, epsilon=epsilon)
        d = dict(T=20.0, p=2.0, F0=1.0, gamma=1e10, sigma=0.1, epsilon=1e-9)
        d.update({k: v for k, v in get_law(law).defaults.items() if k in d})
        d.update({k: v for k, v in given.items() if v is not None})
        T, p, F0, gamma, sigma, epsilon = (d[k] for k in ("T", "p", "F0", "gamma", "sigma",
                                                           "epsilon"))
        n, nth = model.n, model.ntheta
        self.model, self.law, self.n, self.ntheta = model, law, n, nth
        self.fn = model.jit_functions
        self.h = _positive("h", h)
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
        self.tau_max = _positive("tau_max", tau_max, allow_inf=True)
        self.delay = int(delay)
        self.uses_window = law in ("iv-drem", "drem", "composite-learning")
        self.averaged = law != "composite-learning"
        self.epsilon = _positive("epsilon", epsilon)
        self.instrument = law == "iv-drem"
        self.T, self.p, self.F0 = _positive("T", T), float(p), _positive("F0", F0)
        if self.p < 1:
            raise ValueError(f"p must be >= 1, got {p!r}")
        self.gamma = _positive("gamma", gamma)
        self.sigma = _positive("sigma", sigma)
        ts = model.theta_values if theta_star is None else theta_star
        self.theta_star = _vector("theta_star", ts if ts is not None else np.zeros(nth), nth)
        self.theta_hat0 = (np.zeros(nth) if theta_hat0 is None
                           else _vector("theta_hat0", theta_hat0, nth))
        if trajectory is None:
            trajectory = PAPER_TRAJECTORY if n == 2 else generic_trajectory(n)
        tr = trajectory
        unknown = set(tr) - {"amplitude", "omega", "phase", "offset"}
        if unknown:
            raise ValueError(f"unknown trajectory parameter(s) {sorted(unknown)}")
        self.tr_A = _vector("trajectory amplitude", tr["amplitude"], n)
        self.tr_w = _vector("trajectory omega", tr["omega"], n)
        self.tr_phi = _vector("trajectory phase", tr.get("phase", 0.0), n)
        self.tr_c = _vector("trajectory offset", tr.get("offset", 0.0), n)
        self.block = int(block)
        self.m = nth + nth * nth
        if self.uses_window:
            BlockWindow(self.m, self.T, self.h, block=self.block)   # checks T / h early
        # work buffers (preallocated; the step allocates only small temporaries)
        z = lambda *s: np.zeros(s)  # noqa: E731
        self._A, self._B, self._C = z(n, nth), z(n, nth), z(n, nth)
        self._Pi, self._PM, self._E = z(n, nth), z(n, nth), z(n, nth)
        self._F = [z(n, nth) for _ in range(4)]
        self._Delta, self._calY, self._logD = z(1), z(nth), z(1)
        self.reset()

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
        self.tau = np.zeros(n)
        self.tau_d_hat = np.zeros(n)
        self.Delta = 0.0
        self.held = np.zeros(self.m)      # composite learning: (Y_b, Psi_b) at t_e
        self.lambda_min_held = 0.0
        self.window = (BlockWindow(self.m, self.T, self.h, block=self.block)
                       if self.uses_window else None)

    _STATE = ("k", "Phi_f", "Phi_Mf", "u_f", "theta_hat", "zf", "xi", "eta", "X_xi", "X_eta",
              "zeta", "Yavg",
              "tau_prev", "tau", "tau_d_hat", "Delta", "held", "lambda_min_held")
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
        arg = self.tr_w * t + self.tr_phi
        s, c = np.sin(arg), np.cos(arg)
        return (self.tr_A * s + self.tr_c, self.tr_A * self.tr_w * c,
                -self.tr_A * self.tr_w * self.tr_w * s)

    def mu(self, t):
        return mu_saturated(t, self.mu0, self.mu1, self.mu_max)[0]

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
        obs = mu * (PM - self.Phi_Mf) - self.Phi_f            # Pi^T - Phi^T          (8)
        Pi[:] = obs + A
        th = self.theta_hat
        # composite term vartheta_c(theta_hat) = b_c - a theta_hat
        a = 0.0
        if self.law == "composite-learning":
            nth = self.ntheta
            Psi_h = self.held[nth:].reshape(nth, nth)
            theta_c = self.gamma * (self.held[:nth] - Psi_h @ th)                  # (35)
        elif self.uses_window:
            mixing_values(0, self.Yavg[:self.ntheta], self.Yavg[self.ntheta:], 1e-6, 1e-3,
                          self._Delta, self._calY, self._logD)                  # (17), E4
            D = self._Delta[0]
            self.Delta = D
            theta_c = self.gamma * D * (self._calY - D * th)                    # (21)
            a = self.gamma * D * D
        elif self.law == "sigma-modification":
            theta_c = self.sigma * (self.theta_star - th)                       # E5
            a = self.sigma
        else:
            theta_c = np.zeros(self.ntheta)
        tau = (self.K @ r + self.delta_mu * mu * r) + Pi @ th - self.u_f        # (9)
        if self.tau_max < math.inf:
            tau = np.clip(tau, -self.tau_max, self.tau_max)
        if not np.all(np.isfinite(tau)):
            raise FloatingPointError(f"non-finite torque at t = {tk}: the loop diverged")
        self.tau_d_hat = -(obs @ th) + self.u_f                                 # Section 4
        applied = tau if self.delay == 0 else self.tau_prev
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
                nth = self.ntheta
                Pb = y[nth:].reshape(nth, nth)
                lam = np.linalg.eigvalsh(0.5 * (Pb + Pb.T))[0]
                if lam > self.lambda_min_held and lam > self.epsilon:
                    self.lambda_min_held = lam
                    self.held = y.copy()
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
        self.theta_hat = th + h * np.array([phi1(-gi * a * h) for gi in self.Gamma]) \
            * self.Gamma * b
        self.tau_prev = tau.copy()
        self.tau = tau
        self.k += 1
        return tau.copy()
