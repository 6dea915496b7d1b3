"""Each diagnostic of ivdrem.experiments.diagnostics against a case with a known answer."""
import math

import numpy as np
import pytest

from ivdrem.experiments import diagnostics

T_LONG = np.linspace(0.0, 1000.0, 100_001)


def test_power_fit_and_decay_exponent_recover_exact_powers():
    t = T_LONG[1:]
    a, C, r2 = diagnostics.power_fit(t, 3.0 * t ** -0.7)
    assert a == pytest.approx(0.7, abs=1e-12) and C == pytest.approx(3.0, rel=1e-10) and r2 > 0.999999
    # windowed means of an oscillation do not decay; of 1/(t+1) decay with k ~ 1
    assert abs(diagnostics.decay_exponent(T_LONG, 1 + 0.5 * np.sin(3 * T_LONG))) < 0.01
    assert diagnostics.decay_exponent(T_LONG, 1 / (T_LONG + 1)) == pytest.approx(1.0, abs=0.01)


def test_ka1_and_pe_for_delta_one_over_sqrt_t_plus_1():
    """The paper's example: Δ = 1/√(t+1) is not in L2 (KA1 holds) and not PE (vanishes)."""
    delta = 1 / np.sqrt(T_LONG + 1)
    c, S = diagnostics.check_ka1(T_LONG, delta)
    assert c["verdict"] == diagnostics.HOLDS
    np.testing.assert_allclose(S[-1], math.log(1001.0), rtol=1e-5)  # ∫ 1/(t+1) = log(t+1); trapezoid h = 0.01
    assert c["measured"]["int_Delta2_growth_last_half"] == pytest.approx(math.log(1001 / 501), rel=1e-6)
    pe = diagnostics.check_pe(T_LONG, delta)
    assert pe["verdict"] == diagnostics.FAILS
    assert pe["measured"]["decay_exponent_abs_Delta"] == pytest.approx(0.5, abs=0.01)


def test_ka1_fails_for_square_integrable_delta_and_pe_holds_for_persistent_one():
    c, S = diagnostics.check_ka1(T_LONG, np.exp(-T_LONG / 50))
    assert c["verdict"] == diagnostics.FAILS
    assert S[-1] == pytest.approx(25.0, rel=1e-6)                    # ∫ e^(-t/25) = 25
    c, _ = diagnostics.check_ka1(T_LONG, 1 / (T_LONG + 1))                     # Δ² ~ t^-2: in L2
    assert c["verdict"] == diagnostics.FAILS
    persistent = 0.3 + 0.1 * np.sin(0.7 * T_LONG)
    assert diagnostics.check_ka1(T_LONG, persistent)[0]["verdict"] == diagnostics.HOLDS
    assert diagnostics.check_pe(T_LONG, persistent)["verdict"] == diagnostics.HOLDS
    # Δ ≡ 0 is in L2
    assert diagnostics.check_ka1(T_LONG, 0 * T_LONG)[0]["verdict"] == diagnostics.FAILS


def test_excitation_beta_of_constant_regressors():
    """ζ = φ constant: ∫_{t−T}^t ζφᵀ = T ZᵀZ, so β = T^nθ det(ZᵀZ) for t ≥ T."""
    t = np.linspace(0, 50, 5001)
    Z = np.array([[1.0, 0.0], [0.5, 2.0]])                           # ζᵀ, n = 2, nθ = 2
    flat = np.repeat(Z.reshape(-1, 1), t.size, axis=1)
    beta = diagnostics.excitation_beta(t, flat, flat, 2, 2, 10.0)
    assert np.all(np.isnan(beta[t < 10.0 - 1e-9]))
    np.testing.assert_allclose(beta[t >= 10.0], 100.0 * np.linalg.det(Z.T @ Z), rtol=1e-9)


def test_ka2_holds_with_growing_mu_and_fails_with_constant_mu():
    t = np.linspace(0, 600, 60_001)
    tau = np.vstack([7.5 * np.sin(0.5 * np.pi * t), 1.5 * np.sin(0.05 * np.pi * t)])
    dtau = np.vstack([7.5 * 0.5 * np.pi * np.cos(0.5 * np.pi * t),
                      1.5 * 0.05 * np.pi * np.cos(0.05 * np.pi * t)])
    good, L, _ = diagnostics.check_ka2(t, tau, t + 15.0)
    assert good["verdict"] == diagnostics.HOLDS
    # numerical τ̇_d (second order differences) = the analytic derivative
    _, L_exact, _ = diagnostics.check_ka2(t, tau, t + 15.0, dtau_d=dtau)
    np.testing.assert_allclose(L, L_exact, rtol=1e-4)
    bad, L_const, _ = diagnostics.check_ka2(t, tau, 15.0 + 0 * t)
    assert bad["verdict"] == diagnostics.FAILS                                  # μ constant: ∫ grows ~ t
    assert L_const[-1] == pytest.approx(np.trapezoid(np.sum(dtau ** 2, 0), t) / 225, rel=1e-4)


def test_filtered_disturbance_equals_the_analytic_filter_response():
    """ẇ = l(−τ_d − w), w(0) = 0 for τ_d = sin ωt has the closed form below."""
    l, om = 50.0, 1.3
    A, B = -l * l / (l * l + om * om), l * om / (l * l + om * om)
    errs = []
    for nt in (2001, 4001):                                          # h = 0.01, 0.005
        t = np.linspace(0, 20, nt)
        w = diagnostics.filtered_disturbance(t, np.sin(om * t)[None, :], l)[0]
        exact = A * np.sin(om * t) + B * np.cos(om * t) - B * np.exp(-l * t)
        errs.append(np.max(np.abs(w - exact)))
    assert errs[0] < 3e-5                                             # ~ h² ω² / 8
    assert errs[0] / errs[1] == pytest.approx(4.0, rel=0.05)          # second order in h


def _ka3(w_freq, w_phase=0.0):
    t = np.linspace(0, 400, 40_001)
    n, nth = 1, 2
    zeta = np.vstack([np.sin(2.0 * t), np.cos(0.3 * t)])             # ζᵀ: 1 × 2
    w = np.sin(w_freq * t + w_phase)[None, :]
    return diagnostics.check_ka3(t, zeta, w, n, nth, tau_d=w)


def test_ka3_holds_for_independent_frequencies_and_fails_for_a_shared_one():
    good, ints = _ka3(math.pi / 2)
    assert good["verdict"] == diagnostics.HOLDS
    assert good["measured"]["shared_frequency"] is False
    assert np.max(np.abs(ints)) < 5.0                                 # bounded integrals
    bad, ints = _ka3(2.0, 0.4)                                        # ζ's own frequency
    assert bad["verdict"] == diagnostics.FAILS
    assert bad["measured"]["shared_frequency"] is True
    assert bad["measured"]["closest_frequencies"][0] == pytest.approx(2.0, abs=0.02)
    # ∫ sin(2t) sin(2t + 0.4) = t cos(0.4)/2 + bounded: grows linearly
    assert ints[0, -1] == pytest.approx(400 * math.cos(0.4) / 2, rel=0.01)
    assert bad["measured"]["worst_pair"].startswith("ζ_1,1")


def test_prop2_ratio_bounded_for_W_like_dF_over_F_and_growing_for_constant_W():
    t = np.linspace(0, 300, 30_001)
    F, dF = t ** 2 + 1, 2 * t
    good, R = diagnostics.check_prop2(t, (3.0 * dF / F)[None, :], 2.0, 1.0, 20.0)
    assert good["verdict"] == diagnostics.HOLDS
    np.testing.assert_allclose(R[t >= 20], 3.0, rtol=1e-12)
    bad, _ = diagnostics.check_prop2(t, np.ones((1, t.size)), 2.0, 1.0, 20.0)
    assert bad["verdict"] == diagnostics.FAILS


def test_property42_finds_rho_for_the_papers_mu_and_none_for_a_decaying_mu():
    t = np.linspace(0, 300, 3001)
    mu = t + 15.0
    c, p = diagnostics.check_property42(t, mu, 0.8, np.ones_like(t))
    assert c["verdict"] == diagnostics.HOLDS
    rho, drho = p["rho"], p["delta_rho"]
    lhs = (rho - 1 / 0.8) * mu + rho * 1.0 / mu - rho / drho          # Property 4.2 itself
    assert np.all(lhs >= p["mu_LB"] - 1e-9) and np.min(p["mu_LB"]) > 0
    mu_bad = 1.0 / (t + 1.0)                                          # (ρ−1/δ)μ + ρμ̇/μ = −μ/δ < 0
    c, p = diagnostics.check_property42(t, mu_bad, 0.8, -mu_bad ** 2)
    assert c["verdict"] == diagnostics.FAILS and p is None


def test_rate_fit_recovers_the_exponent():
    t = np.linspace(0, 300, 3001)
    c, (a, C) = diagnostics.check_rate(t, 2.0 * (t + 1e-3) ** -1.2)
    assert c["verdict"] == diagnostics.HOLDS and a == pytest.approx(1.2, abs=0.01)
    c, _ = diagnostics.check_rate(t, 5.0 + 0 * t)
    assert c["verdict"] == diagnostics.FAILS
    # a slow decrease towards a floor cannot be told from convergence at this horizon
    c, _ = diagnostics.check_rate(t, 1.0 + 0.5 * np.exp(-t / 400))
    assert c["verdict"] == diagnostics.UNDECIDED


def test_rate_of_a_run_too_short_for_its_windows_is_not_evaluated():
    """Two samples (t_end = 0.1 s at dt_out = 0.1 s): no window of the last half holds
    one, so nothing is fitted and the check says so (it raised IndexError before)."""
    t = np.array([0.0, 0.1])
    c, (a, C) = diagnostics.check_rate(t, np.array([2.0, 1.95]))
    assert c["verdict"] == diagnostics.UNDECIDED and c["note"].startswith("not evaluated")
    assert math.isnan(a) and math.isnan(C)


def test_lyapunov_function_and_bound():
    rng = np.random.default_rng(1)
    n, nth, nt = 2, 3, 5
    r = rng.normal(size=(n, nt))
    A = rng.normal(size=(n, n))
    M = np.repeat((A @ A.T + np.eye(n))[:, :, None], nt, axis=2)
    th = rng.normal(size=(nth, nt))
    G = np.diag([0.1, 0.2, 0.5])
    td = rng.normal(size=(n, nt))
    mu = np.linspace(1, 2, nt)
    V = diagnostics.lyapunov(r, M, th, G, td, mu, 2.5)
    k = 3
    expect = (0.5 * r[:, k] @ M[:, :, k] @ r[:, k] + 0.5 * th[:, k] @ np.linalg.inv(G) @ th[:, k]
              + 1.25 * np.sum((td[:, k] / mu[k]) ** 2))
    assert V[k] == pytest.approx(expect, rel=1e-12)
    t = np.linspace(0, 10, 101)
    W = np.ones((2, t.size))
    ok, bound = diagnostics.check_lyapunov(t, 1.0 + 0.5 * t, W, 0.25, 0 * t, 1.0, 1.0)  # bound = 1 + t/2
    assert ok["verdict"] == diagnostics.HOLDS
    np.testing.assert_allclose(bound, 1 + 0.5 * t)
    bad, _ = diagnostics.check_lyapunov(t, 1.0 + 0.6 * t, W, 0.25, 0 * t, 1.0, 1.0)
    assert bad["verdict"] == diagnostics.FAILS and bad["measured"]["t_max_ratio"] == pytest.approx(10.0)


def test_inactive_composite_term_is_flagged_with_the_fix():
    t = np.linspace(0, 120, 12_001)
    delta = np.where(t > 20, 2.5e-9, 0.0)                             # a 3-link arm's Δ level
    c = diagnostics.check_active(t, delta, 1e10, 0.01, 20.0)
    assert c["verdict"] == diagnostics.FAILS
    assert "gamma = \"auto\"" in c["note"]
    # the γ it suggests makes the term active: κ / (λ_max(Γ) Δ²) = 0.5 / (0.01 · 6.25e-18)
    g = c["measured"]["gamma_auto_from_this_run"]
    assert g == pytest.approx(0.5 / (0.01 * 2.5e-9 ** 2), rel=1e-3)
    assert diagnostics.check_active(t, delta, g, 0.01, 20.0)["verdict"] == diagnostics.HOLDS


def test_gamma_auto_rule():
    from ivdrem.diagrams.gamma_auto import gamma_from_delta
    t = np.linspace(0, 40, 4001)
    delta = np.where(t >= 20, 8e-5 * (1 + 0.1 * np.sin(t)), 0.0)
    out = gamma_from_delta(t, delta, 20.0, 0.01 * np.eye(5))
    mean = np.trapezoid(delta[t >= 20] ** 2, t[t >= 20]) / 20.0
    assert out["gamma"] == pytest.approx(0.5 / (0.01 * mean), rel=1e-12)
    with pytest.raises(ValueError, match="not excited"):
        gamma_from_delta(t, 0 * t, 20.0, 0.01)


def test_json_has_no_arrays_and_no_nan():
    import json
    from ivdrem.experiments.config import read_config, resolve_config
    from ivdrem.reports.synthetic import synthetic_paper_run
    run = synthetic_paper_run(resolve_config(read_config())[0], t_end=60.0)
    for law, lr in run.runs.items():
        d = diagnostics.diagnose(lr, run.config, None, theta=run.theta)
        text = json.dumps(diagnostics.to_json(d), allow_nan=False)
        assert "checks" in text
        ids = [c["id"] for c in d["checks"]]
        assert {"KA1", "KA2", "KA3", "P2", "P4.2", "RATE"} <= set(ids), law


def test_paper_json_has_diagnostics_per_law(tmp_path, monkeypatch, capsys):
    import json
    import ivdrem.experiments.paper as paper
    from ivdrem.cli import main
    from ivdrem.reports.synthetic import synthetic_paper_run

    def fake(config, *, laws=None, progress=True, engine="compiled", log=None, **kw):
        return synthetic_paper_run(config, dt=0.05)
    monkeypatch.setattr(paper, "run_paper", fake)
    out = tmp_path / "o.json"
    assert main(["paper", "--t-end", "60", "--json", str(out), "--quiet"]) == 0
    data = json.loads(out.read_text())
    for law in ("iv-drem", "composite-learning"):
        ids = [c["id"] for c in data[law]["diagnostics"]["checks"]]
        assert ids[:3] == ["KA1", "PE", "KA2"]
        assert all(c["verdict"] in (diagnostics.HOLDS, diagnostics.FAILS, diagnostics.UNDECIDED, diagnostics.NA)
                   for c in data[law]["diagnostics"]["checks"])
    assert "diagnostics of iv-drem" in capsys.readouterr().out


# ------------------------------------------------------------------ a run that does not learn
def _err(t, kind):
    if kind == "grows":
        return 2.0 * (1.0 + 0.05 * t)                      # ‖θ̃‖ moves away from θ
    return 2.0 / (1.0 + 0.2 * t)                           # converging


def test_learning_check_names_the_cause_and_a_remedy_that_is_not_auto():
    t = np.linspace(0.0, 60.0, 6001)
    logd = -20.0 - 0.12 * t                               # the paper's Δ: 7 decades over [T, t_end]
    c = diagnostics.check_learning(t, _err(t, "grows"), 20.0, delta_log10=logd,
                                   mixing="paper", gamma=1e42, gamma_auto=True)
    assert c["verdict"] == diagnostics.FAILS
    assert "spans 4.8 decades" in c["note"] and 'mixing = "eigen"' in c["note"]
    assert 'gamma = "auto"' not in c["note"]
    # a mixing that keeps Δ near 1, under the calibrated γ: a smaller numeric γ, named
    c = diagnostics.check_learning(t, _err(t, "grows"), 20.0, delta_log10=0 * t - 0.1,
                                   mixing="eigen", gamma=50.0, gamma_auto=True)
    assert "100x below the calibrated one" in c["note"] and "try 0.5" in c["note"]
    # the bias floor above ‖θ̃(0)‖: the excitation's, whatever the mixing
    c = diagnostics.check_learning(t, _err(t, "converges"), 20.0,
                                   calW_over_Delta=3.0 + 0 * t, mixing="eigen")
    assert c["verdict"] == diagnostics.FAILS and "bias floor" in c["note"]
    assert "no mixing changes 𝒲/Δ" in c["note"]
    ok = diagnostics.check_learning(t, _err(t, "converges"), 20.0,
                                    calW_over_Delta=0.01 + 0 * t, delta_log10=logd,
                                    mixing="paper")
    assert ok["verdict"] == diagnostics.HOLDS and ok["note"] == ""


def test_a_bias_floor_comparable_to_the_initial_error_is_not_learning():
    """The UR5 after 20 s (docs/mixing.md): ‖θ̃‖ 5.78 → 5.23 with a bias floor of 4.92,
    below ‖θ̃(0)‖ but 85 % of it: θ̂ can at best settle near θ + Ψ⁻¹W, so LEARN fails and
    says why; a floor well below half of ‖θ̃(0)‖ with θ̃ halved holds; a run with Δ whose
    θ̃ shrinks by less than half "has not learned (yet)"."""
    t = np.linspace(0.0, 20.0, 2001)
    err = 5.78 - (5.78 - 5.23) * t / 20.0
    c = diagnostics.check_learning(t, err, 20.0, calW_over_Delta=4.92 + 0 * t, mixing="eigen")
    assert c["verdict"] == diagnostics.FAILS
    assert "85% of ‖θ̃(0)‖ = 5.78, comparable to the initial error" in c["note"]
    assert c["measured"]["bias_floor_share_of_theta_err_0"] == pytest.approx(4.92 / 5.78)
    c = diagnostics.check_learning(t, err, 20.0, calW_over_Delta=0.3 + 0 * t, mixing="eigen")
    assert c["verdict"] == diagnostics.FAILS and "has not learned (yet)" in c["note"]
    assert "0.90 of its start" in c["note"]
    ok = diagnostics.check_learning(t, 5.78 / (1.0 + t), 20.0, calW_over_Delta=0.3 + 0 * t,
                                    mixing="eigen")
    assert ok["verdict"] == diagnostics.HOLDS and ok["note"] == ""
    # a law without Δ is judged by growth alone, as before
    assert diagnostics.check_learning(t, err, 20.0)["verdict"] == diagnostics.HOLDS


def test_inactive_term_under_auto_does_not_advise_auto():
    t = np.linspace(0, 120, 12_001)
    delta = np.where(t > 20, 2.5e-12, 0.0)
    c = diagnostics.check_active(t, delta, 1e10, 0.01, 20.0, gamma_auto=True, mixing="paper")
    assert c["verdict"] == diagnostics.FAILS
    assert 'gamma = "auto"' not in c["note"] and 'mixing = "eigen"' in c["note"]


def _shared_frequency_config(tmp_path):
    """The paper's arm with a 40 N·m disturbance at the reference's own 2 rad/s: condition
    (19) fails, W of (16) does not fade, and θ̂ settles away from θ (measured: ‖θ̃‖ 2.0 →
    7.8 over 60 s, bias floor 7.8)."""
    p = tmp_path / "shared.toml"
    p.write_text("[experiment]\nt_end = 60.0\nlaws = [\"iv-drem\"]\n"
                 "[disturbance]\namplitude = [40.0, 1.5]\nomega = [2.0, 0.15707963267948966]\n")
    return p


def test_a_closed_loop_that_does_not_learn_warns_in_run_summary_and_report(tmp_path, capsys):
    import json
    from ivdrem.cli import main
    from ivdrem.experiments.config import read_config, resolve_config
    from ivdrem.experiments.paper import run_paper
    from ivdrem.reports.content import build_content
    cfg_path = _shared_frequency_config(tmp_path)
    out = tmp_path / "o.json"
    assert main(["paper", "--config", str(cfg_path), "--json", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "WARNING: the run does not learn: the bias floor" in text
    data = json.loads(out.read_text())
    assert any("does not learn" in w for w in data["iv-drem"]["warnings"])
    run = run_paper(resolve_config(read_config(cfg_path))[0], progress=False)
    meta = dict(build_content(run).meta)
    assert "does not learn" in meta["WARNING (iv-drem)"]
    # the paper's own experiment over the same horizon learns: no warning
    good = run_paper(resolve_config(read_config(overrides={"experiment.t_end": 60.0,
                                            "experiment.laws": ["iv-drem"]}))[0], progress=False)
    d = diagnostics.diagnose_run(good)["iv-drem"]
    assert diagnostics.learning_warnings(d) == []
    assert not any(k.startswith("WARNING") for k, _ in build_content(good).meta)


@pytest.mark.parametrize("arm", ["two-link", "planar-3"])
def test_model_functions_over_samples_equal_the_python_functions_sample_by_sample(arm):
    """The diagnostics evaluate Φ and M over a run's samples in one compiled loop (the
    compiled engine's model module): the same numbers as the generated Python functions
    called sample by sample, and the Python path itself where no compiled loop exists."""
    from ivdrem.experiments import diagnostics as dg
    from ivdrem.models import get_model
    model = get_model(arm)
    n, nth, nt = model.n, model.ntheta, 257
    rng = np.random.default_rng(3)
    q, dq, v, dv = (rng.uniform(-2, 2, size=(n, nt)) for _ in range(4))
    theta = np.asarray(model.theta_values, dtype=float)
    phi = dg._model_at_samples(model, "Phi", (n, nth), q, dq, v, dv)
    mass = dg._model_at_samples(model, "M", (n, n), q, theta=theta)
    assert phi.shape == (n, nth, nt) and mass.shape == (n, n, nt)
    for k in range(0, nt, 16):
        np.testing.assert_allclose(phi[:, :, k], model.regressor(q[:, k], dq[:, k], v[:, k],
                                                                 dv[:, k]), rtol=1e-14, atol=0)
        ref = np.empty((n, n))
        model.functions.M(q[:, k], theta, ref)
        np.testing.assert_allclose(mass[:, :, k], ref, rtol=1e-14, atol=0)


def test_model_functions_over_samples_without_a_compiled_module(monkeypatch):
    """A model the compile cache cannot serve is evaluated by its Python functions."""
    from ivdrem.experiments import diagnostics as dg
    from ivdrem.models import two_link
    from ivdrem.sim import compiled
    model = two_link()
    q = np.linspace(-1, 1, 22).reshape(2, 11)
    fast = dg._model_at_samples(model, "Phi", (2, 5), q, q, q, q)

    def refuse(model):
        raise RuntimeError("no compiled module")

    monkeypatch.setattr(compiled, "model_module", refuse)
    slow = dg._model_at_samples(model, "Phi", (2, 5), q, q, q, q)
    np.testing.assert_array_equal(fast, slow)


# ------------------------------------------------------------------ a run shorter than the window
def test_short_horizon_note_follows_the_start_of_the_composite_term():
    # scale-free mixings start (21) at T (ramp T/10); the paper's at 0; any windowed law
    # needs its window full; a law without a window is judged on any horizon
    assert diagnostics.short_horizon_note(1.0, 40.0, "eigen") == (
        "not evaluated: the composite term starts at T = 40 s (the run ends at t = 1 s)")
    assert diagnostics.short_horizon_note(43.0, 40.0, "channel").startswith("not evaluated")
    assert diagnostics.short_horizon_note(45.0, 40.0, "eigen") == ""
    assert "before the window T = 20 s is full" in diagnostics.short_horizon_note(
        10.0, 20.0, "paper")
    assert diagnostics.short_horizon_note(30.0, 20.0, "paper") == ""
    assert diagnostics.short_horizon_note(1.0, 20.0, None, windowed=False) == ""


def test_a_run_shorter_than_the_window_gives_no_verdict_about_learning(tmp_path, capsys):
    """planar-3 ("eigen" mixing, the term starts at T) for 1 s: the learning checks are not
    decided, no learning warning is printed or written, and the note says why."""
    import json
    from ivdrem.cli import main
    out_json = tmp_path / "o.json"
    assert main(["paper", "--config", "examples/planar3.toml", "--t-end", "1",
                 "--laws", "iv-drem", "--json", str(out_json), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "does not learn" not in text and "has not learned" not in text
    assert "inactive" not in text
    assert "note: not evaluated: the composite term starts at T" in text
    data = json.loads(out_json.read_text())
    assert data["iv-drem"]["warnings"] == []
    checks = {c["id"]: c for c in data["iv-drem"]["diagnostics"]["checks"]}
    for cid in ("LEARN", "ACTIVE", "RATE"):
        assert checks[cid]["verdict"] == diagnostics.UNDECIDED, cid
        assert checks[cid]["note"].startswith("not evaluated: the composite term starts at T")
    # what a short run can judge keeps its own verdict and note
    assert not checks["KA2"]["note"].startswith("not evaluated")


def test_learning_is_not_decided_when_the_last_half_has_no_two_windows():
    """A run of a few samples (``ivdrem paper --laws none --t-end 0.1`` records 11): the
    last half's growth cannot be measured, so LEARN is not decided (it said "holds" with a
    growth of nan); the same record with enough samples, θ̃ falling, holds."""
    t = np.linspace(0.0, 0.1, 3)
    short = diagnostics.check_learning(t, np.array([2.0, 1.98, 1.95]), 20.0)
    assert short["verdict"] == diagnostics.UNDECIDED
    assert not np.isfinite(short["measured"]["growth_last_half"])
    assert short["note"].startswith("not evaluated: none of the last half")
    t = np.linspace(0.0, 10.0, 1001)
    long = diagnostics.check_learning(t, 2.0 * np.exp(-0.1 * t), 20.0)
    assert long["verdict"] == diagnostics.HOLDS and np.isfinite(long["measured"]["growth_last_half"])
