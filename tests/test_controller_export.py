"""The controller as an artifact: `ivdrem fmu export --controller` from a configuration, its
refusals (one line, exit 2), the hosts reading h from the FMU, and the stability prediction
of the sampled loop (ivdrem.controller.stability) against actual runs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("fmpy")

from ivdrem.controller.loop import FmuPlant, sampled_loop  # noqa: E402
from ivdrem.controller.stability import UNSTABLE_GROWTH, sampled_stability  # noqa: E402
from ivdrem.cli.fmu import main_fmu  # noqa: E402
from ivdrem.controller.parameters import param_vector  # noqa: E402
from ivdrem.controller.sampled import SampledController  # noqa: E402
from ivdrem.models import get_model, two_link  # noqa: E402

NO_DISTURBANCE = {k: [0.0] * 7 for k in ("amplitude", "omega", "phase", "offset")}


@pytest.fixture(scope="module")
def two_link_plant(tmp_path_factory):
    from ivdrem.fmu import export_fmu
    return export_fmu(two_link(), tmp_path_factory.mktemp("plant") / "Plant.fmu")


def _run(controller, plant_fmu, t_end, disturbance, reference=None):
    """The controller around the plant FMU from the reference's start (``reference``: the
    SampledController that has it, default the controller): (the time the loop diverged
    at, or None; the record)."""
    qd, dqd, _ = (reference or controller).reference(0.0)
    p = FmuPlant(plant_fmu, qd, dqd)
    steps = []
    step = controller.step
    controller.step = lambda t, q, dq: (steps.append(t), step(t, q, dq))[1]
    try:
        rec = sampled_loop(controller, p, t_end, disturbance=disturbance, every=10)
    except Exception:       # the FMU's solver or the controller refuses non-finite values
        return steps[-1], None
    finally:
        try:
            p.close()
        except Exception:   # an FMU left in its error state refuses fmi2Terminate
            pass
    ok = np.all(np.isfinite(rec["q"])) and np.abs(rec["q"]).max() < 1e3
    return (None if ok else t_end), rec


# ----------------------------------------------------------------------------- prediction
@pytest.mark.parametrize("K, stable", [(480.0, True), (540.0, False)])
def test_prediction_against_runs_two_link(two_link_plant, K, stable):
    """On the paper's arm with h = 1 ms the predicted boundary lies between K = 480 and
    540 at t = 0 on the reference (growth 0.999 and 1.13 per step): the C controller around
    the plant FMU runs 0.3 s below it and diverges above it (1e6-fold in ~100 steps)."""
    from ivdrem.controller.clib import CController
    from ivdrem.controller.sampled import SampledController
    st = sampled_stability(two_link(), "iv-drem", K=K, h=1e-3, t_end=0.0, points=1,
                           suggest=False)
    assert st.stable is stable, st.reason()
    assert (st.growth < 1.0 + 1e-9) if stable else (st.growth > 1.1)
    zero = {k: [0.0, 0.0] for k in ("amplitude", "omega", "phase", "offset")}
    diverged, rec = _run(CController(two_link(), "iv-drem", K=K, h=1e-3), two_link_plant,
                         0.3, zero, reference=SampledController(two_link(), "iv-drem"))
    assert (diverged is None) is stable, (K, diverged)


def test_prediction_against_runs_panda(tmp_path):
    """The paper's design (its feedback (9), K of examples/panda.toml, μ₁ = 15) on the
    Panda's URDF at 1 ms is predicted at 1.67 per step (1e6-fold within 27 ms) and diverges
    in the plant FMU within 30 ms; at h = 0.5 ms it is predicted stable and runs; the
    inertia-scaled design (the URDF arms' default) is predicted stable at 1 ms and runs."""
    from ivdrem.controller.sampled import SampledController
    from ivdrem.fmu import export_fmu
    model = get_model("panda")
    K = [2.0, 5.448, 2.175, 2.003, 2.0, 2.0, 2.0]
    plant = export_fmu(model, tmp_path / "Panda.fmu")
    paper = dict(K=K, design="paper")
    st = sampled_stability(model, "none", h=1e-3, t_end=0.0, points=1, suggest=True, **paper)
    assert not st.stable and st.growth > 1.5, st.reason()
    assert st.stable_h == 5e-4
    line = st.reason()
    assert "\n" not in line and "1.67" in line and "--h 0.0005" in line
    diverged, _ = _run(SampledController(model, "none", h=1e-3, **paper), plant, 0.1,
                       NO_DISTURBANCE)
    assert diverged is not None and diverged <= 0.03
    for h, design in ((5e-4, paper), (1e-3, dict(K=K, design="inertia-scaled"))):
        st = sampled_stability(model, "none", h=h, t_end=0.0, points=1, **design)
        assert st.stable and st.growth < 1.0, st.reason()
        diverged, rec = _run(SampledController(model, "none", h=h, **design), plant, 0.1,
                             NO_DISTURBANCE)
        assert diverged is None and np.abs(rec["q"]).max() < 3.0


def test_prediction_threshold_and_horizon():
    """The worst point is where μ is largest (t = 300 s, μ_max = 135): the paper's 2-link
    design holds there (growth 1.0), a K of 300 does not (2.59)."""
    good = sampled_stability(two_link(), "iv-drem", h=1e-3, t_end=300.0, points=3)
    assert good.stable and abs(good.growth - 1.0) < 1e-3
    bad = sampled_stability(two_link(), "iv-drem", K=300.0, h=1e-3, t_end=300.0, points=3,
                            suggest=False)
    assert not bad.stable and bad.worst[0] > 0 and bad.growth > UNSTABLE_GROWTH


# ----------------------------------------------------------------------------- the CLI
def _cli(capsys, *argv):
    code = main_fmu(["export", "--controller", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_export_prints_its_h(tmp_path, capsys):
    from fmpy import read_model_description
    code, out, err = _cli(capsys, "--h", "0.0005", "-o", str(tmp_path / "C.fmu"))
    assert code == 0, err
    assert "h = 0.5 ms" in out and "predicted growth" in out
    md = read_model_description(str(tmp_path / "C.fmu"))
    h = next(v for v in md.modelVariables if v.name == "h")
    assert float(h.start) == 5e-4


def test_refuses_h_not_dividing_the_window(tmp_path, capsys):
    code, out, err = _cli(capsys, "--h", "0.0007", "-o", str(tmp_path / "C.fmu"))
    assert code == 2 and not (tmp_path / "C.fmu").exists()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "--h 0.0007" in lines[0] and "T = 20 s" in lines[0]


def test_export_takes_mix_every(tmp_path, capsys):
    """--mix-every M becomes the FMU's mix_every (the 2-link arm, its paper mixing every 5
    samples) and is printed; a value that is not a whole number from 1 to the window's
    samples (T / h = 20,000 here), or given to a law without a window, is refused in one line
    naming it, before anything is written."""
    from fmpy import read_model_description
    code, out, err = _cli(capsys, "--mix-every", "5", "-o", str(tmp_path / "C.fmu"))
    assert code == 0, err
    assert "mix_every = 5" in out
    md = read_model_description(str(tmp_path / "C.fmu"))
    assert float(next(v for v in md.modelVariables if v.name == "mix_every").start) == 5
    for bad, words in (("0", "from 1 to the window's 20000 samples"), ("2.5", "whole number"),
                       ("abc", "whole number"), ("20001", "20000 samples")):
        code, out, err = _cli(capsys, "--mix-every", bad, "-o", str(tmp_path / "B.fmu"))
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and f"--mix-every {bad}" in lines[0], err
        assert words in lines[0] and not (tmp_path / "B.fmu").exists()
    code, out, err = _cli(capsys, "--law", "none", "--mix-every", "5", "-o",
                          str(tmp_path / "B.fmu"))
    assert code == 2 and "laws with a window" in err and not (tmp_path / "B.fmu").exists()


def test_refuses_unstable_design(tmp_path, capsys):
    cfg = tmp_path / "stiff.toml"
    cfg.write_text("[controller]\nK = [600.0, 600.0]\n")
    code, out, err = _cli(capsys, "--config", str(cfg), "-o", str(tmp_path / "C.fmu"))
    assert code == 2 and not (tmp_path / "C.fmu").exists()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "predicted unstable" in lines[0] and "grows by" in lines[0]
    assert "--despite-prediction" in lines[0]
    code, out, err = _cli(capsys, "--config", str(cfg), "--despite-prediction", "-o",
                          str(tmp_path / "C.fmu"))
    assert code == 0 and (tmp_path / "C.fmu").exists(), err


def test_refuses_a_model_without_generated_code(tmp_path, capsys, monkeypatch):
    """An arm whose controller code cannot be generated is refused in one line before any
    long work (no calibration, no prediction, no file)."""
    import ivdrem.controller.fmu_export as fe

    def broken(model, defaults=None):
        raise AttributeError("'RigidBodyModel' object has no attribute 'Phi_M'")
    monkeypatch.setattr(fe, "generate_controller_sources", broken)
    monkeypatch.setattr(fe, "predict", lambda *a, **k: pytest.fail("predicted"))
    code, out, err = _cli(capsys, "--model", "planar-3", "-o", str(tmp_path / "C.fmu"))
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "cannot be generated" in lines[0]
    assert "planar-3" in lines[0] and not (tmp_path / "C.fmu").exists()


def test_host_reads_h_from_the_fmu(tmp_path, two_link_plant):
    """fmpy_closed_loop steps at the FMU's own h (0.5 ms here) and computes the loop of the
    C reference controller with the same parameters (delay 1)."""
    from ivdrem.controller.clib import CController
    from ivdrem.controller.fmu_export import export_controller_fmu
    from ivdrem.controller.fmu_loop import controller_period, fmpy_closed_loop
    fmu = export_controller_fmu(two_link(), tmp_path / "C.fmu", h=5e-4)
    assert controller_period(fmu) == 5e-4
    rec = fmpy_closed_loop(fmu, two_link_plant, 0.2, every=40)
    assert np.allclose(np.diff(rec["t"]), 0.02)
    ref_ctl = CController(two_link(), "iv-drem", h=5e-4, delay=1)
    p = FmuPlant(two_link_plant, (0.0, 0.3 * np.pi), (0.0, 0.0))
    try:
        ref = sampled_loop(ref_ctl, p, 0.2, every=40)
    finally:
        p.close()
    assert np.array_equal(rec["q"], ref["q"])
    assert np.array_equal(rec["theta_hat"], ref["theta_hat"])


# ----------------------------------------------------------------------------- a URDF arm
#: a window T of 1 s instead of the arm's designed 40 s: the export's stability prediction
#: steps the loop over 1.25 T first (measured in one process at load 5: predict 6.1-8.6 s
#: with the designed window, 0.9-1.3 s with this one); the FMU's equality with the C
#: library does not depend on T, and the composite term is on from 1 s in the 2 s loop
#: around the plant FMU (benchmarks/bench_arm_fmu_loop.py keeps the designed window)
UR5_TOML = """[model]
name = "ur5"
[iv_drem]
gamma = 50.0
T = 1.0
"""


def _drive(fmu, q, dq, steps):
    """Step a controller FMU (FMI 2 or 3) over the measured (q, dq) rows: its outputs
    tau, theta_hat, tau_d_hat, q_d, dq_d after each step, and q_d, dq_d before the first."""
    from ivdrem.controller.fmu_loop import _Slave
    s = _Slave(fmu, "controller", {})
    try:
        n = q.shape[1]
        nth = sum(1 for k in s.vr if k.startswith("theta_hat["))
        names = {"tau": n, "theta_hat": nth, "tau_d_hat": n, "q_d": n, "dq_d": n}
        refs = {k: s.refs([f"{k}[{i}]" for i in range(m)]) for k, m in names.items()}
        start = {k: np.array(s.get(refs[k])) for k in ("q_d", "dq_d")}
        c_in = s.refs([f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)])
        h = float(s.get(s.refs(["h"]))[0])
        out = {k: [] for k in names}
        for k in range(steps):
            s.set(c_in, [*q[k], *dq[k]])
            s.step(k * h, h)
            for name in names:
                out[name].append(np.array(s.get(refs[name])))
        return start, {k: np.array(v) for k, v in out.items()}
    finally:
        s.close()


@pytest.fixture(scope="module")
def ur5_fmus(tmp_path_factory):
    """The UR5's controller FMU from a configuration, FMI 2 by the CLI and FMI 3 by the API
    with the same design."""
    from ivdrem.controller.fmu_export import controller_design, export_controller_fmu
    from ivdrem.experiments.config import read_config
    from ivdrem.experiments.experiment import Experiment
    d = tmp_path_factory.mktemp("ur5")
    cfg = d / "ur5.toml"
    cfg.write_text(UR5_TOML)
    code = main_fmu(["export", "--controller", "--config", str(cfg), "-o", str(d / "C2.fmu")])
    assert code == 0
    experiment = Experiment.from_config(read_config(cfg))
    model = experiment.model
    design = controller_design(experiment, "iv-drem", h=1e-3)
    c3 = export_controller_fmu(model, d / "C3.fmu", fmi_version=3, **design)
    return model, design, {2: d / "C2.fmu", 3: c3}


@pytest.mark.parametrize("version", [2, 3])
def test_ur5_export_validates_and_equals_the_c_library(ur5_fmus, version):
    """fmpy finds nothing to report; over 300 steps near the reference the FMU's tau,
    theta_hat and tau_d_hat equal the C library (CController, delay 1, the FMU's own start
    values) bit for bit, and q_d, dq_d equal the reference (before the first step: at 0)."""
    from fmpy.validation import validate_fmu
    from ivdrem.controller.clib import CController
    from ivdrem.controller.fmu_loop import _fmu_parameters
    from ivdrem.controller.sampled import SampledController
    model, design, fmus = ur5_fmus
    fmu = fmus[version]
    assert validate_fmu(str(fmu)) == []
    m, law, par = _fmu_parameters(fmu)
    assert m.name == "ur5" and law == "iv-drem"
    ref = CController.from_params(model, law, par)
    py = SampledController(model, law, **{**design, "delay": 1})
    steps = 300
    t = 1e-3 * np.arange(steps)
    rq = np.array([py.reference(tk)[0] for tk in t])
    rdq = np.array([py.reference(tk)[1] for tk in t])
    q = rq + 0.01 * np.sin(3 * t)[:, None]
    dq = rdq + 0.03 * np.cos(3 * t)[:, None]
    start, out = _drive(fmu, q, dq, steps)
    assert np.allclose(start["q_d"], rq[0], rtol=0, atol=1e-12)
    assert np.allclose(start["dq_d"], rdq[0], rtol=0, atol=1e-12)
    for k in range(steps):
        tau = ref.step(t[k], q[k], dq[k])
        assert np.array_equal(out["tau"][k], tau), k
        assert np.array_equal(out["theta_hat"][k], ref.theta_hat), k
        assert np.array_equal(out["tau_d_hat"][k], ref.tau_d_hat), k
        qd, dqd = ref.last_reference()
        assert np.array_equal(out["q_d"][k], qd) and np.array_equal(out["dq_d"][k], dqd)
    assert np.allclose(out["q_d"], rq, rtol=0, atol=1e-12)
    assert np.allclose(out["dq_d"], rdq, rtol=0, atol=1e-12)
    assert np.abs(out["tau"]).max() > 0.1


def test_ur5_controller_fmu_closed_around_its_plant_fmu(ur5_fmus, tmp_path):
    """The UR5's controller FMU around the UR5's plant FMU at 1 kHz in FMPy (the host reads
    h and the start q_d(0), dq_d(0) from the FMU): 2 s without divergence, the arm near its
    reference (the 300 s run is benchmarks/bench_arm_fmu_loop.py's)."""
    from ivdrem.controller.fmu_loop import fmpy_closed_loop
    from ivdrem.fmu import export_fmu
    model, design, fmus = ur5_fmus
    plant = export_fmu(model, tmp_path / "UR5.fmu")
    rec = fmpy_closed_loop(fmus[2], plant, 2.0, every=100, outputs=("q_d", "dq_d"))
    assert np.array_equal(rec["q"][0], rec["q_d"][0])        # started on the reference
    assert np.all(np.isfinite(rec["q"])) and np.abs(rec["q"] - rec["q_d"]).max() < 0.2


def test_an_unnamed_urdf_arm_around_pybullet():
    """example-robot-data's UR3 (not a named arm): exported from its default experiment and
    closed by the PyBullet harness at 1 kHz for 1 s, predicted stable, no divergence."""
    pytest.importorskip("pybullet")
    import importlib.util
    from pathlib import Path
    spec = importlib.util.spec_from_file_location(
        "bullet_harness", Path(__file__).parents[1] / "benchmarks" / "bullet_harness.py")
    harness = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(harness)
    urdf = harness.default_urdf()
    if not urdf.is_file():
        pytest.skip("example-robot-data is not installed")
    r = harness.run(urdf, 1.0, mix_every=20, every=250)
    assert r["model"] == "ur3" and r["growth"] < 1.0 and r["diverged"] is None
    assert max(e for _, e, _ in r["rows"]) < 0.5


# ----------------------------------------------------------------------- small gaps
def test_fmu_plant_in_its_error_state_closes_without_raising(tmp_path):
    """A failed step leaves the plant FMU in its error state, where fmi2Terminate is not
    allowed: close() still frees it and removes its files, raising nothing."""
    from fmpy.fmi1 import FMICallException
    from ivdrem.controller.loop import FmuPlant
    from ivdrem.fmu import export_fmu
    plant = FmuPlant(export_fmu(two_link(), tmp_path / "Plant.fmu"), (0.0, 0.3), (0.0, 0.0))
    with pytest.raises(FMICallException):
        plant.step(0.0, 1e-3, [float("nan"), 0.0], [0.0, 0.0])
    with pytest.raises(FMICallException):          # the FMU is in its error state
        plant.fmu.terminate()
    plant.close()
    assert not Path(plant._dir).exists()


_UNNAMED_URDF = """<?xml version="1.0"?>
<robot name="unnamed_two_link">
  <link name="base"/>
  <link name="l1"><inertial><origin xyz="0.1 0 0"/><mass value="1.2"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <link name="l2"><inertial><origin xyz="0.08 0 0"/><mass value="0.8"/>
    <inertia ixx="0.005" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.25 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
</robot>
"""


def test_cosim_controller_fmu_of_a_urdf_file_arm(tmp_path):
    """``ivdrem cosim --controller-fmu`` on the controller FMU of an arm known only by its
    URDF file (no model of that name): the FMU carries the arm's description
    (fmu_export.MODEL_RESOURCE), the command rebuilds the same model (same key) and runs."""
    import zipfile
    from ivdrem.controller.fmu_export import MODEL_RESOURCE, export_controller_fmu
    from ivdrem.controller.fmu_loop import _fmu_parameters
    from ivdrem.cli.fmu import main_cosim
    from ivdrem.models.urdf import from_urdf
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(_UNNAMED_URDF)
    model = from_urdf(urdf, cache=False)
    with pytest.raises(Exception):
        get_model(model.name)                       # not a named arm
    ctl = export_controller_fmu(model, tmp_path / "C.fmu", law="none", h=1e-3, K=5.0)
    assert MODEL_RESOURCE in zipfile.ZipFile(ctl).namelist()
    back, law, par = _fmu_parameters(ctl)
    assert (back.key, back.name, law, par.size) == (model.key, model.name, "none",
                                                   param_vector(SampledController(
                                                       model, "none")).size)
    urdf.unlink()                                   # the FMU alone is enough
    assert main_cosim(["--controller-fmu", str(ctl), "--t-end", "0.05", "--quiet"]) == 0


def test_controller_design_mixes_a_real_arm_every_mix_every_samples():
    """The export's design: the URDF arms' scale-free mixing (and composite learning's
    max-hold) every MIX_EVERY samples (the step within the deadline), the paper's 2-link
    experiment single-rate (its design bit for bit as before)."""
    from ivdrem.controller.fmu_export import MIX_EVERY, controller_design
    from ivdrem.experiments.config import read_config
    from ivdrem.experiments.experiment import Experiment
    ur5_experiment = Experiment.from_config(read_config(None, {"model.name": "ur5"}))
    ur5 = controller_design(ur5_experiment, "iv-drem", h=1e-3)
    assert ur5["mix_every"] == MIX_EVERY == 20
    assert SampledController(get_model("ur5"), "iv-drem",
                             **{**ur5, "gamma": 50.0}).mix_every == 20
    assert controller_design(ur5_experiment, "none").get(
        "mix_every", 1) == 1
    assert controller_design(ur5_experiment,
                             "composite-learning")["mix_every"] == MIX_EVERY  # its max-hold
    paper = controller_design(read_config(None), "iv-drem", h=1e-3)     # data: its Experiment
    assert paper.get("mix_every", 1) == 1
