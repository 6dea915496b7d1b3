#!/usr/bin/env python
"""Cost of one step of the generated C controller, and the memory of its window.

For each model (the paper's 2-link arm, planar-6 by default) and law, the controller
library's sources (ivdrem.controller.codegen) are compiled with a small C driver that calls
``ivc_step`` ``--steps`` times in a loop (measured motion near the reference, no plant, no
Python in the loop) and times it with clock_gettime; the best of ``--reps`` runs is printed
in µs per step beside the target (2-link <= 10 µs, planar-6 <= 100 µs), with the window's
memory (``ivc_window_bytes``: T / (block h) block sums of nθ + nθ² doubles, 1 kHz, T = 20 s)
against the full 20,000-sample history and the 2-link target of 5 MiB.

Usage::

    PYTHONPATH=. python benchmarks/bench_controller.py [--models two-link,planar-6]
                                                       [--laws iv-drem,none] [--steps 20000]
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
int main(int argc, char **argv) {
    long steps = atol(argv[1]), k;
    int law = atoi(argv[2]), reps = atoi(argv[3]), r, i;
    double par[IVC_NPAR], q[IVC_NQ], dq[IVC_NQ], tau[IVC_NQ], best = 1e30, h;
    char msg[256];
    ivc_default_params(par);
    par[IVC_P_LAW] = law;
    par[IVC_P_MU_MAX] = 135.0;
    h = par[IVC_P_H];
    for (r = 0; r < reps; r++) {
        struct timespec a, b;
        ivc_controller *c = ivc_init(par, msg, sizeof msg);
        if (!c) { fprintf(stderr, "%s\n", msg); return 1; }
        clock_gettime(CLOCK_MONOTONIC, &a);
        for (k = 0; k < steps; k++) {
            double t = k * h;
            for (i = 0; i < IVC_NQ; i++) {
                double w = par[IVC_P_TR_OMEGA + i], A0 = par[IVC_P_TR_AMPLITUDE + i];
                q[i] = A0 * sin(w * t + par[IVC_P_TR_PHASE + i]) + par[IVC_P_TR_OFFSET + i]
                       + 0.05 * sin(3 * t);
                dq[i] = A0 * w * cos(w * t + par[IVC_P_TR_PHASE + i]) + 0.15 * cos(3 * t);
            }
            if (ivc_step(c, t, q, dq, tau) != IVC_OK) { fprintf(stderr, "%s\n", ivc_message(c)); return 1; }
        }
        clock_gettime(CLOCK_MONOTONIC, &b);
        {
            double us = ((b.tv_sec - a.tv_sec) * 1e6 + (b.tv_nsec - a.tv_nsec) * 1e-3) / steps;
            if (us < best) best = us;
        }
        if (r == reps - 1) printf("%.4f %lu %.17g\n", best, (unsigned long)ivc_window_bytes(c), tau[0]);
        ivc_free(c);
    }
    return 0;
}
"""

TARGET_US = {"two-link": 10.0, "planar-6": 100.0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="two-link,planar-6")
    ap.add_argument("--laws", default="iv-drem,none")
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)

    from ivdrem.controller.codegen import LAW_CODES, generate_controller_sources
    from ivdrem.models import get_model

    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover
        load = float("nan")
    print(f"C controller step, {args.steps} steps, best of {args.reps} (1-min load {load:.2f})")
    print(f"{'model':<10} {'law':<20} {'n':>2} {'nθ':>3} {'µs/step':>9} {'target':>7} "
          f"{'ratio':>6} {'window MiB':>11} {'full MiB':>9}")
    with tempfile.TemporaryDirectory(prefix="ivdrem_bench_ctl_") as tmp:
        for name in args.models.split(","):
            model = get_model(name)
            d = Path(tmp) / name
            d.mkdir()
            for fn, text in generate_controller_sources(model).items():
                (d / fn).write_text(text)
            (d / "bench.c").write_text(DRIVER)
            exe = d / "bench"
            subprocess.run(["cc", "-O2", "-std=c99", "-D_POSIX_C_SOURCE=199309L", "-I", str(d),
                            str(d / "bench.c"), str(d / "ivdrem_controller.c"),
                            str(d / "controller_model.c"), "-o", str(exe), "-lm"], check=True)
            nth = model.ntheta
            full = 20000 * (nth + nth * nth) * 8 / 2 ** 20   # 20 s at 1 kHz, every sample
            for law in args.laws.split(","):
                out = subprocess.run([str(exe), str(args.steps), str(LAW_CODES[law]),
                                      str(args.reps)], capture_output=True, text=True, check=True)
                us, wbytes, _ = out.stdout.split()
                us = float(us)
                target = TARGET_US.get(name)
                ratio = f"{us / target:6.2f}" if target else "     -"
                tgt = f"{target:7g}" if target else "      -"
                print(f"{name:<10} {law:<20} {model.n:>2} {nth:>3} {us:9.2f} {tgt} {ratio} "
                      f"{int(wbytes) / 2 ** 20:11.3f} {full:9.2f}", flush=True)
    print("window MiB: the block sums (block = 10 samples); full: every sample of the 20 s "
          "window (the 2-link target is <= 5 MiB)")


if __name__ == "__main__":
    main()
