"""Write your own composite term: a normalised IV-DREM law, compiled and run against IV-DREM.

The new term (a variant of eq. (21) with a normalised gain)

    ϑ_c = γ Δ (𝒴 − Δθ̂) / (1 + ν γ Δ²)

keeps (21)'s direction but bounds the contraction rate γΔ²/(1 + νγΔ²) ≤ 1/ν, so a γ that
is too large for a robot cannot stiffen the loop.  Three steps (docs/custom-law.md):

1. a block: a kernel in numba's subset of Python that reads its inputs and writes its
   outputs by port name (``u.calY``, ``y.theta_c``), declared with its ports and parameters;
2. a law: a function that returns the blocks computing ``theta_c`` (here the mixed
   regression (17) of ivdrem.laws plus the new block), registered once with
   ``register_law``; closed_loop, the configuration (its gains in the table
   ``[normalised_iv_drem]``), the figures and the diagnostics then know it by name;
3. run it: ``closed_loop("normalised-iv-drem", model)`` compiles it like any law.

Run:  python examples/custom_law.py [t_end]     (the first run compiles the new diagram)
"""
import sys

import numpy as np

from ivdrem import blocks as block_library
from ivdrem.blocks import _validate as checks
from ivdrem.diagrams import closed_loop
from ivdrem.experiments.metrics import signal
from ivdrem.laws import Law, mixed_regression_blocks, register_law
from ivdrem.models import two_link
from ivdrem.sim import simulate


# 1. the block ---------------------------------------------------------------------------
def normalised_term_output(t, x, u, y, gamma, nu):
    # inputs   u.Delta[0], u.calY (nθ), u.theta_hat (nθ)    (the mixed regression (17))
    # outputs  y.theta_c = gamma Delta (calY - Delta theta_hat) / (1 + nu gamma Delta^2)
    # params   gamma > 0, nu > 0 (s)
    D = u.Delta[0]
    g = gamma / (1.0 + nu * gamma * D * D)
    for i in range(y.theta_c.shape[0]):
        y.theta_c[i] = g * D * (u.calY[i] - D * u.theta_hat[i])


def normalised_term(ntheta, gamma=1e10, nu=1.0, *, name="normalised_term"):
    """The normalised composite term, a block whose kernel reads its ports by name.

    ======  ===========================================
    states  none
    inputs  Delta, calY[nθ], theta_hat[nθ]
    output  theta_c[nθ]
    params  gamma > 0, nu > 0 (s)
    ======  ===========================================
    """
    def validate(p):
        return {**p, "gamma": checks.scalar(name, "gamma", p["gamma"], positive=True),
                "nu": checks.scalar(name, "nu", p["nu"], positive=True)}
    spec = block_library.BlockSpec(
        name=name, inputs=[("Delta", 1), ("calY", ntheta), ("theta_hat", ntheta)],
        outputs=[("theta_c", ntheta)], states=[], x0=np.zeros(0),
        param_names=("gamma", "nu"), output=normalised_term_output,
        direct=("Delta", "calY", "theta_hat"), validate=validate, named_ports=True)
    return block_library.make_block(spec, {"gamma": gamma, "nu": nu})


# 2. the law -----------------------------------------------------------------------------
def build(ctx):
    blocks, outputs = mixed_regression_blocks(ctx, instrument=True)
    return blocks + [normalised_term(ctx.ntheta, ctx.params["gamma"], ctx.params["nu"])], outputs


register_law(Law(
    "normalised-iv-drem", build, label="normalised IV-DREM", color="#56B4E9",
    equation="γΔ(𝒴 − Δθ̂)/(1 + νγΔ²)", description="IV-DREM with a bounded contraction rate",
    section="normalised_iv_drem", defaults=dict(T=20.0, p=2.0, F0=1.0, gamma=1e10, nu=1.0),
    uses_delta=True, instrument="zeta"), replace=True)


# 3. run it against IV-DREM --------------------------------------------------------------
def main(t_end=60.0):
    """Both laws over [0, t_end] on the compiled engine; returns {law: response}."""
    model = two_link()
    theta = np.asarray(model.theta_values)
    out = {}
    for law in ("iv-drem", "normalised-iv-drem"):
        resp = out[law] = simulate(closed_loop(law, model), t_end, progress=False)
        err = np.linalg.norm(theta - signal(resp, "theta_hat")[:, -1])
        print(f"{law:>20s}: ||theta_err(t = {t_end:g} s)|| = {err:.4g}  "
              f"({resp.stats['steps']} steps, {resp.stats['wall_s']:.2f} s)")
    return out


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 60.0)
