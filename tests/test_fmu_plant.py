"""The plant FMU imported as a python-control block (ivdrem.blocks.fmu_plant)."""
from __future__ import annotations

import gc
import shutil
import zipfile

import control as ct
import numpy as np
import pytest
from scipy.integrate import solve_ivp

pytest.importorskip("fmpy")

from ivdrem.fmu import fmu_plant  # noqa: E402
from ivdrem.fmu import export_fmu  # noqa: E402
from ivdrem.models import planar_arm, two_link  # noqa: E402

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc)")


@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    d = tmp_path_factory.mktemp("fmu_plant")
    return {"two-link": (two_link(), export_fmu(two_link(), d / "two.fmu")),
            "planar-3": (planar_arm(3), export_fmu(planar_arm(3), d / "p3.fmu"))}


def fd(model, x, u, theta=None):
    n = model.n
    out = np.empty(n)
    th = model.theta_values if theta is None else theta
    model.functions.forward_dynamics(x[:n], x[n:], u[:n] + u[n:], np.asarray(th, float), out)
    return np.concatenate([x[n:], out])


@pytest.mark.parametrize("name", ["two-link", "planar-3"])
def test_signal_names_and_derivatives(fmus, name):
    model, path = fmus[name]
    n = model.n
    sys = fmu_plant(path)
    assert sys.name == "plant"
    assert sys.input_labels == [f"tau[{i}]" for i in range(n)] + [f"tau_d[{i}]" for i in range(n)]
    assert sys.output_labels == [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]
    assert sys.state_labels == [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]
    try:  # the Python plant block, if present, has exactly the same names
        from ivdrem.blocks.plant import plant
    except ImportError:  # pragma: no cover
        pass
    else:
        ref = plant(model)
        assert (sys.input_labels, sys.output_labels, sys.state_labels) == \
            (ref.input_labels, ref.output_labels, ref.state_labels)
    rng = np.random.default_rng(11)
    worst = 0.0
    for _ in range(100):
        x = rng.uniform(-3, 3, 2 * n)
        u = rng.uniform(-10, 10, 2 * n)
        dx = sys._rhs(0.0, x, u)
        ref = fd(model, x, u)
        worst = max(worst, np.max(np.abs(dx - ref)) / np.max(np.abs(ref)))
        assert np.array_equal(sys._out(0.0, x, u), x)
    assert worst <= 1e-12


def test_simulation_matches_python_plant(fmus):
    model, path = fmus["two-link"]
    q0 = [0.0, 0.3 * np.pi]
    sys = fmu_plant(path, name="fmu", q0=q0)
    np.testing.assert_array_equal(sys.fmu.x0, [0.0, 0.3 * np.pi, 0.0, 0.0])

    def u_of(t):
        return np.array([np.sin(2 * t), np.cos(t), 0.5 * np.sin(0.5 * np.pi * t), 0.0])

    # the same integrator on the block's right-hand side and on the Python plant's
    kw = dict(method="DOP853", rtol=1e-13, atol=1e-13)
    a = solve_ivp(lambda t, x: sys._rhs(t, x, u_of(t)), (0, 2), sys.fmu.x0, **kw)
    b = solve_ivp(lambda t, x: fd(model, x, u_of(t)), (0, 2), sys.fmu.x0, **kw)
    err = np.max(np.abs(a.y[:, -1] - b.y[:, -1]))
    print(f"\nfmu_plant vs Python plant, 2 s, DOP853 1e-13: |x(2) - x_ref(2)| = {err:.1e}")
    assert err < 1e-11

    # through python-control: its linear input interpolation has kinks at every sample, so
    # the adaptive steps of the two runs differ and they agree to the solver tolerance only
    T = np.linspace(0.0, 2.0, 201)
    U = np.array([u_of(t) for t in T]).T
    ctkw = dict(solve_ivp_method="DOP853", solve_ivp_kwargs=dict(rtol=1e-11, atol=1e-11))
    r = ct.input_output_response(sys, T, U, X0=sys.fmu.x0, **ctkw)
    ref = ct.nlsys(lambda t, x, u, p: fd(model, x, u), lambda t, x, u, p: x,
                   inputs=4, outputs=4, states=4, name="ref")
    r0 = ct.input_output_response(ref, T, U, X0=sys.fmu.x0, **ctkw)
    assert np.max(np.abs(r.outputs - r0.outputs)) < 5e-6


def test_parameters_and_recovery(fmus):
    model, path = fmus["two-link"]
    th = np.array([1.2, 0.3, 0.3, 0.45, 1.3])
    sys = fmu_plant(path, params={"theta": th, "g": 9.0}, dq0=[0.1, -0.1])
    assert sys.fmu.parameters["theta2"] == 0.3 and sys.fmu.parameters["g"] == 9.0
    m9 = two_link(g=9.0)
    x, u = np.array([0.1, 0.2, 0.3, -0.4]), np.array([1.0, 2.0, 0.5, -0.5])
    np.testing.assert_allclose(sys._rhs(0.0, x, u), fd(m9, x, u, th), rtol=1e-13, atol=0)
    # an FMU error (non-finite accelerations) is reported with the FMU's message ...
    with pytest.raises(RuntimeError, match="not finite"):
        sys._rhs(0.0, np.array([0.0, 0.0, 1e300, 1e300]), u)
    # ... and the block recovers on the next call
    np.testing.assert_allclose(sys._rhs(0.0, x, u), fd(m9, x, u, th), rtol=1e-13, atol=0)
    # parameters that make M(q0) indefinite fail at construction with the reason
    with pytest.raises(RuntimeError, match="positive definite"):
        fmu_plant(path, params={"theta2": 3.0})
    with pytest.raises(ValueError, match="unknown FMU parameter 'mass'"):
        fmu_plant(path, params={"mass": 1.0})
    with pytest.raises(ValueError, match="q0 must have length 2"):
        fmu_plant(path, q0=[1.0, 2.0, 3.0])


def test_wrong_guid(fmus, tmp_path):
    _, path = fmus["two-link"]
    bad = tmp_path / "bad_guid.fmu"
    with zipfile.ZipFile(path) as zi, zipfile.ZipFile(bad, "w") as zo:
        for item in zi.infolist():
            data = zi.read(item.filename)
            if item.filename == "modelDescription.xml":
                data = data.replace(b'guid="{', b'guid="{0')
            zo.writestr(item, data)
    with pytest.raises(ValueError, match="bad_guid.fmu: fmi2Instantiate failed.*wrong GUID"):
        fmu_plant(bad)


def test_missing_or_foreign_files(tmp_path):
    missing = tmp_path / "nope.fmu"
    with pytest.raises(FileNotFoundError, match="nope.fmu"):
        fmu_plant(missing)
    text = tmp_path / "text.fmu"
    text.write_text("not a zip")
    with pytest.raises(ValueError, match="text.fmu.*not an FMU"):
        fmu_plant(text)
    empty = tmp_path / "empty.fmu"
    with zipfile.ZipFile(empty, "w") as zf:
        zf.writestr("readme.txt", "hello")
    with pytest.raises(ValueError, match="empty.fmu.*no modelDescription.xml"):
        fmu_plant(empty)
    broken = tmp_path / "broken.fmu"
    with zipfile.ZipFile(broken, "w") as zf:
        zf.writestr("modelDescription.xml", "<nonsense/>")
    with pytest.raises(ValueError, match="broken.fmu"):
        fmu_plant(broken)


def test_cleanup(fmus):
    import os
    _, path = fmus["two-link"]
    sys = fmu_plant(path)
    d = sys.fmu.unzipdir
    assert d and os.path.isdir(d)
    del sys
    gc.collect()
    assert not os.path.exists(d)


def test_freed_wrappers_leave_fmpy_logging_intact(fmus, tmp_path):
    """Regression (a segfault seen in CI): fmpy's native logger proxy keeps the last logger
    registered with addLoggerProxy in one global; wrappers that registered their own
    short-lived Python logger left it dangling, and the next FMU that logged an error
    through fmpy's default callbacks crashed the process.  Run that sequence in a
    subprocess: create and free an fmu_plant, then make a default-callback FMU log."""
    import subprocess
    import sys
    import textwrap
    _, path = fmus["two-link"]
    script = textwrap.dedent(f"""
        import gc
        from fmpy import read_model_description, extract
        from fmpy.fmi2 import FMU2Slave
        from fmpy.fmi1 import FMICallException
        from ivdrem.fmu import fmu_plant
        for _ in range(3):
            blk = fmu_plant({str(path)!r})
            del blk
            gc.collect()
        md = read_model_description({str(path)!r})
        d = extract({str(path)!r}, unzipdir={str(tmp_path / 'unz')!r})
        s = FMU2Slave(guid=md.guid, unzipDirectory=d,
                      modelIdentifier=md.coSimulation.modelIdentifier, instanceName="x")
        s.instantiate()
        s.setupExperiment(startTime=0.0)
        s.enterInitializationMode()
        s.exitInitializationMode()
        for _ in range(50):
            try:
                s.deSerializeFMUstate(b"\\0" * 64)     # an error, logged by the FMU
            except FMICallException:
                pass
        print("survived")
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    assert "survived" in p.stdout
    assert "not a serialized state" in p.stdout     # fmpy printed the FMU's whole message
