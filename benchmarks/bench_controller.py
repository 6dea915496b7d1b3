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
int main(int argc, char **argv) {
    long steps = atol(argv[1]), k;
    double par[IVC_NPAR], q[IVC_NQ], dq[IVC_NQ], tau[IVC_NQ], qd[IVC_NQ], dqd[IVC_NQ], h;
    double *us = malloc(sizeof(double) * (size_t)steps);
    char msg[256];
    int i;
    ivc_controller *c;
    (void)argc;
    ivc_default_params(par);            /* the arm's experiment, generated in */
    h = par[IVC_P_H];
    c = ivc_init(par, msg, sizeof msg);
    if (!c || !us) { fprintf(stderr, "%s\n", msg); return 1; }
    for (i = 0; i < IVC_NQ; i++) qd[i] = dqd[i] = 0.0;
    for (k = 0; k < steps; k++) {
        struct timespec a, b;
        double t = k * h;
        if (k > 0) ivc_reference(c, qd, dqd);       /* the reference of the last sample */
        for (i = 0; i < IVC_NQ; i++) {
            q[i] = qd[i] + 0.01 * sin(3.0 * t + i);
            dq[i] = dqd[i] + 0.03 * cos(3.0 * t + i);
        }
        clock_gettime(CLOCK_MONOTONIC, &a);
        if (ivc_step(c, t, q, dq, tau) != IVC_OK) {
            fprintf(stderr, "t = %g: %s\n", t, ivc_message(c));
            return 1;
        }
        clock_gettime(CLOCK_MONOTONIC, &b);
        us[k] = (b.tv_sec - a.tv_sec) * 1e6 + (b.tv_nsec - a.tv_nsec) * 1e-3;
    }
    qsort(us, (size_t)steps, sizeof(double), cmp);
    printf("%.3f %.3f %.3f %lu %.17g\n", us[steps / 2], us[(long)(0.99 * (steps - 1))],
           us[steps - 1], (unsigned long)ivc_window_bytes(c), tau[0]);
    ivc_free(c);
    free(us);
    return 0;
}
"""

#: targets in µs per step: (median, max)
TARGET_US = {"two-link": (4.9, None), "panda": (100.0, 500.0)}
WINDOW_TARGET_MIB = 64.0


def arm_parameters(name, law, h=1e-3, mix_every=None):
    """The flat parameter vector of the controller of ``law`` for the experiment of the
    model ``name`` (the paper's for the 2-link arm, the real-arm experiment otherwise)."""
    from ivdrem.controller.codegen import param_vector
    from ivdrem.controller.fmu_export import controller_design
    from ivdrem.controller.sampled import SampledController
    from ivdrem.experiments.config import load_config, model_from_config
    if name == "two-link":
        from ivdrem.models import two_link
        model = two_link()
        return model, param_vector(SampledController(model, law, mu_max=135.0, h=h))
    config = load_config(None, {"model.name": name})
    model = model_from_config(config)
    design = controller_design(config, law, h=h)
    if design.get("gamma") == "auto":
        design["gamma"] = 1.0
    if mix_every is not None:
        design["mix_every"] = int(mix_every)
    return model, param_vector(SampledController(model, law, **design))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="two-link,panda,ur5,iiwa,xarm7")
    ap.add_argument("--laws", default="iv-drem")
    ap.add_argument("--t-end", type=float, default=300.0, dest="t_end",
                    help="seconds of 1 kHz steps per arm (default %(default)g)")
    ap.add_argument("--mix-every", type=int, default=None, dest="mix_every",
                    help="the URDF arms' mixing (17) every m samples (multi-rate; default: "
                         "the controller's)")
    args = ap.parse_args(argv)

    from ivdrem.controller.codegen import generate_controller_sources

    steps = int(round(args.t_end / 1e-3))
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover
        load = float("nan")
    print(f"C controller step at h = 1 ms, {steps} steps per arm (1-min load {load:.2f})")
    print(f"{'model':<9} {'law':<10} {'n':>2} {'nθ':>3} {'p50 µs':>8} {'p99 µs':>8} "
          f"{'max µs':>8} {'target p50/max':>15} {'window MiB':>11}")
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
                out = subprocess.run([str(exe), str(steps)], capture_output=True, text=True,
                                     check=True)
                p50, p99, mx, wbytes, _ = out.stdout.split()
                p50, p99, mx, mib = float(p50), float(p99), float(mx), int(wbytes) / 2 ** 20
                tgt = TARGET_US.get(name, (None, None))
                tgt_s = "/".join("-" if x is None else f"{x:g}" for x in tgt)
                print(f"{name:<9} {law:<10} {model.n:>2} {model.ntheta:>3} {p50:8.2f} "
                      f"{p99:8.2f} {mx:8.1f} {tgt_s:>15} {mib:11.3f}", flush=True)
    print(f"window MiB: the block sums of (15a) (target <= {WINDOW_TARGET_MIB:g} MiB); "
          "targets: Panda p50 <= 100 µs and max <= 500 µs, 2-link 3.6-4.9 µs")


if __name__ == "__main__":
    main()
