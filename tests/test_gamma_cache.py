"""gamma = "auto" is calibrated once per loop and settings, also across processes: the
calibration is kept in the compile cache under a digest of what it computes from (ivdrem's
source, the loop's kernels, model, parameter values and initial state) and its settings."""
from __future__ import annotations

import numpy as np
import pytest

from ivdrem.diagrams import calibrated_loop, closed_loop
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
    first = calibrated_loop("iv-drem", gains=dict(gamma="auto"), calibration=CAL).gamma_choice
    assert len(runs) == 1 and len(list((tmp / "calibrations").glob("*.json"))) == 1
    again = calibrated_loop("iv-drem", gains=dict(gamma="auto"), calibration=CAL).gamma_choice
    assert len(runs) == 1                                # read, not run again
    assert again == first and type(again["gamma"]) is float


@pytest.mark.parametrize("change", ["parameter", "settings", "source", "initial state"])
def test_what_the_calibration_depends_on_is_calibrated_again(cache, change, monkeypatch):
    tmp, runs = cache
    first = calibrated_loop("iv-drem", gains=dict(gamma="auto"), calibration=CAL).gamma_choice
    kw, cal = {}, dict(CAL)
    if change == "parameter":
        kw["Gamma"] = 0.02 * np.eye(5)
    elif change == "settings":
        cal["rtol"] = 1e-7
    elif change == "source":
        monkeypatch.setattr(jacobian, "_package_digest", lambda: "another ivdrem")
    else:
        kw["q0"] = [0.1, 0.3 * np.pi]
    other = calibrated_loop("iv-drem", gains=dict(gamma="auto"), calibration=cal, **kw).gamma_choice
    assert len(runs) == 2
    if change == "parameter":   # Γ scales the rule's γ and moves θ̂ (the motion, so Δ)
        assert other["gamma"] != first["gamma"]


def test_a_damaged_calibration_file_is_calibrated_again(cache):
    tmp, runs = cache
    first = calibrated_loop("iv-drem", gains=dict(gamma="auto"), calibration=CAL).gamma_choice
    (f,) = (tmp / "calibrations").glob("*.json")
    f.write_text("{not json")
    again = calibrated_loop("iv-drem", gains=dict(gamma="auto"), calibration=CAL).gamma_choice
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


# --------------------------------------------------------------------------- the estimate
def _estimate_args(model):
    from ivdrem.diagrams import arm_reference as arm
    from ivdrem.blocks.sources import fourier_trajectory
    table = arm.design_trajectory(model)
    traj = fourier_trajectory(model.n, float(table["omega_f"]), np.asarray(table["a"], float),
                              np.asarray(table["b"], float), np.asarray(table["offset"], float))
    return {"trajectory": traj, "T": 4.0, "mixing": "eigen"}


def test_the_reference_estimate_is_kept_and_keyed_by_what_it_reads(tmp_path, monkeypatch):
    """The estimate of mean Δ² along the reference (the preflight's check and the run's
    γ "auto" ask for the same one) is computed once per model, reference and numbers, and
    read afterwards, in this process and in the next (a new trajectory block with the same
    parameters reads it too); another reference or window computes it again."""
    from ivdrem.diagrams import gamma_auto
    from ivdrem.models import planar_arm
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    model = planar_arm(3)
    calls, real = [], gamma_auto.reference_mean_delta2

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(gamma_auto, "reference_mean_delta2", counted)
    args = _estimate_args(model)
    first = gamma_auto.check_reference_delta("iv-drem", model, args, variant="eigen")
    assert len(calls) == 1 and len(list((tmp_path / "estimates").glob("*.json"))) == 1
    again = gamma_auto.check_reference_delta("iv-drem", model, _estimate_args(model),
                                             variant="eigen")
    assert len(calls) == 1 and again == first
    # the run's γ "auto" asks with t_cal = 2T, the horizon the preflight's check means
    ch = gamma_auto.calibrate_gamma("iv-drem", model, _estimate_args(model))
    assert ch["source"] == "reference" and ch["t_cal"] == 8.0
    assert len(calls) == 1 and ch["reference_log10_mean_Delta2"] == first[0]
    gamma_auto._ESTIMATES.clear()                        # as a new process: from the disk
    assert gamma_auto.check_reference_delta("iv-drem", model, args, variant="eigen") == first
    assert len(calls) == 1
    # the value kept is the value computed
    par = _law_numbers()
    assert first == [float(v) for v in real(model, args["trajectory"], T=4.0, p=par["p"],
                                            F0=par["F0"], l=50.0, variant="eigen")]
    gamma_auto.check_reference_delta("iv-drem", model, {**args, "T": 5.0}, variant="eigen")
    assert len(calls) == 2
    other = _estimate_args(model)
    params = other["trajectory"].params
    params["q_d_a"] = 0.9 * np.asarray(params["q_d_a"])
    gamma_auto.check_reference_delta("iv-drem", model, other, variant="eigen")
    assert len(calls) == 3
    # a damaged file is computed again
    gamma_auto._ESTIMATES.clear()
    for f in (tmp_path / "estimates").glob("*.json"):
        f.write_text("[not json")
    assert gamma_auto.check_reference_delta("iv-drem", model, args, variant="eigen") == first
    assert len(calls) == 4


def _law_numbers():
    from ivdrem import laws
    par = laws.resolve_params(laws.get_law("iv-drem"), {"T": 4.0})
    return {"p": float(par["p"]), "F0": float(par["F0"])}


def test_a_reference_block_ivdrem_did_not_write_is_not_kept(tmp_path, monkeypatch):
    import control as ct
    from ivdrem.diagrams import gamma_auto
    from ivdrem.models import two_link
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    traj = ct.nlsys(None, lambda t, x, u, p: np.zeros(6), inputs=0, outputs=6, name="ref")
    assert gamma_auto._estimate_path(two_link(), traj, {"T": 1.0}) is None
    assert gamma_auto._estimate_path(two_link(), {"omega": [1.0, 2.0]}, {"T": 1.0}) is not None
