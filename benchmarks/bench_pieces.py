#!/usr/bin/env python
"""The cost of returning to Python often enough that Ctrl-C and SIGTERM stop a long compiled
call within about 0.1 s: (1) the stability prediction's prefix in pieces (so that Ctrl-C and
SIGTERM stop it: ``ivdrem.controller.stability.run_in_pieces``, pieces of PIECE_S = 0.1 s of
wall time) against the same loop in one compiled call (``pieces=N + 1``), side by side,
alternating, in one process, both warm; and whether the points are the same, bit for bit.
The difference is within the noise of two cores shared with other work, so the cost is
also bounded from its parts: the calls a prefix makes in pieces, times the cost of one
call measured on the 2-link arm (20000 pieces of one step against one call).

Arms: the Panda's prefix as ``ivdrem fmu export --controller`` runs it (examples/panda.toml,
its design, the FMU's delay 1, the configuration's disturbance, 1.25 windows T), and the
2-link arm's IV-DREM (the cheapest step ivdrem has, ~13 µs: the largest share for the calls
between pieces).

(2) The C stepper's reports by wall time (``ivdrem.sim.simulator.REPORT_WALL_S``: about
every 0.1 s between the 200 reports of an ``advance``) against the 200 alone
(``REPORT_WALL_S = inf``), on the paper's IV-DREM loop (Rodas5P, ``--paper-t`` s) and the
2-link loop at fixed step (RK4, h = 1e-4, 20 s: 2e5 cheap steps); the cost of one report
measured as (2).

Usage::

    ./run python benchmarks/bench_pieces.py [--rounds 5] [--two-link-t 100] [--paper-t 300]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from ivdrem.controller import stability


def _panda_prefix_args():
    """The arguments of closed_loop_prefix in the Panda's export prediction (captured from
    fmu_export.predict with the prefix replaced by a recorder)."""
    from ivdrem.controller.fmu_export import controller_design, predict, resolve_gamma
    from ivdrem.experiments.config import read_config
    from ivdrem.experiments.experiment import Experiment
    experiment = Experiment.from_config(read_config("examples/panda.toml"), laws=["iv-drem"])
    model = experiment.model
    design = controller_design(experiment, "iv-drem", h=experiment.h)
    design, _ = resolve_gamma(model, "iv-drem", design, experiment)
    seen = []
    real = stability.closed_loop_prefix

    def record(*a, **k):
        seen.append((a, k))
        raise _Captured
    stability.closed_loop_prefix = record
    try:
        predict(model, "iv-drem", design, experiment)
    except _Captured:
        pass
    finally:
        stability.closed_loop_prefix = real
    return seen[0]


class _Captured(Exception):
    pass


def _same(a, b):
    (pa, da), (pb, db) = a, b
    return (len(pa) == len(pb) and (da is None) == (db is None)
            and all(x[0] == y[0] and all(np.array_equal(u, v) for u, v in zip(x[1:], y[1:]))
                    for x, y in zip(pa, pb)))


def _calls(a, k):
    """How many calls the prefix makes in pieces (the default)."""
    calls = [0]
    real = stability.run_in_pieces

    def counted(piece, *rest, **kw):
        def one(k_stop):
            calls[0] += 1
            return piece(k_stop)
        return real(one, *rest, **kw)
    stability.run_in_pieces = counted
    try:
        stability.closed_loop_prefix(*a, **k)
    finally:
        stability.run_in_pieces = real
    return calls[0]


def _per_call(rounds):
    """Seconds one more call costs: the 2-link prefix of 20000 steps in pieces of one step
    against one call (best of ``rounds`` each, alternating)."""
    from ivdrem.models import two_link
    m = two_link()
    kw = dict(h=1e-3, delay=1)
    walls = {1: [], 20001: []}
    for r in range(rounds):
        for p in ((1, 20001) if r % 2 == 0 else (20001, 1)):
            t0 = time.perf_counter()
            stability.closed_loop_prefix(m, "iv-drem", m.theta_values, 20.0, pieces=p, **kw)
            walls[p].append(time.perf_counter() - t0)
    return (min(walls[1]) - min(walls[20001])) / 20000


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--two-link-t", type=float, default=100.0,
                    help="the 2-link prefix's length in s (default 100)")
    ap.add_argument("--paper-t", type=float, default=300.0,
                    help="the paper loop's run in s (default 300)")
    ap.add_argument("--no-stepper", action="store_true",
                    help="the prefix only, not the stepper's reports")
    args = ap.parse_args(argv)
    from ivdrem.models import two_link
    m2 = two_link()
    cases = {"panda (export)": _panda_prefix_args(),
             "two-link iv-drem": ((m2, "iv-drem", m2.theta_values, args.two_link_t),
                                  dict(h=1e-3, delay=1))}
    print(f"load at start {os.getloadavg()[0]:.1f}")
    stability.closed_loop_prefix(m2, "iv-drem", m2.theta_values, 0.2, h=1e-3, delay=1)
    per_call = _per_call(args.rounds)
    print(f"one more call of the compiled loop: {per_call * 1e6:.1f} µs (2-link, 20000 "
          f"pieces of one step against one call, best of {args.rounds})", flush=True)
    worst = 0.0
    for name, (a, k) in cases.items():
        N = int(round(a[3] / k.get("h", 1e-3)))
        stability.closed_loop_prefix(*a[:3], 0.2, **k)            # warm: built, loaded
        walls = {"pieces": [], "one call": []}
        cpus = {"pieces": [], "one call": []}
        results = {}
        for r in range(args.rounds):
            order = ("pieces", "one call") if r % 2 == 0 else ("one call", "pieces")
            for how in order:
                t0, c0 = time.perf_counter(), time.thread_time()
                res = stability.closed_loop_prefix(
                    *a, **k, pieces=None if how == "pieces" else N + 1)
                cpus[how].append(time.thread_time() - c0)
                walls[how].append(time.perf_counter() - t0)
                results.setdefault(how, res)
        same = _same(results["pieces"], results["one call"])
        best = {h: min(w) for h, w in walls.items()}
        med = {h: float(np.median(w)) for h, w in walls.items()}
        cpu = {h: min(w) for h, w in cpus.items()}
        cost = best["pieces"] / best["one call"] - 1.0
        worst = max(worst, cost)
        calls = _calls(a, k)
        bound = calls * per_call / best["one call"]
        print(f"{name}: {N} steps; pieces / one call - 1 = {cost * 100:+.2f} % wall (best of "
              f"{args.rounds}: {best['pieces']:.3f} s / {best['one call']:.3f} s; median "
              f"{med['pieces']:.3f} / {med['one call']:.3f} s), "
              f"{(cpu['pieces'] / cpu['one call'] - 1) * 100:+.2f} % thread CPU (best: "
              f"{cpu['pieces']:.3f} / {cpu['one call']:.3f} s); {calls} calls x "
              f"{per_call * 1e6:.1f} µs = {bound * 100:.3f} % of the one call; points "
              f"{'identical' if same else 'DIFFER'}; load {os.getloadavg()[0]:.1f}",
              flush=True)
        if not same:
            return 1
    if not args.no_stepper and not _stepper_reports(args):
        return 1
    print(f"load at end {os.getloadavg()[0]:.1f}")
    return 0


def _stepper_reports(args):
    """(2): the stepper's runs with the reports by wall time and without, alternating."""
    import math

    from ivdrem.diagrams import closed_loop
    from ivdrem.models import two_link  # noqa: F401 - the loops' model
    from ivdrem.sim import simulate
    from ivdrem.sim import simulator as sim_module
    real = sim_module.Simulator._report_trampoline
    count = [0]

    def counted(self, t):
        count[0] += 1
        return real(self, t)
    sim_module.Simulator._report_trampoline = counted
    loop = closed_loop("iv-drem")
    cases = {f"paper IV-DREM {args.paper_t:g} s (rodas5p)": (args.paper_t, {}),
             "paper IV-DREM 20 s (rk4, h = 1e-4)": (20.0, dict(method="rk4", h=1e-4))}
    ok = True
    try:
        for name, (t_end, kw) in cases.items():
            simulate(loop, 1.0, progress=False, **kw)              # compiled, warm
            walls, calls, outs = {}, {}, {}
            for r in range(args.rounds):
                order = (sim_module.REPORT_WALL_S, math.inf, 1e-6)
                for every in (order if r % 2 == 0 else order[::-1]):
                    sim_module.REPORT_WALL_S = every
                    count[0] = 0
                    t0 = time.perf_counter()
                    res = simulate(loop, t_end, progress=False, **kw)
                    walls.setdefault(every, []).append(time.perf_counter() - t0)
                    calls[every] = count[0]
                    outs.setdefault(every, np.asarray(res.outputs))
                sim_module.REPORT_WALL_S = order[0]
            default = order[0]
            best = {e: min(w) for e, w in walls.items()}
            per = (best[1e-6] - best[math.inf]) / max(1, calls[1e-6] - calls[math.inf])
            extra = calls[default] - calls[math.inf]
            same = all(np.array_equal(outs[e], outs[math.inf]) for e in outs)
            ok = ok and same
            print(f"{name}: {calls[default]} reports ({extra} by wall time) against "
                  f"{calls[math.inf]}; one report {per * 1e6:.1f} µs ({calls[1e-6]} reports "
                  f"at every step: {best[1e-6]:.2f} s / {best[math.inf]:.2f} s), so "
                  f"{extra * per / best[math.inf] * 100:.3f} % of the run; measured "
                  f"{(best[default] / best[math.inf] - 1) * 100:+.2f} % (best of "
                  f"{args.rounds}); outputs {'identical' if same else 'DIFFER'}; load "
                  f"{os.getloadavg()[0]:.1f}", flush=True)
    finally:
        sim_module.Simulator._report_trampoline = real
    return ok


if __name__ == "__main__":
    raise SystemExit(main())
