"""The sampled controller: Python reference, generated C library, controller FMU, FMU loops.

Independent checks: the continuous closed loop of ivdrem (same saturated mu) that the
sampled loop converges to at first order in h; the paper's conclusions C1-C3 on the
sampled loop (ivdrem.experiments.metrics); the C library against the Python reference
(two implementations of the same algorithm, one with LAPACK's SVD and one with a Jacobi
SVD); the FMU loop in two FMI hosts (FMPy, libcosim) against the Python reference (the
300 s run of both hosts is in tests/test_controller_block.py, which shares its FMPy run).
"""
import math

import numpy as np
import pytest

from ivdrem.controller.sampled import SAMPLED_LAWS, SampledController
from ivdrem.models import two_link

THETA = np.array([1.3, 0.28, 0.32, 0.4, 1.4])
Q0 = (0.0, 0.3 * np.pi)


@pytest.fixture(scope="module")
def controller_fmu(tmp_path_factory):
    from ivdrem.controller.fmu_export import export_controller_fmu
    return export_controller_fmu(two_link(), tmp_path_factory.mktemp("ctl") / "Controller.fmu",
                                 law="iv-drem", mu_max=135.0)


def _loop(ctrl, plant_fmu, t_end, **kw):
    from ivdrem.controller.loop import FmuPlant, sampled_loop
    plant = FmuPlant(plant_fmu, Q0, (0.0, 0.0), substep=min(ctrl.h, 1e-3))
    try:
        return sampled_loop(ctrl, plant, t_end, **kw)
    finally:
        plant.close()


_REF = SampledController()


def _measurements(ctl, k):
    """A smooth measured motion near the paper's reference (no plant needed)."""
    t = k * ctl.h
    qd, dqd, _ = _REF.reference(t)
    return t, qd + 0.05 * np.sin(3 * t) + 0.02, dqd + 0.15 * np.cos(3 * t)


# ----------------------------------------------------------------------- C = Python
@pytest.mark.parametrize("law", SAMPLED_LAWS)
@pytest.mark.parametrize("delay", [0, 1])
def test_c_library_equals_python_reference(law, delay):
    from ivdrem.controller.clib import CController
    kw = dict(mu_max=135.0, delay=delay, T=0.5, tau_max=40.0)
    py, c = SampledController(law=law, **kw), CController(law=law, **kw)
    worst_tau = worst_th = 0.0
    for k in range(1500):                 # the 0.5 s window wraps three times
        t, q, dq = _measurements(py, k)
        a, b = py.step(t, q, dq), c.step(t, q, dq)
        worst_tau = max(worst_tau, np.abs(a - b).max() / max(1.0, np.abs(a).max()))
        worst_th = max(worst_th, np.abs(py.theta_hat - c.theta_hat).max())
    assert worst_tau < 1e-12 and worst_th < 1e-12
    assert np.abs(py.tau_d_hat - c.tau_d_hat).max() < 1e-10
    if law in ("iv-drem", "drem"):
        assert py.Delta != 0.0 and abs(py.Delta - c.Delta) <= 1e-9 * abs(py.Delta)
    assert np.abs(py.theta_hat).max() > 1e-4         # the estimate moved


def test_state_save_restore_continues_bit_for_bit():
    from ivdrem.controller.clib import CController
    kw = dict(mu_max=135.0, T=0.2)
    for ctl in (SampledController(**kw), CController(**kw)):
        for k in range(250):
            ctl.step(*_measurements(ctl, k))
        saved = ctl.state()
        first = [ctl.step(*_measurements(ctl, k)) for k in range(250, 400)]
        th1 = ctl.theta_hat
        ctl.set_state(saved)
        again = [ctl.step(*_measurements(ctl, k)) for k in range(250, 400)]
        assert all(np.array_equal(a, b) for a, b in zip(first, again))
        assert np.array_equal(th1, ctl.theta_hat)


def test_bad_input_is_refused_with_the_state_unchanged():
    from ivdrem.controller.clib import CController, CControllerError
    for ctl in (SampledController(mu_max=135.0), CController(mu_max=135.0)):
        ctl.step(*_measurements(ctl, 0))
        saved = ctl.state()
        err = (ValueError, CControllerError)
        with pytest.raises(err, match="non-finite"):
            ctl.step(1e-3, [np.nan, 0.0], [0.0, 0.0])
        with pytest.raises(err, match="t ="):
            ctl.step(5e-3, [0.0, 0.0], [0.0, 0.0])
        after = ctl.state()
        if isinstance(saved, bytes):                      # the C state, byte for byte
            assert after == saved
        else:
            assert all(np.array_equal(after[k], saved[k]) for k in saved if k != "window")
            assert all(np.array_equal(after["window"][k], saved["window"][k])
                       for k in saved["window"])
        assert np.all(np.isfinite(ctl.step(1e-3, [0.0, 0.0], [0.0, 0.0])))  # goes on at t_1
    for bad, match in ((dict(mu_max=5.0), "mu_max"), (dict(delay=2), "delay"),
                       (dict(T=0.0105), "whole number"), (dict(law="pid"), "sampled form"),
                       (dict(Gamma=[[1, 1], [1, 1]]), "Gamma"), (dict(h=-1), "h")):
        with pytest.raises(ValueError, match=match):
            SampledController(**bad)


def test_torque_saturation():
    ctl = SampledController(mu_max=135.0, tau_max=0.5)
    taus = [ctl.step(*_measurements(ctl, k)) for k in range(200)]
    assert np.abs(taus).max() == pytest.approx(0.5)


# ----------------------------------------------------------------------- against continuous
def test_sampled_loop_converges_to_the_continuous_loop_at_first_order(plant_fmu):
    """theta_hat, q of the sampled loop (Python reference, torque held over each sample)
    approach ivdrem's continuous closed loop with the same saturated mu like O(h)."""
    from ivdrem.controller.continuous import continuous_closed_loop
    from ivdrem.sim import simulate
    t_end = 1.0     # measured: errors 1.55e-3, 7.73e-4, 3.86e-4; orders 1.004, 1.002
    r = simulate(continuous_closed_loop("iv-drem", mu_max=135.0), t_end, dt_out=0.5,
                 rtol=1e-9, atol=1e-11, h_max=0.01)
    lab = list(r.output_labels)
    th = r.outputs[[lab.index(f"theta_hat[{j}]") for j in range(5)], -1]
    q = r.outputs[[lab.index(f"q[{i}]") for i in range(2)], -1]
    errs = []
    for h in (1e-3, 5e-4, 2.5e-4):
        s = _loop(SampledController(mu_max=135.0, h=h), plant_fmu, t_end, every=10 ** 6)
        errs.append(max(np.abs(s["theta_hat"][-1] - th).max(), np.abs(s["q"][-1] - q).max()))
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all((orders > 0.8) & (orders < 1.3)), (errs, orders)
    assert errs[0] < 0.01


@pytest.fixture(scope="module")
def c_loop_300s(plant_fmu):
    """c_loop_300s(law): the 1 kHz loop (C library, delay 0, mu_max = 135) over 300 s of
    the paper experiment, recorded every 0.1 s and at 300 s; each law's run made once (the
    conclusions C1-C3 read both laws' runs)."""
    from ivdrem.controller.clib import CController
    runs = {}

    def run(law="iv-drem"):
        if law not in runs:
            runs[law] = _loop(CController(law=law, mu_max=135.0), plant_fmu, 300.0, every=100)
        return runs[law]
    return run


@pytest.mark.slow
def test_sampled_loop_keeps_the_conclusions_c1_c3(c_loop_300s):
    """The 1 kHz loop (C library, 300 s of the paper experiment, mu_max = 135): C1-C3 of
    ivdrem.experiments.metrics hold."""
    from ivdrem.controller.loop import as_response
    from ivdrem.experiments.metrics import conclusions
    from ivdrem.experiments.paper import LawRun, PaperRun
    runs = {law: LawRun(law, as_response(c_loop_300s(law)), {})
            for law in ("iv-drem", "composite-learning")}
    got = {c["id"]: c for c in conclusions(PaperRun({}, THETA, None, runs))}
    for cid in ("C1", "C2", "C3"):
        assert got[cid]["verdict"] is True, got[cid]


# ----------------------------------------------------------------------- the FMU
def test_controller_fmu_validates_and_refuses_bad_calls(controller_fmu, tmp_path):
    import fmpy
    from fmpy.fmi1 import FMICallException
    from fmpy.fmi2 import FMU2Slave
    from fmpy.validation import validate_fmu
    assert validate_fmu(str(controller_fmu)) == []
    md = fmpy.read_model_description(str(controller_fmu))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    assert md.coSimulation.canGetAndSetFMUstate
    assert "delay" not in vr
    unz = fmpy.extract(str(controller_fmu), unzipdir=tmp_path / "u")
    msgs = []

    def fresh():
        f = FMU2Slave(guid=md.guid, unzipDirectory=unz,
                      modelIdentifier=md.coSimulation.modelIdentifier, instanceName="c")
        f.instantiate(loggingOn=False, callbacks=None)
        return f
    f = fresh()
    with pytest.raises(FMICallException):                 # a step before initialization
        f.doStep(0.0, 1e-3)
    f.freeInstance()
    f = fresh()
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.setReal([vr["mu_max"]], [5.0])                      # below mu1 = 15
    with pytest.raises(FMICallException):
        f.exitInitializationMode()
    f.freeInstance()
    f = fresh()
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.exitInitializationMode()
    with pytest.raises(FMICallException):                 # NaN input
        f.setReal([vr["q[0]"]], [math.nan])
    f.freeInstance()
    f = fresh()
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.exitInitializationMode()
    with pytest.raises(FMICallException):                 # step size != h
        f.doStep(0.0, 2e-3)
    f.freeInstance()
    f = fresh()
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.exitInitializationMode()
    with pytest.raises(FMICallException):                 # h is fixed after initialization
        f.setReal([vr["h"]], [2e-3])
    f.freeInstance()
    del msgs


def test_controller_fmu_state_restore_mid_run_bit_for_bit(controller_fmu, tmp_path):
    import fmpy
    from fmpy.fmi2 import FMU2Slave
    md = fmpy.read_model_description(str(controller_fmu))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    unz = fmpy.extract(str(controller_fmu), unzipdir=tmp_path / "u")
    f = FMU2Slave(guid=md.guid, unzipDirectory=unz,
                  modelIdentifier=md.coSimulation.modelIdentifier, instanceName="c")
    f.instantiate(callbacks=None)
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.setReal([vr["T"]], [0.2])                           # the window wraps in the run
    f.exitInitializationMode()
    ref = SampledController(mu_max=135.0, T=0.2)
    ins = [vr[f"q[{i}]"] for i in range(2)] + [vr[f"dq[{i}]"] for i in range(2)]
    outs = [vr[f"tau[{i}]"] for i in range(2)] + [vr[f"theta_hat[{j}]"] for j in range(5)]

    def run(k0, k1):
        ys = []
        for k in range(k0, k1):
            t, q, dq = _measurements(ref, k)
            f.setReal(ins, [*q, *dq])
            f.doStep(t, 1e-3)
            ys.append(f.getReal(outs))
        return ys
    run(0, 300)
    s = f.getFMUstate()
    blob = f.serializeFMUstate(s)
    first = run(300, 700)
    f.setFMUstate(s)
    assert run(300, 700) == first
    s2 = f.deSerializeFMUstate(blob)
    f.setFMUstate(s2)
    assert run(300, 700) == first
    f.freeFMUstate(s)
    f.freeFMUstate(s2)
    f.terminate()
    f.freeInstance()
    assert len(blob) > 20 * 30 * 8             # the window's 20 block sums are in it


def test_fmu_loop_in_fmpy_equals_the_python_reference(controller_fmu, plant_fmu):
    """Controller FMU + plant FMU in FMPy (Jacobi) = Python reference with delay 1, over
    5 s with the window T set to 2 s at initialization (it wraps twice); the 300 s run of
    the default 20 s window is tests/test_controller_block.py's."""
    from ivdrem.controller.fmu_loop import fmpy_closed_loop
    a = fmpy_closed_loop(controller_fmu, plant_fmu, 5.0, controller_start={"T": 2.0})
    b = _loop(SampledController(mu_max=135.0, delay=1, T=2.0), plant_fmu, 5.0)
    assert np.abs(a["theta_hat"] - b["theta_hat"]).max() < 1e-9
    assert np.abs(a["q"] - b["q"]).max() < 1e-9
    assert np.abs(b["theta_hat"][-1] - b["theta_hat"][0]).max() > 0.1     # it adapts


def test_cli_exports_the_controller_fmu(tmp_path, capsys):
    from fmpy.validation import validate_fmu
    from ivdrem.cli.fmu import main_fmu
    out = tmp_path / "Controller.fmu"
    assert main_fmu(["export", "--controller", "--law", "none", "-o", str(out)]) == 0
    assert validate_fmu(str(out)) == []
    assert main_fmu(["export", "--controller", "-o", str(out)]) == 0      # ours: replaced
    other = tmp_path / "notes.fmu"
    other.write_text("not an FMU")
    assert main_fmu(["export", "--controller", "-o", str(other)]) == 2
    assert other.read_text() == "not an FMU"
    assert main_fmu(["export", "--controller", "--law", "pid", "-o", str(out)]) == 2
    assert main_fmu(["export", "--controller", "--q0", "0", "1", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "law 'pid'" in err and "notes.fmu" in err


def test_cli_cosim_controller_fmu(controller_fmu, plant_fmu, tmp_path, capsys):
    from ivdrem.cli.fmu import main_cosim
    assert main_cosim(["--controller-fmu", str(controller_fmu), "--fmu", str(plant_fmu),
                       "--t-end", "2"]) == 0
    out = capsys.readouterr().out
    assert "max |theta_hat - theta_hat_ref| = 0" in out
    assert main_cosim(["--controller-fmu", str(tmp_path / "none.fmu"), "--t-end", "2"]) == 2
    assert main_cosim(["--controller-fmu", str(plant_fmu), "--t-end", "2"]) == 2
    assert "not a controller FMU" in capsys.readouterr().err


def test_ssp_file_runs_in_libcosim_as_the_fmpy_loop(controller_fmu, plant_fmu, tmp_path):
    pytest.importorskip("libcosimpy")
    import zipfile
    from ivdrem.controller.fmu_loop import fmpy_closed_loop
    from ivdrem.controller.ssp import libcosim_ssp_loop, write_ssp
    ssp = write_ssp(controller_fmu, plant_fmu, tmp_path / "loop.ssp")
    with zipfile.ZipFile(ssp) as zf:
        names = set(zf.namelist())
        ssd = zf.read("SystemStructure.ssd").decode()
    assert {"SystemStructure.ssd", "resources/Plant.fmu", "resources/Controller.fmu"} <= names
    assert ssd.count("<ssd:Connection ") == 6
    r = libcosim_ssp_loop(ssp, 3.0)
    a = fmpy_closed_loop(controller_fmu, plant_fmu, 3.0)
    assert np.array_equal(r["t"], a["t"][1:])
    assert np.abs(r["theta_hat"] - a["theta_hat"][1:]).max() < 1e-12
    assert np.abs(r["q"] - a["q"][1:]).max() < 1e-12


def test_c_library_for_a_planar_arm_equals_python_reference():
    """The generated C for another model (planar-3, nθ = 6, the generic reference)."""
    from ivdrem.controller.clib import CController
    from ivdrem.models import get_model
    model = get_model("planar-3")
    kw = dict(mu_max=135.0, T=0.3, gamma=1e6)
    py, c = SampledController(model, **kw), CController(model, **kw)
    for k in range(800):
        t = k * 1e-3
        qd, dqd, _ = py.reference(t)
        q, dq = qd + 0.05 * np.sin(2 * t), dqd + 0.1 * np.cos(2 * t)
        a, b = py.step(t, q, dq), c.step(t, q, dq)
        assert np.abs(a - b).max() <= 1e-12 * max(1.0, np.abs(a).max())
    assert np.abs(py.theta_hat - c.theta_hat).max() < 1e-12
    assert py.Delta != 0.0


def test_the_c_library_builds_alone_as_plain_c99(tmp_path):
    """The generated sources compile with -std=c99 -pedantic -Werror and a main of ours
    (no Python, libm only) and give the torques of the Python reference."""
    import shutil
    import subprocess
    from ivdrem.controller.codegen import generate_controller_sources
    if shutil.which("cc") is None:
        pytest.skip("no C compiler")
    for name, text in generate_controller_sources(two_link()).items():
        (tmp_path / name).write_text(text)
    (tmp_path / "main.c").write_text(r"""
#include <math.h>
#include <stdio.h>
#include "ivdrem_controller.h"
int main(void) {
    double par[IVC_NPAR], q[2], dq[2], tau[2];
    char msg[256];
    int k;
    ivc_controller *c;
    ivc_default_params(par);
    par[IVC_P_MU_MAX] = 135.0;
    c = ivc_init(par, msg, sizeof msg);
    if (!c) { puts(msg); return 1; }
    for (k = 0; k < 500; k++) {
        double t = k * 1e-3;
        q[0] = 0.3 * sin(t); q[1] = 0.9 + 0.1 * t; dq[0] = 0.3 * cos(t); dq[1] = 0.1;
        if (ivc_step(c, t, q, dq, tau) != IVC_OK) { puts(ivc_message(c)); return 1; }
    }
    printf("%.17g %.17g\n", tau[0], tau[1]);
    ivc_free(c);
    return 0;
}
""")
    exe = tmp_path / "main"
    subprocess.run(["cc", "-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2",
                    "-I", str(tmp_path), str(tmp_path / "main.c"),
                    str(tmp_path / "ivdrem_controller.c"), str(tmp_path / "controller_model.c"),
                    "-o", str(exe), "-lm"], check=True, capture_output=True)
    got = np.array(subprocess.run([str(exe)], capture_output=True, text=True,
                                  check=True).stdout.split(), dtype=float)
    py = SampledController(mu_max=135.0)
    for k in range(500):
        t = k * 1e-3
        tau = py.step(t, [0.3 * math.sin(t), 0.9 + 0.1 * t], [0.3 * math.cos(t), 0.1])
    assert np.abs(got - tau).max() <= 1e-12 * np.abs(tau).max()


@pytest.mark.slow
def test_sampled_loop_against_the_continuous_loop_over_3_windows(plant_fmu):
    """theta_hat(60 s) of the 1 kHz loop (C library) against ivdrem's continuous loop with
    the same saturated mu: within the issue's 1e-3 (measured 2.55e-5 at h = 1 ms), and half
    that at 0.5 ms (first order: measured 1.28e-5, ratio 1.99).  60 s is 3 T of the paper's
    window T = 20 s: the window filling, the composite term switching on at T and the
    learning after it all run, so a sampled loop that departs from the continuous one in
    any phase shows in theta_hat(60 s).  Over the paper's 300 s the same comparison
    measured 4.7e-6 at h = 1 ms."""
    from ivdrem.controller.clib import CController
    from ivdrem.controller.continuous import continuous_closed_loop
    from ivdrem.sim import simulate
    t_end = 60.0
    r = simulate(continuous_closed_loop("iv-drem", mu_max=135.0), t_end, dt_out=1.0,
                 rtol=1e-7, atol=1e-9, h_max=0.5)
    lab = list(r.output_labels)
    th = r.outputs[[lab.index(f"theta_hat[{j}]") for j in range(5)], -1]
    errs = [np.abs(_loop(CController(mu_max=135.0, h=h), plant_fmu, t_end,
                         every=10 ** 6)["theta_hat"][-1] - th).max() for h in (1e-3, 5e-4)]
    assert errs[0] < 1e-3
    assert 1.7 < errs[0] / errs[1] < 2.3, errs


def test_controller_fmu_tunable_gain_mid_run_equals_the_c_library(controller_fmu, tmp_path):
    """A tunable gain (K[0], gamma) set between steps acts as ivc_set_param does."""
    import fmpy
    from fmpy.fmi2 import FMU2Slave
    from ivdrem.controller.clib import CController
    md = fmpy.read_model_description(str(controller_fmu))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    assert {v.name: v.variability for v in md.modelVariables}["K[0]"] == "tunable"
    f = FMU2Slave(guid=md.guid, unzipDirectory=fmpy.extract(str(controller_fmu),
                                                             unzipdir=tmp_path / "u"),
                  modelIdentifier=md.coSimulation.modelIdentifier, instanceName="c")
    f.instantiate(callbacks=None)
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.exitInitializationMode()
    c = CController(mu_max=135.0, delay=1)
    untuned = CController(mu_max=135.0, delay=1)
    ins = [vr[f"q[{i}]"] for i in range(2)] + [vr[f"dq[{i}]"] for i in range(2)]
    outs = [vr["tau[0]"], vr["tau[1]"]]
    for k in range(400):
        if k == 200:
            f.setReal([vr["K[0]"], vr["gamma"]], [5.0, 3e9])
            c.set_param("K", 5.0, 0)
            c.set_param("gamma", 3e9)
        t, q, dq = _measurements(c, k)
        f.setReal(ins, [*q, *dq])
        f.doStep(t, 1e-3)
        tuned = c.step(t, q, dq)
        assert f.getReal(outs) == list(tuned)
        plain = untuned.step(t, q, dq)
    assert np.abs(tuned - plain).max() > 1e-3                  # the new gains acted
    f.terminate()
    f.freeInstance()


def test_the_paper_q0_and_the_default_h_are_the_default_configurations():
    """q(0) = (0, 0.3π) and the controller's h = 1 ms are written once, in the default
    configuration: every default of the controller reads them there (bit for bit the
    values typed before), and no module of the package types them again."""
    import inspect
    import re
    from pathlib import Path

    import ivdrem
    from ivdrem.controller import block, fmu_loop, loop, sampled, ssp
    from ivdrem.experiments.config import read_config, resolve_config
    from ivdrem.plants import mujoco

    config = resolve_config(read_config(None))[0]
    assert loop.paper_q0() == loop.PAPER_Q0 == tuple(config["initial"]["q0"]) == Q0
    assert loop.default_period() == float(config["solver"]["h"]) == 1e-3
    assert SampledController().h == 1e-3 == _REF.h
    assert block.controller_block(backend="python").dt == 1e-3
    assert sampled.PAPER_TRAJECTORY == dict(
        amplitude=[0.4 * np.pi, 0.3 * np.pi], omega=[2.0, 0.3], phase=[0.0, np.pi / 2],
        offset=[0.2 * np.pi, 0.3 * np.pi]) == config["trajectory"]
    # the signatures say None (resolved inside), not a number typed again
    for fn, names in ((SampledController.__init__, ("h",)), (block.controller_block, ("h",)),
                      (block.sampled_closed_loop, ("h", "q0")), (mujoco.load, ("h",)),
                      (fmu_loop.libcosim_closed_loop, ("q0",)), (ssp.write_ssp, ("q0",)),
                      (ssp.libcosim_ssp_loop, ("q0",))):
        params = inspect.signature(fn).parameters
        for name in names:
            assert params[name].default is None, (fn.__qualname__, name)
    # the package's sources: 0.3π (or its digits) nowhere but experiments/default.toml
    root = Path(ivdrem.__file__).parent
    typed = [str(p.relative_to(root)) for p in sorted(root.rglob("*.py"))
             if re.search(r"0\.3 ?\* ?(np|math)\.pi|0\.94247779", p.read_text(encoding="utf-8"))]
    assert typed == [], typed
