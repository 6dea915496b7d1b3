"""Blocks ivdrem did not write in the compiled engine: python-control's linear blocks, a
user's plain-nlsys plant (compiled by numba, or called back into Python), and the error
of a block that raises."""
import math
import warnings

import numpy as np
import pytest
import control as ct

from ivdrem.diagrams import closed_loop
from ivdrem.models import two_link
from ivdrem.sim import DiagramPlan, simulate, SimulationError
from ivdrem.sim.compiled import BlockError
from ivdrem.sim.foreign import PythonBlockNotice

MODEL = two_link()
THETA = np.array(MODEL.theta_values, dtype=float)
GRAVITY = 9.81
T_RUN = 1.5
TOL = dict(method="rodas5p", rtol=1e-8, atol=1e-10)


def _linear_diagram():
    """r -> K (ss, with D) -> sum (e1 - y) -> G (tf, strictly proper) -> y; r from a
    plain nlsys source with a parameter."""
    g = ct.tf([2.0, 1.0], [1.0, 3.0, 2.0], inputs="e", outputs="y", name="G")
    k = ct.ss([[-1.0]], [[1.0]], [[0.5]], [[2.0]], inputs="r", outputs="e1", name="K")
    sj = ct.summing_junction(inputs=["e1", "-y"], output="e", name="sum")
    gain = ct.ss([], [], [], [[0.25]], inputs="y", outputs="y4", name="gain")

    def source_out(t, x, u, params):
        return np.array([np.sin(params["w"] * t) + 0.5])
    src = ct.nlsys(None, source_out, inputs=0, outputs=["r"], params={"w": 2.0}, name="src")
    # a static nonlinearity with direct feedthrough (found by the probe), compiled by numba
    sat = ct.nlsys(None, saturation_out, inputs=["y"], outputs=["ys"],
                   params={"level": 0.3}, name="sat")
    return ct.interconnect([g, k, sj, gain, src, sat], outputs=["y", "e", "y4", "ys"],
                           check_unused=False, name="linear")


def saturation_out(t, x, u, params):
    return np.array([params.get("level", 1.0) * math.tanh(u[0] / params["level"])])


def test_ss_tf_and_summing_junction_compile_and_equal_the_reference_engine():
    d = _linear_diagram()
    with warnings.catch_warnings():
        warnings.simplefilter("error", PythonBlockNotice)    # everything compiled
        a = simulate(d, T_RUN, progress=False, method="dp45", rtol=1e-10, atol=1e-12)
    b = simulate(d, T_RUN, engine="reference", progress=False, method="dp45", rtol=1e-10,
                 atol=1e-12)
    np.testing.assert_allclose(a.outputs, b.outputs, rtol=0, atol=1e-12)
    # and python-control's own solver agrees to its tolerance (an independent path)
    resp = ct.input_output_response(d, a.time, 0, solve_ivp_kwargs=dict(rtol=1e-10,
                                                                        atol=1e-12))
    np.testing.assert_allclose(a.outputs, resp.outputs, rtol=0, atol=1e-8)


def test_linear_blocks_supply_their_exact_jacobian():
    from ivdrem.sim.simulator import Simulator
    sim = Simulator(_linear_diagram(), method="rodas5p")
    sim._start()
    x = np.array([0.3, -0.2, 0.1])
    J = sim.engine.jacobian(0.4, x, sim.W)
    # closed loop by hand: G = ss(tf) with its own A, B, C; K = ss(-1, 1, 0.5, 2)
    G = ct.ss(ct.tf([2.0, 1.0], [1.0, 3.0, 2.0]))
    Ag, Bg, Cg = (np.asarray(m) for m in (G.A, G.B, G.C))
    A = np.zeros((3, 3))
    A[:2, :2] = Ag - Bg @ Cg
    A[:2, 2:] = Bg * 0.5
    A[2, 2] = -1.0
    np.testing.assert_allclose(J, A, atol=1e-12)
    sat = next(b for b in sim.plan.blocks if b.sys.name == "sat")
    assert sat.spec.runs == "numba" and list(sat.direct_inputs) == [sat.u.start]


def test_a_function_returning_the_wrong_size_is_refused_before_the_run():
    from ivdrem.sim.compiled import CompileError, _param_layout
    bad = ct.nlsys(lambda t, x, u, p: np.zeros(3), None, inputs=0, outputs=["z[0]", "z[1]"],
                   states=2, name="bad")
    plan = DiagramPlan.from_diagram(ct.interconnect([bad], outputs=["z"]))
    with pytest.raises(CompileError, match="'bad': its update function returns 3 values, "
                                           "but the block has 2 states"):
        _param_layout(plan)


# ---- a user's own plant for the 2-link arm: a plain ct.nlsys, its own numpy M, C, g
def user_arm_update(t, x, u, params):
    # states x = [q1, q2, dq1, dq2]; inputs u = [tau (2), tau_d (2)]; params theta (5)
    th = params["theta"]
    c2, s2 = np.cos(x[1]), np.sin(x[1])
    M = np.array([[th[0] + 2 * th[1] * c2, th[2] + th[1] * c2],
                  [th[2] + th[1] * c2, th[2]]])
    C = np.array([[-th[1] * s2 * x[3], -th[1] * s2 * (x[2] + x[3])],
                  [th[1] * s2 * x[2], 0.0]])
    g = np.array([th[3] * GRAVITY * np.cos(x[0] + x[1]) + th[4] * GRAVITY * np.cos(x[0]),
                  th[3] * GRAVITY * np.cos(x[0] + x[1])])
    tau = u[0:2] + u[2:4]
    ddq = np.linalg.solve(M, tau - C @ x[2:4] - g)
    return np.array([x[2], x[3], ddq[0], ddq[1]])


def user_arm_output(t, x, u, params):
    return x.copy()


SETTINGS = {"gravity": GRAVITY}      # a Python dict: numba cannot compile a function using it


def dict_arm_update(t, x, u, params):
    th = params["theta"]
    grav = SETTINGS["gravity"]
    c2, s2 = np.cos(x[1]), np.sin(x[1])
    M = np.array([[th[0] + 2 * th[1] * c2, th[2] + th[1] * c2],
                  [th[2] + th[1] * c2, th[2]]])
    C = np.array([[-th[1] * s2 * x[3], -th[1] * s2 * (x[2] + x[3])],
                  [th[1] * s2 * x[2], 0.0]])
    g = np.array([th[3] * grav * np.cos(x[0] + x[1]) + th[4] * grav * np.cos(x[0]),
                  th[3] * grav * np.cos(x[0] + x[1])])
    ddq = np.linalg.solve(M, u[0:2] + u[2:4] - C @ x[2:4] - g)
    return np.array([x[2], x[3], ddq[0], ddq[1]])


def _user_plant(update):
    return ct.nlsys(update, user_arm_output, inputs=["tau[0]", "tau[1]", "tau_d[0]", "tau_d[1]"],
                    outputs=["q[0]", "q[1]", "dq[0]", "dq[1]"],
                    states=["q[0]", "q[1]", "dq[0]", "dq[1]"], params={"theta": THETA},
                    name="plant")


@pytest.fixture(scope="module")
def ivdrem_loop():
    d = closed_loop("iv-drem", MODEL)
    return d, simulate(d, T_RUN, progress=False, **TOL), DiagramPlan.from_diagram(d).x0


def _q(resp):
    names = list(resp.output_labels)
    return resp.outputs[[names.index("q[0]"), names.index("q[1]")]]


def test_user_plant_as_plain_nlsys_is_compiled_and_equals_the_ivdrem_plant(ivdrem_loop):
    _, ref, x0 = ivdrem_loop
    d = closed_loop("iv-drem", MODEL, replace={"plant": _user_plant(user_arm_update)})
    with warnings.catch_warnings():
        warnings.simplefilter("error", PythonBlockNotice)    # numba compiled it
        resp = simulate(d, T_RUN, x0=x0, progress=False, **TOL)
    assert np.max(np.abs(_q(resp) - _q(ref))) < 1e-9
    assert resp.stats["engine"] == "compiled"


def test_user_plant_numba_cannot_compile_runs_in_python_and_still_matches(ivdrem_loop):
    _, ref, x0 = ivdrem_loop
    d = closed_loop("iv-drem", MODEL, replace={"plant": _user_plant(dict_arm_update)})
    with pytest.warns(PythonBlockNotice, match=r"'plant' \(.*global 'SETTINGS'.*\) run in Python"):
        resp = simulate(d, T_RUN, x0=x0, progress=False, **TOL)
    assert np.max(np.abs(_q(resp) - _q(ref))) < 1e-9


class _Limit:
    """An object numba cannot see: a block using it runs in Python."""
    t_max = 10.0


LIMIT = _Limit()


def numba_raising_update(t, x, u, params):
    if t > params["t_fail"]:
        raise ValueError("joint limit exceeded")
    return np.array([-x[0] + 1.0])


def python_raising_update(t, x, u, params):
    if t > LIMIT.t_max:
        raise KeyError("the user's lookup failed")
    return np.array([-2.0 * x[0] + u[0]])


@pytest.fixture(scope="module")
def raising_diagram():
    """A numba-compiled block and a Python block, each raising after a time of its own;
    one diagram (one compile) for both tests."""
    a = ct.nlsys(numba_raising_update, None, inputs=0, outputs=["a"], states=1,
                 params={"t_fail": 10.0}, name="numba_block")
    b = ct.nlsys(python_raising_update, None, inputs=["a"], outputs=["b"], states=1,
                 name="python_block")
    g = ct.tf([1.0], [1.0, 1.0], inputs="b", outputs="y", name="G")
    return ct.interconnect([a, b, g], outputs=["y"], name="raising")


def test_a_numba_block_that_raises_names_the_block_and_the_time(raising_diagram):
    LIMIT.t_max = 10.0
    with pytest.warns(PythonBlockNotice, match="'python_block'"):
        # the time named: the first evaluation after t_fail, a stage of the step across it
        with pytest.raises(BlockError, match=r"block 'numba_block' raised at t = 0\.[5-7]\d* s: "
                                             r"ValueError: joint limit exceeded") as info:
            simulate(raising_diagram, 1.0, params={"t_fail": 0.5}, progress=False)
    assert isinstance(info.value, SimulationError)
    assert isinstance(info.value.__cause__, ValueError)
    assert 0.5 < info.value.t < 0.75 and info.value.block == "numba_block"
    # the same diagram runs to the end when nothing raises (the bookkeeping is harmless)
    with pytest.warns(PythonBlockNotice):
        resp = simulate(raising_diagram, 1.0, progress=False)
    assert np.all(np.isfinite(resp.outputs))


def test_a_python_block_that_raises_names_the_block_and_chains_its_exception(raising_diagram):
    LIMIT.t_max = 0.5
    try:
        with pytest.warns(PythonBlockNotice):
            with pytest.raises(BlockError, match=r"block 'python_block' \(running in Python\) "
                                                 r"raised at t = 0\.[5-7]\d* s: KeyError") as info:
                simulate(raising_diagram, 1.0, progress=False)
    finally:
        LIMIT.t_max = 10.0
    assert isinstance(info.value.__cause__, KeyError)


def _doubled(a):
    return 2.0 * a


def helper_using_update(t, x, u, params):
    return -_doubled(x) * params.get("k", 3.0) + params["b"]


def test_user_source_reads_params_as_arguments_and_says_why_not_otherwise():
    """What numba is given (no compile here): params["b"] and params.get("k", 3.0) become
    arguments or the default, helpers come along; the reasons for running in Python."""
    from ivdrem.sim.foreign import _user_function_source, _NotCompilable
    src, keys, extra = _user_function_source(helper_using_update, "update", {"b": 1.0})
    assert keys == ["b"] and "3.0" in src and "params" not in src
    assert extra == ["def _doubled(a):\n    return 2.0 * a"]
    ns = {}
    exec("\n\n".join(extra + [src]), ns)          # the rewritten function computes the same
    x = np.array([0.5, -1.0])
    np.testing.assert_array_equal(ns["_user_update"](0.0, x, None, 1.0),
                                  helper_using_update(0.0, x, None, {"b": 1.0}))
    for fn, why in ((lambda t, x, u, p: x, "lambda"), (dict_arm_update, "global 'SETTINGS'"),
                    (python_raising_update, "global 'LIMIT'")):
        with pytest.raises(_NotCompilable, match=why):
            _user_function_source(fn, "update", {"theta": THETA})

    def passes_params_on(t, x, u, params):
        return user_arm_update(t, x, u, params)
    with pytest.raises(_NotCompilable, match="other than as params"):
        _user_function_source(passes_params_on, "update", {"theta": THETA})


def test_the_reference_engine_names_a_raising_block_too(raising_diagram):
    with pytest.raises(BlockError, match=r"block 'numba_block' raised at t = 0\.5\d* s: "
                                         r"ValueError: joint limit exceeded") as info:
        simulate(raising_diagram, 1.0, params={"t_fail": 0.5}, engine="reference",
                 method="rk4", h=0.01, progress=False)
    assert isinstance(info.value.__cause__, ValueError) and info.value.block == "numba_block"
