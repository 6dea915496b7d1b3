"""Mixing step, paper eq. (17) with erratum E4, and its scale-free variants (docs/mixing.md).

"paper": s = 1 + ||Psi||_F, Psi_n = Psi/s, Delta = det Psi_n, calY = adj(Psi_n) Y / s, so
that calY_i = Delta theta_i + calW_i with calW = adj(Psi_n) W / s.  The adjugate is used,
never an inverse: Psi is singular at the start of every run.  "eigen" divides det Psi and
adj(Psi) Y by prod_j (sigma_j + f0) instead of s^nθ (a per-eigenvalue, least-squares-type
normalisation), "channel" divides channel i by its guarded (i, i) cofactor (Delta_i =
1/[Psi^-1]_ii for a symmetric positive definite Psi).  Determinant and adjugate come from
the singular value decomposition (ivdrem.blocks._kernels), O(nθ^3) and exact at singular
Psi, or, while Psi/s is well conditioned, by cheaper routes exact to the same rounding:
"paper" adj = det * inverse from one LU, "eigen" the singular values and one LU solve
(docs/mixing.md); the output Delta_log10 = log10 |Delta| stays finite where Delta underflows.
"""
from __future__ import annotations

import numpy as np

from .jacobians import mixing_jacobian
from ._core import BlockSpec, make_block, ParameterError
from ._kernels import mixing_values, MIXING_VARIANTS

__all__ = ["mixing", "MIXING_VARIANTS", "DEFAULT_F_REL", "DEFAULT_GUARD", "start_of_term",
           "START_RAMP_REL"]

#: f0 of "eigen" relative to ||Psi||_F (f0 = 1e-6 lambda_max in the source, docs/mixing.md)
DEFAULT_F_REL = 1e-6
#: guard of "channel": c_i = sqrt(C_ii^2 + guard^2 ||C_i,:||^2)
DEFAULT_GUARD = 1e-3
#: ramp of the composite term's start relative to the window T (scale-free variants)
START_RAMP_REL = 0.1


def start_of_term(variant, T):
    """(t_on, t_ramp) of the composite term (21) for a mixing variant (docs/mixing.md):
    the paper's mixing starts at t = 0 (its Delta grows with Psi, so its weight does), the
    scale-free variants at t = T, when the window (15a) is full (their Delta is about 1 as
    soon as Psi has full rank, while the bias Psi^-1 W of (17) is still large)."""
    if variant == "paper":
        return 0.0, 0.0
    return float(T), START_RAMP_REL * float(T)


def mixing_output(t, x, u, y, ntheta, variant, f_rel, guard):
    # inputs   u.Y_Psi = [Y (nθ), Psi (nθ*nθ row-major)]
    # outputs  y.Delta (1, or nθ for "channel"), y.calY (nθ), y.Delta_log10 = log10|Delta|
    Y = u.Y_Psi[0:ntheta]
    Psi = u.Y_Psi[ntheta:ntheta + ntheta * ntheta]
    mixing_values(variant, Y, Psi, f_rel, guard, y.Delta, y.calY, y.Delta_log10)


def delta_size(ntheta, variant):
    """Entries of the Delta output: one per channel for "channel", else one."""
    return ntheta if variant == "channel" else 1


def mixing(ntheta, variant="paper", *, f_rel=DEFAULT_F_REL, guard=DEFAULT_GUARD,
           input="avg", name="mixing"):
    """Determinant/adjugate mixing (17): nθ scalar regressions calY_i = Delta_i theta_i + calW_i.

    ``variant`` is "paper" (eq. 17), "eigen" (Delta = prod sigma_j/(sigma_j + f0),
    f0 = f_rel ||Psi||_F) or "channel" (Delta_i = det Psi / c_i, c_i the guarded (i, i)
    cofactor); docs/mixing.md gives each formula and what it keeps of Theorem 2.

    ======  ==========================================================
    states  none
    inputs  <input>[nθ + nθ*nθ] = [Y, Psi]
    output  Delta[k], calY[nθ], Delta_log10[k] (k = nθ for "channel", else 1)
    params  none (variant, f_rel, guard are structural constants)
    ======  ==========================================================
    """
    if variant not in MIXING_VARIANTS:
        raise ParameterError(f"block '{name}': unknown mixing variant {variant!r}; choose one "
                             f"of {', '.join(MIXING_VARIANTS)}")
    for key, v in (("f_rel", f_rel), ("guard", guard)):
        if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
            raise ParameterError(f"block '{name}': mixing {key} must be a number > 0, got {v!r}")
    k = delta_size(ntheta, variant)
    spec = BlockSpec(name=name, inputs=[(input, ntheta + ntheta * ntheta)],
                     outputs=[("Delta", k), ("calY", ntheta), ("Delta_log10", k)],
                     states=[], x0=np.zeros(0),
                     param_names=("ntheta", "variant", "f_rel", "guard"),
                     output=mixing_output, direct=(input,),
                     named_ports=True, kernel_names={input: "Y_Psi"}, jacobian=mixing_jacobian,
                     constants={"ntheta": ntheta, "variant": MIXING_VARIANTS.index(variant),
                                "f_rel": float(f_rel), "guard": float(guard)},
                     info={"variant": variant})
    return make_block(spec, {})
