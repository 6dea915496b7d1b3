"""Co-simulation of the controller with the plant FMU: ivdrem.fmu.cosim.

Coupling: explicit (Jacobi) sample-and-hold at communication step H, so the difference to
the all-Python closed loop is first order in H.  Measured on the paper's loop (IV-DREM,
t_end = 2 s, reference RK4 at h = 2.5e-4 s), max over the run and components:

    H [s]     q          theta_hat   tau_d_hat
    1e-3      3.03e-3    1.25e-3     0.341
    5e-4      1.52e-3    6.20e-4     0.170
    2.5e-4    7.57e-4    3.09e-4     0.0847
    order     1.00       1.00..1.01  1.00..1.01

The bounds below are these numbers with a margin of 1.5x; the observed order must lie in
0.7 .. 1.5 (first order; the integrators inside each side are fourth order and do not show).
"""
from __future__ import annotations

import os
import shutil
import zipfile

import numpy as np
import pytest

pytest.importorskip("fmpy")

from ivdrem.fmu import export_fmu  # noqa: E402
from ivdrem.cli.fmu import main_cosim  # noqa: E402
from ivdrem.fmu.cosim import CosimComparison, compare_to_python, cosimulate  # noqa: E402
from ivdrem.models import two_link  # noqa: E402

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc)")

T_END = 2.0
STEPS = (1e-3, 5e-4, 2.5e-4)
# measured max errors at H = 1e-3 (see the module docstring) times 1.5
BOUND_1MS = {"q": 4.5e-3, "theta_hat": 1.9e-3, "tau_d_hat": 0.51}


@pytest.fixture(scope="module")
def fmu(tmp_path_factory):
    return export_fmu(two_link(), tmp_path_factory.mktemp("cosim") / "two_link.fmu")


@pytest.fixture(scope="module")
def comparison(fmu):
    return compare_to_python(fmu, T_END, STEPS, law="iv-drem", progress=False)


def test_outputs_and_initial_sample(comparison):
    from ivdrem.diagrams import closed_loop
    ref = comparison.reference
    res = comparison.results[0]
    assert list(res.output_labels) == list(closed_loop("iv-drem").output_labels)
    assert res.time.size == round(T_END / STEPS[0]) + 1
    np.testing.assert_allclose(res.time, STEPS[0] * np.arange(res.time.size), atol=1e-12)
    # the FMU starts at the Python plant's q0 = (0, 0.3 pi), dq0 = 0 ...
    q0 = res.outputs[[0, 1], 0]
    np.testing.assert_allclose(q0, [0.0, 0.3 * np.pi], atol=1e-15)
    np.testing.assert_array_equal(res.outputs[[2, 3], 0], 0.0)
    # ... so at t = 0 every signal (tau included) equals the all-Python loop's
    np.testing.assert_allclose(res.outputs[:, 0], ref.outputs[:, 0], rtol=1e-12, atol=1e-12)
    assert np.all(np.isfinite(res.outputs))
    st = res.stats
    assert st["comm_steps"] == 2000 and st["fmu_substep"] <= STEPS[0]


def test_close_to_python(comparison):
    print("\n" + str(comparison))
    for s, bound in BOUND_1MS.items():
        errs = comparison.errors[s]
        assert errs[0] < bound, (s, errs)
        # and proportionally smaller at H/4
        assert errs[-1] < bound / 4 * 1.2, (s, errs)


def test_first_order_in_comm_step(comparison):
    assert isinstance(comparison, CosimComparison)
    for s in ("q", "theta_hat", "tau_d_hat"):
        e = comparison.errors[s]
        assert np.all(np.diff(e) < 0), (s, e)           # error decreases as H halves
        for o in comparison.orders[s]:
            assert 0.7 <= o <= 1.5, (s, comparison.orders[s])
    assert comparison.ok
    assert comparison.verdict().startswith("OK")
    table = comparison.table()
    assert "tau_d_hat" in table and "order" in table


def test_jacobi_coupling_first_step(fmu):
    """Over [0, H] the FMU integrates with tau(0), tau_d(0) held (Jacobi sample-and-hold)."""
    from scipy.integrate import solve_ivp
    H = 1e-3
    res = cosimulate(fmu, 4 * H, comm_step=H, progress=False)
    lab = list(res.output_labels)
    m = two_link()
    u0 = res.outputs[[lab.index(s) for s in ("tau[0]", "tau[1]")], 0] \
        + res.outputs[[lab.index(s) for s in ("tau_d[0]", "tau_d[1]")], 0]

    def f(t, x):
        ddq = np.empty(2)
        m.functions.forward_dynamics(x[:2], x[2:], u0, np.asarray(m.theta_values, float), ddq)
        return np.concatenate([x[2:], ddq])
    sol = solve_ivp(f, (0, H), res.outputs[:4, 0], method="DOP853", rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(res.outputs[:4, 1], sol.y[:, -1], rtol=0, atol=1e-11)


def test_engines_agree(fmu):
    """The controller on the reference engine (python-control evaluation) gives the same run."""
    a = cosimulate(fmu, 0.005, comm_step=1e-3, progress=False)
    b = cosimulate(fmu, 0.005, comm_step=1e-3, engine="reference", progress=True)
    np.testing.assert_allclose(b.outputs, a.outputs, rtol=1e-9, atol=1e-9)


def test_missing_and_unsuitable_fmu(tmp_path, fmu):
    with pytest.raises(FileNotFoundError, match="not found"):
        cosimulate(tmp_path / "nope.fmu", 0.01)
    bad = tmp_path / "bad.fmu"
    bad.write_text("not a zip")
    with pytest.raises(ValueError, match="not an FMU"):
        cosimulate(bad, 0.01)
    # model exchange only: drop the CoSimulation element
    me = tmp_path / "me_only.fmu"
    with zipfile.ZipFile(fmu) as src, zipfile.ZipFile(me, "w") as dst:
        for item in src.infolist():
            data = src.read(item.filename)
            if item.filename == "modelDescription.xml":
                xml = data.decode()
                a, b = xml.index("<CoSimulation"), xml.index("</CoSimulation>")
                data = (xml[:a] + xml[b + len("</CoSimulation>"):]).encode()
            dst.writestr(item, data)
    with pytest.raises(ValueError, match="does not support co-simulation"):
        cosimulate(me, 0.01)


def test_model_mismatch_and_bad_steps(fmu):
    from ivdrem.models import planar_arm
    with pytest.raises(ValueError, match="n = 2 degrees of freedom.*n = 1"):
        cosimulate(fmu, 0.01, model=planar_arm(1))
    with pytest.raises(ValueError, match="whole number of communication steps"):
        cosimulate(fmu, 0.0105, comm_step=1e-3)
    with pytest.raises(ValueError, match="comm_step"):
        cosimulate(fmu, 0.01, comm_step=-1)
    with pytest.raises(ValueError, match="fmu_substep"):
        cosimulate(fmu, 0.01, comm_step=1e-3, fmu_substep=2e-3)
    with pytest.raises(ValueError, match="multiple"):
        compare_to_python(fmu, 0.03, comm_steps=(1e-3, 3e-4))


def test_divergence_is_reported(fmu):
    """A comm step far above the loop's time constant (K = 2000: m_min / K ~ 5e-5 s) diverges
    within a few steps; the error names the co-simulation step and suggests a smaller H."""
    from ivdrem.sim import SimulationError
    with pytest.raises(SimulationError, match=r"comm_step H = 0.001 s.*smaller comm_step"):
        cosimulate(fmu, 0.2, comm_step=1e-3, K=2000.0, progress=False)


def test_divergence_stops_the_comparison_before_the_reference(fmu, monkeypatch):
    """compare_to_python co-simulates at the coarsest step first (listed last here): when the
    coupling diverges there, its error (time, H, cause) is raised and the all-Python loop is
    neither built nor simulated, and no other step is co-simulated."""
    import ivdrem.diagrams as diagrams
    import ivdrem.fmu.cosim as cosim
    import ivdrem.sim as sim
    from ivdrem.sim import SimulationError
    calls = {"simulate": 0, "closed_loop": 0, "cosim": []}

    def simulate(*a, **k):
        calls["simulate"] += 1
        raise AssertionError("the reference ran")

    real_closed_loop, real_cosimulate = diagrams.closed_loop, cosim.cosimulate

    def closed_loop(*a, **k):
        if not k.get("external_plant"):
            calls["closed_loop"] += 1
        return real_closed_loop(*a, **k)

    def cosimulate(*a, **k):
        calls["cosim"].append(k["comm_step"])
        return real_cosimulate(*a, **k)
    monkeypatch.setattr(sim, "simulate", simulate)
    monkeypatch.setattr(diagrams, "closed_loop", closed_loop)
    monkeypatch.setattr(cosim, "cosimulate", cosimulate)
    with pytest.raises(SimulationError,
                       match=r"comm_step H = 0.001 s failed near t = .*smaller comm_step"):
        compare_to_python(fmu, 0.2, (5e-4, 2.5e-4, 1e-3), K=2000.0, progress=False)
    assert calls == {"simulate": 0, "closed_loop": 0, "cosim": [1e-3]}


def test_comparison_equals_the_runs_one_by_one(comparison, fmu):
    """Whatever order compare_to_python runs them in, its numbers are those of the
    reference and the co-simulations run one at a time, bit for bit."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import simulate
    ref = simulate(closed_loop("iv-drem"), T_END, method="rk4", h=min(STEPS),
                   dt_out=min(STEPS), return_states=False, progress=False)
    np.testing.assert_array_equal(comparison.reference.outputs, ref.outputs)
    labels = list(ref.output_labels)
    for i, H in enumerate(STEPS):
        res = cosimulate(fmu, T_END, comm_step=H, progress=False)
        np.testing.assert_array_equal(comparison.results[i].outputs, res.outputs)
        stride = round(H / min(STEPS))
        for s in comparison.signals:
            rows = [j for j, lab in enumerate(labels) if lab.startswith(s + "[")]
            err = np.max(np.abs(res.outputs[rows] - ref.outputs[rows][:, ::stride]))
            assert comparison.errors[s][i] == err, (s, H)
    assert list(comparison.wall) == ["python"] + [f"cosim H={H:g}" for H in STEPS]


def test_one_closed_loop_at_a_time(fmu, monkeypatch):
    """While the all-Python reference runs, the only closed loop alive is its own (the
    first co-simulation's controller is freed), and none is kept after the comparison."""
    import weakref
    import ivdrem.diagrams as diagrams
    import ivdrem.sim as sim
    built, alive_at_reference = [], []
    real_closed_loop, real_simulate = diagrams.closed_loop, sim.simulate

    def closed_loop(*a, **k):
        d = real_closed_loop(*a, **k)
        built.append((d.name, weakref.ref(d)))
        return d

    def simulate(*a, **k):
        alive_at_reference.append([name for name, ref in built if ref() is not None])
        return real_simulate(*a, **k)
    monkeypatch.setattr(diagrams, "closed_loop", closed_loop)
    monkeypatch.setattr(sim, "simulate", simulate)
    compare_to_python(fmu, 0.01, progress=False)
    assert [name for name, _ in built] == ["controller[iv-drem]", "closed_loop[iv-drem]",
                                           "controller[iv-drem]", "controller[iv-drem]"]
    assert alive_at_reference == [["closed_loop[iv-drem]"]]
    assert [name for name, ref in built if ref() is not None] == []


def test_reference_cost_is_refused_before_any_run(fmu, monkeypatch):
    """The reference's cost guard is priced from the controller before the first
    co-simulation (not after it, as simulate's own guard would be)."""
    import ivdrem.fmu.cosim as cosim
    from ivdrem.sim.guards import CostLimitError

    def cosimulate(*a, **k):
        raise AssertionError("a co-simulation ran")
    monkeypatch.setattr(cosim, "cosimulate", cosimulate)
    with pytest.raises(CostLimitError, match="the all-Python reference run would record .* GiB"):
        compare_to_python(fmu, 40000.0, (1e-3, 5e-4, 2.5e-4), progress=False)
    with pytest.raises(ValueError, match="unknown signal 'nope'"):
        compare_to_python(fmu, 0.01, signals=("q", "nope"), progress=False)


def _gain_for_growth(target, H=1e-3):
    """The 2-link arm's K (scalar) at which the predicted growth per step is `target`."""
    from ivdrem.fmu.cosim import coupling_stability
    lo, hi = 2.0, 1e5
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if coupling_stability(two_link(), H, 1.0, K=mid).growth < target:
            lo = mid
        else:
            hi = mid
    return hi


def test_prediction_on_the_paper_arm_runs_the_check():
    """The paper's loop at its three steps: no divergence predicted (the comparison above
    runs and converges at first order), and the fastest mode is M(q0)^-1 (K + delta_mu mu)."""
    from ivdrem.fmu.cosim import coupling_stability
    m = two_link()
    M = np.empty((2, 2))
    m.functions.M(np.array([0.0, 0.3 * np.pi]), np.asarray(m.theta_values, float), M)
    for H in STEPS:
        st = coupling_stability(m, H, 300.0)
        assert not st.diverges and st.growth < 1.0 + 1e-9, st.reason()
        fastest = max(np.linalg.eigvals(np.linalg.solve(M, (2 + 0.8 * 15) * np.eye(2))).real)
        assert st.rate == pytest.approx(fastest)
        assert "no divergence predicted" in st.reason()


def test_predicted_divergence_does_diverge(fmu):
    """Soundness on the 2-link arm: at the gain where the predicted growth per step reaches
    the threshold DIVERGING_GROWTH (K ~ 390; the scalar bound H lambda_max = 2.5), the
    co-simulation diverges within a few dozen steps; just below, nothing is predicted.
    (Measured: K = 330, growth 1.12, already diverges at t = 0.096 s; K = 315-325, growth
    1.03-1.09, runs 1 s: the margin of the threshold.)"""
    from ivdrem.fmu.cosim import DIVERGING_GROWTH, coupling_stability
    from ivdrem.sim import SimulationError
    K = _gain_for_growth(DIVERGING_GROWTH)
    st = coupling_stability(two_link(), 1e-3, 1.0, K=K)
    assert st.diverges and 2.4 < 1e-3 * st.rate < 2.6, st.reason()
    assert not coupling_stability(two_link(), 1e-3, 1.0, K=0.99 * K).diverges
    with pytest.raises(SimulationError, match=r"comm_step H = 0.001 s failed near t = 0.0[0-4]"):
        cosimulate(fmu, 1.0, comm_step=1e-3, K=K, progress=False)
    # the growth of the fastest mode is about |1 - H lambda_max| (module docstring)
    big = coupling_stability(two_link(), 1e-3, 1.0, K=2000.0)
    assert big.diverges and big.growth == pytest.approx(1e-3 * big.rate - 1, rel=0.02)
    assert "A stable coupling needs H below" in big.reason()


def test_prediction_needs_the_horizon_and_its_assumptions():
    """Not predicted: a horizon too short for a million-fold growth, a nonzero theta_hat0
    (then Pi^T theta_hat adds a velocity gain the map leaves out), replaced blocks."""
    from ivdrem.fmu.cosim import coupling_stability
    m = two_link()
    K = _gain_for_growth(1.9)
    assert coupling_stability(m, 1e-3, 1.0, K=K).diverges
    assert not coupling_stability(m, 1e-3, 0.01, K=K).diverges     # 1.9^10 < 1e6
    st = coupling_stability(m, 1e-3, 1.0, K=K, theta_hat0=[1.0, 0, 0, 0, 0])
    assert st.growth is None and not st.diverges and "theta_hat0" in st.reason()
    assert coupling_stability(m, 1e-3, 1.0, K=K, theta_hat0=np.zeros(5)).diverges
    assert coupling_stability(m, 1e-3, 1.0, K=K, replace={"disturbance": None}).growth is None
    with pytest.raises(ValueError, match="whole number of communication steps"):
        coupling_stability(m, 1e-3, 0.0105)


def test_report_check_on_the_paper_arm_is_run():
    """The report's FMU check (ivdrem.cli.report.fmu_check) on the paper's configuration:
    not predicted to diverge, so run, and first order."""
    from ivdrem.experiments.config import read_config, resolve_config
    from ivdrem.cli.report import fmu_check
    rows, cmp = fmu_check(resolve_config(read_config(None))[0], 1.0, progress=False)
    assert cmp.ok and rows["verdict"]["max |co-sim − Python|"].startswith("OK")
    assert len(rows) == 1 + 3 * 3


def test_cleanup_on_error(fmu, monkeypatch):
    """An error in the middle of the run still terminates/frees the FMU and its files."""
    import fmpy
    from ivdrem.sim import Simulator
    dirs = []
    real_extract = fmpy.extract

    def extract(*a, **k):
        d = real_extract(*a, **k)
        dirs.append(d)
        return d
    monkeypatch.setattr(fmpy, "extract", extract)
    calls = {"n": 0}
    real_advance = Simulator.advance

    def advance(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 5:
            raise RuntimeError("boom")
        return real_advance(self, *a, **k)
    monkeypatch.setattr(Simulator, "advance", advance)
    with pytest.raises(RuntimeError, match="boom"):
        cosimulate(fmu, 0.01, comm_step=1e-3, progress=False)
    assert len(dirs) == 1 and not os.path.exists(dirs[0])


def test_cli(capsys, fmu):
    assert main_cosim(["--t-end", "2", "--quiet"]) == 0
    out = capsys.readouterr().out
    for word in ("signal", "max |co-sim - Python|", "order", "theta_hat", "tau_d_hat", "OK"):
        assert word in out
    assert main_cosim(["--t-end", "0.01", "--comm-step", "2e-3", "--fmu", str(fmu),
                       "--quiet"]) == 0


def test_cli_bad_input(capsys, tmp_path):
    assert main_cosim(["--fmu", str(tmp_path / "missing.fmu"), "--t-end", "0.01",
                       "--quiet"]) == 2
    assert "not found" in capsys.readouterr().err
    assert main_cosim(["--t-end", "-1", "--quiet"]) == 2
    assert main_cosim(["--comm-step", "0", "--quiet"]) == 2
    assert main_cosim(["--law", "nonsense"]) == 2


def test_cli_refuses_a_coupling_predicted_to_diverge_before_building_anything(
        capsys, tmp_path, monkeypatch):
    """ivdrem cosim with gains whose 1 ms coupling is predicted to diverge (K = 2000 on the
    2-link arm: H lambda_max = 12.6) stops with exit 2 and the prediction's numbers, before
    any closed loop is built or FMU exported; --despite-prediction runs it, and it then
    fails as predicted (exit 1)."""
    import ivdrem.diagrams as diagrams
    from ivdrem.fmu import export as fmu_export
    cfg = tmp_path / "stiff.toml"
    cfg.write_text("[controller]\nK = [2000.0, 2000.0]\n")
    built = []
    real_closed_loop, real_export = diagrams.closed_loop, fmu_export.export_fmu
    monkeypatch.setattr(diagrams, "closed_loop", lambda *a, **k: built.append("loop")
                        or real_closed_loop(*a, **k))
    monkeypatch.setattr(fmu_export, "export_fmu", lambda *a, **k: built.append("fmu")
                        or real_export(*a, **k))
    assert main_cosim(["--config", str(cfg), "--t-end", "0.1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "predicted to diverge" in err and "--comm-step below" in err
    assert not built
    assert main_cosim(["--config", str(cfg), "--t-end", "0.1", "--quiet",
                       "--despite-prediction"]) == 1
    assert "run failed" in capsys.readouterr().err and built


def test_cli_takes_a_configuration_and_another_robot(capsys, tmp_path, fmu):
    """ivdrem cosim --config: the configuration's robot (planar-3), gains, reference and q(0)
    on both sides; its plant FMU exported from that model; first order in H."""
    from pathlib import Path
    cfg = Path(__file__).resolve().parents[1] / "examples" / "planar3.toml"
    assert main_cosim(["--config", str(cfg), "--law", "none", "--t-end", "1", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "planar-3 plant exported" in out and "OK: the co-simulation converges" in out
    # an FMU of another robot is refused against this configuration's model
    assert main_cosim(["--config", str(cfg), "--law", "none", "--t-end", "0.01",
                       "--fmu", str(fmu), "--quiet"]) == 2
    assert "error" in capsys.readouterr().err
