#!/usr/bin/env python
"""ivdrem's drop-in (ivdrem.pycontrol.input_output_response) against
ct.input_output_response, side by side in one run.

Systems: nonlinear systems of python-control's test suite (the kinematic car of
iosys_test.py with a sinusoidal steering input, the Van der Pol oscillator of its
phase-plane tests, here also at mu = 100 where it is stiff) and the predator-prey example of
python-control's documentation (nlsys, "Example: predator-prey", 0.10.2; its input is
zero: the open-loop run of the documentation).

Each call has the same arguments on both sides (solve_ivp's defaults: RK45 / dp45 at rtol
1e-3, atol 1e-6; the stiff case also with ``solve_ivp_method="Radau"`` / Rodas5P).  Every
call is repeated ``--reps`` times after a warm-up (ivdrem's compile and cache load apart);
the median wall time is printed with the ratio python-control / ivdrem, and the largest
output error of each against solve_ivp's DOP853 at rtol 1e-12 on the same right-hand
side, relative to the largest output.

Usage::

    PYTHONPATH=. python benchmarks/bench_pycontrol.py [--reps 3] [--engine compiled]
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import control as ct
from scipy.integrate import solve_ivp

from ivdrem import pycontrol as pc


def kincar_update(t, x, u, params):
    # the kinematic car of python-control's iosys_test.py (wheelbase l)
    l = params.get("l", 1.0)
    return np.array([np.cos(x[2]) * u[0], np.sin(x[2]) * u[0], np.tan(u[1]) * u[0] / l])


def kincar_output(t, x, u, params):
    return x[0:2].copy()


def vanderpol_update(t, x, u, params):
    mu = params.get("mu", 1.0)
    return np.array([x[1], mu * (1.0 - x[0] * x[0]) * x[1] - x[0]])


def predprey_update(t, x, u, params):
    # python-control's documentation example (Lotka-Volterra with a predator satiation
    # term); its parameters as given there
    r = params.get("r", 1.6)
    d = params.get("d", 0.56)
    b = params.get("b", 0.6)
    k = params.get("k", 125.0)
    a = params.get("a", 3.2)
    c = params.get("c", 50.0)
    H, L = x[0], x[1]
    dH = (r + u[0]) * H * (1.0 - H / k) - (a * H * L) / (c + H)
    dL = b * (a * H * L) / (c + H) - d * L
    return np.array([dH, dL])


def cases():
    car = ct.nlsys(kincar_update, kincar_output, inputs=["v", "delta"], outputs=["x", "y"],
                   states=3, name="kincar", params={"l": 1.0})
    T = np.linspace(0, 20, 201)
    U = np.vstack([10 * np.ones_like(T), 0.1 * np.sin(T)])
    vdp = ct.nlsys(vanderpol_update, None, inputs=0, states=2, outputs=2, name="vanderpol",
                   params={"mu": 1.0})
    Tv = np.linspace(0, 20, 401)
    pp = ct.nlsys(predprey_update, None, inputs=("u",), outputs=("H", "L"),
                  states=("H", "L"), name="predprey")
    Tp = np.linspace(0, 70, 500)
    return [
        ("kinematic car (iosys_test)", car, T, U, [0, 0, 0], {}, None),
        ("Van der Pol mu=1 (phaseplot_test)", vdp, Tv, 0, [2, 0], {"mu": 1.0}, None),
        ("Van der Pol mu=100, RK45", vdp, np.linspace(0, 200, 401), 0, [2, 0],
         {"mu": 100.0}, None),
        ("Van der Pol mu=100, Radau", vdp, np.linspace(0, 200, 401), 0, [2, 0],
         {"mu": 100.0}, "Radau"),
        ("predator-prey (documentation)", pp, Tp, 0, [10, 10], {}, None),
    ]


def _reference(sys, T, U, X0, params):
    """DOP853 at rtol 1e-12 on python-control's own right-hand side and output."""
    sys._update_params(params)
    Ua = np.broadcast_to(np.asarray(U, float), (sys.ninputs, T.size)) if sys.ninputs \
        else np.zeros((0, T.size))

    def u_at(t):
        return np.array([np.interp(t, T, row) for row in Ua])
    sol = solve_ivp(lambda t, x: sys._rhs(t, x, u_at(t)), (T[0], T[-1]), X0,
                    method="DOP853", t_eval=T, rtol=1e-12, atol=1e-12)
    return np.column_stack([sys._out(t, sol.y[:, i], u_at(t)) for i, t in enumerate(T)])


def _time(fn, reps):
    fn()                                   # warm-up: compile, caches, imports
    walls = []
    for _ in range(reps):
        t0 = time.perf_counter()
        resp = fn()
        walls.append(time.perf_counter() - t0)
    return statistics.median(walls), resp


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--engine", default="compiled", choices=("compiled", "reference"))
    a = ap.parse_args(argv)
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    print(f"{'system':36s} {'python-control s':>16s} {'ivdrem s':>10s} {'ratio':>7s} "
          f"{'err python-control':>18s} {'err ivdrem':>11s}")
    for name, sys, T, U, X0, params, method in cases():
        kw = dict(params=params)
        if method:
            kw["solve_ivp_method"] = method
        ref = _reference(sys, T, U, X0, params)
        scale = np.max(np.abs(ref))
        t_ct, r_ct = _time(lambda: ct.input_output_response(sys, T, U, X0, **kw), a.reps)
        t_iv, r_iv = _time(lambda: pc.input_output_response(sys, T, U, X0, engine=a.engine,
                                                            **kw), a.reps)
        e_ct = np.max(np.abs(np.reshape(r_ct.y, ref.shape) - ref)) / scale
        e_iv = np.max(np.abs(np.reshape(r_iv.y, ref.shape) - ref)) / scale
        print(f"{name:36s} {t_ct:16.4f} {t_iv:10.4f} {t_ct / t_iv:7.1f} {e_ct:18.2e} "
              f"{e_iv:11.2e}", flush=True)
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
