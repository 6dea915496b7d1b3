#!/usr/bin/env python
"""Cost of one step of the generated C controller per arm, and the memory of its window.

For each model (the paper's 2-link arm and the named URDF arms by default) the controller
library's sources (ivdrem.controller.codegen) are generated with the parameters of that
arm's experiment (the configuration's defaults: its reference, gains, window T, mixing,
design; ``ivdrem.controller.fmu_export.controller_design``) and compiled with a small C
driver that calls ``ivc_step`` once per sample over ``--t-end`` seconds at h = 1 ms (the
measured motion: the controller's own reference of the previous sample plus a small
oscillation, no plant, no Python in the loop) and times every step with clock_gettime.  It
prints p50 / p99 / max in µs per step beside the targets (Panda with IV-DREM: median
<= 100 µs, max <= 500 µs; the 2-link arm's step 3.6-4.9 µs), and the window's memory
(``ivc_window_bytes``, target <= 64 MiB).  γ "auto" is set to 1 (the step's cost does not
depend on its value; the export resolves it).

Usage::

    ./run python benchmarks/bench_controller.py [--models two-link,panda,ur5,iiwa,xarm7]
                                                [--laws iv-drem] [--t-end 300] [--mix-every M]
                                                [--phases]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
from pathlib import Path

DRIVER = r"""
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "ivdrem_controller.h"
static int cmp(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}
static double since(clockid_t clock, const struct timespec *a) {
    struct timespec b;
    clock_gettime(clock, &b);
    return (b.tv_sec - a->tv_sec) * 1e6 + (b.tv_nsec - a->tv_nsec) * 1e-3;
}
/* the measured motion of sample k: the reference of the last sample plus an oscillation */
static void motion(ivc_controller *c, long k, double h, double *q, double *dq) {
    double qd[IVC_NQ], dqd[IVC_NQ], t = k * h;
    int i;
    for (i = 0; i < IVC_NQ; i++) qd[i] = dqd[i] = 0.0;
    if (k > 0) ivc_reference(c, qd, dqd);
    for (i = 0; i < IVC_NQ; i++) {
        q[i] = qd[i] + 0.01 * sin(3.0 * t + i);
        dq[i] = dqd[i] + 0.03 * cos(3.0 * t + i);
    }
}
/* argv: steps, the first sample of the isolated period, its length (samples), repeats */
int main(int argc, char **argv) {
    long steps = atol(argv[1]), k0 = atol(argv[2]), period = atol(argv[3]), k, kmax = 0;
    int repeats = atoi(argv[4]), i, r;
    double par[IVC_NPAR], q[IVC_NQ], dq[IVC_NQ], tau[IVC_NQ], h, iso = 0.0, isosum = 0.0;
    double *us = malloc(sizeof(double) * (size_t)steps), *cpu = malloc(sizeof(double) * (size_t)steps);
    char msg[256];
    void *saved = NULL;
    size_t size;
    ivc_controller *c;
    (void)argc;
    ivc_default_params(par);            /* the arm's experiment, generated in */
    h = par[IVC_P_H];
    c = ivc_init(par, msg, sizeof msg);
    if (!c || !us || !cpu) { fprintf(stderr, "%s\n", msg); return 1; }
    size = ivc_state_size(c);
    for (k = 0; k < steps; k++) {
        struct timespec a, ca;
        double t = k * h;
        motion(c, k, h, q, dq);
        if (k >= k0 && k < k0 + period) {
            /* in isolation: the same step `repeats` times from the same state, the fastest
             * (the step's own cost, without the neighbours' preemptions) */
            double best = INFINITY;
            if (!saved) saved = malloc(size);
            ivc_get_state(c, saved, size);
            for (r = 0; r < repeats; r++) {
                double dt;
                ivc_set_state(c, saved, size);
                clock_gettime(CLOCK_MONOTONIC, &a);
                ivc_step(c, t, q, dq, tau);
                dt = since(CLOCK_MONOTONIC, &a);
                if (dt < best) best = dt;
            }
            ivc_set_state(c, saved, size);
            if (best > iso) iso = best;
            isosum += best;
        }
        clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ca);
        clock_gettime(CLOCK_MONOTONIC, &a);
        if (ivc_step(c, t, q, dq, tau) != IVC_OK) {
            fprintf(stderr, "t = %g: %s\n", t, ivc_message(c));
            return 1;
        }
        us[k] = since(CLOCK_MONOTONIC, &a);
        cpu[k] = since(CLOCK_THREAD_CPUTIME_ID, &ca);
        if (us[k] > us[kmax]) kmax = k;
    }
    {
        double tmax = kmax * h, mean_iso = period > 0 ? isosum / period : 0.0;
        qsort(us, (size_t)steps, sizeof(double), cmp);
        qsort(cpu, (size_t)steps, sizeof(double), cmp);
        printf("%.3f %.3f %.3f %lu %.17g %.3f %.3f %.4f %.3f %.3f\n", us[steps / 2],
               us[(long)(0.99 * (steps - 1))], us[steps - 1], (unsigned long)ivc_window_bytes(c),
               tau[0], iso, mean_iso, tmax, cpu[(long)(0.99 * (steps - 1))], cpu[steps - 1]);
    }
    ivc_free(c);
    free(us);
    free(cpu);
    free(saved);
    return 0;
}
"""

#: --phases: the pieces of one step, each the fastest of `repeats` runs from the same state
#: (ivc_state copied back), at the sample given: the step without its job's work, the job's
#: start, one slice of its per-sample budget, the whole job (units of n multiply-adds, ns per
#: unit); the mixing (17) for IV-DREM and DREM, the max-hold's lambda_min for composite
#: learning.  It includes the library's own source to reach its static functions.
PHASES_DRIVER = r"""
#include "ivdrem_controller.c"
#include <time.h>
static double now(void) { struct timespec a; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a); return a.tv_sec * 1e6 + a.tv_nsec * 1e-3; }
static void motion(ivc_controller *c, long k, double h, double *q, double *dq) {
    double qd[IVC_NQ], dqd[IVC_NQ], t = k * h;
    int i;
    for (i = 0; i < IVC_NQ; i++) qd[i] = dqd[i] = 0.0;
    if (k > 0) ivc_reference(c, qd, dqd);
    for (i = 0; i < IVC_NQ; i++) { q[i] = qd[i] + 0.01 * sin(3.0 * t + i); dq[i] = dqd[i] + 0.03 * cos(3.0 * t + i); }
}
/* argv: the sample at which to measure, repeats */
int main(int argc, char **argv) {
    long k0 = atol(argv[1]), k;
    int repeats = atoi(argv[2]), r, mixes, lam;
    double par[IVC_NPAR], q[IVC_NQ], dq[IVC_NQ], tau[IVC_NQ], h, t0, t1;
    double base = 1e99, begin = 1e99, slice = 1e99, job = 1e99, units = 0, per = 0, sweeps = 0;
    static ivc_state saved;
    char msg[256];
    ivc_controller *c;
    (void)argc;
    ivc_default_params(par);
    h = par[IVC_P_H];
    c = ivc_init(par, msg, sizeof msg);
    if (!c) { fprintf(stderr, "%s\n", msg); return 1; }
    if (k0 % c->mix_every == 0) k0 += 1;        /* a sample inside a period */
    for (k = 0; k < k0; k++) { motion(c, k, h, q, dq); ivc_step(c, k * h, q, dq, tau); }
    saved = c->s;
    mixes = c->law == IVC_LAW_IV_DREM || c->law == IVC_LAW_DREM;
    lam = c->law == IVC_LAW_COMPOSITE;
    motion(c, k0, h, q, dq);
    for (r = 0; r < repeats; r++) {
        double u = 0;
        c->s = saved; c->s.mix_phase = MIX_DONE; c->s.lam_phase = LAM_DONE;
        t0 = now(); ivc_step(c, k0 * h, q, dq, tau); t1 = now();
        if (t1 - t0 < base) base = t1 - t0;
        if (!mixes && !lam) continue;
        c->s = saved;
        t0 = now(); if (mixes) mix_begin(c, c->s.Yavg); else lam_begin(c, c->s.lam_in); t1 = now();
        if (t1 - t0 < begin) begin = t1 - t0;
        t0 = now(); if (mixes) mix_work(c, c->mix_units); else lam_work(c, c->lam_units); t1 = now();
        if (t1 - t0 < slice) slice = t1 - t0;
        c->s = saved;
        t0 = now();
        if (mixes) { mix_begin(c, c->s.Yavg); u = mix_work(c, -1.0); }
        else { lam_begin(c, c->s.lam_in); u = lam_work(c, -1.0); }
        t1 = now();
        if (t1 - t0 < job) { job = t1 - t0; units = u; sweeps = c->s.mix_sweep; }
    }
    per = mixes ? c->mix_units : (lam ? c->lam_units : 0);
    printf("%.2f %.2f %.2f %.0f %.2f %.0f %.3f %g\n", base, begin, slice, per, job, units,
           units > 0 ? 1e3 * job / units : 0.0, sweeps);
    ivc_free(c);
    return 0;
}
"""

#: targets in µs per step: (median, max)
TARGET_US = {"two-link": (4.9, None), "panda": (100.0, 500.0)}
WINDOW_TARGET_MIB = 64.0


def arm_parameters(name, law, h=1e-3, mix_every=None):
    """The flat parameter vector of the controller of ``law`` for the experiment of the
    model ``name`` (the paper's for the 2-link arm, the real-arm experiment otherwise)."""
    from ivdrem.controller.parameters import param_vector
    from ivdrem.controller.fmu_export import controller_design
    from ivdrem.controller.sampled import SampledController
    from ivdrem.experiments.config import read_config, resolve_config, model_from_config
    if name == "two-link":
        from ivdrem.models import two_link
        model = two_link()
        return model, param_vector(SampledController(model, law, mu_max=135.0, h=h))
    config = resolve_config(read_config(None, {"model.name": name}))[0]
    model = model_from_config(config)
    design = controller_design(config, law, h=h)
    if design.get("gamma") == "auto":
        design["gamma"] = 1.0
    if mix_every is not None:
        design["mix_every"] = int(mix_every)
    return model, param_vector(SampledController(model, law, **design))


def _index(model, name):
    """The offset of parameter `name` in the flat vector (ivdrem_controller.h's layout)."""
    from ivdrem.controller.parameters import param_layout
    off = 0
    for pname, size, _ in param_layout(model):
        if pname == name:
            return off
        off += size
    raise KeyError(name)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="two-link,panda,ur5,iiwa,xarm7")
    ap.add_argument("--laws", default="iv-drem")
    ap.add_argument("--t-end", type=float, default=300.0, dest="t_end",
                    help="seconds of 1 kHz steps per arm (default %(default)g)")
    ap.add_argument("--mix-every", type=int, default=None, dest="mix_every",
                    help="the URDF arms' mixing (17) every m samples (multi-rate; default: "
                         "the controller's)")
    ap.add_argument("--isolate-at", type=float, default=None, dest="isolate_at",
                    help="time (s) of the mixing period whose steps are also timed in "
                         "isolation (default: the middle of the run)")
    ap.add_argument("--repeats", type=int, default=10,
                    help="repeats of each isolated step, the fastest kept (default %(default)s)")
    ap.add_argument("--phases", action="store_true",
                    help="also time the pieces of one step at the isolated period (PHASES_DRIVER)")
    args = ap.parse_args(argv)

    from ivdrem.controller.codegen import generate_controller_sources

    steps = int(round(args.t_end / 1e-3))
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover
        load = float("nan")
    print(f"C controller step at h = 1 ms, {steps} steps per arm (1-min load {load:.2f})")
    print(f"{'model':<9} {'law':<10} {'n':>2} {'nθ':>3} {'m':>3} {'p50 µs':>8} {'p99 µs':>8} "
          f"{'max µs':>8} {'at s':>8} {'cpu p99':>8} {'cpu max':>8} {'iso max':>8} {'iso mean':>8} "
          f"{'target p50/max':>15} "
          f"{'window MiB':>11}")
    with tempfile.TemporaryDirectory(prefix="ivdrem_bench_ctl_") as tmp:
        for name in args.models.split(","):
            for law in args.laws.split(","):
                model, par = arm_parameters(name, law, mix_every=args.mix_every)
                d = Path(tmp) / f"{name}_{law}"
                d.mkdir()
                for fn, text in generate_controller_sources(model, par).items():
                    (d / fn).write_text(text)
                (d / "bench.c").write_text(DRIVER)
                exe = d / "bench"
                subprocess.run(["cc", "-O2", "-std=c99", "-D_POSIX_C_SOURCE=199309L", "-I",
                                str(d), str(d / "bench.c"), str(d / "ivdrem_controller.c"),
                                str(d / "controller_model.c"), "-o", str(exe), "-lm"],
                               check=True)
                m = int(par[_index(model, "mix_every")])
                k0 = int(round((args.t_end / 2 if args.isolate_at is None else args.isolate_at)
                               / 1e-3)) // m * m
                out = subprocess.run([str(exe), str(steps), str(k0), str(m), str(args.repeats)],
                                     capture_output=True, text=True, check=True)
                p50, p99, mx, wbytes, _, iso, iso_mean, at, cpu99, cpumax = out.stdout.split()
                p50, p99, mx, mib = float(p50), float(p99), float(mx), int(wbytes) / 2 ** 20
                tgt = TARGET_US.get(name, (None, None))
                tgt_s = "/".join("-" if x is None else f"{x:g}" for x in tgt)
                print(f"{name:<9} {law:<10} {model.n:>2} {model.ntheta:>3} {m:>3} {p50:8.2f} "
                      f"{p99:8.2f} {mx:8.1f} {float(at):8.3f} {float(cpu99):8.1f} {float(cpumax):8.1f} "
                      f"{float(iso):8.1f} "
                      f"{float(iso_mean):8.1f} {tgt_s:>15} {mib:11.3f}", flush=True)
                if args.phases:
                    (d / "phases.c").write_text(PHASES_DRIVER)
                    pexe = d / "phases"
                    subprocess.run(["cc", "-O2", "-std=c99", "-D_POSIX_C_SOURCE=199309L", "-I",
                                    str(d), str(d / "phases.c"), str(d / "controller_model.c"),
                                    "-o", str(pexe), "-lm"], check=True)
                    out = subprocess.run([str(pexe), str(k0), str(max(args.repeats, 10))],
                                         capture_output=True, text=True, check=True)
                    base, begin, slc, per, job, units, ns, sweeps = map(float, out.stdout.split())
                    job_name = {"composite-learning": "lambda_min"}.get(law, "mixing")
                    print(f"    phases: step without job work {base:.1f} µs; {job_name} job: "
                          f"start {begin:.1f} µs, a slice ({per:.0f} units) {slc:.1f} µs, whole "
                          f"{job:.1f} µs for {units:.0f} units ({ns:.1f} ns/unit"
                          + (f", {sweeps:g} sweeps" if job_name == "mixing" else "") + ")",
                          flush=True)
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover
        load = float("nan")
    print(f"m: the mixing every m samples (its work spread over them); p50/p99/max: wall "
          f"time of a step; at s: time of the slowest; cpu p99/max: the thread's CPU time "
          f"(without the time it was preempted); iso max / mean: the steps of one mixing period (t = "
          f"{'t_end/2' if args.isolate_at is None else args.isolate_at}) timed alone, the "
          f"fastest of {args.repeats} repeats from the same state (1-min load now {load:.2f})")
    print(f"window MiB: the block sums of (15a) (target <= {WINDOW_TARGET_MIB:g} MiB); "
          "targets: Panda p50 <= 100 µs and max <= 500 µs, 2-link 3.6-4.9 µs")


if __name__ == "__main__":
    main()
