"""A real robot between the plant and the controller: its sensors and its actuator limits.

The paper's analysis assumes exact q and q̇ and an exact torque.  A robot measures its
joint angles with encoders, differentiates them for q̇, answers one sample late and limits
the torque and its rate.  :class:`Imperfections` lists these, each off by default (then the
numbers pass through untouched, so a loop with ``Imperfections()`` equals the loop without
it bit for bit); :meth:`Imperfections.start` makes the per-run state (:class:`Robot`),
seeded.  Typical figures (docs/mujoco.md):

=====================  ==========================================  =========================
option                 what                                        typical
=====================  ==========================================  =========================
``encoder_counts``     counts per revolution of the joint encoder  2^18 (Franka), 2^20 (UR)
``encoder_noise``      white noise on the angle before the         up to 1 count (the last
                       encoder rounds it, σ in counts              count's jitter)
``velocity``           "exact", "difference" (filtered difference  "difference", 100-500 Hz
                       of the measured positions) or "noise"       cut-off; σ 1e-3 rad/s
``measurement_delay``  samples between measuring and the torque    1 (one 1 ms cycle)
``tau_limit``          |τ_i| ≤ tau_limit_i (N·m)                   Panda 87 / 12 N·m
``tau_rate_limit``     |τ_k − τ_k−1| ≤ rate · h (N·m/s)            Franka 1000 N·m/s
=====================  ==========================================  =========================

The payload and the joint friction are properties of the plant
(:func:`ivdrem.plants.mujoco.load`), not of the signals.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

__all__ = ["Imperfections", "Robot", "REALISTIC", "VELOCITY_MODES"]

#: how q̇ reaches the controller
VELOCITY_MODES = ("exact", "difference", "noise")


def _limit(name, value, n):
    """A per-joint limit (scalar or n entries), positive, or None (no limit)."""
    if value is None:
        return None
    a = np.asarray(value, dtype=float).reshape(-1)
    if a.size == 1:
        a = np.full(n, float(a[0]))
    if a.size != n or not np.all(a > 0) or np.any(np.isnan(a)):
        raise ValueError(f"{name} must be a positive number or {n} positive numbers, got "
                         f"{value!r}")
    return a


@dataclass(frozen=True)
class Imperfections:
    """A robot's sensing and actuation, each option off by default.

    Parameters
    ----------
    encoder_counts : float or None
        Counts per revolution of every joint's encoder; the measured angle is the nearest
        multiple of 2π/encoder_counts (None: exact).
    encoder_noise : float
        Standard deviation, in counts, of a white noise added to the angle before the
        encoder rounds it (the jitter of its last count; needs ``encoder_counts``).  Drawn
        from the seeded generator, so the seed changes the run.
    velocity : "exact", "difference" or "noise"
        "difference": q̇ is the difference of consecutive measured angles over h, filtered
        by a first-order low-pass of cut-off ``velocity_cutoff`` Hz (exact discretisation,
        pole e^{−2π f_c h}), started at q̇(0); "noise": the true q̇ plus white noise of
        standard deviation ``velocity_noise`` (rad/s).
    measurement_delay : 0 or 1
        The controller's step at t_k receives the measurement of t_{k−delay} (q(0) at k = 0).
    tau_limit, tau_rate_limit : float, n floats or None
        The torque reaching the plant is clipped to ±tau_limit and its change per sample
        to ±tau_rate_limit·h, from τ_{−1} = 0 (a robot's first command is 0).  The
        controller is not told (its filters use the torque it asked for).
    seed : int
        Seed of the noise (numpy's default generator).
    """

    encoder_counts: float | None = None
    encoder_noise: float = 0.0
    velocity: str = "exact"
    velocity_cutoff: float = 200.0
    velocity_noise: float = 0.0
    measurement_delay: int = 0
    tau_limit: object = None
    tau_rate_limit: object = None
    seed: int = 0

    def __post_init__(self):
        if self.encoder_counts is not None:
            c = float(self.encoder_counts)
            if not (math.isfinite(c) and c > 0):
                raise ValueError(f"encoder_counts must be a positive number of counts per "
                                 f"revolution, got {self.encoder_counts!r}")
        if not (math.isfinite(float(self.encoder_noise)) and self.encoder_noise >= 0):
            raise ValueError(f"encoder_noise must be a standard deviation >= 0 (counts), got "
                             f"{self.encoder_noise!r}")
        if self.encoder_noise > 0 and self.encoder_counts is None:
            raise ValueError("encoder_noise is in counts of the encoder: it needs "
                             "encoder_counts")
        if self.velocity not in VELOCITY_MODES:
            raise ValueError(f"velocity must be one of {', '.join(VELOCITY_MODES)}, got "
                             f"{self.velocity!r}")
        if not (math.isfinite(float(self.velocity_cutoff)) and self.velocity_cutoff > 0):
            raise ValueError(f"velocity_cutoff must be a positive frequency in Hz, got "
                             f"{self.velocity_cutoff!r}")
        if not (math.isfinite(float(self.velocity_noise)) and self.velocity_noise >= 0):
            raise ValueError(f"velocity_noise must be a standard deviation >= 0 (rad/s), got "
                             f"{self.velocity_noise!r}")
        if self.measurement_delay not in (0, 1):
            raise ValueError(f"measurement_delay must be 0 or 1 samples, got "
                             f"{self.measurement_delay!r}")
        if not isinstance(self.seed, (int, np.integer)):
            raise ValueError(f"seed must be an integer, got {self.seed!r}")

    @property
    def active(self) -> list[str]:
        """The options that change anything, as text (empty: the ideal robot)."""
        out = []
        if self.encoder_counts is not None:
            out.append(f"encoder {self.encoder_counts:g} counts/rev")
        if self.encoder_noise > 0:
            out.append(f"encoder noise σ = {self.encoder_noise:g} counts")
        if self.velocity == "difference":
            out.append(f"velocity by a filtered difference ({self.velocity_cutoff:g} Hz)")
        elif self.velocity == "noise" and self.velocity_noise > 0:
            out.append(f"velocity noise σ = {self.velocity_noise:g} rad/s")
        if self.measurement_delay:
            out.append(f"measurement delay {self.measurement_delay} sample")
        if self.tau_limit is not None:
            out.append(f"torque limit {np.asarray(self.tau_limit).tolist()} N·m")
        if self.tau_rate_limit is not None:
            out.append(f"torque rate limit {np.asarray(self.tau_rate_limit).tolist()} N·m/s")
        return out

    @property
    def random(self) -> bool:
        """Whether the run draws noise (then its ``seed`` changes it)."""
        return self.encoder_noise > 0 or (self.velocity == "noise" and self.velocity_noise > 0)

    def scaled(self, level: float) -> "Imperfections":
        """The same robot with its sensor noise ``level`` times larger: the encoder's
        quantum (2π/counts) and the velocity noise σ times ``level`` (the encoder noise,
        in counts, grows with the count)."""
        level = float(level)
        if not (math.isfinite(level) and level > 0):
            raise ValueError(f"noise level must be a positive number, got {level!r}")
        return replace(self, encoder_counts=None if self.encoder_counts is None
                       else self.encoder_counts / level,
                       velocity_noise=self.velocity_noise * level)

    def start(self, n: int, h: float, q0, dq0) -> "Robot":
        """The state of one run (n joints, sample h, the plant's q(0), q̇(0))."""
        return Robot(self, n, h, q0, dq0)

    def as_dict(self) -> dict:
        return {f.name: (np.asarray(getattr(self, f.name)).tolist()
                         if isinstance(getattr(self, f.name), np.ndarray)
                         else getattr(self, f.name))
                for f in fields(self) if not f.name.startswith("_")}


#: The realistic Panda-like sensing of docs/mujoco.md: 2^18 counts per revolution, velocity
#: by a filtered difference at 200 Hz, one sample of measurement delay.
REALISTIC = Imperfections(encoder_counts=2.0 ** 18, velocity="difference",
                          velocity_cutoff=200.0, measurement_delay=1)


class Robot:
    """One run's sensors and actuator (made by :meth:`Imperfections.start`).

    ======  ===================================================================
    states  q_prev[n] (last measured angle), dq_f[n] (filtered difference),
            held (the measurement waiting one sample), tau_prev[n] (last torque
            applied, for the rate limit), the noise generator
    inputs  measure: q[n], dq[n] of the plant at t_k; actuate: τ_k of the controller
    output  measure: (q_m, dq_m) for the controller; actuate: τ applied to the plant
    params  an :class:`Imperfections`, h
    ======  ===================================================================
    """

    def __init__(self, spec: Imperfections, n: int, h: float, q0, dq0):
        self.spec, self.n, self.h = spec, int(n), float(h)
        self.quantum = None if spec.encoder_counts is None else \
            2.0 * math.pi / float(spec.encoder_counts)
        self.tau_limit = _limit("tau_limit", spec.tau_limit, n)
        self.tau_rate_limit = _limit("tau_rate_limit", spec.tau_rate_limit, n)
        self.rng = np.random.default_rng(spec.seed)
        self.jitter = None if spec.encoder_noise == 0 else \
            float(spec.encoder_noise) * self.quantum           # σ in rad
        # the filtered difference: pole e^{-2π f_c h}, started at rest values
        self.pole = math.exp(-2.0 * math.pi * spec.velocity_cutoff * self.h)
        self.q_prev = self._quantize(np.array(q0, dtype=float))
        self.dq_f = np.array(dq0, dtype=float)
        self.held = None
        self.tau_prev = np.zeros(self.n)

    def _quantize(self, q):
        if self.quantum is None:
            return q
        return self.quantum * np.round(q / self.quantum)

    def measure(self, q, dq):
        """(q_m, dq_m) the controller receives at t_k from the plant's q(t_k), q̇(t_k)."""
        s = self.spec
        if self.jitter is not None:
            q = q + self.jitter * self.rng.standard_normal(self.n)
        qm = self._quantize(q)
        if s.velocity == "difference":
            raw = (qm - self.q_prev) / self.h
            self.dq_f = raw + self.pole * (self.dq_f - raw)     # x+ = u + p (x - u)
            dqm = self.dq_f.copy()
        elif s.velocity == "noise":
            dqm = dq + s.velocity_noise * self.rng.standard_normal(self.n)
        else:
            dqm = dq
        self.q_prev = qm
        if s.measurement_delay:
            out = (qm, dqm) if self.held is None else self.held
            self.held = (np.copy(qm), np.copy(dqm))
            return out
        return qm, dqm

    def actuate(self, tau):
        """The torque that reaches the plant for the controller's command ``tau``."""
        if self.tau_rate_limit is not None:
            step = self.tau_rate_limit * self.h
            tau = self.tau_prev + np.clip(tau - self.tau_prev, -step, step)
        if self.tau_limit is not None:
            tau = np.clip(tau, -self.tau_limit, self.tau_limit)
        if self.tau_rate_limit is not None:
            self.tau_prev = np.copy(tau)
        return tau
