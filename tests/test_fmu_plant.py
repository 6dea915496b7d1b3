"""The plant FMU imported as a block (ivdrem.fmu.fmu_plant):
its Python (fmpy) path, its declaration, and the closed loop on both engines."""
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



# ----------------------------------------------------------------------------- closed loop
PAPER_Q0 = [0.0, 0.3 * np.pi]       # the Python plant's q(0) in closed_loop (two-link)


@pytest.fixture(scope="module")
def paper_fmu(tmp_path_factory):
    """The two-link plant FMU with the Python plant's q(0) as its start values."""
    return export_fmu(two_link(), tmp_path_factory.mktemp("fmu_loop") / "TwoLink.fmu",
                      q0=PAPER_Q0)


def _q(resp, n=2):
    labels = list(resp.output_labels)
    assert labels[:n] == [f"q[{i}]" for i in range(n)]
    return np.asarray(resp.outputs)[:n]


def test_one_spelling(paper_fmu):
    """The FMU plant is ivdrem.fmu.fmu_plant only (the block library does not re-export a
    block of a later layer, docs/developers.md); importing the block library loads no
    fmpy, and ivdrem.fmu.fmu_plant is the function (no submodule shadows it)."""
    import subprocess
    import sys
    import ivdrem.blocks
    import ivdrem.fmu
    assert ivdrem.fmu.fmu_plant is fmu_plant
    assert not hasattr(ivdrem.blocks, "fmu_plant") and "fmu_plant" not in ivdrem.blocks.__all__
    blk = ivdrem.fmu.fmu_plant(paper_fmu, name="fmu")
    assert isinstance(blk, ct.NonlinearIOSystem) and blk.name == "fmu"
    code = ("import sys, ivdrem.blocks as b; assert 'fmpy' not in sys.modules; "
            "import ivdrem.fmu; f = ivdrem.fmu.fmu_plant; import ivdrem.fmu.plant; "
            "assert f is ivdrem.fmu.fmu_plant is ivdrem.fmu.plant.fmu_plant; print(f.__module__)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.strip() == "ivdrem.fmu.plant"


def test_declaration(paper_fmu):
    from ivdrem.blocks import BlockSpec
    blk = fmu_plant(paper_fmu)
    spec = blk.ivdrem
    assert isinstance(spec, BlockSpec) and spec.kind == "ode"
    assert spec.inputs == [("tau", 2), ("tau_d", 2)]
    assert spec.outputs == [("q", 2), ("dq", 2)] and spec.states == [("q", 2), ("dq", 2)]
    assert spec.direct == () == blk.fmu.direct       # q, dq depend on the states only
    np.testing.assert_array_equal(spec.x0, PAPER_Q0 + [0.0, 0.0])
    # the kernels' parameters are runtime constants, not python-control parameters
    assert dict(blk.params) == {}
    assert set(spec.param_names) == set(spec.constants)


def test_kernels_as_python_equal_the_fmpy_path(paper_fmu):
    """The kernels run as plain Python (calling the compiled helper fmi2_evaluate, as the
    compiled engine's sparsity probe runs them) give bit for bit what the fmpy path gives."""
    from ivdrem.fmu.plant import fmu_plant_output, fmu_plant_update
    blk = fmu_plant(paper_fmu)
    spec = blk.ivdrem
    args = [spec.constants[k] for k in spec.param_names]
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, u = rng.uniform(-2, 2, 4), rng.uniform(-5, 5, 4)
        dx, y = np.empty(4), np.empty(4)
        fmu_plant_update(0.3, x, u, dx, *args)
        fmu_plant_output(0.3, x, u, y, *args)
        np.testing.assert_array_equal(dx, blk._rhs(0.3, x, u))
        np.testing.assert_array_equal(y, blk._out(0.3, x, u))
    # NaN in, NaN out (no FMU call): the step control rejects such a trial step
    dx = np.zeros(4)
    fmu_plant_update(0.3, np.array([np.nan, 0, 0, 0]), np.zeros(4), dx, *args)
    assert np.all(np.isnan(dx)) and np.all(np.isnan(blk._rhs(0.3, [np.nan, 0, 0, 0], np.zeros(4))))


def test_generated_code_holds_no_addresses(paper_fmu):
    """Two instances (other C addresses) generate the same diagram source, which contains
    none of the addresses: the cached module serves every process."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim.compiled import _param_layout, generate_source
    from ivdrem.sim.plan import DiagramPlan
    model = two_link()
    a, b = fmu_plant(paper_fmu), fmu_plant(paper_fmu)
    ta, tb = a.ivdrem.constants["fmi"], b.ivdrem.constants["fmi"]
    assert ta[0] != tb[0]                          # two components
    assert all(float(v).is_integer() and v < 2.0 ** 53 for v in ta)
    srcs, Ps = [], []
    for blk in (a, b):
        plan = DiagramPlan.from_diagram(closed_loop("iv-drem", model, replace={"plant": blk}))
        exprs, P = _param_layout(plan)
        program = generate_source(plan, exprs)
        srcs.append(program.source + repr(program.tables))
        Ps.append(P)
    assert srcs[0] == srcs[1]
    for v in ta:
        assert repr(float(v)) not in srcs[0] and str(int(v)) not in srcs[0]
    assert set(ta) <= set(Ps[0]) and set(tb) <= set(Ps[1])


def test_address_must_fit_a_float64(paper_fmu):
    from ivdrem.fmu.plant import _address_table
    blk = fmu_plant(paper_fmu)
    inst = blk.fmu.instance

    class Far:
        path = inst.path
        component_address = 2 ** 53 + 2
        address = staticmethod(inst.address)
    with pytest.raises(ValueError, match="does not fit a float64"):
        _address_table(Far(), blk.ivdrem.info["report"])


def test_closed_loop_compiled_equals_python_plant(paper_fmu):
    """closed_loop with the FMU plant on the default (compiled) engine and method: the same
    run as the Python plant's loop, q within 1e-7 over 10 s (measured ~1e-11)."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import simulate
    model = two_link()
    fmu_loop = closed_loop("iv-drem", model, replace={"plant": fmu_plant(paper_fmu, name="plant")})
    a = simulate(fmu_loop, 10.0, progress=False)
    b = simulate(closed_loop("iv-drem", model), 10.0, progress=False)
    assert a.stats["steps"] > 100
    err = float(np.max(np.abs(_q(a) - _q(b))))
    print(f"\nFMU plant vs Python plant, compiled, 10 s: max |q - q_ref| = {err:.1e}")
    assert err < 1e-7
    np.testing.assert_array_equal(_q(a)[:, 0], PAPER_Q0)


def test_closed_loop_reference_engine(paper_fmu):
    """The reference engine runs the FMU plant through fmpy (python-control evaluation):
    the same run as the compiled Python-plant loop (short horizon: the path is slow)."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import simulate
    model = two_link()
    fmu_loop = closed_loop("iv-drem", model, replace={"plant": fmu_plant(paper_fmu, name="plant")})
    kw = dict(method="dp45", progress=False)
    a = simulate(fmu_loop, 0.5, engine="reference", **kw)
    b = simulate(closed_loop("iv-drem", model), 0.5, **kw)
    err = float(np.max(np.abs(_q(a) - _q(b))))
    print(f"\nFMU plant (reference engine) vs Python plant, 0.5 s: max |q - q_ref| = {err:.1e}")
    assert err < 1e-7


def test_fmu_error_stops_the_compiled_loop(paper_fmu):
    """theta1 = 0.5 keeps M(q) positive definite at q(0) but not once q2 falls below about
    0.54 rad (det M = 0.0576 - 0.0784 cos^2 q2): the FMU refuses, the compiled run stops
    with the FMU's own message and the time, and the block works again afterwards."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import SimulationError, simulate
    blk = fmu_plant(paper_fmu, name="plant", params={"theta1": 0.5})
    loop = closed_loop("iv-drem", two_link(), replace={"plant": blk})
    with pytest.raises(SimulationError) as info:
        simulate(loop, 10.0, progress=False)
    msg = str(info.value)
    assert "M(q) is singular or not positive definite" in msg, msg
    assert "plant: FMU TwoLink.fmu: fmi2GetDerivatives at t = " in msg, msg
    # the compiled engine names the block, the kernel and the time
    assert "block 'plant' raised at t = " in msg and "(in its update function)" in msg
    # the FMU was reset: the block evaluates again, and a short run completes
    x0 = blk.ivdrem.x0
    assert np.all(np.isfinite(blk._rhs(0.0, x0, np.zeros(4))))
    r = simulate(loop, 0.2, progress=False)
    assert np.all(np.isfinite(r.outputs))


@pytest.mark.parametrize("engine", ["compiled", "reference"])
def test_fmu_error_early_on_both_engines(paper_fmu, engine):
    """Started at q2 = 0.56 rad moving down at 5 rad/s, M(q) (theta1 = 0.5) loses positive
    definiteness within milliseconds: both engines stop with the FMU's message."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import SimulationError, simulate
    blk = fmu_plant(paper_fmu, name="plant", params={"theta1": 0.5}, q0=[0.0, 0.56],
                    dq0=[0.0, -5.0])
    loop = closed_loop("iv-drem", two_link(), q0=[0.0, 0.56], dq0=[0.0, -5.0],
                       replace={"plant": blk})
    stop = r"block 'plant' raised at t = 0[.0-9]* s: FmuEvaluationError"   # both engines
    with pytest.raises(SimulationError, match=stop + r": plant: FMU TwoLink.fmu: "
                       r"fmi2GetDerivatives at t = .*M\(q\) is singular"):
        simulate(loop, 0.1, engine=engine, method="dp45", progress=False)


def test_start_values_are_the_initial_state(fmus, tmp_path):
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim.plan import DiagramPlan
    model = two_link()
    path = export_fmu(model, tmp_path / "start.fmu", q0=[0.1, -0.2], dq0=[0.3, 0.05])
    blk = fmu_plant(path)
    np.testing.assert_array_equal(blk.ivdrem.x0, [0.1, -0.2, 0.3, 0.05])
    plan = DiagramPlan.from_diagram(closed_loop("iv-drem", model, q0=[0.1, -0.2],
                                                dq0=[0.3, 0.05], replace={"plant": blk}))
    entry = next(b for b in plan.blocks if b.sys is blk)
    np.testing.assert_array_equal(plan.x0[entry.x], [0.1, -0.2, 0.3, 0.05])
    # q0 / dq0 given: set on the FMU before initialization, and the block starts there
    blk2 = fmu_plant(path, q0=[1.0, 2.0])
    np.testing.assert_array_equal(blk2.ivdrem.x0, [1.0, 2.0, 0.3, 0.05])
    np.testing.assert_array_equal(blk2.fmu.x0, blk2.ivdrem.x0)


# ----------------------------------------------------------------------------- ModelStructure
_XML = """<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="m" guid="{0}">
  <ModelVariables>
    <ScalarVariable name="u1" valueReference="10" causality="input"><Real start="0"/></ScalarVariable>
    <ScalarVariable name="u2" valueReference="11" causality="input"><Real start="0"/></ScalarVariable>
    <ScalarVariable name="x" valueReference="0" causality="local"><Real/></ScalarVariable>
    <ScalarVariable name="y1" valueReference="1" causality="output"><Real/></ScalarVariable>
    <ScalarVariable name="y2" valueReference="2" causality="output"><Real/></ScalarVariable>
    <ScalarVariable name="y3" valueReference="3" causality="output"><Real/></ScalarVariable>
  </ModelVariables>
  <ModelStructure>
    <Outputs>
      <Unknown index="4" dependencies="1 3"/>
      <Unknown index="5" dependencies=""/>
      <Unknown index="6"/>
    </Outputs>
  </ModelStructure>
</fmiModelDescription>
"""


def test_output_dependencies_from_model_structure():
    from ivdrem.fmu.describe import direct_ports, output_dependencies
    deps = output_dependencies(_XML)
    # indices are 1-based positions in ModelVariables; no attribute: depends on everything
    assert deps == {"y1": frozenset({"u1", "x"}), "y2": frozenset(), "y3": None}
    ports = {"a": ["u1"], "b": ["u2"]}
    assert direct_ports(deps, ["y1"], ports) == ("a",)
    assert direct_ports(deps, ["y2"], ports) == ()
    assert direct_ports(deps, ["y3"], ports) == ("a", "b")
    assert direct_ports(deps, ["y1", "y2"], ports) == ("a",)
    assert direct_ports(deps, ["not listed"], ports) == ("a", "b")
    with pytest.raises(ValueError, match="variable index '9'"):
        output_dependencies(_XML.replace('index="6"', 'index="9"'))
    with pytest.raises(ValueError, match="not valid XML"):
        output_dependencies("<fmiModelDescription")


def test_fmu_declaring_feedthrough_is_direct(fmus, tmp_path):
    """An FMU whose outputs carry no dependencies attribute depends, per FMI 2.0, on all its
    inputs: the block is direct, and the plan then finds the loop algebraic."""
    import re
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import simulate
    from ivdrem.sim.plan import AlgebraicLoopError
    _, path = fmus["two-link"]
    direct = tmp_path / "direct.fmu"
    with zipfile.ZipFile(path) as zi, zipfile.ZipFile(direct, "w") as zo:
        for item in zi.infolist():
            data = zi.read(item.filename)
            if item.filename == "modelDescription.xml":
                xml = data.decode()
                a, b = xml.index("<Outputs>"), xml.index("</Outputs>")
                xml = xml[:a] + re.sub(r' dependencies="[^"]*"', "", xml[a:b]) + xml[b:]
                data = xml.encode()
            zo.writestr(item, data)
    blk = fmu_plant(direct)
    assert blk.ivdrem.direct == ("tau", "tau_d")
    loop = closed_loop("iv-drem", two_link(), q0=[0.0, 0.0], replace={"plant": blk})
    with pytest.raises(AlgebraicLoopError, match="plant"):
        simulate(loop, 0.1, progress=False)


# ----------------------------------------------------------------------------- FmuInstance
@pytest.mark.parametrize("interface", ["model exchange", "co-simulation"])
def test_instance_wrapper(fmus, interface):
    """The one wrapper of the plant block and the co-simulation: start values, an error
    with the FMU's message, reset with the same start values, release with the owner."""
    import os
    from ivdrem.fmu import FmuError, FmuInstance
    _, path = fmus["two-link"]

    class Owner:
        pass
    owner = Owner()
    inst = FmuInstance(path, interface, owner=owner, label="blk")
    d = inst.unzipdir
    assert d and os.path.isdir(d)
    inst.initialize({"q[0]": 0.5})
    vr_q0, vr_tau0 = inst.value_reference("q[0]"), inst.value_reference("tau[0]")
    assert inst.fmu.getReal([vr_q0]) == [0.5]
    assert inst.component_address > 0 and inst.address("fmi2SetReal") > 0
    with pytest.raises(FmuError, match=r"blk: FMU two.fmu: setting tau failed: "
                                       r"fmi2SetReal: the value of tau\[0\] is not finite"):
        inst.call("setting tau", inst.fmu.setReal, [vr_tau0], [float("nan")])
    assert inst.broken and "not finite" in inst.messages[-1]
    inst.recover()                       # fmi2Reset, then the same start values again
    assert not inst.broken and inst.fmu.getReal([vr_q0]) == [0.5]
    del owner
    gc.collect()
    assert inst.closed and not os.path.exists(d)
