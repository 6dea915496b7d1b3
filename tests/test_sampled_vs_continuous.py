"""The inertia-scaled design of (9) in continuous time, and the sampled loop against it.

The continuous control-law block with ``design="inertia-scaled"`` (ivdrem.blocks.control_law)
is the sampled controller's feedback M̂(q)(K + δ_μ μ) r in continuous time, so the sampled
loop (ivdrem.controller.sampled) has a continuous loop with the same gains to converge to.

Independent checks: the block's torque against the model's own M(q) (the composite
rigid-body algorithm on a URDF arm, sympy's M on the 2-link) times the paper's feedback; its
analytic Jacobian against central differences of its output kernel; its declared direct
feedthrough against moving each input; the python-control engine against the compiled one;
the sampled controller's torque at a sample against the block's on the same signals (two
implementations of one law); the sampled loop's θ̂, q approaching the continuous loop at
first order in h on the UR5 (the observed order of three step sizes).
"""
import os

import numpy as np
import pytest

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ivdrem import blocks as block_library  # noqa: E402
from ivdrem.blocks._core import ParameterError, flat_kernel, kernel_args  # noqa: E402
from ivdrem.models import get_model, two_link  # noqa: E402

DELTA_MU = 0.8


def _block(model, K):
    return block_library.control_law(model.n, model.ntheta, K=K, delta_mu=DELTA_MU,
                                     design="inertia-scaled", model=model)


def _random_inputs(model, rng):
    n, nth = model.n, model.ntheta
    return dict(q=rng.uniform(-1.0, 1.0, n), r=rng.standard_normal(n),
                mu=np.array([rng.uniform(15.0, 135.0)]),
                Pi=rng.standard_normal(n * nth), theta_hat=rng.standard_normal(nth),
                u_f=rng.standard_normal(n), chi=rng.standard_normal(n))


def _flat_inputs(spec, ins):
    return np.concatenate([ins[name] for name, _ in spec.inputs])


def _output(block, t, u):
    spec = block.ivdrem
    y = np.full(spec.noutputs, np.nan)
    flat_kernel(spec, "output")(t, np.zeros(0), u, y,
                                *kernel_args(spec, spec.validate(dict(block.params))))
    return y


# ----------------------------------------------------------------------- the block
@pytest.mark.parametrize("name", ["two-link", "ur5"])
def test_torque_is_the_models_inertia_times_the_papers_feedback(name):
    """tau = M(q, theta_nominal)(K + δ_μ μ) r + Πᵀθ̂ + χ − u_f with M from the model's own
    inertia function (not the regressor Φ_M the block uses), a full SPD K (χ: the
    observer's injection at theta_nominal, the design's default)."""
    m = two_link() if name == "two-link" else get_model(name)
    rng = np.random.default_rng(7)
    A = rng.standard_normal((m.n, m.n))
    K = A @ A.T + m.n * np.eye(m.n)
    blk = _block(m, K)
    M = np.empty((m.n, m.n))
    for _ in range(4):
        ins = _random_inputs(m, rng)
        m.functions.M(ins["q"], m.theta_values, M)
        Pi = ins["Pi"].reshape(m.n, m.ntheta)
        want = (M @ ((K + DELTA_MU * ins["mu"][0] * np.eye(m.n)) @ ins["r"])
                + Pi @ ins["theta_hat"] + ins["chi"] - ins["u_f"])
        got = _output(blk, 0.3, _flat_inputs(blk.ivdrem, ins))
        assert np.abs(got - want).max() <= 1e-11 * np.abs(want).max(), (got, want)


@pytest.mark.parametrize("name", ["two-link", "ur5"])
def test_analytic_jacobian_matches_central_differences(name):
    """The block's Jacobian kernel (d tau / d(q, r, mu, Π, θ̂, u_f), the q columns from the
    regressor's generated derivative Φ_M_jac) against central differences of its output."""
    m = two_link() if name == "two-link" else get_model(name)
    rng = np.random.default_rng(11)
    blk = _block(m, rng.uniform(1.0, 20.0, m.n))
    spec = blk.ivdrem
    args = kernel_args(spec, spec.validate(dict(blk.params)))
    jac_k = flat_kernel(spec, "jacobian")
    for _ in range(3):
        u = _flat_inputs(spec, _random_inputs(m, rng))
        jac = np.zeros((spec.noutputs, spec.ninputs))
        jac_k(0.2, np.zeros(0), u.copy(), jac, *args)
        fd = np.zeros_like(jac)
        for c in range(u.size):
            step = 1e-5 * max(abs(u[c]), 1.0)
            up, um = u.copy(), u.copy()
            up[c] += step
            um[c] -= step
            fd[:, c] = (_output(blk, 0.2, up) - _output(blk, 0.2, um)) / (up[c] - um[c])
        scale = np.abs(fd).max()
        assert np.abs(jac - fd).max() <= 1e-7 * scale
        big = np.abs(fd) >= 1e-4 * scale          # entry by entry: the q columns carry mu
        assert (np.abs(jac - fd)[big] / np.abs(fd)[big]).max() <= 1e-6


def test_declared_feedthrough_moves_the_torque_and_q_is_an_input():
    """Every declared direct input (q included: M̂(q)) moves tau; the paper's design has no
    q input, so the two designs are different blocks."""
    m = get_model("ur5")
    rng = np.random.default_rng(3)
    blk = _block(m, 5.0)
    spec = blk.ivdrem
    assert set(spec.direct) == {name for name, _ in spec.inputs}
    u = _flat_inputs(spec, _random_inputs(m, rng))
    y0 = _output(blk, 0.0, u)
    for name, sl in spec.port_slices("inputs").items():
        up = u.copy()
        up[sl] += rng.uniform(0.5, 1.5, sl.stop - sl.start)
        assert np.any(_output(blk, 0.0, up) != y0), name
    paper = block_library.control_law(m.n, m.ntheta, K=5.0)
    assert "q" not in [p for p, _ in paper.ivdrem.inputs]


def test_one_enumeration_of_the_designs_and_clear_refusals():
    from ivdrem.controller import sampled
    from ivdrem.diagrams import closed_loop
    from ivdrem.experiments import config as cfg
    assert sampled.DESIGNS is block_library.DESIGNS
    assert cfg.OPTIONAL["controller"]["design"].choices is block_library.DESIGNS
    with pytest.raises(ValueError, match="design = 'inertia' is not a design of \\(9\\).*"
                                         "'inertia-scaled'"):
        closed_loop("none", design="inertia")
    with pytest.raises(ParameterError, match="needs the robot model"):
        block_library.control_law(2, 5, design="inertia-scaled")
    with pytest.raises(ParameterError, match="theta_nominal.*length 5"):
        block_library.control_law(2, 5, design="inertia-scaled", model=two_link(),
                                  theta_nominal=[1.0, 2.0])


def test_sampled_torque_equals_the_blocks_on_the_same_signals():
    """SampledController's first torque (all filters at zero, so the observer's Π_Xᵀ = Φᵀ
    and its injection χ = μ Φ_Mᵀ(q, r) θ_nominal) equals the continuous block's on the same
    q, r, μ, Π_X, χ: one law, two implementations."""
    from ivdrem.controller.sampled import SampledController
    m = get_model("ur5")
    rng = np.random.default_rng(5)
    K = rng.uniform(2.0, 20.0, m.n)
    th0 = rng.standard_normal(m.ntheta)
    ctl = SampledController(m, "none", K=K, design="inertia-scaled", theta_hat0=th0)
    qd, dqd, ddqd = ctl.reference(0.0)
    q, dq = qd + 0.03 * rng.standard_normal(m.n), dqd + 0.1 * rng.standard_normal(m.n)
    tau = ctl.step(0.0, q, dq)
    e, de = qd - q, dqd - dq
    r, v, dv = de + e, dqd + e, ddqd + de
    mu = ctl.mu(0.0)
    PM, P = np.empty((m.n, m.ntheta)), np.empty((m.n, m.ntheta))
    m.functions.Phi_M(q, r, PM)
    m.functions.Phi(q, dq, v, dv, P)
    blk = _block(m, K)
    ins = dict(q=q, r=r, mu=np.array([mu]), Pi=P.ravel(), theta_hat=th0,
               u_f=np.zeros(m.n), chi=mu * PM @ m.theta_values)
    want = _output(blk, 0.0, _flat_inputs(blk.ivdrem, ins))
    assert np.abs(tau - want).max() <= 1e-10 * np.abs(want).max()


# ----------------------------------------------------------------------- the loop
def test_both_engines_agree_on_the_inertia_scaled_loop():
    """The 2-link loop with the inertia-scaled law, python-control's engine against the
    compiled one (which uses the block's analytic Jacobian), and it is not the paper's."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import simulate
    loop = closed_loop("iv-drem", design="inertia-scaled", K=3.0)
    kw = dict(method="rk4", h=1e-3, dt_out=0.05, progress=False)
    ref = simulate(loop, 0.2, engine="reference", **kw)
    comp = simulate(loop, 0.2, engine="compiled", **kw)
    lab = list(ref.output_labels)
    assert lab == list(comp.output_labels)
    scale = np.abs(ref.outputs).max(axis=1, keepdims=True) + 1e-300
    assert np.abs(ref.outputs - comp.outputs).max() <= 1e-9 * scale.max()
    paper = simulate(closed_loop("iv-drem", K=3.0), 0.2, engine="compiled", **kw)
    tau = [lab.index(f"tau[{i}]") for i in range(2)]
    assert np.abs(paper.outputs[tau] - comp.outputs[tau]).max() > 1e-3


def test_configuration_selects_the_design_with_the_sampled_controllers_gains():
    """[controller] design = "inertia-scaled": the continuous loop's K is the configured
    joint gain over M̂_ii(q0), the sampled controller's K that gain within its delay rule
    (floor GAIN_FLOOR, cap h (K + (1 + δ_μ) μ_max) <= 0.5 for the FMU's one-sample delay)."""
    from ivdrem.controller.sampled import GAIN_FLOOR, gain_budget
    from ivdrem.controller.fmu_export import controller_design
    from ivdrem.experiments.config import closed_loop_kwargs, read_config, resolve_config
    m = get_model("ur5")
    config = resolve_config(read_config(None, overrides={"model.name": "ur5",
                                          "controller.design": "inertia-scaled"}))[0]
    kw = closed_loop_kwargs(config, "iv-drem")
    assert kw["design"] == "inertia-scaled"
    M = np.empty((m.n, m.n))
    q0 = np.asarray(config["initial"]["q0"], float)
    m.functions.M(q0, np.asarray(config["model"]["theta"], float), M)
    want = np.asarray(config["controller"]["K"], float) / np.diag(M)
    np.testing.assert_allclose(np.diag(kw["K"]), want, rtol=1e-13)
    sampled = controller_design(config, "iv-drem", h=1e-3)
    cap = gain_budget(1) / 1e-3 - (1.0 + DELTA_MU) * sampled.get("mu_max", 135.0)
    np.testing.assert_allclose(np.diag(sampled["K"]), np.minimum(np.maximum(want, GAIN_FLOOR),
                                                                 cap), rtol=1e-13)
    assert cap == pytest.approx(257.0) and np.all(np.diag(sampled["K"]) >= GAIN_FLOOR)


# ----------------------------------------------------------------------- sampled → continuous
#: the comparison's gains on the UR5 (1/s: the inertia-scaled design's K)
K_UR5 = (4.0, 4.0, 4.0, 8.0, 8.0, 16.0)


def _first_order(law, t_end, **gains):
    """θ̂ and the tracking error e of the sampled loop at h = 4, 2, 1 ms against the
    continuous loop with the same gains on the UR5: (differences, observed orders)."""
    from ivdrem.controller.continuous import sampled_against_continuous
    m = get_model("ur5")
    res = sampled_against_continuous(m, law, hs=(4e-3, 2e-3, 1e-3), t_end=t_end, K=K_UR5,
                                     theta_hat0=0.5 * np.asarray(m.theta_values), **gains)
    assert res["theta_moved"] > 1e-3          # θ̂ moves: the comparison is not of zeros
    out = {}
    for key in ("theta", "e"):
        d = np.asarray(res[key])
        out[key] = (d, np.log2(d[:-1] / d[1:]))
    return out


def test_sampled_loop_approaches_the_continuous_loop_at_first_order_in_h():
    """Adaptation (11) with the observer's Π_X and the inertia-scaled feedback (the
    injection at θ_nominal), 0.5 s: max |θ̂_h − θ̂_c| and max |e_h − e_c| over the output
    times halve with h (measured: θ̂ 5.36e-5, 2.68e-5, 1.34e-5; e 1.25e-3, 6.26e-4,
    3.13e-4; orders 1.000, 1.000 and 1.003, 1.001)."""
    res = _first_order("none", 0.5)
    for key, (d, orders) in res.items():
        assert np.all((orders > 0.8) & (orders < 1.2)), (key, d, orders)
    assert res["theta"][0][-1] < 1e-4 and res["e"][0][-1] < 1e-3


@pytest.mark.slow
def test_iv_drem_sampled_loop_approaches_the_continuous_loop_at_first_order_in_h():
    """The same with IV-DREM over 1 s ("eigen" mixing, a window T = 0.2 s of (15a), the
    composite term (21) on from T; Δ ≈ 9e-11 there, so γ = 1e21): the window's sums over
    the samples and the mixing (17) keep the first order (measured: θ̂ 1.22e-3, 6.47e-4,
    3.35e-4, orders 0.92, 0.95; e 1.54e-3, 7.74e-4, 3.89e-4, orders 0.99, 0.99; the
    compile of the UR5's windowed loop dominates the time)."""
    res = _first_order("iv-drem", 1.0, T=0.2, gamma=1e21, mixing="eigen")
    for key, (d, orders) in res.items():
        assert np.all((orders > 0.8) & (orders < 1.2)), (key, d, orders)


def test_real_arm_loop_without_K_takes_the_joint_gains_over_the_nominal_inertia():
    """closed_loop(design="inertia-scaled") on the UR5 with K left at None: the control
    law's K is the experiment's joint gains (design_gains, N m s) over M̂_ii(q0), the
    sampled controller's K before its cap."""
    from ivdrem.controller.sampled import inertia_scaled_gains
    from ivdrem.diagrams import closed_loop
    from ivdrem.diagrams import arm_reference as arm
    m = get_model("ur5")
    loop = closed_loop("none", m, design="inertia-scaled")
    law = next(s for s in loop.syslist if s.name == "control_law")
    q0, _ = arm.initial_state(arm.design_trajectory(m))
    M = np.empty((m.n, m.n))
    m.functions.M(np.asarray(q0, float), m.theta_values, M)
    want = np.asarray(arm.design_gains(m, q0), float) / np.diag(M)
    np.testing.assert_allclose(np.diag(law.params["K"]), want, rtol=1e-13)
    # the sampled design floors and caps them for the FMU's one-sample delay
    # (docs/controller.md, "Sampled designs"; tests/test_sampled_stability.py)
    from ivdrem.controller.sampled import GAIN_FLOOR, gain_budget
    np.testing.assert_allclose(inertia_scaled_gains(m, arm.design_gains(m, q0), q0, 1e-3),
                               np.minimum(np.maximum(want, GAIN_FLOOR),
                                          gain_budget(1) / 1e-3 - (1 + DELTA_MU) * 135.0),
                               rtol=1e-13)
    assert "q" in [p for p, _ in law.ivdrem.inputs]
