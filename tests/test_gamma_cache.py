"""gamma = "auto" is calibrated once per loop and settings, also across processes: the
calibration is kept in the compile cache under a digest of what it computes from (ivdrem's
source, the loop's kernels, model, parameter values and initial state) and its settings."""
from __future__ import annotations

import numpy as np
import pytest

from ivdrem.diagrams import closed_loop
from ivdrem.sim import jacobian

CAL = {"t_cal": 4.0}


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty compile cache, and the calibration runs counted (calibrate_gamma imports
    simulate from ivdrem.sim when it runs)."""
    import ivdrem.sim as sim
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    runs, real = [], sim.simulate

    def counted(*a, **k):
        runs.append(1)
        return real(*a, **k)

    monkeypatch.setattr(sim, "simulate", counted)
    return tmp_path, runs


def test_a_repeated_calibration_reads_the_kept_one(cache):
    tmp, runs = cache
    first = closed_loop("iv-drem", gamma="auto", calibration=CAL).gamma_choice
    assert len(runs) == 1 and len(list((tmp / "calibrations").glob("*.json"))) == 1
    again = closed_loop("iv-drem", gamma="auto", calibration=CAL).gamma_choice
    assert len(runs) == 1                                # read, not run again
    assert again == first and type(again["gamma"]) is float


@pytest.mark.parametrize("change", ["parameter", "settings", "source", "initial state"])
def test_what_the_calibration_depends_on_is_calibrated_again(cache, change, monkeypatch):
    tmp, runs = cache
    first = closed_loop("iv-drem", gamma="auto", calibration=CAL).gamma_choice
    kw, cal = {}, dict(CAL)
    if change == "parameter":
        kw["Gamma"] = 0.02 * np.eye(5)
    elif change == "settings":
        cal["rtol"] = 1e-7
    elif change == "source":
        monkeypatch.setattr(jacobian, "_package_digest", lambda: "another ivdrem")
    else:
        kw["q0"] = [0.1, 0.3 * np.pi]
    other = closed_loop("iv-drem", gamma="auto", calibration=cal, **kw).gamma_choice
    assert len(runs) == 2
    if change == "parameter":   # Γ scales the rule's γ and moves θ̂ (the motion, so Δ)
        assert other["gamma"] != first["gamma"]


def test_a_damaged_calibration_file_is_calibrated_again(cache):
    tmp, runs = cache
    first = closed_loop("iv-drem", gamma="auto", calibration=CAL).gamma_choice
    (f,) = (tmp / "calibrations").glob("*.json")
    f.write_text("{not json")
    again = closed_loop("iv-drem", gamma="auto", calibration=CAL).gamma_choice
    assert len(runs) == 2 and again == first


def test_a_loop_with_a_block_ivdrem_did_not_write_has_no_digest():
    """A user's nlsys in the loop: what it computes cannot be keyed, so nothing is kept."""
    import control as ct
    from ivdrem.sim.plan import DiagramPlan
    lag = ct.nlsys(lambda t, x, u, p: -x + u, lambda t, x, u, p: x, inputs=1, outputs=1,
                   states=1, name="lag")
    d = ct.interconnect([lag], inputs=["u[0]"], outputs=["y[0]"])
    assert jacobian.run_digest(DiagramPlan.from_diagram(d)) is None
    plan = DiagramPlan.from_diagram(closed_loop("iv-drem"))
    assert jacobian.run_digest(plan) == jacobian.run_digest(plan)
