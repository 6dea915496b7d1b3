"""γ "auto" from the reference estimate (ivdrem.diagrams.gamma_auto, docs/mixing.md): the
default for the scale-free mixings, no loop simulated, the rule applied to the estimate, and
within 10 % of the calibration run's γ (the rule before) on a planar arm; the paper's mixing
keeps its calibration run."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

from ivdrem.diagrams import calibrated_loop
from ivdrem.models import planar_arm

ROOT = Path(__file__).resolve().parents[1]


def _planar3():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from bench_arms import planar_experiment
    finally:
        sys.path.pop(0)
    exp = planar_experiment(3)
    return dict(trajectory=exp["trajectory"], disturbance=exp["disturbance"], q0=exp["q0"])


@pytest.fixture
def no_simulation(monkeypatch, tmp_path):
    import ivdrem.sim as sim
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))

    def refuse(*a, **k):
        raise AssertionError("a calibration run was simulated")
    monkeypatch.setattr(sim, "simulate", refuse)


def test_eigen_gamma_auto_simulates_nothing_and_follows_the_rule(no_simulation):
    from ivdrem.diagrams.gamma_auto import DEFAULT_RATE, reference_mean_delta2
    kw = _planar3()
    d = calibrated_loop("iv-drem", planar_arm(3), **kw)          # "eigen", γ "auto" by default
    ch = d.gamma_choice
    assert ch["variant"] == "eigen" and ch["source"] == "reference" and ch["passes"] == []
    T = ch["window"][0]
    assert ch["window"] == [T, 2 * T] and ch["t_cal"] == 2 * T
    est = reference_mean_delta2(planar_arm(3), kw["trajectory"], T=T, p=2.0, F0=1.0,
                                l=50.0, variant="eigen")
    assert ch["log10_mean_Delta2"] == est[0] == ch["reference_log10_mean_Delta2"]
    assert ch["gamma"] == pytest.approx(DEFAULT_RATE / (0.01 * 10.0 ** est[0]), rel=1e-12)
    term = [s for s in d.syslist if s.name == "drem_term"][0]
    assert term.params["gamma"] == pytest.approx(ch["gamma"])


def test_channel_gamma_auto_is_one_gamma_per_parameter_from_the_estimate(no_simulation):
    d = calibrated_loop("iv-drem", planar_arm(3), gains=dict(mixing="channel"), **_planar3())
    ch = d.gamma_choice
    assert ch["source"] == "reference" and len(ch["gamma"]) == planar_arm(3).ntheta
    for g, lm in zip(ch["gamma"], ch["log10_mean_Delta2"]):
        assert math.log10(g) == pytest.approx(math.log10(0.5 / 0.01) - lm, abs=1e-9)


def test_the_estimate_is_within_ten_percent_of_the_calibration_run():
    """The γ the rule gave before (a calibration run over [0, 2T], Rodas5P; kept in the
    compile cache once run) and the γ of the estimate, "eigen" on planar-3 (measured
    0.026 %; every benchmark arm in docs/mixing.md)."""
    kw = _planar3()
    run = calibrated_loop("iv-drem", planar_arm(3), calibration={"source": "run",
                                                                 "method": "rodas5p"}, **kw)
    ref = calibrated_loop("iv-drem", planar_arm(3), **kw)
    assert run.gamma_choice["source"] == "run" and len(run.gamma_choice["passes"]) == 1
    assert ref.gamma_choice["gamma"] == pytest.approx(run.gamma_choice["gamma"], rel=0.1)


def test_the_paper_mixing_keeps_its_calibration_run_and_bad_sources_are_refused():
    from ivdrem.diagrams.gamma_auto import calibrate_gamma
    ch = calibrated_loop("iv-drem", gains=dict(gamma="auto"),
                         calibration={"t_cal": 4.0}).gamma_choice
    assert ch["variant"] == "paper" and ch["source"] == "run" and len(ch["passes"]) == 1
    with pytest.raises(ValueError, match="source must be 'reference' or 'run', got 'guess'"):
        calibrate_gamma("iv-drem", planar_arm(3), dict(mixing="eigen", **_planar3()),
                        source="guess")
