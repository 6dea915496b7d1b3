"""The sampled loop against the continuous loop with the same gains, on a real arm.

:func:`ivdrem.controller.continuous.sampled_against_continuous`: the continuous loop with
``design="inertia-scaled"`` (the control-law block M̂(q)(K + δ_μ μ) r + Πᵀθ̂ − u_f, μ
saturated as the sampled controller's; Rodas5P at rtol 1e-9, atol 1e-11) against the
sampled controller (Python reference, ``--backend c`` the C library) with the same K (1/s),
δ_μ, μ, reference, observer, window T, γ and mixing around the arm's own dynamics, at each
step h.  Both take the real-arm experiment of docs/experiment.md.

Prints, per h: max |θ̂_h − θ̂_c| and max |e_h − e_c| over the output times (every
t_end/5 and at t_end), the ratio to the next larger h and the observed order
log(ratio)/log(h ratio); first order in h gives ratios near 2 per halving.

    ./run python benchmarks/bench_sampled_vs_continuous.py                     # UR5, 1 s
    ./run python benchmarks/bench_sampled_vs_continuous.py --law none --t-end 0.5
"""
from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

#: the gains of the comparison (1/s, the inertia-scaled design's K), UR5's six joints
K_UR5 = (4.0, 4.0, 4.0, 8.0, 8.0, 16.0)


def table(res):
    """The rows of the printed table (h in ms, the two differences, ratios, orders)."""
    hs = res["h"]
    lines = [f"{'h (ms)':>7} {'max|θ̂_h-θ̂_c|':>14} {'ratio':>6} {'order':>6} "
             f"{'max|e_h-e_c|':>13} {'ratio':>6} {'order':>6} {'wall s':>7}"]
    for i, h in enumerate(hs):
        cells = []
        for key in ("theta", "e"):
            v = res[key][i]
            if i:
                ratio = res[key][i - 1] / v
                order = np.log(ratio) / np.log(hs[i - 1] / h)
                cells.append(f"{v:14.4g} {ratio:6.3f} {order:6.3f}")
            else:
                cells.append(f"{v:14.4g} {'':>6} {'':>6}")
        lines.append(f"{h * 1e3:7g} {cells[0]} {cells[1]} {res['wall'][i]:7.1f}")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="ur5")
    ap.add_argument("--law", default="iv-drem")
    ap.add_argument("--t-end", type=float, default=1.0)
    ap.add_argument("--T", type=float, default=0.2, help="window T of (15a), s")
    # on the UR5's reference a window of 0.2 s gives Δ ≈ 1.6e-10 ("eigen" mixing): γ = 1e21
    # makes the composite term of (21) the larger part of θ̂'s motion (γ Δ² Γ ≈ 0.3 /s)
    ap.add_argument("--gamma", type=float, default=1e21, help="γ of (21)")
    ap.add_argument("--h", type=float, nargs="+", default=[4e-3, 2e-3, 1e-3])
    ap.add_argument("--backend", choices=("python", "c"), default="python")
    a = ap.parse_args(argv)
    from ivdrem.controller.continuous import sampled_against_continuous
    from ivdrem.laws import get_law
    from ivdrem.models import get_model
    m = get_model(a.model)
    K = K_UR5 if a.model == "ur5" else [4.0] * m.n
    window = "T" in get_law(a.law).defaults
    extra = dict(T=a.T, gamma=a.gamma, mixing="eigen") if window else {}
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    t0 = time.perf_counter()
    res = sampled_against_continuous(m, a.law, hs=a.h, t_end=a.t_end, K=K,
                                     theta_hat0=0.5 * np.asarray(m.theta_values),
                                     backend=a.backend, **extra)
    r = res["continuous"]
    lab = list(r.output_labels)
    delta = next((lab.index(x) for x in ("Delta", "Delta[0]") if x in lab), None)
    print(f"{a.model}, law {a.law}, K = {list(K)} 1/s, t_end = {a.t_end:g} s"
          + (f", T = {a.T:g} s, γ = {a.gamma:g}, mixing eigen" if window else "")
          + f": continuous loop {r.stats['steps']} steps, compile {r.stats['compile_s']:.1f} s,"
          f" sim {r.stats['sim_s']:.1f} s; max |θ̂_c - θ̂(0)| = {res['theta_moved']:.3g}"
          + (f", Δ(t_end) = {r.outputs[delta, -1]:.3g}" if delta is not None else ""))
    print("\n".join(table(res)))
    print(f"total {time.perf_counter() - t0:.0f} s; load average at end: "
          f"{os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    sys.exit(main())
