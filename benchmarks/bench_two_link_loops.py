#!/usr/bin/env python
"""The paper's 2-link 1 kHz loop over the paper's 300 s: every host against its reference.

The test suite checks these equivalences over 60 s = 3 T (the window filling, the composite
term switching on at T = 20 s, the learning after it: tests/test_controller_block.py,
tests/test_controller_sampled.py); this script measures them over the whole experiment
(``--t-end``, default 300 s), IV-DREM, mu_max = 135, plant FMU of ivdrem:

* ivdrem's simulation of the controller block (delay 1, Rodas5P rtol 1e-9) against the
  controller FMU closed around the plant FMU in FMPy (max |Δθ̂|, max |Δq|; the tests
  require 1e-6);
* the controller FMU in FMPy and in libcosim against the C library's loop
  (ivdrem.controller.loop, delay 1; 1e-6), and ‖θ̂(t_end) − θ‖ / ‖θ‖;
* θ̂(t_end) of the C library's loop (delay 0) at h = 1 ms and 0.5 ms against ivdrem's
  continuous loop with the same saturated mu (the issue's 1e-3; halving with h).

Usage::

    ./run python benchmarks/bench_two_link_loops.py [--t-end 300]
"""
from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

Q0 = (0.0, 0.3 * np.pi)


def _signals(r, name, n):
    lab = list(r.output_labels)
    return r.outputs[[lab.index(f"{name}[{i}]") for i in range(n)]]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t-end", type=float, default=300.0, dest="t_end")
    a = ap.parse_args(argv)
    from ivdrem.controller.block import sampled_closed_loop
    from ivdrem.controller.clib import CController
    from ivdrem.controller.continuous import continuous_closed_loop
    from ivdrem.controller.fmu_export import export_controller_fmu
    from ivdrem.controller.fmu_loop import fmpy_closed_loop, libcosim_closed_loop
    from ivdrem.controller.loop import FmuPlant, sampled_loop
    from ivdrem.fmu import export_fmu
    from ivdrem.models import TWO_LINK_THETA, two_link
    from ivdrem.sim import simulate
    warnings.simplefilter("ignore")
    theta = np.array(TWO_LINK_THETA)

    def c_loop(t_end, substep, **kw):
        plant = FmuPlant(plant_fmu, Q0, (0.0, 0.0), substep=substep)
        try:
            return sampled_loop(CController(mu_max=135.0, **kw), plant, t_end)
        finally:
            plant.close()

    with tempfile.TemporaryDirectory(prefix="ivdrem_two_link_loops_") as tmp:
        plant_fmu = export_fmu(two_link(), Path(tmp) / "Plant.fmu")
        ctl_fmu = export_controller_fmu(two_link(), Path(tmp) / "Controller.fmu",
                                        law="iv-drem", mu_max=135.0)
        t0 = time.perf_counter()
        fm = fmpy_closed_loop(ctl_fmu, plant_fmu, a.t_end)
        r = simulate(sampled_closed_loop(mu_max=135.0, delay=1)[0], fm["t"], rtol=1e-9,
                     atol=1e-11)
        print(f"t_end = {a.t_end:g} s")
        print(f"block (ivdrem) - FMPy loop: max|Δθ̂| "
              f"{np.abs(_signals(r, 'theta_hat', 5).T - fm['theta_hat']).max():.2e}, "
              f"max|Δq| {np.abs(_signals(r, 'q', 2).T - fm['q']).max():.2e}")
        ref = c_loop(a.t_end, 1e-3, delay=1)
        for host, rec in (("FMPy", fm),
                          ("libcosim", libcosim_closed_loop(ctl_fmu, plant_fmu, a.t_end))):
            print(f"{host} loop - C library loop: max|Δθ̂| "
                  f"{np.abs(rec['theta_hat'] - ref['theta_hat']).max():.2e}, "
                  f"max|Δq| {np.abs(rec['q'] - ref['q']).max():.2e}")
        print(f"‖θ̂(t_end) - θ‖ / ‖θ‖ = "
              f"{np.linalg.norm(ref['theta_hat'][-1] - theta) / np.linalg.norm(theta):.3g}")
        c = simulate(continuous_closed_loop("iv-drem", mu_max=135.0), a.t_end, dt_out=1.0,
                     rtol=1e-7, atol=1e-9, h_max=0.5)
        th = _signals(c, "theta_hat", 5)[:, -1]
        errs = [np.abs(c_loop(a.t_end, min(h, 1e-3), h=h)["theta_hat"][-1] - th).max()
                for h in (1e-3, 5e-4)]
        print(f"sampled - continuous θ̂(t_end): h = 1 ms {errs[0]:.2e}, 0.5 ms "
              f"{errs[1]:.2e}, ratio {errs[0] / errs[1]:.3f}")
        print(f"wall {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
