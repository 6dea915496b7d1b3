#!/usr/bin/env python
"""IV-DREM at the size of real arms: per arm nθ, states, steps, sim seconds, peak memory and
‖θ̃(t_end)‖/‖θ̃(0)‖, the paper's mixing (17) and the best variant side by side, and the
fitted growth of sim time with nθ (docs/mixing.md).

Usage::

    ./run python benchmarks/bench_arms.py                      # planar-2..6, 300 s, paper + eigen
    ./run python benchmarks/bench_arms.py --t-end 60 --arms planar-4,planar-5
    ./run python benchmarks/bench_arms.py --variants paper,eigen,channel --json out.json
    ./run python benchmarks/bench_arms.py --accuracy           # the mixing's own accuracy only
    OPENBLAS_NUM_THREADS=1 ./run python benchmarks/bench_arms.py --arms ur5,panda --variants eigen --t-end 60
                                                               # the real arms (docs/mixing-derivations.md, "On real arms")
    OPENBLAS_NUM_THREADS=1 ./run python benchmarks/bench_arms.py --step --arms panda,ur5
                                                               # a Rosenbrock step's parts (docs/performance.md)
    ./run python benchmarks/bench_arms.py --model-calls --arms panda [--against OTHER.so]
                                                               # the model's derivatives one Jacobian calls

Run it with ``OPENBLAS_NUM_THREADS=1``: on a shared 2-core machine OpenBLAS's own threads
slow the mixing's small SVDs down instead of up.  The UR5 and the Panda
are not in the default list: each first run compiles its loops for minutes and 60 s of
simulation take minutes more (docs/mixing-derivations.md, "On real arms").

``--arms`` takes model names of ``ivdrem.models.get_model`` or ``module:factory`` (a
function returning an EulerLagrangeModel).  Each run is a child process (peak memory is its
maximum resident set); the planar arms get :func:`planar_experiment` (a reference exciting
every joint at its own frequency, disturbances at frequencies the reference does not
have), other arms closed_loop's own defaults for their model.  ``--accuracy`` compares the
paper's Δ and 𝒲 = 𝒴 − Δθ (with Y = Ψθ exactly, so 𝒲 should be 0) of the signed-SVD mixing
against the Faddeev-LeVerrier recursion it replaced, on each arm's reference Ψ.
"""
from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
try:
    import ivdrem  # noqa: F401
except ImportError:
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

PI = math.pi
#: reference frequencies per joint (rad/s), distinct; planar-3 is examples/planar3.toml
OMEGA = (1.0, 1.7, 2.3, 3.1, 3.7, 4.6, 5.3, 5.9)
#: disturbance frequencies per joint (rad/s): the paper's two, then ones of no reference joint
D_OMEGA = (0.5 * PI, 0.05 * PI, 0.25 * PI, 0.1 * PI, 0.03 * PI, 0.4 * PI, 0.07 * PI, 0.6 * PI)


def planar_experiment(n):
    """closed_loop keyword arguments of the planar-n experiment: trajectory, disturbance, q0."""
    if not 1 <= n <= len(OMEGA):
        raise ValueError(f"planar_experiment: n must be in 1..{len(OMEGA)}, got {n}")
    amp = ([0.4 * PI, 0.3 * PI] + [0.2 * PI] * n)[:n]
    off = ([0.2 * PI, 0.3 * PI] + [0.0] * n)[:n]
    phase = [0.0 if i % 2 == 0 else PI / 2 for i in range(n)]
    traj = dict(amplitude=amp, omega=list(OMEGA[:n]), phase=phase, offset=off)
    dist = dict(amplitude=([7.5, 1.5] + [0.5] * n)[:n], omega=list(D_OMEGA[:n]),
                phase=[0.0] * n, offset=[0.0] * n)
    q0 = ([0.0, 0.3 * PI] + [0.0] * n)[:n]
    return dict(trajectory=traj, disturbance=dist, q0=q0, dq0=[0.0] * n)


def planar_config_overrides(n):
    """The same experiment as configuration overrides (``ivdrem paper --config`` keys)."""
    e = planar_experiment(n)
    return {"model.name": f"planar-{n}", "initial.q0": e["q0"],
            **{f"trajectory.{k}": v for k, v in e["trajectory"].items()},
            **{f"disturbance.{k}": v for k, v in e["disturbance"].items()}}


def resolve_model(spec):
    """A model from a name of ivdrem.models.get_model or "module:factory"."""
    if ":" in spec:
        mod, fn = spec.split(":", 1)
        return getattr(importlib.import_module(mod), fn)()
    from ivdrem.models import get_model
    return get_model(spec)


def _experiment(model):
    """The planar arms' experiment, or for another arm the configuration's own (the real-arm
    reference and disturbance designed for it, q(0) on the reference, the window T)."""
    import re
    m = re.fullmatch(r"planar-(\d+)", model.name)
    if m:
        return planar_experiment(int(m.group(1)))
    from ivdrem.experiments.config import closed_loop_kwargs, read_config, resolve_config
    kw = closed_loop_kwargs(resolve_config(read_config(overrides={"model.name": model.name}))[0], "iv-drem")
    # T: the window the real-arm design gives (a common period of reference and disturbance)
    return {**{k: kw[k] for k in ("trajectory", "disturbance", "q0", "dq0")},
            "T": kw["gains"]["T"]}


def _window(exp):
    """The window T of an experiment of :func:`_experiment` (a gain of the law), taken out
    of it: {"T": T}, or nothing for the planar arms' (the law's own T)."""
    T = exp.pop("T", None)
    return {} if T is None else {"T": T}


# ----------------------------------------------------------------- reference Ψ and Δ
def reference_psi(model, exp, *, t_end=40.0, dt=0.01, l=50.0, T=20.0, p=2.0, F0=1.0):
    """(t, Ψ(t), Y/θ-free) of (15a)-(15b) along the reference with perfect tracking:
    φ = ζ = the filtered Φ(q_d, q̇_d, q̈_d) of (14), Ψ = ∫Ḟψ/F with ψ = ∫_{t−T}^t ζζᵀ."""
    from scipy.integrate import cumulative_trapezoid
    tr = exp["trajectory"]
    a, w = np.asarray(tr["amplitude"], float), np.asarray(tr["omega"], float)
    ph, c = np.asarray(tr["phase"], float), np.asarray(tr["offset"], float)
    t = np.arange(0.0, t_end + 0.5 * dt, dt)
    arg = np.outer(w, t) + ph[:, None]
    q = a[:, None] * np.sin(arg) + c[:, None]
    dq = (a * w)[:, None] * np.cos(arg)
    ddq = -(a * w * w)[:, None] * np.sin(arg)
    n, nth = model.n, model.ntheta
    Phi = np.empty((t.size, n, nth))
    buf = np.empty((n, nth))
    for k in range(t.size):
        model.functions.Phi(q[:, k], dq[:, k], dq[:, k], ddq[:, k], buf)
        Phi[k] = buf
    Z = np.zeros_like(Phi)                       # ζ̇ = l(Φ − ζ), first-order hold
    e = math.exp(-l * dt)
    b2 = 1.0 - (1.0 - e) / (l * dt)
    for k in range(1, t.size):
        Z[k] = e * Z[k - 1] + (1.0 - e) * Phi[k - 1] + b2 * (Phi[k] - Phi[k - 1])
    prod = np.einsum("tjk,tjl->tkl", Z, Z)
    cum = cumulative_trapezoid(prod, t, axis=0, initial=0.0)
    lag = int(round(T / dt))
    psi = cum.copy()
    psi[lag:] -= cum[:-lag]
    F, dF = t ** p + F0, p * t ** (p - 1)
    Psi = cumulative_trapezoid(dF[:, None, None] * psi, t, axis=0, initial=0.0) / F[:, None, None]
    return t, Psi


def reference_delta(model, exp, *, t_end=40.0, **kw):
    """(t, {variant: Δ (k × n_t)}, {variant: log10|Δ| (k × n_t)}) of every mixing variant on
    the reference Ψ of :func:`reference_psi`."""
    from ivdrem.blocks._kernels import MIXING_VARIANTS, mixing_values
    from ivdrem.blocks.mixing import DEFAULT_F_REL, DEFAULT_GUARD
    t, Psi = reference_psi(model, exp, t_end=t_end, **kw)
    nth = model.ntheta
    D, L = {}, {}
    Y = np.zeros(nth)
    calY = np.empty(nth)
    for code, v in enumerate(MIXING_VARIANTS):
        k = nth if v == "channel" else 1
        D[v], L[v] = np.empty((k, t.size)), np.empty((k, t.size))
        d, lg = np.empty(k), np.empty(k)
        for i in range(t.size):
            mixing_values(code, Y, np.ascontiguousarray(Psi[i]).ravel(), DEFAULT_F_REL,
                          DEFAULT_GUARD, d, calY, lg)
            D[v][:, i], L[v][:, i] = d, lg
    return t, D, L


def faddeev_leverrier(A):
    """det A and adj A by the Faddeev-LeVerrier recursion (the mixing's method before the
    signed SVD): M_1 = I, c_{n-k} = -tr(A M_k)/k, M_{k+1} = A M_k + c_{n-k} I."""
    n = A.shape[0]
    M = np.eye(n)
    c = 1.0
    for k in range(1, n + 1):
        AM = A @ M
        c = -np.trace(AM) / k
        if k < n:
            M = AM + c * np.eye(n)
    sign = 1.0 if n % 2 == 1 else -1.0
    return -sign * c, sign * M


def accuracy_rows(arms, t_end=40.0):
    """Per arm: the paper's Δ and the numerical bias ‖𝒲‖/|Δ| (Y = Ψθ, so exactly 0) of the
    signed SVD and of Faddeev-LeVerrier, at t = t_end on the reference Ψ; mpmath at 60 digits
    as the oracle of Δ.  Arms with a Fourier reference (the real arms) are left out: the
    reference Ψ here integrates sinusoids."""
    import mpmath as mp
    from ivdrem.blocks._kernels import det_adj
    rows = []
    for spec in arms:
        model = resolve_model(spec)
        exp = _experiment(model)
        if not isinstance(exp["trajectory"], dict):    # a real arm's Fourier reference block
            continue
        t, Psi = reference_psi(model, exp, t_end=t_end)
        P0 = Psi[-1]
        s = 1.0 + np.linalg.norm(P0)
        P = P0 / s
        theta = np.asarray(model.theta_values, float)
        Y = P0 @ theta
        with mp.workdps(60):
            ref = float(mp.det(mp.matrix(P.tolist())))
        adj = np.empty_like(P)
        d_svd = det_adj(np.ascontiguousarray(P), adj)
        W_svd = adj @ Y / s - d_svd * theta
        d_fl, adj_fl = faddeev_leverrier(P)
        W_fl = adj_fl @ Y / s - d_fl * theta
        rows.append(dict(arm=model.name, ntheta=model.ntheta, cond=float(np.linalg.cond(P)),
                         Delta=ref, rel_err_svd=abs(d_svd - ref) / abs(ref),
                         rel_err_fl=abs(d_fl - ref) / abs(ref),
                         bias_svd=float(np.linalg.norm(W_svd) / abs(ref)),
                         bias_fl=float(np.linalg.norm(W_fl) / abs(ref)),
                         theta_norm=float(np.linalg.norm(theta))))
    return rows


# ----------------------------------------------------------------- one closed-loop run
def run_one(spec, variant, t_end, method="rodas5p", rtol=2e-4, atol=2e-6, h_max=5.0):
    """One IV-DREM run of arm `spec` with mixing `variant` and gamma = "auto" (the rule of
    docs/mixing.md, calibrated with the same solver): the row of the table."""
    import resource
    import warnings
    from ivdrem.diagrams import calibrated_loop
    from ivdrem.diagrams.gamma_auto import GainRuleError
    from ivdrem.experiments.metrics import signal
    from ivdrem.sim import simulate
    t0 = time.perf_counter()
    model = resolve_model(spec)
    n, nth = model.n, model.ntheta
    solver = dict(method=method, rtol=rtol, atol=atol, h_max=h_max)
    row = dict(arm=model.name, variant=variant, ntheta=nth, t_end=t_end)
    try:
        exp = _experiment(model)
        window = _window(exp)
        d = calibrated_loop("iv-drem", model, gains=dict(mixing=variant, gamma="auto", **window),
                            theta_hat0=np.zeros(nth), K=2.0 * np.eye(n), **exp,
                            calibration=solver)
    except GainRuleError as e:
        row.update(refused=str(e))
        return row
    row["build_s"] = time.perf_counter() - t0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = simulate(d, t_end, progress=False, return_states=False, allow_long=True, **solver)
    theta = np.asarray(model.theta_values, float)
    err = np.linalg.norm(theta[:, None] - signal(r, "theta_hat"), axis=0)
    g = d.gamma_choice["gamma"]
    row.update(states=int(r.stats.get("states", 0) or _states(d)), steps=int(r.stats["steps"]),
               rejected=int(r.stats.get("rejected", 0)), sim_s=float(r.stats["sim_s"]),
               err0=float(err[0]), err_end=float(err[-1]), ratio=float(err[-1] / err[0]),
               gamma=[float(np.min(g)), float(np.max(g))] if np.ndim(g) else [float(g)] * 2,
               peak_MiB=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    return row


def step_row(spec, variant="eigen", t_at=None, steps=40, method="rodas5p", rtol=2e-4,
             atol=2e-6, h_max=5.0, gamma="auto"):
    """What a Rodas5P step of arm `spec`'s IV-DREM loop costs at t_at (default: 5 s after
    the window T, when the composite term is on and the adaptation law's rows of df/dx are
    no longer mostly zero): the next `steps` steps as the stepper takes them, and its parts
    through the engine's entry points at the state reached (a right-hand side, the Jacobian
    with the right-hand side it evaluates first, the factorisation of c I - J, a solve).
    Times are this thread's CPU time (time.thread_time), best of 5, so that a loaded
    machine's waiting is not counted; the same computation each time."""
    from ivdrem.diagrams import calibrated_loop
    from ivdrem.sim import _stepper_codes
    from ivdrem.sim._diagram import LU_WORK_ROWS
    from ivdrem.sim.simulator import Simulator
    model = resolve_model(spec)
    n, nth = model.n, model.ntheta
    solver = dict(method=method, rtol=rtol, atol=atol, h_max=h_max)
    exp = _experiment(model)
    window = _window(exp)
    d = calibrated_loop("iv-drem", model, gains=dict(mixing=variant, gamma=gamma, **window),
                        theta_hat0=np.zeros(nth), K=2.0 * np.eye(n), **exp,
                        calibration=solver if isinstance(gamma, str) else None)
    T = float(window.get("T") or 20.0)
    t_at = T + 5.0 if t_at is None else float(t_at)
    sim = Simulator(d, **solver)
    sim.advance(t_at)
    k0, c0, t0 = int(sim.stats[0]), time.thread_time(), sim.t
    while int(sim.stats[0]) - k0 < steps:
        sim.advance(sim.t + 0.05)
    per_step = (time.thread_time() - c0) / (int(sim.stats[0]) - k0)
    E, W, x, t = sim.engine, sim.W, sim.x.copy(), float(sim.t)
    mod, tb, P = E.module, E.tables, E.P
    nx = x.size

    def best(f, reps):
        f()
        out = []
        for _ in range(5):
            a = time.thread_time()
            for _ in range(reps):
                f()
            out.append((time.thread_time() - a) / reps)
        return 1e3 * min(out)

    J, tmp, dx = np.zeros(int(tb.lu_rowptr[-1])), np.zeros(nx), np.zeros(nx)
    rhs = best(lambda: mod.diagram_eval(W, P, _stepper_codes.RHS, t, x, dx), 20)
    jac = best(lambda: mod.diagram_jacobian(W, P, t, x, J, tmp), 5)
    piv = np.zeros(nx, dtype=np.int64)
    LU = np.zeros(int(tb.lu_rowptr[-1]) + LU_WORK_ROWS * nx)
    c = 1.0 / (0.2 * max(sim.tf[_stepper_codes.F_H], 1e-6))
    fac = best(lambda: mod.slu_factor(J, nx, c, LU, piv, tb.lu_perm, tb.lu_rowptr,
                                      tb.lu_colidx, tb.lu_diagp, tb.lu_panel_rows,
                                      tb.lu_panel_kptr, tb.lu_panel_k), 5)
    b = np.random.default_rng(0).standard_normal(nx)
    sol = best(lambda: mod.slu_solve(LU, nx, tb.lu_perm, tb.lu_rowptr, tb.lu_colidx,
                                     tb.lu_diagp, b.copy()), 20)
    return dict(arm=model.name, states=nx, t=t, t_from=t0, steps=int(sim.stats[0]) - k0,
                step_ms=1e3 * per_step, rhs_ms=rhs, jacobian_ms=jac, factor_ms=fac,
                solve_ms=sol, chain_runs=int(tb.jac_run_dst.size),
                lu_nnz=int(tb.lu_rowptr[-1]), theta_hat=_theta_hat(sim).tolist(),
                gamma=np.asarray(d.gamma_choice["gamma"] if isinstance(gamma, str) else gamma,
                                 float).tolist())


# ----------------------------------------------------------------- the model's derivatives
#: what the blocks' Jacobian kernels ask the robot model for in one Jacobian of the loop
#: (ivdrem/blocks/jacobians.py): block, function, arguments (v = dq where the block passes
#: q̇ twice)
JACOBIAN_MODEL_CALLS = (
    ("observer", "Phi_M_jac", ("q", "r")), ("observer", "Phi_jac", ("q", "dq", "v", "dv")),
    ("observer", "Phi_C_jac", ("q", "dq", "r")), ("observer", "Phi_dM_jac", ("q", "dq", "r")),
    ("filter", "Phi_M_jac", ("q", "dq")), ("filter", "Phi_C_jac", ("q", "dq", "dq")),
    ("filter", "Phi_dM_jac", ("q", "dq", "dq")), ("filter", "Phi_G_jac", ("q",)),
    ("plant", "Phi_jac", ("q", "dq", "dq", "qdd")),
    ("instrument", "Phi_jac", ("qd", "dqd", "dqd", "ddqd")))


def model_call_rows(spec, against=None, reps=15, calls=40):
    """The robot model's C functions a Jacobian of the loop calls (JACOBIAN_MODEL_CALLS), each
    timed in this thread's CPU time (best of `reps` x `calls`) at random arguments; with
    `against` (the path of another version's C library of the same model, e.g. from the
    compile cache of a previous version's run) the two alternately in this process, and the
    largest difference of their results relative to the largest entry."""
    import ctypes
    from ivdrem.models import _c_engine
    model = resolve_model(spec)
    if _c_engine.load(model) is None:
        raise SystemExit("model_call_rows: no C compiler (the model's C library is timed)")
    libs = {"this": (ctypes.CDLL(str(_c_engine.library_path(model.key))),
                     _c_engine.symbol_prefix(model.key))}
    if against:
        # the library's name starts with the key of its model (_c_engine.library_path)
        libs["other"] = (ctypes.CDLL(str(against)), f"ivdrem_{Path(against).name[:16]}_")
    n, nb = model.n, model.ntheta
    rng = np.random.default_rng(0)
    vals = {a: rng.uniform(-1.5, 1.5, n)
            for a in ("q", "dq", "r", "v", "dv", "qdd", "qd", "dqd", "ddqd")}
    rows = []
    for block, name, args in JACOBIAN_MODEL_CALLS:
        prep, best = {}, {}
        for lab, (lib, pre) in libs.items():
            fn = getattr(lib, pre + name)
            fn.restype = None
            out = np.zeros((n, nb, len(args) * n))
            ptrs = [ctypes.c_void_p(vals[a].ctypes.data) for a in args]
            prep[lab] = (fn, ptrs + [ctypes.c_void_p(out.ctypes.data)], out)
            best[lab] = math.inf
        for _ in range(reps):
            for lab, (fn, ptrs, _out) in prep.items():
                c0 = time.thread_time()
                for _ in range(calls):
                    fn(*ptrs)
                best[lab] = min(best[lab], (time.thread_time() - c0) / calls)
        row = dict(arm=model.name, block=block, function=name, us=1e6 * best["this"])
        if against:
            a, b = prep["this"][2], prep["other"][2]
            row.update(other_us=1e6 * best["other"],
                       max_rel_diff=float(np.max(np.abs(a - b)) / np.max(np.abs(b))))
        rows.append(row)
    return rows


def _theta_hat(sim):
    idx = [i for i, label in enumerate(sim.state_labels) if "theta_hat" in label]
    return np.asarray(sim.x)[idx]


def _fmt_step(r):
    if "failed" in r:
        return f"{r['arm']:>10s}  failed: {r['failed']}"
    return (f"{r['arm']:>10s} {r['states']:6d} {r['t_from']:7.2f} {r['steps']:5d} "
            f"{r['step_ms']:8.2f} {r['rhs_ms']:7.3f} {r['jacobian_ms']:9.3f} "
            f"{r['factor_ms']:8.3f} {r['solve_ms']:7.3f} {r['chain_runs']:8d} {r['lu_nnz']:8d}")


def _states(diagram):
    return int(sum(s.nstates for s in diagram.syslist))


def _child(spec, variant, t_end, timeout, mode="--one"):
    cmd = [sys.executable, __file__, mode, spec, variant, str(t_end)]
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return dict(arm=spec, variant=variant, failed=f"over {timeout:g} s")
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        return dict(arm=spec, variant=variant, failed=(out.stderr.strip().splitlines() or ["?"])[-1])
    return json.loads(lines[-1])


def growth_exponent(rows, key="sim_s"):
    """p of key ∝ nθ^p, least squares in log-log over the rows that ran."""
    pts = [(r["ntheta"], r[key]) for r in rows if key in r and r[key] > 0]
    if len(pts) < 2:
        return float("nan")
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def _fmt_row(r):
    head = f"{r['arm']:>10s} {r['variant']:>8s}"
    if "refused" in r:
        return f"{head}  refused: {r['refused']}"
    if "failed" in r:
        return f"{head}  failed: {r['failed']}"
    return (f"{head} {r['ntheta']:4d} {r['states']:6d} {r['steps']:8d} {r['rejected']:7d} "
            f"{r['sim_s']:8.2f} {r['peak_MiB']:8.0f} {r['err0']:7.3g} {r['err_end']:9.3g} "
            f"{r['ratio']:9.3g}  {r['gamma'][0]:.2g}..{r['gamma'][1]:.2g}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arms", default="planar-2,planar-3,planar-4,planar-5,planar-6",
                    help="comma-separated model names or module:factory")
    ap.add_argument("--variants", default="paper,eigen")
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--timeout", type=float, default=1800.0, help="per run, s")
    ap.add_argument("--json", default=None)
    ap.add_argument("--accuracy", action="store_true", help="the mixing's accuracy only")
    ap.add_argument("--step", action="store_true",
                    help="a Rosenbrock step's cost and parts per arm, 5 s after the window T")
    ap.add_argument("--model-calls", action="store_true",
                    help="the robot model's derivatives a Jacobian calls, per arm (µs each)")
    ap.add_argument("--against", default=None, metavar="LIB",
                    help="with --model-calls: another version's C library of the (one) arm, "
                         "timed alternately with this one")
    ap.add_argument("--one", nargs=3, metavar=("ARM", "VARIANT", "T_END"), help=argparse.SUPPRESS)
    ap.add_argument("--one-step", nargs=3, metavar=("ARM", "VARIANT", "T_AT"),
                    help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        print(json.dumps(run_one(a.one[0], a.one[1], float(a.one[2]))), flush=True)
        return 0
    if a.one_step:
        t_at = None if a.one_step[2] == "auto" else float(a.one_step[2])
        print(json.dumps(step_row(a.one_step[0], a.one_step[1], t_at)), flush=True)
        return 0
    arms = [s.strip() for s in a.arms.split(",") if s.strip()]
    if a.model_calls:
        if a.against and len(arms) != 1:
            raise SystemExit("--against compares one arm's libraries: give one arm in --arms")
        print(f"# the robot model's derivatives one Jacobian calls, this thread's CPU µs per call "
              f"(load {os.getloadavg()[0]:.1f}; best of 15 x 40"
              + (f"; 'other' = {a.against}, alternated)" if a.against else ")"))
        rows = []
        for spec in arms:
            rs = model_call_rows(spec, a.against)
            rows += rs
            for r in rs:
                line = f"{r['arm']:>10s} {r['block']:>10s} {r['function']:>11s} {r['us']:8.1f}"
                if a.against:
                    line += (f"  other {r['other_us']:8.1f}  ratio {r['other_us'] / r['us']:5.2f}"
                             f"  max rel diff {r['max_rel_diff']:.1e}")
                print(line, flush=True)
            tot = sum(r["us"] for r in rs)
            line = f"{rs[0]['arm']:>10s} {'all':>10s} {'(one Jac.)':>11s} {tot:8.1f}"
            if a.against:
                other = sum(r["other_us"] for r in rs)
                line += f"  other {other:8.1f}  ratio {other / tot:5.2f}"
            print(line, flush=True)
        if a.json:
            Path(a.json).write_text(json.dumps({"model_calls": rows}, indent=1))
        return 0
    if a.step:
        print(f"# a Rodas5P step of IV-DREM, this thread's CPU ms (load "
              f"{os.getloadavg()[0]:.1f}); its parts at the state reached, best of 5")
        print(f"{'arm':>10s} {'states':>6s} {'from t':>7s} {'steps':>5s} {'step ms':>8s} "
              f"{'rhs ms':>7s} {'jac ms':>9s} {'LU ms':>8s} {'solve':>7s} {'runs':>8s} "
              f"{'L+U':>8s}")
        rows = []
        for spec in arms:
            # the mixing: the last of --variants ("eigen" by default; the paper's (17) is
            # not run on the real arms, docs/mixing.md)
            for v in [v.strip() for v in a.variants.split(",") if v.strip()][-1:]:
                r = _child(spec, v, "auto", a.timeout, mode="--one-step")
                rows.append(r)
                print(_fmt_step(r), flush=True)
        if a.json:
            Path(a.json).write_text(json.dumps({"steps": rows}, indent=1))
        return 0
    print("mixing accuracy on the reference Ψ at t = 40 s (Y = Ψθ, so 𝒲 = 0 exactly):")
    print(f"{'arm':>10s} {'nθ':>4s} {'cond P':>9s} {'Δ (mpmath)':>11s} {'relerr SVD':>11s} "
          f"{'relerr F-L':>11s} {'‖𝒲‖/|Δ| SVD':>13s} {'‖𝒲‖/|Δ| F-L':>13s} {'‖θ‖':>6s}")
    acc = accuracy_rows(arms)
    for r in acc:
        print(f"{r['arm']:>10s} {r['ntheta']:4d} {r['cond']:9.2e} {r['Delta']:11.3e} "
              f"{r['rel_err_svd']:11.2e} {r['rel_err_fl']:11.2e} {r['bias_svd']:13.2e} "
              f"{r['bias_fl']:13.2e} {r['theta_norm']:6.2f}", flush=True)
    out = {"accuracy": acc}
    if not a.accuracy:
        variants = [v.strip() for v in a.variants.split(",") if v.strip()]
        print(f"\nIV-DREM, gamma = \"auto\", Rodas5P, {a.t_end:g} s (one child process per run):")
        print(f"{'arm':>10s} {'variant':>8s} {'nθ':>4s} {'states':>6s} {'steps':>8s} "
              f"{'rejectd':>7s} {'sim s':>8s} {'peak MiB':>8s} {'‖θ̃(0)‖':>7s} {'‖θ̃(end)‖':>9s} "
              f"{'ratio':>9s}  γ")
        rows = []
        for spec in arms:
            for v in variants:
                r = _child(spec, v, a.t_end, a.timeout)
                rows.append(r)
                print(_fmt_row(r), flush=True)
        print("\nfitted growth of sim seconds with nθ (least squares, log-log):")
        for v in variants:
            sel = [r for r in rows if r["variant"] == v]
            print(f"  {v:>8s}: sim_s ∝ nθ^{growth_exponent(sel):.2f}   "
                  f"(target ≤ nθ^3; planar-6 target ≤ 10 s)")
        out["runs"] = rows
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
