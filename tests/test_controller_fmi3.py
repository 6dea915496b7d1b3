"""The sampled controller as an FMI 3.0 co-simulation FMU (fmi3_controller.c).

Independent check: the FMI 2.0 controller FMU of the same library (fmi2_controller.c),
closed around the same plant FMU in FMPy; the FMI 3.0 loop must equal it bit for bit.
"""
import numpy as np
import pytest

from ivdrem.models import two_link


@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    from ivdrem.controller.fmu_export import export_controller_fmu
    d = tmp_path_factory.mktemp("ctl3")
    return {v: export_controller_fmu(two_link(), d / f"C{v}.fmu", law="iv-drem", mu_max=135.0,
                                     fmi_version=v) for v in (2, 3)}


def test_fmi3_fmu_validates(fmus):
    from fmpy import read_model_description
    from fmpy.validation import validate_fmu
    assert validate_fmu(str(fmus[3])) == []
    md = read_model_description(str(fmus[3]))
    assert md.fmiVersion == "3.0" and md.coSimulation.canGetAndSetFMUstate
    import zipfile
    names = zipfile.ZipFile(fmus[3]).namelist()
    assert any(n.startswith("binaries/x86_64-linux/") and n.endswith(".so") for n in names)


def test_bad_fmi_version_refused(tmp_path):
    from ivdrem.controller.fmu_export import export_controller_fmu
    with pytest.raises(ValueError, match="fmi_version"):
        export_controller_fmu(two_link(), tmp_path / "x.fmu", fmi_version=4)


def test_fmi3_loop_equals_the_fmi2_loop_bit_for_bit(fmus, plant_fmu):
    from ivdrem.controller.fmu_loop import fmpy_closed_loop
    a = fmpy_closed_loop(fmus[3], plant_fmu, 3.0, every=10)
    b = fmpy_closed_loop(fmus[2], plant_fmu, 3.0, every=10)
    for k in ("q", "dq", "tau", "theta_hat"):
        assert np.array_equal(a[k], b[k]), k
    assert np.abs(a["theta_hat"][-1] - a["theta_hat"][0]).max() > 1e-3   # it adapts


def _slave(path):
    from ivdrem.controller.fmu_loop import _Slave
    return _Slave(path, "c3", {})


def test_fmi3_state_restore_mid_run_continues_bit_for_bit(fmus):
    s = _slave(fmus[3])
    try:
        vr_in = s.refs(["q[0]", "q[1]", "dq[0]", "dq[1]"])
        vr_out = s.refs(["tau[0]", "tau[1]", "theta_hat[0]", "Delta"])
        h = 1e-3

        def run(k0, k1):
            out = []
            for k in range(k0, k1):
                t = k * h
                s.set(vr_in, [np.sin(t), np.cos(2 * t), 0.3 * t, -0.1])
                s.step(t, h)
                out.append(s.get(vr_out))
            return np.array(out)
        run(0, 200)
        st = s.fmu.getFMUState()
        a = run(200, 400)
        s.fmu.setFMUState(st)
        b = run(200, 400)
        s.fmu.freeFMUState(st)
        assert np.array_equal(a, b) and np.abs(a).max() > 0
    finally:
        s.close()


def test_fmi3_bad_calls_give_fmi3Error_and_a_message(fmus):
    from fmpy.fmi1 import FMICallException
    s = _slave(fmus[3])
    try:
        vr = s.refs(["q[0]"])
        with pytest.raises(FMICallException):
            s.fmu.doStep(0.0, 2e-3)                          # wrong step size
        assert "must equal the controller's sample period" in s.messages[-1]
        s.fmu.reset()
        with pytest.raises(FMICallException):
            s.fmu.doStep(0.0, 1e-3)                          # before initialization
        assert "illegal call sequence" in s.messages[-1]
        s.fmu.reset()
        with pytest.raises(FMICallException):
            s.set(vr, [float("nan")])                        # NaN input
        assert "not finite" in s.messages[-1]
        s.fmu.reset()
        with pytest.raises(FMICallException):
            s.set(s.refs(["tau[0]"]), [1.0])                 # an output
        assert "cannot be set" in s.messages[-1]
        s.fmu.reset()                                        # the instance recovers
        s.fmu.enterInitializationMode(startTime=0.0)
        s.fmu.exitInitializationMode()
        s.step(0.0, 1e-3)
    finally:
        s.close()


def test_cli_exports_the_fmi3_controller(tmp_path, capsys):
    from fmpy import read_model_description
    from ivdrem.cli.fmu import main_fmu as main
    out = tmp_path / "C3.fmu"
    assert main(["export", "--controller", "--fmi-version", "3", "-o", str(out)]) == 0
    assert read_model_description(str(out)).fmiVersion == "3.0"


def test_fmi3_tunable_gain_after_initialization_acts_as_in_the_fmi2_fmu(fmus):
    """K[0] and gamma (variability="tunable" in the FMI 3.0 modelDescription) set through
    fmi3SetFloat64 between steps change the torque exactly as fmi2SetReal does in the FMI 2.0
    FMU; h (fixed) set after initialization is refused with fmi3Error and a message."""
    from fmpy import read_model_description
    from fmpy.fmi1 import FMICallException
    md = read_model_description(str(fmus[3]))
    var = {v.name: v.variability for v in md.modelVariables}
    assert var["K[0]"] == var["gamma"] == "tunable" and var["h"] == "fixed"
    s3, s2, plain = _slave(fmus[3]), _slave(fmus[2]), _slave(fmus[3])
    try:
        vr_in = s3.refs(["q[0]", "q[1]", "dq[0]", "dq[1]"])
        vr_out = s3.refs(["tau[0]", "tau[1]", "theta_hat[0]", "K[0]", "gamma"])
        vr_gains = s3.refs(["K[0]", "gamma"])
        assert vr_in == s2.refs(["q[0]", "q[1]", "dq[0]", "dq[1]"])
        h = 1e-3
        for k in range(400):
            if k == 200:
                s3.set(vr_gains, [5.0, 3e9])
                s2.set(vr_gains, [5.0, 3e9])
            t = k * h
            for s in (s3, s2, plain):
                s.set(vr_in, [0.3 * np.sin(t), 0.9 + 0.1 * t, 0.3 * np.cos(t), 0.1])
                s.step(t, h)
            a, b = s3.get(vr_out), s2.get(vr_out)
            assert a == b, (k, a, b)                           # bit for bit
        assert a[3:] == [5.0, 3e9]
        untuned = plain.get(vr_out)
        assert max(abs(x - y) for x, y in zip(a[:2], untuned[:2])) > 1e-3   # the gains acted
        with pytest.raises(FMICallException):
            s3.set(s3.refs(["h"]), [2e-3])
        assert "fmi3SetFloat64: parameter h is fixed after initialization" in s3.messages[-1]
        s3.fmu.reset()                                     # out of Error, so close() can
        s3.fmu.enterInitializationMode(startTime=0.0)      # terminate it
        s3.fmu.exitInitializationMode()
    finally:
        for s in (s3, s2, plain):
            s.close()


@pytest.mark.parametrize("version", [2, 3])
def test_fmu_rebuilt_from_its_sources_alone_runs_as_shipped(fmus, version, tmp_path):
    """The files the FMU itself lists (FMI 2.0: modelDescription SourceFiles, FMI 3.0:
    sources/buildDescription.xml) compile from sources/ alone as plain C99 (-pedantic
    -Werror) into a binary that gives the shipped binary's outputs bit for bit."""
    import shutil
    import subprocess
    import zipfile
    from fmpy import read_model_description
    if shutil.which("cc") is None:
        pytest.skip("no C compiler")
    md = read_model_description(str(fmus[version]))
    (config,) = md.buildConfigurations
    files = [f for s in config.sourceFileSets for f in s.sourceFiles]
    assert "fmi_controller_common.c" in files
    root = tmp_path / "fmu"
    zipfile.ZipFile(fmus[version]).extractall(root)
    (binary,) = (root / "binaries").glob("*/*.so")
    src = root / "sources"
    binary.unlink()
    subprocess.run(["cc", "-shared", "-fPIC", "-O2", "-std=c99", "-pedantic", "-Wall", "-Wextra",
                    "-Werror", "-fvisibility=hidden", "-Wl,--no-undefined", "-I", str(src),
                    *[str(src / f) for f in files], "-o", str(binary), "-lm"],
                   check=True, capture_output=True)
    rebuilt = tmp_path / "rebuilt.fmu"
    shutil.make_archive(str(rebuilt.with_suffix("")), "zip", root)
    rebuilt.with_suffix(".zip").rename(rebuilt)

    def run(path):
        s = _slave(path)
        try:
            vr_in = s.refs(["q[0]", "q[1]", "dq[0]", "dq[1]"])
            vr_out = s.refs(["tau[0]", "tau[1]", "theta_hat[0]", "tau_d_hat[1]", "Delta"])
            out = []
            for k in range(300):
                t = k * 1e-3
                s.set(vr_in, [np.sin(t), np.cos(2 * t), 0.3 * t, -0.1])
                s.step(t, 1e-3)
                out.append(s.get(vr_out))
            return np.array(out)
        finally:
            s.close()
    a, b = run(rebuilt), run(fmus[version])
    assert np.array_equal(a, b) and np.abs(a).max() > 0


def test_libcosim_refuses_the_fmi3_fmu_with_its_reason(fmus, plant_fmu):
    """The installed libcosim (0.11.2 in libcosimpy 0.0.6) has no FMI 3.0 loader
    (docs/controller.md); the libcosim loop says so instead of crashing on the null slave.
    When a libcosim that loads FMI 3.0 is installed this fails: then add the libcosim FMI 3
    loop test (agreement as the FMI 2 one)."""
    from ivdrem.controller.fmu_loop import libcosim_closed_loop
    with pytest.raises(RuntimeError, match="Unsupported FMI version"):
        libcosim_closed_loop(fmus[3], plant_fmu, 0.01)
    r = libcosim_closed_loop(fmus[2], plant_fmu, 0.01, every=1)     # FMI 2.0 still loads
    assert r["theta_hat"].shape[0] == 11
