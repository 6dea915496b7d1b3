"""simulate() takes ct.input_output_response's calling convention and gives its answer.

timepts (an end time or an array of times), inputs (a constant or an array over timepts,
linearly interpolated as python-control does), initial_state (a full vector, None, or one
entry per subsystem), params and t_eval; the response fills inputs and params.  Checked
against ct.input_output_response itself (scipy's solve_ivp at tight tolerances) on a loop
of linear and nonlinear blocks without delays, on both engines.
"""
from __future__ import annotations

import numpy as np
import pytest
import control as ct

from ivdrem.blocks import BlockSpec, make_block
from ivdrem.sim import simulate, Simulator
from ivdrem.sim.simulator import input_kinks, interpolate_inputs


# ----------------------------------------------------------------------------- blocks
def lti_update(t, x, u, dx, A, B, C, D):
    """Linear block dx/dt = A x + B u.

    states x[n]; inputs u[m]; outputs y = C x + D u; params A (n x n), B (n x m),
    C (p x n), D (p x m)."""
    for i in range(x.shape[0]):
        s = 0.0
        for j in range(x.shape[0]):
            s += A[i, j] * x[j]
        for j in range(u.shape[0]):
            s += B[i, j] * u[j]
        dx[i] = s


def lti_output(t, x, u, y, A, B, C, D):
    for i in range(y.shape[0]):
        s = 0.0
        for j in range(x.shape[0]):
            s += C[i, j] * x[j]
        for j in range(u.shape[0]):
            s += D[i, j] * u[j]
        y[i] = s


def lti_output_strict(t, x, u, y, A, B, C, D):
    """y = C x: a strictly proper block (D = 0, no direct feedthrough)."""
    for i in range(y.shape[0]):
        s = 0.0
        for j in range(x.shape[0]):
            s += C[i, j] * x[j]
        y[i] = s


def pendulum_update(t, x, u, dx, g_over_l, damping, gain):
    """Damped pendulum driven by a torque.

    states theta, omega; inputs tau (control), d (disturbance); outputs theta, omega;
    params g_over_l (1/s^2), damping (1/s), gain (1/(kg m^2))."""
    dx[0] = x[1]
    dx[1] = -g_over_l * np.sin(x[0]) - damping * x[1] + gain * (u[0] + u[1])


def pendulum_output(t, x, u, y, g_over_l, damping, gain):
    y[0] = x[0]
    y[1] = x[1]


def lti_block(name, A, B, C, D, x0=None):
    A, B, C, D = (np.atleast_2d(np.asarray(M, float)) for M in (A, B, C, D))
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    spec = BlockSpec(name, inputs=[("u", m)], outputs=[("y", p)], states=[("x", n)],
                     x0=np.zeros(n) if x0 is None else np.asarray(x0, float),
                     param_names=tuple(f"{name}_{M}" for M in "ABCD"),
                     output=lti_output if np.any(D) else lti_output_strict,
                     update=lti_update, direct=("u",) if np.any(D) else ())
    # parameter names per block: python-control merges a diagram's params into one dict
    return make_block(spec, dict(zip(spec.param_names, (A, B, C, D))))


def pendulum_block(x0=(0.3, 0.0)):
    spec = BlockSpec("pendulum", inputs=[("tau", 1), ("d", 1)],
                     outputs=[("theta", 1), ("omega", 1)], states=[("theta", 1), ("omega", 1)],
                     x0=np.asarray(x0, float), param_names=("g_over_l", "damping", "gain"),
                     output=pendulum_output, update=pendulum_update)
    return make_block(spec, {"g_over_l": 9.81, "damping": 0.4, "gain": 2.0})


def pendulum_loop():
    """r -> 2nd-order prefilter -> PI-D controller (direct feedthrough) -> pendulum (sin),
    with a disturbance d on the torque.  Inputs r, d; outputs theta, omega, tau, r_f."""
    wn = 4.0
    prefilter = lti_block("prefilter", [[0, 1], [-wn ** 2, -1.2 * wn]], [[0], [wn ** 2]],
                          [[1, 0]], [[0]])
    kp, ki, kd = 12.0, 6.0, 3.0
    ctrl = lti_block("ctrl", [[0]], [[1, -1, 0]], [[ki]], [[kp, -kp, -kd]])
    pend = pendulum_block()
    # a 2-state ss block would do for the prefilter; ivdrem's compiled engine needs kernels
    return ct.interconnect(
        [prefilter, ctrl, pend], name="pendulum_loop",
        connections=[["ctrl.u[0]", "prefilter.y[0]"], ["ctrl.u[1]", "pendulum.theta[0]"],
                     ["ctrl.u[2]", "pendulum.omega[0]"], ["pendulum.tau[0]", "ctrl.y[0]"]],
        inplist=["prefilter.u[0]", "pendulum.d[0]"], inputs=["r", "d"],
        outlist=["pendulum.theta[0]", "pendulum.omega[0]", "ctrl.y[0]", "prefilter.y[0]"],
        outputs=["theta", "omega", "tau", "r_f"])


def input_series(T):
    """A reference with corners and a disturbance sampled from a sine: the interpolant
    has a kink at (nearly) every point of T."""
    r = np.where(T < 1.5, 0.0, np.where(T < 3.0, 0.8, -0.4)) + 0.2 * np.abs(T - 2.0)
    d = 0.5 * np.sin(2.3 * T)
    return np.vstack([r, d])


# tight tolerances on both sides: the comparison is at the level of the solvers' errors
# The inputs have a kink at every sample and solve_ivp does not stop at kinks: DOP853 steps
# across them left the reference 3.1e-9 off with scipy 1.17 (against Radau and ivdrem's
# runs, which land on the kinks); capped at 5 ms it agrees with Radau to 2e-12.
IVP = dict(method="DOP853", rtol=1e-13, atol=1e-14, max_step=0.005)
TOL = dict(rtol=1e-10, atol=1e-12)


@pytest.fixture(scope="module")
def loop():
    return pendulum_loop()


@pytest.fixture(scope="module")
def case(loop):
    """The python-control answer: timepts from 0.5 s, time-varying inputs, an initial
    state and a parameter override."""
    T = np.linspace(0.5, 5.0, 46)
    U = input_series(T)
    X0 = np.array([0.1, -0.2, 0.05, 0.6, 0.4])     # prefilter (2), ctrl (1), pendulum (2)
    params = {"g_over_l": 7.5}
    ref = ct.input_output_response(loop, T, U, X0, params=params, return_states=True,
                                   solve_ivp_kwargs=IVP)
    return T, U, X0, params, ref


def _err(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


# ------------------------------------------------------------- equals input_output_response
@pytest.mark.parametrize("engine, method", [("reference", "dp45"), ("compiled", "dp45"),
                                            ("compiled", "rodas5p")])
def test_equals_input_output_response(loop, case, engine, method):
    T, U, X0, params, ref = case
    r = simulate(loop, T, U, X0, params, engine=engine, method=method, progress=False, **TOL)
    assert np.array_equal(r.time, T)
    assert list(r.output_labels) == list(ref.output_labels)
    assert list(r.input_labels) == ["r", "d"]
    err = _err(r.outputs, ref.outputs)
    assert err < 2e-9, err                            # solver tolerance (|y| ~ 1)
    assert _err(r.states, ref.states) < 2e-9
    # the run is not trivially close: the inputs and the override move it far
    assert _err(ref.outputs[0], ct.input_output_response(
        loop, T, 0, X0, params=params, solve_ivp_kwargs=IVP).outputs[0]) > 0.1
    # response fields: the inputs at the output times, the params of the run
    assert np.allclose(r.inputs, ref.inputs, rtol=0, atol=1e-15)
    assert r.params == params
    assert r.stats["engine"] == engine


def test_t_eval_and_end_time_conventions(loop, case):
    """t_eval picks the output times inside [timepts[0], timepts[-1]]; a number timepts
    with constant inputs is the run from 0 (today's convention) = an array from 0."""
    T, U, X0, params, ref_T = case
    te = np.linspace(0.7, 4.9, 15)
    ref = ct.input_output_response(loop, T, U, X0, params=params, t_eval=te,
                                   solve_ivp_kwargs=IVP)
    r = simulate(loop, T, U, X0, params, t_eval=te, method="dp45", progress=False, **TOL)
    assert np.array_equal(r.time, te)
    assert _err(r.outputs, ref.outputs) < 2e-9
    assert np.allclose(r.inputs, ref.inputs, rtol=0, atol=1e-15)
    # constant inputs: a vector over the inputs, or u= (the older name) with t_end=
    T2 = np.linspace(0.0, 2.0, 5)
    ref2 = ct.input_output_response(loop, T2, [0.5, -0.1], X0, solve_ivp_kwargs=IVP)
    a = simulate(loop, 2.0, [0.5, -0.1], X0, dt_out=0.5, method="dp45", progress=False,
                 **TOL)
    b = simulate(loop, t_end=2.0, u=[0.5, -0.1], x0=X0, dt_out=0.5, method="dp45",
                 progress=False, **TOL)
    assert np.array_equal(a.time, T2) and np.array_equal(a.outputs, b.outputs)
    assert _err(a.outputs, ref2.outputs) < 2e-9
    assert np.array_equal(a.inputs, np.tile([[0.5], [-0.1]], (1, 5)))
    assert a.params == {}


def test_initial_state_forms(loop):
    """None: the blocks' own initial states; one entry per subsystem (None = own);
    python-control's list of parts; a number."""
    own = np.r_[np.zeros(3), 0.3, 0.0]       # prefilter, ctrl at 0; pendulum (0.3, 0)
    kw = dict(engine="reference", method="rk4", h=0.01, dt_out=0.05, progress=False)
    base = simulate(loop, 0.1, 0, None, **kw)
    assert np.array_equal(base.states[:, 0], own)
    full = simulate(loop, 0.1, 0, own, **kw)
    assert np.array_equal(base.outputs, full.outputs)
    per = simulate(loop, 0.1, 0, [None, [0.2], None], **kw)
    assert np.array_equal(per.states[:, 0], [0, 0, 0.2, 0.3, 0.0])
    parts = simulate(loop, 0.1, 0, [[0, 0], 0.2, [0.3, 0.0]], **kw)
    assert np.array_equal(parts.outputs, per.outputs)
    zero = simulate(loop, 0.1, 0, 0.0, **kw)
    assert np.array_equal(zero.states[:, 0], np.zeros(5))


def test_plain_python_control_blocks_reference_engine():
    """ct.ss, ct.tf, ct.nlsys and a summing junction (no ivdrem declarations) on the
    reference engine equal input_output_response."""
    lowpass = ct.ss([[0, 1], [-9, -3]], [[0], [9]], [[1, 0]], [[0]], name="lowpass",
                    inputs="r", outputs="rf")
    lag = ct.tf([2], [0.5, 1], name="lag", inputs="rf", outputs="rl")

    def pend_rhs(t, x, u, params):
        return [x[1], -params.get("w2", 9.81) * np.sin(x[0]) - 0.3 * x[1] + u[0]]
    pend = ct.nlsys(pend_rhs, lambda t, x, u, params: x, inputs="tau", outputs=["th", "om"],
                    states=2, name="pend", params={"w2": 9.81})
    total = ct.summing_junction(["rl", "d"], "tau", name="sum")
    diagram = ct.interconnect([lowpass, lag, pend, total], inplist=["r", "d"],
                              outlist=["th", "om", "rl"], name="plain")
    T = np.linspace(0.0, 4.0, 41)
    U = np.vstack([np.where(T < 1.0, 0.0, 1.0), 0.4 * np.cos(3.0 * T)])
    X0 = [0.1, 0.0, 0.2, 0.5, -0.2]
    ref = ct.input_output_response(diagram, T, U, X0, params={"w2": 5.0},
                                   solve_ivp_kwargs=IVP, return_states=True)
    r = simulate(diagram, T, U, X0, {"w2": 5.0}, engine="reference", method="dp45",
                 progress=False, **TOL)
    assert _err(r.outputs, ref.outputs) < 2e-9
    assert _err(r.states, ref.states) < 2e-9
    assert np.allclose(r.inputs, ref.inputs, rtol=0, atol=1e-15)


# ----------------------------------------------------------------- the input interpolant
def _passthrough(t, x, u, params):
    return u


def test_interpolant_is_python_controls():
    """interpolate_inputs and the stepper's external inputs (what both engines evaluate at
    every stage, read here through a static passthrough block) = python-control's own
    interpolant, read off the same passthrough, at the nodes, between them and beyond the
    ends (linear extrapolation)."""
    rng = np.random.default_rng(1)
    T = np.cumsum(rng.uniform(0.05, 0.3, 12))
    U = rng.normal(size=(2, T.size))
    t = np.r_[T, rng.uniform(T[0] - 0.5, T[-1] + 0.5, 40)]
    passthrough = ct.nlsys(None, _passthrough, inputs=2, outputs=2, name="pass")
    expected = ct.input_output_response(passthrough, T, U, t_eval=t).outputs
    assert np.array_equal(interpolate_inputs(T, U, t), expected)
    loop = ct.interconnect([passthrough], inputs=passthrough.input_labels,
                           outputs=passthrough.output_labels, name="pass_loop")
    for engine in ("compiled", "reference"):
        s = Simulator(loop, engine=engine)
        s.set_inputs(U, T)
        got = np.zeros((t.size, 2))
        for i, ti in enumerate(t):
            s.engine.record(float(ti), s.x, s.W, got[i])
        assert np.array_equal(got.T, expected), engine
        s.set_inputs(np.array([1.5, -2.0]))       # no table: held as they are
        row = np.zeros(2)
        s.engine.record(3.0, s.x, s.W, row)
        assert list(row) == [1.5, -2.0]
        s.close()


def test_kinks_where_the_slope_changes():
    T = np.linspace(0.0, 1.0, 11)
    ramp = np.vstack([3.0 * T + 1.0, -0.7 * T])         # straight lines: no kink
    assert input_kinks(T, ramp).size == 0
    tri = np.vstack([np.abs(T - 0.3), 0 * T])           # one corner at 0.3
    assert np.allclose(input_kinks(T, tri), [0.3])
    assert input_kinks(T[:2], ramp[:, :2]).size == 0


def test_steps_end_at_the_kinks(loop):
    """An adaptive run cuts its steps at the kinks of the input interpolant: the loose
    default-tolerance run is as accurate across a corner as away from one."""
    T = np.array([0.0, 1.0, 1.0 + 1e-3, 3.0])
    U = np.vstack([[0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 0.0]])   # a fast ramp up
    sim = Simulator(loop, method="dp45", engine="reference", rtol=1e-6, atol=1e-9)
    sim.set_inputs(U, T)
    assert np.array_equal(sim._kinks, [1.0, 1.0 + 1e-3])
    stops = []
    orig = sim._chunk

    def chunk(t_stop, *a):
        stops.append(t_stop)
        return orig(t_stop, *a)
    sim._chunk = chunk
    sim.advance(3.0)
    sim.close()
    assert stops == [1.0, 1.0 + 1e-3, 3.0]
    ref = ct.input_output_response(loop, T, U, sim.plan.x0, solve_ivp_kwargs=IVP,
                                   t_eval=[3.0])
    assert _err(sim.outputs_at_current(), ref.outputs[:, -1]) < 1e-5


def test_cost_guard_counts_given_output_times(loop):
    """With output times given as an array the guard prices their number (not a dt_out
    grid), and refuses before any work."""
    from ivdrem.sim.guards import CostLimitError, estimate_cost, check_diagram_cost
    est = estimate_cost(10.0, noutputs=4, nstates=5, samples=7)
    assert est.samples == 7 and est.bytes == 7 * 9 * 8
    with pytest.raises(CostLimitError, match=r"1e\+03 samples x 9 signals"):
        check_diagram_cost(loop, 1.0, samples=1000, max_bytes=1000)


def test_readme_example_siso_shapes():
    """The README's example: a SISO system's outputs and inputs come back 1-D, as from
    ct.input_output_response, and equal it."""
    lowpass = ct.ss([[-2.0]], [[2.0]], [[1.0]], [[0.0]], name="lowpass", inputs="r",
                    outputs="y")
    sys = ct.interconnect([lowpass], inplist=["r"], outlist=["y"], name="lp")
    T = np.linspace(0.0, 5.0, 51)
    resp = simulate(sys, T, np.sin(T), [0.5], engine="reference", progress=False, **TOL)
    ref = ct.input_output_response(sys, T, np.sin(T), [0.5], solve_ivp_kwargs=IVP)
    assert resp.outputs.shape == ref.outputs.shape == (51,)
    assert resp.inputs.shape == ref.inputs.shape == (51,)
    assert _err(resp.outputs, ref.outputs) < 1e-9
    # y = 0.5 e^{-2t} + the response to sin over the interpolated input: far from y(0)
    assert abs(resp.outputs[-1] - 0.5) > 0.5


def test_cutting_at_kinks_buys_accuracy(loop, case):
    """Default-tolerance Rodas5P with and without its steps ending at the kinks (a kink at
    each timept): cut, its error against the tight python-control run is far smaller."""
    T, U, X0, params, _ = case
    te = np.array([2.0, 5.0])
    ref = ct.input_output_response(loop, T, U, X0, params=params, t_eval=te,
                                   solve_ivp_kwargs=IVP).outputs
    errs = []
    for cut in (True, False):
        sim = Simulator(loop, params=params, x0=X0, t0=T[0])
        sim.set_inputs(U, T)
        if not cut:
            sim._kinks = np.zeros(0)
        out_y = np.zeros((te.size, loop.noutputs))
        sim.advance(T[-1], out_t=te.copy(), out_y=out_y)
        errs.append(_err(out_y.T, ref))
    assert errs[0] < 1e-5 and errs[1] > 30 * errs[0], errs


# ----------------------------------------------------------------------------- recording
def test_records_into_a_transposed_array_as_into_a_row_major_one():
    """The stepper writes a sample's outputs and states into a row-major (samples x
    columns) array or into the transpose of one (a response's (columns x samples) array):
    the same numbers either way, bit for bit; any other layout is refused."""
    from ivdrem.diagrams import closed_loop
    d = closed_loop("iv-drem")
    out_t = np.linspace(0.0, 2.0, 401)
    filled = []
    for transposed in (False, True):
        sim = Simulator(d)
        shape_y, shape_x = (out_t.size, d.noutputs), (out_t.size, d.nstates)
        if transposed:
            y, x = np.empty(shape_y[::-1]).T, np.empty(shape_x[::-1]).T
        else:
            y, x = np.empty(shape_y), np.empty(shape_x)
        assert sim.advance(2.0, out_t=out_t.copy(), out_y=y, out_x=x) == out_t.size
        filled.append((y, x))
    assert np.array_equal(filled[0][0], filled[1][0])
    assert np.array_equal(filled[0][1], filled[1][1])
    sim = Simulator(d)
    with pytest.raises(TypeError, match="row-major"):
        sim.advance(1.0, out_t=out_t[:5].copy(), out_y=np.empty((10, 2 * d.noutputs))[::2, ::2])


def decay_until_update(t, x, u, dx, rate, t_fail):
    """dx/dt = -rate x; raises once t passes t_fail (a block that fails part-way)."""
    if t > t_fail:
        raise ValueError("past t_fail")
    for i in range(x.shape[0]):
        dx[i] = -rate * x[i]


def decay_output(t, x, u, y, rate, t_fail):
    for i in range(x.shape[0]):
        y[i] = x[i]


def test_a_run_stopped_part_way_keeps_every_sample_before_the_stop():
    """A run that a block stops part-way (the stepper leaves by its failure exit) has
    written every sample it counted, the same numbers in the transposed layout as in a
    row-major recording of the same run, and simulate(partial=True) returns exactly those
    (its response's arrays start as broadcast placeholders)."""
    from ivdrem.pycontrol import flatten
    from ivdrem.sim.errors import BlockError
    spec = BlockSpec("decay", inputs=[], outputs=[("y", 3)], states=[("x", 3)],
                     x0=np.array([1.0, -2.0, 0.5]), param_names=("rate", "t_fail"),
                     output=decay_output, update=decay_until_update)
    blk = flatten(make_block(spec, {"rate": 0.7, "t_fail": 1.2345}))
    out_t = np.arange(0.0, 3.0, 0.01)
    got = []
    for transposed in (False, True):
        sim = Simulator(blk)
        if transposed:
            y, x = np.full((3, out_t.size), np.nan).T, np.full((3, out_t.size), np.nan).T
        else:
            y, x = np.full((out_t.size, 3), np.nan), np.full((out_t.size, 3), np.nan)
        with pytest.raises(BlockError, match="past t_fail"):
            sim.advance(3.0, out_t=out_t.copy(), out_y=y, out_x=x)
        got.append((sim.recorded, y, x))
    (n0, y0, x0), (n1, y1, x1) = got
    assert n0 == n1 and 0 < n0 < out_t.size
    assert out_t[n0 - 1] <= 1.2345       # the samples of the steps accepted before the stop
    assert np.array_equal(y0, y1, equal_nan=True) and np.array_equal(x0, x1, equal_nan=True)
    assert not np.isnan(y1[:n0]).any() and np.isnan(y1[n0:]).all()
    np.testing.assert_allclose(y1[:n0, 0], np.exp(-0.7 * out_t[:n0]), rtol=1e-5)
    r = simulate(blk, 3.0, dt_out=0.01, partial=True, progress=False)
    assert not r.success and "past t_fail" in r.message
    assert r.t.size == n0
    assert np.array_equal(r.y.T, y0[:n0]) and np.array_equal(r.x.T, x0[:n0])


def test_a_run_holds_its_recorded_outputs_once():
    """simulate() records into the response's own arrays: the run's peak memory grows by
    what the response holds, not twice that (TimeResponseData copies what it is given, so a
    run that recorded into arrays of its own and handed them over held both at once)."""
    import subprocess
    import sys
    code = """
import resource, sys
import numpy as np
from ivdrem.diagrams import closed_loop
from ivdrem.sim import simulate
d = closed_loop("iv-drem")
simulate(d, 0.5, progress=False)                          # compiled, warm
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
r = simulate(d, 10.0, dt_out=2e-4, progress=False)       # 50,001 samples
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
held = (r.y.nbytes + r.x.nbytes + r.u.nbytes + r.t.nbytes) / 1024
print((after - before) / held)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    growth = float(out.split()[-1])
    assert growth < 1.4, f"peak memory grew by {growth:.2f}x the recorded arrays"
