"""Tests of the measured numbers and conclusions C1-C3 (ivdrem.experiments.metrics)."""
import json

import control as ct
import numpy as np
import pytest

from ivdrem.experiments.config import read_config, resolve_config
from ivdrem.experiments.metrics import (
    calW,
    conclusions,
    format_conclusions,
    norm,
    rms,
    signal,
    signal_names,
    summary,
    tau_d_error,
    theta_error,
)
from ivdrem.reports.synthetic import SyntheticPaperRun, synthetic_lawrun, synthetic_paper_run

CFG = resolve_config(read_config())[0]
THETA = np.array(CFG["model"]["theta"])
T_END = 100.0
T = np.linspace(0.0, T_END, 2001)


def err_with_norm(profile):
    """θ̃ (5 × n_t) whose Euclidean norm is exactly `profile` (a function of t)."""
    direction = THETA / np.linalg.norm(THETA)
    return direction[:, None] * profile(T)[None, :]


def tau_err(amplitude):
    return amplitude * np.vstack([np.sin(1.5 * T), np.cos(1.5 * T)])  # ‖τ̃_d‖ = amplitude


def make_run(cl_profile, iv_profile, cl_tau=1.0, iv_tau=0.1):
    runs = {
        "iv-drem": synthetic_lawrun("iv-drem", T, THETA, err_with_norm(iv_profile), tau_err(iv_tau), CFG),
        "composite-learning": synthetic_lawrun(
            "composite-learning", T, THETA, err_with_norm(cl_profile), tau_err(cl_tau), CFG),
    }
    return SyntheticPaperRun(config=CFG, theta=THETA, runs=runs)


def by_id(run):
    return {c["id"]: c for c in conclusions(run)}


STALLED = lambda t: 1.0 + 0.0 * t                      # noqa: E731  ‖θ̃‖ constant
CONVERGING = lambda t: np.exp(-t / 10.0)               # noqa: E731  ratio e^-10


# --------------------------------------------------------------------------- signals
def test_signal_by_label_and_base_name():
    t = np.linspace(0, 1, 11)
    labels = ["mu", "theta_hat[1]", "theta_hat[0]", "e[0]"]
    y = np.vstack([t, 2 * t, 3 * t, 4 * t])
    resp = ct.TimeResponseData(t, y, output_labels=labels, issiso=False)
    np.testing.assert_array_equal(signal(resp, "mu"), t)
    th = signal(resp, "theta_hat")
    assert th.shape == (2, 11)
    np.testing.assert_array_equal(th[0], 3 * t)  # ordered by index, not label order
    np.testing.assert_array_equal(th[1], 2 * t)
    np.testing.assert_array_equal(signal(resp, "theta_hat[1]"), 2 * t)
    assert signal(resp, "e").shape == (1, 11)
    assert signal_names(resp) == ["mu", "theta_hat", "e"]
    with pytest.raises(KeyError, match="available: mu, theta_hat, e"):
        signal(resp, "tau")


def test_errors_and_calW_are_what_the_outputs_say():
    run = make_run(STALLED, CONVERGING)
    lr = run.runs["iv-drem"]
    th_err = theta_error(lr, THETA)
    np.testing.assert_allclose(th_err, THETA[:, None] - signal(lr, "theta_hat"))
    np.testing.assert_allclose(norm(th_err), CONVERGING(T), rtol=1e-12, atol=1e-14)
    both = theta_error(run)  # PaperRun: dict per law, theta from run.theta
    assert set(both) == {"iv-drem", "composite-learning"}
    np.testing.assert_allclose(both["iv-drem"], th_err)
    np.testing.assert_allclose(tau_d_error(lr), tau_err(0.1), atol=1e-12)
    W = calW(lr, THETA)
    Delta = signal(lr, "Delta")
    np.testing.assert_allclose(signal(lr, "calY"), Delta * THETA[:, None] + W, atol=1e-18)
    assert W.shape == (5, T.size) and np.all(W[:, T < 20.0] == 0)


def test_rms_and_norm():
    t = np.linspace(0, 2 * np.pi, 100001)
    assert rms(t, np.sin(t)) == pytest.approx(1 / np.sqrt(2), rel=1e-6)
    assert rms(t, 3 + 0 * t) == pytest.approx(3.0)
    np.testing.assert_allclose(norm(np.array([[3.0], [4.0]])), [5.0])


# --------------------------------------------------------------------------- conclusions
def test_all_conclusions_pass():
    c = by_id(make_run(STALLED, CONVERGING))
    assert [k for k in c] == ["C1", "C2", "C3", "C4"]
    assert c["C4"]["verdict"] is None and "drem" in c["C4"]["note"]   # DREM not run
    for cid in ("C1", "C2", "C3"):
        assert c[cid]["verdict"] is True, c[cid]
        assert set(c[cid]) >= {"id", "statement", "measured", "threshold", "verdict"}
    assert c["C1"]["measured"]["max_rel_deviation_last_half"] == pytest.approx(0.0, abs=1e-12)
    assert c["C1"]["measured"]["end_to_initial_ratio"] == pytest.approx(1.0)
    assert c["C2"]["measured"]["end_to_initial_ratio"] == pytest.approx(np.exp(-10.0), rel=1e-9)
    assert c["C3"]["measured"]["ratio"] == pytest.approx(0.1, rel=1e-9)
    assert c["C3"]["measured"]["tau_d_err_rms_last20_composite_learning"] == pytest.approx(1.0)
    json.dumps(conclusions(make_run(STALLED, CONVERGING)))  # serializable


def test_c1_fails_when_baseline_still_drifts():
    # ‖θ̃‖ = 0.2 + 0.8 e^{-t/30}: not converged, but drops 30 % over the last half
    c = by_id(make_run(lambda t: 0.2 + 0.8 * np.exp(-t / 30.0), CONVERGING))["C1"]
    mid = 0.2 + 0.8 * np.exp(-50 / 30.0)
    end = 0.2 + 0.8 * np.exp(-100 / 30.0)
    assert c["measured"]["theta_err_norm_mid"] == pytest.approx(mid)
    assert c["measured"]["max_rel_deviation_last_half"] == pytest.approx((mid - end) / mid)
    assert c["measured"]["end_to_initial_ratio"] > 0.1
    assert c["verdict"] is False


def test_c1_fails_when_baseline_converges():
    c = by_id(make_run(lambda t: 0.05 + 0.0 * t + 0.95 * (t == 0), CONVERGING))["C1"]
    assert c["measured"]["max_rel_deviation_last_half"] == pytest.approx(0.0)  # flat last half ...
    assert c["measured"]["end_to_initial_ratio"] == pytest.approx(0.05)      # ... but converged
    assert c["verdict"] is False


def test_c1_boundary_ten_percent():
    # oscillation of ±9 % around the mid-run value passes, ±11 % fails
    ok = by_id(make_run(lambda t: 1 + 0.09 * np.sin(t - 50.0), CONVERGING))["C1"]
    bad = by_id(make_run(lambda t: 1 + 0.11 * np.sin(t - 50.0), CONVERGING))["C1"]
    assert ok["measured"]["max_rel_deviation_last_half"] == pytest.approx(0.09, rel=1e-3)
    assert bad["measured"]["max_rel_deviation_last_half"] == pytest.approx(0.11, rel=1e-3)
    assert ok["verdict"] is True and bad["verdict"] is False


def test_c2_fails_when_not_converged_enough():
    c = by_id(make_run(STALLED, lambda t: np.exp(-t / 50.0)))["C2"]  # ratio e^-2 = 0.135
    assert c["measured"]["end_to_initial_ratio"] == pytest.approx(np.exp(-2.0))
    assert c["measured"]["theta_err_norm_max_last_quarter"] < c["measured"]["theta_err_norm_max_second_quarter"]
    assert c["verdict"] is False


def test_c2_fails_on_a_late_burst():
    # ends small, but a burst in the last quarter exceeds the second quarter's maximum
    prof = lambda t: np.exp(-t / 10.0) + 0.5 * np.exp(-((t - 85.0) / 2.0) ** 2)  # noqa: E731
    c = by_id(make_run(STALLED, prof))["C2"]
    assert c["measured"]["end_to_initial_ratio"] <= 0.1
    assert c["measured"]["theta_err_norm_max_last_quarter"] >= c["measured"]["theta_err_norm_max_second_quarter"]
    assert c["verdict"] is False


def test_c3_boundary():
    assert by_id(make_run(STALLED, CONVERGING, cl_tau=1.0, iv_tau=0.49))["C3"]["verdict"] is True
    c = by_id(make_run(STALLED, CONVERGING, cl_tau=1.0, iv_tau=0.6))["C3"]
    assert c["measured"]["ratio"] == pytest.approx(0.6, rel=1e-9)
    assert c["verdict"] is False


def test_c3_uses_only_last_20_percent():
    # IV-DREM's τ̃_d is huge before t = 0.8 t_end and tiny after: C3 still holds
    amp = np.where(T < 0.8 * T_END - 1.0, 50.0, 0.1)
    runs = make_run(STALLED, CONVERGING).runs
    iv = synthetic_lawrun("iv-drem", T, THETA, err_with_norm(CONVERGING),
                          amp[None, :] * np.vstack([np.sin(1.5 * T), np.cos(1.5 * T)]), CFG)
    run = SyntheticPaperRun(CFG, THETA, {"iv-drem": iv, "composite-learning": runs["composite-learning"]})
    c = by_id(run)["C3"]
    assert c["measured"]["window_start"] == pytest.approx(80.0)
    assert c["measured"]["ratio"] == pytest.approx(0.1, rel=1e-9)
    assert c["verdict"] is True


def test_missing_law_is_not_evaluated():
    run = make_run(STALLED, CONVERGING)
    run.runs.pop("composite-learning")
    c = by_id(run)
    assert c["C1"]["verdict"] is None and c["C3"]["verdict"] is None
    assert "composite-learning" in c["C1"]["note"]
    assert c["C2"]["verdict"] is True
    assert "not evaluated" in format_conclusions(conclusions(run))


def test_a_run_shorter_than_the_window_judges_no_conclusion():
    """A run that ends before the window (15a) is full (the composite term cannot have
    acted) gives C1-C3 no verdict, with the diagnostics' note, while its numbers are kept;
    the same profiles over the whole horizon are judged (the synthetic C2 would FAIL at 1 s:
    ‖θ̃‖ has not fallen yet)."""
    T_win = float(CFG["iv_drem"]["T"])
    t_short = np.linspace(0.0, 1.0, 101)
    assert t_short[-1] <= T_win
    direction = THETA / np.linalg.norm(THETA)
    runs = {law: synthetic_lawrun(law, t_short, THETA, direction[:, None] * np.ones_like(t_short),
                                  0.1 * np.vstack([np.sin(t_short), np.cos(t_short)]), CFG)
            for law in ("iv-drem", "composite-learning")}
    short = by_id(SyntheticPaperRun(config=CFG, theta=THETA, runs=runs))
    for cid in ("C1", "C2", "C3"):
        assert short[cid]["verdict"] is None, cid
        assert short[cid]["note"] == (f"not evaluated: the run ends at t = 1 s, before the "
                                      f"window T = {T_win:g} s is full")
        assert short[cid]["measured"]                     # the numbers are still there
    assert short["C2"]["measured"]["end_to_initial_ratio"] == pytest.approx(1.0)
    # the horizon past the window: judged as before
    full = by_id(make_run(STALLED, CONVERGING))
    assert T_END > T_win and all(full[c]["verdict"] is True for c in ("C1", "C2", "C3"))


def test_synthetic_paper_run_flags():
    def verdicts(**kw):
        return [c["verdict"] for c in conclusions(synthetic_paper_run(t_end=60.0, dt=0.05, **kw))]
    assert verdicts() == [True, True, True, None]
    assert verdicts(cl_converges=True) == [False, True, True, None]
    assert verdicts(iv_converges=False) == [True, False, True, None]
    assert verdicts(iv_tau_better=False) == [True, True, False, None]
    # C4: DREM without the instrument stalls in the synthetic run -> the instrument matters
    assert verdicts(laws=["iv-drem", "composite-learning", "drem"])[3] is True
    assert verdicts(laws=["iv-drem", "composite-learning", "drem"], iv_converges=False)[3] is False


# --------------------------------------------------------------------------- summary
def test_summary_schema_and_values():
    run = make_run(STALLED, CONVERGING)
    s = summary(run.runs["iv-drem"], THETA)
    assert set(s) == {"t_end", "theta_hat", "theta_err_norm", "e_max_last20", "tau_d_err_rms_last20", "wall_s"}
    assert s["t_end"] == T_END
    assert s["theta_err_norm"] == pytest.approx(np.exp(-10.0))
    np.testing.assert_allclose(s["theta_hat"], THETA - THETA / np.linalg.norm(THETA) * np.exp(-10.0))
    assert s["tau_d_err_rms_last20"] == pytest.approx(0.1)
    e = signal(run.runs["iv-drem"], "e")
    last = T >= 80.0
    assert s["e_max_last20"] == pytest.approx(np.max(np.linalg.norm(e[:, last], axis=0)))
    assert s["wall_s"] == run.runs["iv-drem"].stats["wall_s"]
    json.dumps(s)
