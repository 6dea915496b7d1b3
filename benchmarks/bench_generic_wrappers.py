#!/usr/bin/env python
"""A generic kernel wrapper (sizes, port bounds, parameter slots and constants read from the
block's header in P: one compiled wrapper for every arm) against the wrapper specialised
to the block's sizes (literal shapes, offsets and constants), call for call, side by side
in one process on one arm's IV-DREM loop; the two write the same numbers, bit for bit
(checked here for every wrapper timed).

Usage::

    ./run python benchmarks/bench_generic_wrappers.py [--arm panda] [--seconds 0.02] [--reps 7]
    ./run python benchmarks/bench_generic_wrappers.py --step [--arm panda] [--t 0.5]

``--step`` instead times the whole loop's right-hand side, Jacobian and steps of the
arm's simulation with each kind of wrapper (the two simulations take the same steps).

Prints, per wrapper of the blocks without a robot model, the best CPU time (this thread's:
a loaded machine's waiting is not counted) per call of each
(a numba loop calling the wrapper by address, as the C stepper does) and their ratio.
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
try:
    import ivdrem  # noqa: F401
except ImportError:
    sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from ivdrem._native_call import call_c  # noqa: E402


@njit(cache=False)
def _calls(address, t, xp, up, outp, pp, n):
    status = 0
    for _ in range(n):
        status += call_c(address, (t, xp, up, outp, pp))
    return status


def _diagram(arm):
    from bench_arms import _experiment, _window, resolve_model
    from ivdrem.diagrams import closed_loop
    model = resolve_model(arm)
    exp = _experiment(model)
    return closed_loop("iv-drem", model, gains=dict(mixing="eigen", gamma=1.0,
                                                     **_window(exp)),
                       theta_hat0=np.zeros(model.ntheta), K=2.0 * np.eye(model.n), **exp)


def _inputs(b, rng):
    """Random states and inputs for block b (the mixing's Psi symmetric positive definite,
    so its step takes the path a run takes)."""
    x = rng.standard_normal(b.sys.nstates)
    u = rng.standard_normal(b.sys.ninputs)
    if b.spec.name.startswith("mixing") or b.sys.name == "mixing":
        nth = int(round((np.sqrt(1 + 4 * u.size) - 1) / 2))
        A = rng.standard_normal((nth, nth))
        u[nth:] = (A @ A.T + nth * np.eye(nth)).reshape(-1)
    return x, u


def step_rows(arm, t_at, reps, steps):
    """(ms of a right-hand side, of a Jacobian, of a step) of arm's loop at t_at with
    specialised and with generic wrappers: {generic: (rhs, jacobian, step)}, and whether the
    two simulations stayed equal bit for bit."""
    from ivdrem.sim import _stepper_codes, compiled
    from ivdrem.sim.simulator import Simulator
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = _diagram(arm)
        sims = {}
        for generic in (False, True):
            compiled.GENERIC_WRAPPERS = generic
            try:
                sims[generic] = Simulator(d, method="rodas5p", rtol=2e-4, atol=2e-6, h_max=5.0)
            finally:
                compiled.GENERIC_WRAPPERS = True
            sims[generic].advance(t_at)
    best = {g: [np.inf] * 3 for g in sims}
    for _ in range(reps):
        for g, sim in sims.items():
            E, W, x, t = sim.engine, sim.W, sim.x.copy(), float(sim.t)
            dx = np.zeros_like(x)
            J = np.zeros(int(E.tables.lu_rowptr[-1]))
            tmp = np.zeros_like(x)
            c = time.thread_time()
            for _ in range(10):
                E.module.diagram_eval(W, E.P, _stepper_codes.RHS, t, x, dx)
            best[g][0] = min(best[g][0], (time.thread_time() - c) / 10)
            c = time.thread_time()
            E.module.diagram_jacobian(W, E.P, t, x, J, tmp)
            best[g][1] = min(best[g][1], time.thread_time() - c)
            k0, c = int(sim.stats[0]), time.thread_time()
            while int(sim.stats[0]) - k0 < steps:
                sim.advance(sim.t + 0.01)
            best[g][2] = min(best[g][2], (time.thread_time() - c) / (int(sim.stats[0]) - k0))
    same = (sims[False].t == sims[True].t and np.array_equal(sims[False].x, sims[True].x))
    return {g: [1e3 * v for v in b] for g, b in best.items()}, same


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arm", default="panda")
    ap.add_argument("--seconds", type=float, default=0.02, help="per timing (default 0.02)")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--blocks", default="", help="comma-separated block names (default: all)")
    ap.add_argument("--step", action="store_true",
                    help="time the loop's right-hand side, Jacobian and steps instead")
    ap.add_argument("--t", type=float, default=0.5, help="--step: from this time (s)")
    ap.add_argument("--steps", type=int, default=10, help="--step: steps per timing")
    a = ap.parse_args(argv)
    if a.step:
        best, same = step_rows(a.arm, a.t, a.reps, a.steps)
        print(f"{a.arm} from t = {a.t} s: best of {a.reps}, ms (CPU time of this thread)")
        print(f"{'':12s} {'specialised':>12s} {'generic':>10s} {'ratio':>7s}")
        for k, what in enumerate(("rhs", "jacobian", "step")):
            print(f"{what:12s} {best[False][k]:12.3f} {best[True][k]:10.3f} "
                  f"{best[True][k] / best[False][k]:7.3f}")
        print(f"the two simulations equal bit for bit: {same}")
        return 0 if same else 1
    from ivdrem.sim import compiled
    from ivdrem.sim.plan import DiagramPlan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = DiagramPlan.from_diagram(_diagram(a.arm), None, None)
    forms = {}
    for generic in (False, True):
        slots, P = compiled._param_layout(plan, generic=generic)
        mods = compiled.kernel_modules(plan, slots)
        compiled._load_kernels(mods.deps)
        forms[generic] = (mods, P)
    rng = np.random.default_rng(1)
    rows = []
    for b in plan.blocks:
        if b.spec.kind != "ode" or not compiled.generic_block(b):
            continue
        if a.blocks and b.sys.name not in a.blocks.split(","):
            continue
        x, u = _inputs(b, rng)
        for role in ("output", "update", "jacobian"):
            if (b.index, role) not in forms[True][0].windex:
                continue
            ny, nx, nu = b.sys.noutputs, b.sys.nstates, b.sys.ninputs
            shape = {"output": (ny,), "update": (nx,), "jacobian": (ny + nx, nx + nu)}[role]
            best, outs = {}, {}
            args = {}
            # one output buffer for both (where it lies against x and u changes the
            # time of the vectorised loops: 4K aliasing)
            out = np.zeros(shape)
            for generic, (mods, P) in forms.items():
                w = mods.wrappers[mods.windex[(b.index, role)]][2]
                p = P[mods.pbase[b.index]:]
                args[generic] = (sys.modules[w].wrapper.address, out, p)
            for generic, (addr, out, p) in args.items():     # compile the loop, check
                out[...] = 0.0
                if _calls(addr, 0.7, x.ctypes.data, u.ctypes.data, out.ctypes.data,
                          p.ctypes.data, 1):
                    raise RuntimeError(f"{b.sys.name} {role}: the kernel raised")
                outs[generic] = out.copy()
                best[generic] = np.inf
            same = np.array_equal(outs[False], outs[True], equal_nan=True)
            addr, out, p = args[False]
            c = time.thread_time()
            _calls(addr, 0.7, x.ctypes.data, u.ctypes.data, out.ctypes.data, p.ctypes.data, 10)
            # about --seconds per timing, at least 10 calls
            calls = max(10, int(a.seconds / max((time.thread_time() - c) / 10, 1e-9)))
            for _ in range(a.reps):       # alternate the two, so load hits both alike
                for generic, (addr, out, p) in args.items():
                    c = time.thread_time()
                    _calls(addr, 0.7, x.ctypes.data, u.ctypes.data, out.ctypes.data,
                           p.ctypes.data, calls)
                    best[generic] = min(best[generic], (time.thread_time() - c) / calls)
            rows.append((b.sys.name, role, best[False], best[True], same))
    print(f"{a.arm}: best of {a.reps} timings of about {a.seconds} s each, ns per call")
    print(f"{'block':18s} {'role':9s} {'specialised':>12s} {'generic':>10s} {'ratio':>7s}  "
          "bit for bit")
    for name, role, s, g, same in rows:
        print(f"{name:18s} {role:9s} {1e9 * s:12.1f} {1e9 * g:10.1f} {g / s:7.3f}  {same}")
    tot_s, tot_g = sum(r[2] for r in rows), sum(r[3] for r in rows)
    print(f"{'all':28s} {1e9 * tot_s:12.1f} {1e9 * tot_g:10.1f} {tot_g / tot_s:7.3f}  "
          f"{all(r[4] for r in rows)}")
    return 0 if all(r[4] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
