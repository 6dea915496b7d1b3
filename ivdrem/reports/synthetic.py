"""Synthetic paper runs: made-up but consistent signals with the layout of a real run.

They let the report and the metrics be tested (and a report layout previewed) in a
second, without simulating anything.  Nothing here is a simulation result: every
signal is a closed-form curve chosen so that the conclusions C1-C3 come out as asked.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import control as ct
import numpy as np

__all__ = ["SyntheticLawRun", "SyntheticPaperRun", "synthetic_lawrun", "synthetic_paper_run"]


@dataclass
class SyntheticLawRun:
    """Duck type of ``ivdrem.experiments.paper.LawRun``."""

    law: str
    response: Any
    stats: dict = field(default_factory=dict)


@dataclass
class SyntheticPaperRun:
    """Duck type of ``ivdrem.experiments.paper.PaperRun``."""

    config: dict
    theta: np.ndarray
    runs: dict
    synthetic: bool = True


def _sinusoids(spec, t):
    a, w, ph, c = (np.asarray(spec[k], dtype=float)[:, None] for k in ("amplitude", "omega", "phase", "offset"))
    return a * np.sin(w * t[None, :] + ph) + c


def synthetic_lawrun(law, t, theta, theta_err, tau_d_err, config, *, e=None, delta=None,
                     calW=None, lambda_min=None, stats=None) -> SyntheticLawRun:
    """A LawRun whose outputs are built from the given errors.

    theta_err (nθ × n_t) = θ − θ̂ and tau_d_err (n × n_t) = τ_d − τ̂_d are given; the
    other outputs are made consistent with them (θ̂ = θ − θ̃, τ̂_d = τ_d − τ̃_d,
    q = q_d − e, r = ė + αe, 𝒴 = Δθ + 𝒲, μ = mu0·t + mu1, ...).
    """
    t = np.asarray(t, dtype=float)
    theta = np.asarray(theta, dtype=float)
    nth, n_t = theta.size, t.size
    qd = _sinusoids(config["trajectory"], t)
    n = qd.shape[0]
    tau_d = _sinusoids(config["disturbance"], t)
    if e is None:
        e0 = qd[:, :1] - np.asarray(config["initial"]["q0"], dtype=float)[:, None]
        e = e0 * np.exp(-t / 2.0)[None, :] + 1e-3 * np.sin(2.0 * t)[None, :]
    e = np.asarray(e, dtype=float).reshape(n, n_t)
    alpha = float(config["controller"]["alpha"])
    de = np.gradient(e, t, axis=1) if n_t > 1 else np.zeros_like(e)
    r = de + alpha * e
    mu = float(config["controller"]["mu0"]) * t + float(config["controller"]["mu1"])
    K = np.asarray(config["controller"]["K"], dtype=float)[:, None]
    tau_d_hat = tau_d - np.asarray(tau_d_err, dtype=float).reshape(n, n_t)
    grav = 9.81 * np.vstack([np.cos(qd[0])] * n) * theta[-1]
    tau = (K + float(config["controller"]["delta_mu"]) * mu[None, :]) * r + grav - tau_d_hat
    theta_hat = theta[:, None] - np.asarray(theta_err, dtype=float).reshape(nth, n_t)

    labels, rows = [], []

    def add(name, x):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[0] == 1 and name in ("mu", "Delta", "lambda_min_held"):
            labels.append(name)
            rows.append(x[0])
            return
        for i in range(x.shape[0]):
            labels.append(f"{name}[{i}]")
            rows.append(x[i])

    add("q", qd - e)
    add("q_d", qd)
    add("e", e)
    add("r", r)
    add("tau", tau)
    add("tau_d", tau_d)
    add("tau_d_hat", tau_d_hat)
    add("theta_hat", theta_hat)
    add("mu", mu)
    if law in ("iv-drem", "drem"):
        T = float(config["iv_drem"]["T"])
        if delta is None:
            on = t >= T
            delta = np.where(on, 1e-4 * (1 - np.exp(-(t - T) / 3.0)) * T / np.maximum(t, T), 0.0)
        if calW is None:
            decay = np.where(t >= T, (T / np.maximum(t, T)) ** 3, 0.0)
            calW = 1e-6 * decay[None, :] * np.sin(np.outer(np.arange(1, nth + 1), t))
        delta = np.asarray(delta, dtype=float)
        add("Delta", delta)
        add("calY", delta[None, :] * theta[:, None] + np.asarray(calW, dtype=float))
    if law == "composite-learning":
        if lambda_min is None:
            T = float(config["composite_learning"]["T"])
            raw = 2e-3 * (1 - np.exp(-t / T)) * (1 + 0.3 * np.sin(0.2 * t))
            lambda_min = np.maximum.accumulate(raw)
        add("lambda_min_held", lambda_min)
    resp = ct.TimeResponseData(t, np.vstack(rows), output_labels=labels, issiso=False,
                               title=f"synthetic {law}")
    if stats is None:
        solver = config["solver"]
        stats = {"method": solver["method"], "steps": int(40 * t[-1]), "rejected": int(0.3 * t[-1]),
                 "rhs_calls": int(280 * t[-1]), "wall_s": 0.01 * t[-1], "rtol": solver["rtol"],
                 "atol": solver["atol"], "h": solver["h"]}
    return SyntheticLawRun(law=law, response=resp, stats=stats)


def synthetic_paper_run(config=None, *, t_end=None, dt=None, laws=None, cl_converges=False,
                        iv_converges=True, iv_tau_better=True) -> SyntheticPaperRun:
    """A PaperRun with made-up signals; by default C1, C2, C3 all hold.

    cl_converges=True makes composite learning converge (C1 fails), iv_converges=False
    makes IV-DREM stall (C2 fails), iv_tau_better=False gives IV-DREM the baseline's
    τ_d error (C3 fails).
    """
    from ..experiments.config import read_config

    if config is None:   # the paper's 2-link experiment: its data is complete (no model needed)
        config = read_config()
    config = getattr(config, "config", config)     # an Experiment's configuration
    t_end = float(config["experiment"]["t_end"] if t_end is None else t_end)
    dt = float(config["experiment"]["dt_out"] if dt is None else dt)
    laws = list(config["experiment"]["laws"] if laws is None else laws)
    config = {s: dict(v) for s, v in config.items()}
    config["experiment"] = dict(config["experiment"], t_end=t_end, dt_out=dt, laws=laws)
    t = np.linspace(0.0, t_end, int(round(t_end / dt)) + 1)
    theta = np.asarray(config["model"]["theta"], dtype=float)
    theta0_err = theta - np.asarray(config["initial"]["theta_hat0"], dtype=float)
    wig = np.sin(np.outer(np.arange(1, theta.size + 1), 0.7 * t))

    def stalled():
        shape = 0.35 + 0.65 * np.exp(-t / (t_end / 12))
        return theta0_err[:, None] * shape[None, :] * (1 + 0.02 * wig)

    def converging():
        shape = np.exp(-t / (t_end / 8))
        return theta0_err[:, None] * shape[None, :] * (1 + 0.05 * wig)

    tau_w = config["disturbance"]["omega"]
    tau_big = np.vstack([0.6 * np.sin(tau_w[i] * t + 0.4) + 0.1 * np.sin(3 * t) for i in range(len(tau_w))])
    tau_small = tau_big * (0.05 + 0.95 * np.exp(-t / (t_end / 6)))[None, :]
    runs = {}
    for law in laws:
        if law == "composite-learning":
            err = converging() if cl_converges else stalled()
            tau_err = tau_big
        elif law == "iv-drem":
            err = converging() if iv_converges else stalled()
            tau_err = tau_small if iv_tau_better else tau_big
        else:
            err = stalled()
            tau_err = tau_big
        runs[law] = synthetic_lawrun(law, t, theta, err, tau_err, config)
    return SyntheticPaperRun(config=config, theta=theta, runs=runs)
