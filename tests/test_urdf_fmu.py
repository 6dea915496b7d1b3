"""The plant FMU of a URDF arm (``ivdrem fmu export --model panda``): its C code (the recursive
Newton-Euler algorithm) against Pinocchio's ``aba`` through fmi2GetDerivatives, at 200 random
states, torques and disturbances per arm, relative error <= 1e-10 (measured about 1e-13);
FMPy's validation of the FMU; a short co-simulation."""
from __future__ import annotations

import ctypes
import warnings

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")
fmpy = pytest.importorskip("fmpy")
from fmpy import extract, read_model_description, simulate_fmu  # noqa: E402
from fmpy.fmi2 import FMU2Model  # noqa: E402
from fmpy.validation import validate_fmu  # noqa: E402

from ivdrem.fmu.export import export_fmu  # noqa: E402
from ivdrem.models import arm  # noqa: E402
from ivdrem.models import urdf as urdf_mod  # noqa: E402


def _available(name):
    try:
        urdf_mod.arm_urdf(name)
        return True
    except ImportError:
        return False


CASES = [pytest.param(a, o, marks=pytest.mark.skipif(not _available(a), reason="arms extra"))
         for a, o in (("panda", {}), ("ur5", {"friction": "viscous+coulomb"}))]


@pytest.mark.parametrize("name, options", CASES)
def test_fmu_derivatives_vs_aba(tmp_path, name, options):
    model = arm(name, **options)
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # no C compiler warning either
        path = export_fmu(model, tmp_path / f"{name}.fmu")
    assert validate_fmu(str(path)) == []
    md = read_model_description(str(path))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    d = extract(str(path), unzipdir=tmp_path / "unz")
    fmu = FMU2Model(guid=md.guid, unzipDirectory=d,
                    modelIdentifier=md.modelExchange.modelIdentifier, instanceName="a")
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    fmu.enterContinuousTimeMode()
    n = model.n
    pm = model.pinocchio_model()
    pd = pm.createData()
    rng = np.random.default_rng(0)
    dx = (ctypes.c_double * (2 * n))()
    worst = 0.0
    th = np.asarray(model.theta_values)
    Fo = np.empty(n)
    for _ in range(200):
        q = rng.uniform(-np.pi, np.pi, n)
        dq = rng.uniform(-2, 2, n)
        tau, tau_d = rng.uniform(-20, 20, n), rng.uniform(-5, 5, n)
        fmu.setContinuousStates((ctypes.c_double * (2 * n))(*q, *dq), 2 * n)
        fmu.setReal([vr[f"tau[{i}]"] for i in range(n)] + [vr[f"tau_d[{i}]"] for i in range(n)],
                    list(tau) + list(tau_d))
        fmu.getDerivatives(dx, 2 * n)
        model.jit_functions.F(dq, th, Fo)    # Pinocchio has no friction: subtract it
        ref = pin.aba(pm, pd, model.pinocchio_configuration(q), dq, tau + tau_d - Fo)
        got = np.array(dx[:])
        assert np.array_equal(got[:n], dq)
        worst = max(worst, np.max(np.abs(got[n:] - ref)) / np.max(np.abs(ref)))
    fmu.terminate()
    fmu.freeInstance()
    print(f"{name}: FMU derivatives vs pin.aba, 200 states: max rel. error {worst:.1e}")
    assert worst <= 1e-10
    # co-simulation runs (RK4 sub-steps) and stays finite
    res = simulate_fmu(str(path), fmi_type="CoSimulation", stop_time=0.2, output_interval=0.01)
    assert np.all(np.isfinite(res["q[0]"]))


@pytest.mark.skipif(not _available("panda"), reason="arms extra")
def test_cli_export_panda(tmp_path, capsys):
    from ivdrem.cli.fmu import main_fmu
    out = tmp_path / "panda.fmu"
    assert main_fmu(["export", "--model", "panda", "-o", str(out)]) == 0
    assert "model panda, n = 7, ntheta = 43" in capsys.readouterr().out
    md = read_model_description(str(out))
    names = [v.name for v in md.modelVariables]
    assert "Izz1R" in names and "tau[6]" in names
    units = {v.name: v.unit for v in md.modelVariables}
    assert units["mx2"] == "kg.m" and units["Izz1R"] == "kg.m2"
