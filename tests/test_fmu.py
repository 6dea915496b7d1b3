"""Plant FMU: export, validation, agreement with the Python plant, FMI behaviour.

Measured agreement (printed with ``pytest -s``; asserted bounds in the tests):
* derivatives (fmi2GetDerivatives) vs ``model.functions.forward_dynamics``: max-norm relative
  difference <= 1e-12 at 200+ random states, inputs and parameter vectors per model;
* model exchange (fmpy simulate_fmu, CVode rtol = 1e-12) and co-simulation (RK4 sub-steps)
  vs scipy DOP853 (rtol = atol = 1e-13) on forward_dynamics with piecewise-constant inputs.
"""
from __future__ import annotations

import ctypes
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

fmpy = pytest.importorskip("fmpy")
from fmpy import extract, read_model_description, simulate_fmu  # noqa: E402
from fmpy.fmi1 import FMICallException  # noqa: E402
from fmpy.fmi2 import (FMU2Model, FMU2Slave, fmi2CallbackAllocateMemoryTYPE,  # noqa: E402
                       fmi2CallbackFreeMemoryTYPE, fmi2CallbackFunctions,
                       fmi2CallbackLoggerTYPE)
from fmpy.validation import validate_fmu  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

from ivdrem.fmu import export_fmu  # noqa: E402
from ivdrem.cli.fmu import main_fmu  # noqa: E402
from ivdrem.models import get_model, planar_arm, two_link  # noqa: E402

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc)")


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    """The 2-link FMU (through the CLI) and the planar-3 FMU (through export_fmu)."""
    d = tmp_path_factory.mktemp("fmu")
    two = d / "two_link.fmu"
    assert main_fmu(["export", "--model", "two-link", "-o", str(two)]) == 0
    p3 = export_fmu(planar_arm(3), d / "planar3.fmu")
    return {"two-link": (get_model("two-link"), two), "planar-3": (planar_arm(3), p3)}


@pytest.fixture(params=["two-link", "planar-3"])
def case(request, fmus):
    return fmus[request.param]


class Log:
    """fmi2 callbacks that collect the FMU's log messages.

    The FMU passes complete text (no printf arguments), so no fmpy.logging.addLoggerProxy:
    that proxy keeps the last registered logger in one native global, which dangles once a
    Log is garbage-collected and crashes later FMUs that log (seen as a segfault in CI)."""

    def __init__(self):
        self.messages = []
        cb = fmi2CallbackFunctions()
        cb.logger = fmi2CallbackLoggerTYPE(self._log)
        cb.allocateMemory = fmi2CallbackAllocateMemoryTYPE(fmpy.calloc)
        cb.freeMemory = fmi2CallbackFreeMemoryTYPE(fmpy.free)
        self.callbacks = cb

    def _log(self, env, name, status, category, message):
        self.messages.append((status, category.decode(), message.decode().replace("%%", "%")))

    def text(self):
        return "\n".join(m for _, _, m in self.messages)


class Vars:
    """Value references by name."""

    def __init__(self, md):
        self.md = md
        self.vr = {v.name: v.valueReference for v in md.modelVariables}
        self.n = sum(1 for v in md.modelVariables if v.name.startswith("q["))

    def __call__(self, *names):
        return [self.vr[s] for s in names]

    def vec(self, base):
        return [self.vr[f"{base}[{i}]"] for i in range(self.n)]


def load(path, kind, tmp_path, name="inst", log=None):
    md = read_model_description(str(path))
    d = extract(str(path), unzipdir=tmp_path / f"unz_{name}")
    cls = FMU2Model if kind == "me" else FMU2Slave
    ident = (md.modelExchange if kind == "me" else md.coSimulation).modelIdentifier
    fmu = cls(guid=md.guid, unzipDirectory=d, modelIdentifier=ident, instanceName=name)
    fmu.instantiate(callbacks=log.callbacks if log else None)
    return fmu, Vars(md)


def theta_names(model):
    return list(model.theta_names)


def param_names(model):
    return list(model.theta_names) + [str(s) for s in model.constants]


def fd(model, q, dq, tau, theta):
    out = np.empty(model.n)
    model.functions.forward_dynamics(np.asarray(q, float), np.asarray(dq, float),
                                     np.asarray(tau, float), np.asarray(theta, float), out)
    return out


def random_theta(model, rng, q):
    """theta_values scaled by U(0.8, 1.2), with M(q) positive definite, condition < 1e3."""
    th0 = np.asarray(model.theta_values)
    Mb = np.empty((model.n, model.n))
    while True:
        th = th0 * rng.uniform(0.8, 1.2, th0.size)
        model.functions.M(np.asarray(q, float), th, Mb)
        ev = np.linalg.eigvalsh(Mb)
        if ev[0] > 1e-3 * ev[-1]:
            return th


# ----------------------------------------------------------------------------- contents
def test_cli_export_contents(fmus):
    model, path = fmus["two-link"]
    with zipfile.ZipFile(path) as zf:
        names = set(zf.namelist())
        assert {"modelDescription.xml", "binaries/linux64/ivdrem_two_link.so",
                "sources/fmi2_plant.c", "sources/plant_model.c", "sources/plant_model.h",
                "sources/fmi2Functions.h", "sources/fmi2FunctionTypes.h",
                "sources/fmi2TypesPlatform.h", "documentation/index.html"} <= names
        hdir = Path(fmpy.__file__).parent / "c-code"
        for h in ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h"):
            assert zf.read(f"sources/{h}") == (hdir / h).read_bytes()  # fmpy's copies
        code = zf.read("sources/plant_model.c").decode()
    assert "plant_forward_dynamics_k" in code and "cos(q[1])" in code


def test_cli_errors(tmp_path, capsys):
    assert main_fmu(["export", "--model", "nonsense", "-o", str(tmp_path / "x.fmu")]) == 2
    assert "unknown model" in capsys.readouterr().err
    assert main_fmu(["export", "--q0", "1", "-o", str(tmp_path / "x.fmu")]) == 2
    assert "q0 must have length 2" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main_fmu(["export"])  # -o is required
    assert not (tmp_path / "x.fmu").exists()


def test_export_argument_errors(tmp_path):
    with pytest.raises(ValueError, match="substep"):
        export_fmu(two_link(), tmp_path / "a.fmu", substep=0.0)
    with pytest.raises(ValueError, match="dq0"):
        export_fmu(two_link(), tmp_path / "a.fmu", dq0=[np.nan, 0])


def test_validate_fmpy(case):
    _, path = case
    assert validate_fmu(str(path)) == []


def test_fmutool_check(case):
    exe = shutil.which("fmutool") or shutil.which("fmutool", path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.skip("fmu-manipulation-toolbox is not installed (pip install fmu-manipulation-toolbox)")
    _, path = case
    res = subprocess.run([exe, "-input", str(path), "-check"], capture_output=True, text=True,
                         timeout=120)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out
    assert "ERROR" not in out and "No semantic error" in out, out


def test_model_description(case):
    model, path = case
    md = read_model_description(str(path))
    n = model.n
    assert md.fmiVersion == "2.0" and md.modelExchange and md.coSimulation
    assert md.modelExchange.modelIdentifier == md.coSimulation.modelIdentifier
    assert md.modelExchange.canGetAndSetFMUstate and md.coSimulation.canGetAndSetFMUstate
    assert md.coSimulation.canSerializeFMUstate
    expect = ([(f"q[{i}]", "output", "continuous", "rad") for i in range(n)]
              + [(f"dq[{i}]", "output", "continuous", "rad/s") for i in range(n)]
              + [(f"der(q[{i}])", "local", "continuous", "rad/s") for i in range(n)]
              + [(f"der(dq[{i}])", "local", "continuous", "rad/s2") for i in range(n)]
              + [(f"tau[{i}]", "input", "continuous", "N.m") for i in range(n)]
              + [(f"tau_d[{i}]", "input", "continuous", "N.m") for i in range(n)]
              + [(p, "parameter", "fixed", None) for p in param_names(model)]
              + [("cs_substep", "parameter", "fixed", "s")])
    got = [(v.name, v.causality, v.variability, v.unit) for v in md.modelVariables]
    assert [g[:3] for g in got] == [e[:3] for e in expect]
    for g, e in zip(got, expect):
        if e[3] is not None:
            assert g[3] == e[3], g
    assert dict((g[0], g[3]) for g in got)["g"] == "m/s2"
    assert [v.valueReference for v in md.modelVariables] == list(range(len(expect)))
    starts = {v.name: float(v.start) for v in md.modelVariables if v.start is not None}
    for k, nm in enumerate(param_names(model)):
        expected = (list(model.theta_values) + list(model.constants.values()))[k]
        assert starts[nm] == expected
    # state order = [q, dq] and outputs = the states
    assert [d.variable.name for d in md.derivatives] == \
        [f"der(q[{i}])" for i in range(n)] + [f"der(dq[{i}])" for i in range(n)]
    assert [d.variable.derivative.name for d in md.derivatives] == \
        [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]
    assert [(o.variable.name, [x.name for x in o.dependencies]) for o in md.outputs] == \
        [(s, [s]) for s in [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]]


def _pattern(f, base, knowns, unknowns):
    """{unknown: set of knowns whose perturbation changes it} (finite differences)."""
    y0 = np.asarray(f(base), float)
    dep = {u: set() for u in unknowns}
    for k in knowns:
        pert = dict(base)
        pert[k] = base[k] * 1.01 + 0.013
        y = np.asarray(f(pert), float)
        for u, a, b in zip(unknowns, y0, y):
            if a != b:
                dep[u].add(k)
    return dep


def test_model_structure_matches_code(case, tmp_path):
    """The declared dependencies equal what the binary does (perturbation of every known)."""
    model, path = case
    rng = np.random.default_rng(3)
    fmu, V = load(path, "me", tmp_path)
    md = V.md
    n = model.n
    states = [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]
    inputs = [f"tau[{i}]" for i in range(n)] + [f"tau_d[{i}]" for i in range(n)]
    params = param_names(model) + ["cs_substep"]
    ders = [d.variable.name for d in md.derivatives]
    base = {s: rng.uniform(-1, 1) for s in states + inputs}
    base.update({v.name: float(v.start) for v in md.modelVariables if v.name in params})

    def at_init(values):  # unknowns evaluated in initialization mode from the knowns
        fmu.reset()
        fmu.setReal(V(*values), list(values.values()))
        fmu.enterInitializationMode()
        return fmu.getReal(V(*ders))

    init = _pattern(at_init, base, states + inputs + params, ders)
    declared = {u.variable.name: {x.name for x in u.dependencies} for u in md.initialUnknowns}
    assert declared == init
    # continuous-time mode: knowns are states and inputs
    fmu.reset()
    fmu.setReal(V(*params), [base[p] for p in params])
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    fmu.enterContinuousTimeMode()
    dx = (ctypes.c_double * (2 * n))()

    def ct_mode(values):
        x = [values[s] for s in states]
        fmu.setContinuousStates((ctypes.c_double * (2 * n))(*x), 2 * n)
        fmu.setReal(V(*inputs), [values[s] for s in inputs])
        fmu.getDerivatives(dx, 2 * n)
        return list(dx)

    cont = _pattern(ct_mode, {k: base[k] for k in states + inputs}, states + inputs, ders)
    declared = {u.variable.name: {x.name for x in u.dependencies} for u in md.derivatives}
    assert declared == cont
    fmu.terminate()
    fmu.freeInstance()


# ----------------------------------------------------------------------------- numbers
def test_derivatives_match_python_plant(case, tmp_path):
    """fmi2GetDerivatives == forward_dynamics at 220 random (q, dq, tau, tau_d, theta)."""
    model, path = case
    n = model.n
    rng = np.random.default_rng(0)
    fmu, V = load(path, "me", tmp_path)
    dx = (ctypes.c_double * (2 * n))()
    worst = 0.0
    for _ in range(220):
        q, dq = rng.uniform(-np.pi, np.pi, n), rng.uniform(-3, 3, n)
        tau, tau_d = rng.uniform(-20, 20, n), rng.uniform(-5, 5, n)
        th = random_theta(model, rng, q)
        fmu.reset()
        fmu.setReal(V(*theta_names(model)) + V.vec("q"), list(th) + list(q))
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        fmu.enterContinuousTimeMode()
        fmu.setContinuousStates((ctypes.c_double * (2 * n))(*q, *dq), 2 * n)
        fmu.setReal(V.vec("tau") + V.vec("tau_d"), list(tau) + list(tau_d))
        fmu.getDerivatives(dx, 2 * n)
        ref = fd(model, q, dq, tau + tau_d, th)
        got = np.array(dx[:])
        assert np.array_equal(got[:n], dq)
        worst = max(worst, np.max(np.abs(got[n:] - ref)) / np.max(np.abs(ref)))
    print(f"\n{model.name}: derivatives vs forward_dynamics, 220 samples: max rel. diff {worst:.2e}")
    assert worst <= 1e-12
    fmu.terminate()
    fmu.freeInstance()


@pytest.mark.parametrize("name, other", [
    ("two-link", lambda: two_link(g=3.7)),
    ("planar-3", lambda: planar_arm(3, lengths=[0.8, 1.3, 0.6], g=11.0)),
])
def test_constants_are_parameters(fmus, tmp_path, name, other):
    """Overriding g (and link lengths) on the FMU == the Python plant built with them."""
    _, path = fmus[name]
    model = other()
    n = model.n
    fmu, V = load(path, "me", tmp_path)
    values = {str(s): v for s, v in model.constants.items()}
    values.update(zip(model.theta_names, model.theta_values))  # planar: theta from lengths
    fmu.setReal(V(*values), list(values.values()))
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    fmu.enterContinuousTimeMode()
    rng = np.random.default_rng(5)
    dx = (ctypes.c_double * (2 * n))()
    worst = 0.0
    for _ in range(50):
        q, dq, tau = rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), rng.uniform(-9, 9, n)
        fmu.setContinuousStates((ctypes.c_double * (2 * n))(*q, *dq), 2 * n)
        fmu.setReal(V.vec("tau") + V.vec("tau_d"), list(tau) + [0.0] * n)
        fmu.getDerivatives(dx, 2 * n)
        ref = fd(model, q, dq, tau, model.theta_values)
        worst = max(worst, np.max(np.abs(np.array(dx[n:]) - ref)) / np.max(np.abs(ref)))
    assert worst <= 1e-12
    fmu.terminate()
    fmu.freeInstance()


# piecewise-constant inputs: new (tau, tau_d) every 0.25 s on [0, 2]
T_END, T_SWITCH, H_COMM = 2.0, 0.25, 0.01


def _inputs(n, seed=1):
    rng = np.random.default_rng(seed)
    k = int(round(T_END / T_SWITCH))
    return rng.uniform(-4, 4, (k, 2 * n))


def _reference(model, x0, U, t_out, theta=None):
    """scipy DOP853 (rtol = atol = 1e-13) on forward_dynamics, restarted at every switch."""
    n = model.n
    th = np.asarray(model.theta_values if theta is None else theta, float)

    def f(t, x, u):
        return np.concatenate([x[n:], fd(model, x[:n], x[n:], u[:n] + u[n:], th)])

    out = np.empty((t_out.size, 2 * n))
    x = np.asarray(x0, float)
    for k in range(len(U)):
        a, b = k * T_SWITCH, (k + 1) * T_SWITCH
        sol = solve_ivp(f, (a, b), x, method="DOP853", rtol=1e-13, atol=1e-13, args=(U[k],),
                        dense_output=True)
        sel = (t_out >= a - 1e-12) & (t_out <= b + 1e-12)
        out[sel] = sol.sol(t_out[sel]).T
        x = sol.y[:, -1]
    return out


def _cosim(path, tmp_path, model, U, substep, name="cs", params=None, x0=None):
    n = model.n
    s, V = load(path, "cs", tmp_path, name=name)
    s.setupExperiment(startTime=0.0)
    values = {"cs_substep": substep, **(params or {})}
    if x0 is not None:
        values.update({f"q[{i}]": x0[i] for i in range(n)})
        values.update({f"dq[{i}]": x0[n + i] for i in range(n)})
    s.setReal(V(*values), list(values.values()))
    s.enterInitializationMode()
    s.exitInitializationMode()
    out_vr = V.vec("q") + V.vec("dq")
    Y = [s.getReal(out_vr)]
    steps = int(round(T_END / H_COMM))
    per = int(round(T_SWITCH / H_COMM))
    for j in range(steps):
        s.setReal(V.vec("tau") + V.vec("tau_d"), list(U[j // per]))
        s.doStep(j * H_COMM, H_COMM)
        Y.append(s.getReal(out_vr))
    s.terminate()
    s.freeInstance()
    return np.array(Y)


def test_model_exchange_and_cosimulation_vs_reference(case, tmp_path):
    model, path = case
    n = model.n
    U = _inputs(n)
    t_out = np.round(np.arange(0, T_END + 1e-9, H_COMM), 12)
    x0 = np.zeros(2 * n)
    x0[:n] = np.linspace(0.2, 0.9, n)
    ref = _reference(model, x0, U, t_out)

    # model exchange: fmpy + CVode; input switches are time events of fmpy's Input
    names = [f"tau[{i}]" for i in range(n)] + [f"tau_d[{i}]" for i in range(n)]
    rows = []
    for k in range(len(U)):
        rows += [(k * T_SWITCH, *U[k]), ((k + 1) * T_SWITCH, *U[k])]
    sig = np.array(rows, dtype=[("time", float)] + [(s, float) for s in names])
    res = simulate_fmu(str(path), fmi_type="ModelExchange", solver="CVode",
                       relative_tolerance=1e-12, output_interval=H_COMM, stop_time=T_END,
                       input=sig, start_values={f"q[{i}]": x0[i] for i in range(n)})
    cols = [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]
    Y = np.column_stack([res[c] for c in cols])
    idx = [np.flatnonzero(np.abs(res["time"] - t) < 1e-9)[-1] for t in t_out]
    err_me = np.max(np.abs(Y[idx] - ref))

    # co-simulation: RK4 sub-steps of 2e-3, 1e-3, 1e-4 inside communication steps of 0.01
    err_cs = {h: np.max(np.abs(_cosim(path, tmp_path, model, U, h, name=f"cs{h:g}", x0=x0) - ref))
              for h in (2e-3, 1e-3, 1e-4)}
    print(f"\n{model.name}: max |x - x_ref| over [0, {T_END}] s: ME (CVode rtol 1e-12) {err_me:.1e}; "
          + ", ".join(f"CS RK4 h={h:g} {e:.1e}" for h, e in err_cs.items()))
    assert err_me < 1e-6
    assert err_cs[1e-3] < 1e-5
    assert err_cs[1e-4] < 1e-9
    assert err_cs[2e-3] / err_cs[1e-3] > 10  # fourth order: ~16 for a halved sub-step


def test_parameter_overrides_cosim(fmus, tmp_path):
    """theta, g, start values and cs_substep set before initialization are all used."""
    _, path = fmus["two-link"]
    model = two_link(g=5.0)
    th = np.array([1.1, 0.25, 0.35, 0.5, 1.2])
    x0 = np.array([0.3, -0.2, 0.5, 0.1])
    U = _inputs(2, seed=7)
    params = dict(zip(model.theta_names, th), g=5.0)
    Y = _cosim(path, tmp_path, model, U, 1e-4, params=params, x0=x0)
    ref = _reference(model, x0, U, np.round(np.arange(0, T_END + 1e-9, H_COMM), 12), theta=th)
    assert np.max(np.abs(Y - ref)) < 1e-9


# ----------------------------------------------------------------------------- FMI behaviour
def _run(s, V, t0, steps, u):
    Y = []
    for j in range(steps):
        s.setReal(V.vec("tau") + V.vec("tau_d"), u)
        s.doStep(t0 + j * H_COMM, H_COMM)
        Y.append(s.getReal(V.vec("q") + V.vec("dq")))
    return np.array(Y)


def test_fmu_state_save_restore_serialize(fmus, tmp_path):
    model, path = fmus["two-link"]
    s, V = load(path, "cs", tmp_path)
    s.setupExperiment(startTime=0.0)
    s.enterInitializationMode()
    s.exitInitializationMode()
    u = [1.0, -0.5, 0.2, 0.1]
    _run(s, V, 0.0, 30, u)
    st = s.getFMUstate()
    y1 = _run(s, V, 0.3, 30, u)
    s.setFMUstate(st)  # back to t = 0.3: the next doStep must start at 0.3
    y2 = _run(s, V, 0.3, 30, u)
    assert np.array_equal(y1, y2)
    blob = s.serializeFMUstate(st)
    st2 = s.deSerializeFMUstate(blob)
    s.setFMUstate(st2)
    assert np.array_equal(_run(s, V, 0.3, 30, u), y1)
    s.freeFMUstate(st)
    s.freeFMUstate(st2)
    with pytest.raises(FMICallException):
        s.deSerializeFMUstate(b"\0" * len(blob))
    s.freeInstance()

    # model exchange: restore continuous states and mode
    m, V = load(path, "me", tmp_path, name="me")
    m.enterInitializationMode()
    m.exitInitializationMode()
    m.enterContinuousTimeMode()
    x = (ctypes.c_double * 4)(0.1, 0.2, 0.3, 0.4)
    m.setContinuousStates(x, 4)
    st = m.getFMUstate()
    m.setContinuousStates((ctypes.c_double * 4)(9, 9, 9, 9), 4)
    m.setFMUstate(st)
    got = (ctypes.c_double * 4)()
    m.getContinuousStates(got, 4)
    assert list(got) == [0.1, 0.2, 0.3, 0.4]
    m.freeFMUstate(st)
    m.terminate()
    m.freeInstance()


def test_reset_and_two_instances(fmus, tmp_path):
    model, path = fmus["planar-3"]
    n = model.n
    ua, ub = list(np.linspace(-1, 1, 2 * n)), list(np.linspace(2, 0, 2 * n))
    a, V = load(path, "cs", tmp_path, name="a")
    b, _ = load(path, "cs", tmp_path, name="b")
    th_b = np.asarray(model.theta_values) * 1.1
    for s, extra in ((a, {}), (b, dict(zip(model.theta_names, th_b)))):
        s.setupExperiment(startTime=0.0)
        s.setReal(V(*extra, "q[0]"), list(extra.values()) + [0.4])
        s.enterInitializationMode()
        s.exitInitializationMode()
    ya, yb = [], []
    for j in range(40):  # interleaved
        ya.append(_run(a, V, j * H_COMM, 1, ua)[0])
        yb.append(_run(b, V, j * H_COMM, 1, ub)[0])
    ya, yb = np.array(ya), np.array(yb)
    # reset a, reconfigure as b: must reproduce b's trajectory exactly
    a.reset()
    a.setupExperiment(startTime=0.0)
    a.setReal(V(*model.theta_names, "q[0]"), list(th_b) + [0.4])
    a.enterInitializationMode()
    a.exitInitializationMode()
    assert np.array_equal(_run(a, V, 0.0, 40, ub), yb)
    # and a fresh single instance reproduces a's first trajectory
    b.reset()
    b.setupExperiment(startTime=0.0)
    b.setReal(V("q[0]"), [0.4])
    b.enterInitializationMode()
    b.exitInitializationMode()
    assert np.array_equal(_run(b, V, 0.0, 40, ua), ya)
    assert not np.allclose(ya, yb)
    for s in (a, b):
        s.terminate()
        s.freeInstance()


def _expect_error(log, call, text):
    n0 = len(log.messages)
    with pytest.raises(FMICallException) as e:
        call()
    assert e.value.status == 3  # fmi2Error
    new = "\n".join(m for _, _, m in log.messages[n0:])
    assert text in new, new
    assert all(c == "logStatusError" for _, c, _ in log.messages[n0:])


def test_bad_values_and_wrong_state_give_fmi2Error(fmus, tmp_path):
    model, path = fmus["two-link"]
    log = Log()
    s, V = load(path, "cs", tmp_path, log=log)
    # wrong state: doStep before initialization
    _expect_error(log, lambda: s.doStep(0.0, 0.01), "illegal call sequence")
    s.reset()  # allowed from the Error state
    _expect_error(log, lambda: s.setReal(V("cs_substep"), [0.0]), "cs_substep must be > 0")
    s.reset()
    _expect_error(log, lambda: s.setReal(V("theta1"), [float("inf")]), "not finite")
    s.reset()
    _expect_error(log, lambda: s.setReal(V("der(dq[0])"), [1.0]), "calculated and cannot be set")
    s.reset()
    _expect_error(log, lambda: s.setReal([12345], [1.0]), "unknown value reference")
    s.reset()
    # parameters that make M(q) indefinite: theta2 > sqrt(theta1 theta3) roughly
    s.setReal(V("theta2"), [3.0])
    s.enterInitializationMode()
    _expect_error(log, s.exitInitializationMode, "not positive definite")
    s.reset()
    s.enterInitializationMode()
    s.exitInitializationMode()
    st = s.getFMUstate()
    _expect_error(log, lambda: s.setReal(V("tau[0]"), [float("nan")]), "not finite")
    s.setFMUstate(st)  # recover from the Error state with a saved state
    _expect_error(log, lambda: s.setReal(V("theta1"), [1.0]), "only be set before")
    s.setFMUstate(st)
    _expect_error(log, lambda: s.setReal(V("q[0]"), [1.0]), "only be set before")
    s.setFMUstate(st)
    _expect_error(log, lambda: s.doStep(0.5, 0.01), "differs from the FMU time")
    s.setFMUstate(st)
    s.doStep(0.0, 0.01)  # usable again
    s.freeFMUstate(st)
    s.terminate()
    s.freeInstance()

    m, V = load(path, "me", tmp_path, name="me", log=log)
    dx = (ctypes.c_double * 4)()
    _expect_error(log, lambda: m.getDerivatives(dx, 4), "illegal call sequence")
    m.reset()
    m.enterInitializationMode()
    m.exitInitializationMode()
    m.enterContinuousTimeMode()
    _expect_error(log, lambda: m.setContinuousStates((ctypes.c_double * 4)(0, np.inf, 0, 0), 4),
                  "not finite")
    m.reset()
    m.enterInitializationMode()
    m.exitInitializationMode()
    m.enterContinuousTimeMode()
    _expect_error(log, lambda: m.getDerivatives(dx, 3), "expected 4")
    m.freeInstance()

    # wrong GUID: no instance, a message
    md = read_model_description(str(path))
    d = extract(str(path), unzipdir=tmp_path / "guid")
    bad = FMU2Slave(guid="{00000000-0000-0000-0000-000000000000}", unzipDirectory=d,
                    modelIdentifier=md.coSimulation.modelIdentifier, instanceName="x")
    with pytest.raises(Exception, match="Failed to instantiate"):
        bad.instantiate(callbacks=log.callbacks)
    assert "wrong GUID" in log.text()
    bad.freeLibrary()


# ----------------------------------------------------------------------------- portability
HOST_C = r"""
/* minimal FMI 2.0 co-simulation host: dlopen(RTLD_NOW), a few steps, print the outputs */
#include <dlfcn.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include "fmi2Functions.h"

static void logger(fmi2ComponentEnvironment e, fmi2String name, fmi2Status s, fmi2String cat,
                   fmi2String msg, ...) {
    va_list ap;
    (void)e; (void)name; (void)cat;
    va_start(ap, msg);
    printf("LOG %d ", (int)s);
    vprintf(msg, ap);
    printf("\n");
    va_end(ap);
}

#define LOAD(f) f##TYPE *f; *(void **)(&f) = dlsym(h, #f); \
    if (!f) { printf("MISSING %s\n", #f); return 3; }

int main(int argc, char **argv) {
    void *h;
    int n, steps, i, j;
    fmi2Component c;
    fmi2CallbackFunctions cb = {logger, calloc, free, NULL, NULL};
    fmi2ValueReference vr[64];
    fmi2Real v[64];
    if (argc < 5) return 1;
    n = atoi(argv[3]);
    steps = atoi(argv[4]);
    h = dlopen(argv[1], RTLD_NOW | RTLD_LOCAL);
    if (!h) { printf("DLOPEN_FAILED %s\n", dlerror()); return 2; }
    {
    LOAD(fmi2Instantiate) LOAD(fmi2SetupExperiment) LOAD(fmi2EnterInitializationMode)
    LOAD(fmi2ExitInitializationMode) LOAD(fmi2SetReal) LOAD(fmi2GetReal) LOAD(fmi2DoStep)
    LOAD(fmi2Terminate) LOAD(fmi2FreeInstance)
    if (fmi2GetReal(NULL, vr, 0, v) != fmi2Error) { printf("NULL_NOT_REJECTED\n"); return 4; }
    c = fmi2Instantiate("host", fmi2CoSimulation, argv[2], "", &cb, fmi2False, fmi2False);
    if (!c) { printf("INSTANTIATE_FAILED\n"); return 5; }
    if (fmi2SetupExperiment(c, fmi2False, 0, 0.0, fmi2False, 0) != fmi2OK) return 6;
    for (i = 0; i < 2 * n; i++) { vr[i] = (fmi2ValueReference)(4 * n + i); v[i] = 0.5 * (i + 1); }
    if (fmi2SetReal(c, vr, (size_t)(2 * n), v) != fmi2OK) return 7;
    if (fmi2EnterInitializationMode(c) != fmi2OK || fmi2ExitInitializationMode(c) != fmi2OK) return 8;
    for (j = 0; j < steps; j++)
        if (fmi2DoStep(c, j * 0.01, 0.01, fmi2True) != fmi2OK) { printf("STEP_FAILED\n"); return 9; }
    for (i = 0; i < 2 * n; i++) vr[i] = (fmi2ValueReference)i;
    if (fmi2GetReal(c, vr, (size_t)(2 * n), v) != fmi2OK) return 10;
    for (i = 0; i < 2 * n; i++) printf("%.17g\n", v[i]);
    fmi2Terminate(c);
    fmi2FreeInstance(c);
    }
    dlclose(h);
    return 0;
}
"""


def test_c_host_dlopen_needs_only_libc_libm(fmus, tmp_path):
    model, path = fmus["planar-3"]
    n = model.n
    md = read_model_description(str(path))
    d = Path(extract(str(path), unzipdir=tmp_path / "unz"))
    so = d / "binaries" / "linux64" / f"{md.coSimulation.modelIdentifier}.so"
    (tmp_path / "host.c").write_text(HOST_C)
    exe = tmp_path / "host"
    # no -lm: libm must come in as a dependency of the FMU itself
    subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-D_POSIX_C_SOURCE=200809L",
                    "-I", str(d / "sources"), str(tmp_path / "host.c"), "-o", str(exe), "-ldl"],
                   check=True, capture_output=True)
    res = subprocess.run([str(exe), str(so), md.guid, str(n), "50"], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    values = np.array([float(x) for x in res.stdout.split("\n") if x and not x.startswith("LOG")])
    # the same run through fmpy: identical numbers
    s, V = load(path, "cs", tmp_path, name="py")
    s.setupExperiment(startTime=0.0)
    s.setReal(V.vec("tau") + V.vec("tau_d"), [0.5 * (i + 1) for i in range(2 * n)])
    s.enterInitializationMode()
    s.exitInitializationMode()
    for j in range(50):
        s.doStep(j * 0.01, 0.01)
    assert np.array_equal(values, np.array(s.getReal(V.vec("q") + V.vec("dq"))))
    s.terminate()
    s.freeInstance()
    if shutil.which("readelf"):
        dyn = subprocess.run(["readelf", "-d", str(so)], capture_output=True, text=True).stdout
        needed = {line.split("[")[1].split("]")[0] for line in dyn.splitlines() if "(NEEDED)" in line}
        assert needed <= {"libc.so.6", "libm.so.6"}, needed
        syms = subprocess.run(["readelf", "--dyn-syms", "-W", str(so)], capture_output=True,
                              text=True).stdout
        exported = {ln.split()[-1] for ln in syms.splitlines()
                    if " GLOBAL " in ln and " DEFAULT " in ln and " UND " not in ln}
        assert exported and all(e.startswith("fmi2") for e in exported), exported


@pytest.mark.skipif(shutil.which("cmake") is None, reason="fmpy compile needs cmake")
def test_fmpy_compile_rebuilds_from_sources(fmus, tmp_path):
    """sources/ is complete: `fmpy compile` (CMake, -Wall -Wextra -Wpedantic -Werror) rebuilds it."""
    model, path = fmus["two-link"]
    src_only = tmp_path / "src_only.fmu"
    with zipfile.ZipFile(path) as zi, zipfile.ZipFile(src_only, "w") as zo:
        for item in zi.infolist():
            if not item.filename.startswith("binaries/"):
                zo.writestr(item, zi.read(item.filename))
    res = subprocess.run([sys.executable, "-m", "fmpy", "compile", "--all-warnings",
                          "--warning-as-error", str(src_only)], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    U = _inputs(2, seed=3)
    a = _cosim(path, tmp_path, model, U, 1e-3, name="orig")
    b = _cosim(src_only, tmp_path, model, U, 1e-3, name="rebuilt")
    assert np.max(np.abs(a - b)) <= 1e-12 * np.max(np.abs(a))


@pytest.mark.parametrize("make", [lambda: planar_arm(1),
                                  lambda: planar_arm(2, friction=True, parameters="full")],
                         ids=["planar-1", "planar-2-friction-full"])
def test_other_models(make, tmp_path):
    """Edge cases of the code generation: n = 1 (constant M), friction F(dq), full parameters."""
    model = make()
    n = model.n
    path = export_fmu(model, tmp_path / "m.fmu", q0=np.full(n, 0.1))
    assert validate_fmu(str(path)) == []
    fmu, V = load(path, "me", tmp_path)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    fmu.enterContinuousTimeMode()
    rng = np.random.default_rng(2)
    dx = (ctypes.c_double * (2 * n))()
    for _ in range(30):
        q, dq, tau = rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), rng.uniform(-9, 9, n)
        fmu.setContinuousStates((ctypes.c_double * (2 * n))(*q, *dq), 2 * n)
        fmu.setReal(V.vec("tau"), list(tau))
        fmu.getDerivatives(dx, 2 * n)
        ref = fd(model, q, dq, tau, model.theta_values)
        assert np.max(np.abs(np.array(dx[n:]) - ref)) <= 1e-12 * np.max(np.abs(ref))
    fmu.terminate()
    fmu.freeInstance()
