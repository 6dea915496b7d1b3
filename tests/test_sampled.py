"""Sampled (discrete-time) blocks in the engine (ivdrem/sim/sampled.py, stepper.c's
sample function): python-control's discrete-time semantics inside a continuous diagram.

Each result is checked against something independent: python-control's own discrete-time
simulation, a closed-form solution, and a hand-written recursion of a mixed loop (the
plant's exact solution under a held input).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import control as ct

from ivdrem.sim import Simulator, simulate, sampled, AlgebraicLoopError
from ivdrem.sim.errors import BlockError
from ivdrem.sim.foreign import direct_inputs

ENGINES = ("compiled", "reference")


def _quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*a, **k)


# ------------------------------------------------------------------ declarations
def test_feedthrough_of_a_sampled_block_is_its_output_functions():
    reads_state = ct.nlsys(lambda t, x, u, p: x + u, lambda t, x, u, p: 2.0 * x,
                           inputs=["u"], outputs=["y"], states=1, dt=0.1, name="a")
    reads_input = ct.nlsys(lambda t, x, u, p: x + u, lambda t, x, u, p: x + 3.0 * u,
                           inputs=["u"], outputs=["y"], states=1, dt=0.1, name="b")
    sa, sb = sampled(reads_state), sampled(reads_input)
    assert direct_inputs(sa) == () and direct_inputs(sb) == (0,)
    # the stand-in is continuous-time and keeps the block's signals and states
    assert sa.dt == 0 and list(sa.state_labels) == list(reads_state.state_labels)
    assert sampled(sa) is sa
    with pytest.raises(ValueError, match="continuous-time"):
        sampled(ct.nlsys(lambda t, x, u, p: -x, None, states=1, name="c"))
    # python-control alone cannot evaluate it: an error, never held zeros
    plant = ct.nlsys(lambda t, x, u, p: -x + u, lambda t, x, u, p: x, inputs=["y"],
                     outputs=["u"], states=1, name="p")
    d = ct.interconnect([plant, sampled(reads_state)], inputs=[], outputs=["u"])
    with pytest.raises(RuntimeError, match="ivdrem.sim.simulate"):
        ct.input_output_response(d, [0.0, 0.1], 0.0, [0.0, 0.0])


@pytest.mark.parametrize("method", ["rodas5p", "dp45"])
def test_updates_land_exactly_on_the_sample_grid(method):
    t0, h = 0.3, 0.01
    calls = []

    def update(t, x, u, p):
        calls.append(t)
        return x + h * u

    acc = ct.nlsys(update, lambda t, x, u, p: x, inputs=["w"], outputs=["z"], states=1,
                   dt=h, name="acc")
    src = ct.nlsys(lambda t, x, u, p: [1.0], lambda t, x, u, p: x, inputs=[], outputs=["w"],
                   states=1, name="src")
    d = ct.interconnect([src, sampled(acc)], inputs=[], outputs=["z", "w"])
    r = _quiet(simulate, d, np.linspace(t0, t0 + 0.5, 7), 0.0, [0.0, 0.0], method=method,
               engine="reference")
    k = np.arange(len(calls))
    assert np.array_equal(np.array(calls), t0 + k * h)      # bit for bit t0 + k h
    assert len(calls) == 50
    # z[k] = h * sum_{j<k} w(t_j), w(t) = t - t0: held between samples
    tk = t0 + h * np.floor((r.time - t0) / h + 1e-9)
    kk = np.round((tk - t0) / h)
    assert np.allclose(r.outputs[0], h * h * kk * (kk - 1) / 2, rtol=0, atol=1e-12)


@pytest.mark.parametrize("engine", ENGINES)
def test_two_rates_each_block_updates_on_its_own_grid(engine):
    # counters at dt = 0.1 and 0.25 in one continuous diagram: each is updated only where
    # its own grid falls (the stepper marks the due periods; 0.5 is on both grids)
    calls = {"fast": [], "slow": []}

    def counter(name):
        def update(t, x, u, p):
            calls[name].append(t)
            return x + 1.0
        return ct.nlsys(update, lambda t, x, u, p: x, inputs=["w"], outputs=["n_" + name],
                        states=1, dt={"fast": 0.1, "slow": 0.25}[name], name=name)

    src = ct.nlsys(lambda t, x, u, p: [1.0], lambda t, x, u, p: x, inputs=[], outputs=["w"],
                   states=1, name="src")
    d = ct.interconnect([src, sampled(counter("fast")), sampled(counter("slow"))],
                        inputs=[], outputs=["n_fast", "n_slow"])
    r = _quiet(simulate, d, np.linspace(0.0, 1.0, 41), 0.0, [0.0, 0.0, 0.0], engine=engine)
    # x[k] = f(t_{k-1}, x[k-1], u[k-1]): called with the previous sample time
    assert np.allclose(calls["fast"], 0.1 * np.arange(10), rtol=0, atol=1e-12)
    assert np.allclose(calls["slow"], 0.25 * np.arange(4), rtol=0, atol=1e-12)
    # the held count at t is the number of the block's grid points in (0, t]
    t = r.time
    assert np.array_equal(r.outputs[0], np.floor(t / 0.1 + 1e-9))
    assert np.array_equal(r.outputs[1], np.floor(t / 0.25 + 1e-9))


# ------------------------------------------------------------------ whole discrete diagrams
@pytest.mark.parametrize("engine", ENGINES)
def test_discrete_diagram_equals_python_control(engine):
    h = 0.05
    A = np.array([[0.9, 0.1], [-0.2, 0.8]])
    G = ct.ss(A, [[0.0], [1.0]], [[1.0, 0.0]], [[0.5]], dt=h, name="G", inputs="u",
              outputs="y")
    gain = ct.nlsys(lambda t, x, u, p: 0.97 * x + 0.1 * np.sin(5 * t) + 0.0 * u,
                    lambda t, x, u, p: x - 0.2 * u, inputs=["w"], outputs=["u"], states=1,
                    dt=h, name="K")
    d = ct.interconnect([gain, G], inputs=["w"], outputs=["y", "u"])
    T = np.arange(0, 2 + 1e-9, h)
    w = np.cos(3 * T)
    x0 = [1.0, 0.3, -0.2]
    ref = ct.input_output_response(d, T, w, x0)
    r = _quiet(simulate, d, T, w, x0, engine=engine)
    assert np.max(np.abs(r.outputs - ref.outputs)) <= 1e-12
    assert np.max(np.abs(r.states - ref.states)) <= 1e-12


def test_linear_discrete_system_closed_form():
    # x[k+1] = a x[k] + b, y = x: x[k] = a^k x0 + b (1 - a^k) / (1 - a)
    a, b, x0, h = 0.8, 0.5, 2.0, 0.125
    sys = ct.ss([[a]], [[b]], [[1.0]], [[0.0]], dt=h, inputs="one", outputs="y", name="lin")
    d = ct.interconnect([sys], inputs=["one"], outputs=["y"])
    T = np.arange(0, 3 + 1e-9, h)
    k = np.arange(T.size)
    exact = a ** k * x0 + b * (1 - a ** k) / (1 - a)
    r = _quiet(simulate, d, T, 1.0, [x0])
    assert np.max(np.abs(np.atleast_2d(r.outputs)[0] - exact)) <= 1e-13
    # zero-order hold between samples: y(t_k + h/2) = y[k]
    r2 = _quiet(simulate, d, T[-1], 1.0, [x0], t_eval=T[:-1] + h / 2)
    assert np.max(np.abs(np.atleast_2d(r2.outputs)[0] - exact[:-1])) <= 1e-13


def test_algebraic_loop_through_direct_sampled_blocks():
    f = lambda t, x, u, p: x            # noqa: E731
    a = ct.nlsys(f, lambda t, x, u, p: x + u, inputs=["b"], outputs=["a"], states=1,
                 dt=0.1, name="A")
    b = ct.nlsys(f, lambda t, x, u, p: x + u, inputs=["a"], outputs=["b"], states=1,
                 dt=0.1, name="B")
    d = ct.interconnect([a, b], inputs=[], outputs=["a"])
    with pytest.raises(AlgebraicLoopError):
        _quiet(simulate, d, 1.0, 0.0, [0.0, 0.0])


# ------------------------------------------------------------------ a mixed loop
PLANT_A, PLANT_B = 2.0, 3.0          # dy/dt = -a y + b u
KP, KI, REF = 0.8, 1.5, 1.0          # u_k = kp e_k + ki z_k, z_{k+1} = z_k + h e_k


def _mixed_loop(h):
    plant = ct.nlsys(lambda t, x, u, p: -PLANT_A * x + PLANT_B * u, lambda t, x, u, p: x,
                     inputs=["u"], outputs=["y"], states=["y"], name="plant")
    pi = ct.nlsys(lambda t, z, y, p: z + h * (REF - y), lambda t, z, y, p: KP * (REF - y) + KI * z,
                  inputs=["y"], outputs=["u"], states=["z"], dt=h, name="pi")
    return ct.interconnect([plant, sampled(pi)], inputs=[], outputs=["y", "u"])


def _mixed_reference(h, y0, n):
    """The loop by hand: the plant's exact solution over one sample with u held."""
    e = math.exp(-PLANT_A * h)
    y, z, ys, us = y0, 0.0, [], []
    for _ in range(n + 1):
        err = REF - y
        u = KP * err + KI * z
        ys.append(y)
        us.append(u)
        y = e * y + (1 - e) * PLANT_B / PLANT_A * u
        z = z + h * err
    return np.array(ys), np.array(us)


@pytest.mark.parametrize("engine", ENGINES)
def test_mixed_loop_continuous_plant_sampled_pi(engine):
    h, y0 = 0.02, 0.2
    T = np.arange(0, 2 + 1e-9, h)
    ys, us = _mixed_reference(h, y0, T.size - 1)
    r = _quiet(simulate, _mixed_loop(h), T, 0.0, [y0, 0.0], engine=engine, rtol=1e-11,
               atol=1e-13)
    assert np.max(np.abs(r.outputs[0] - ys)) <= 1e-9
    assert np.max(np.abs(r.outputs[1] - us)) <= 1e-9
    # u is held between samples
    mid = _quiet(simulate, _mixed_loop(h), T[-1], 0.0, [y0, 0.0], engine=engine,
                 t_eval=T[:-1] + 0.37 * h)
    assert np.max(np.abs(mid.outputs[1] - us[:-1])) <= 1e-9


def test_mixed_loop_fixed_step_rk4():
    h, y0 = 0.02, 0.2
    T = np.arange(0, 1 + 1e-9, h)
    ys, _ = _mixed_reference(h, y0, T.size - 1)
    r = _quiet(simulate, _mixed_loop(h), T, 0.0, [y0, 0.0], method="rk4", h=h / 8)
    assert np.max(np.abs(r.outputs[0] - ys)) <= 1e-8
    with pytest.raises(ValueError, match="divide every sample period"):
        _quiet(simulate, _mixed_loop(h), T, 0.0, [y0, 0.0], method="rk4", h=0.003)


def test_chunks_and_restart_continue_exactly():
    h, y0 = 0.02, 0.2
    d = _mixed_loop(h)
    T = np.arange(0, 1 + 1e-9, 0.1)
    one = _quiet(simulate, d, T, 0.0, [y0, 0.0])

    def chunked(ends):
        sim = _quiet(Simulator, d, x0=[y0, 0.0])
        out = []
        for t in ends:
            sim.advance(t)
            if any(abs(t - s) < 1e-12 for s in T):
                out.append(np.concatenate([sim.outputs_at_current(), sim.x]))
        sim.close()
        return np.array(out).T
    ref = np.vstack([one.outputs, one.states])[:, 1:]
    # chunks that end on sample times take the same steps: bit for bit
    assert np.array_equal(chunked(T[1:]), ref)
    # a chunk ending between samples (0.33) adds a step: equal to the tolerance
    off = chunked([0.1, 0.2, 0.3, 0.33, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0])
    assert np.max(np.abs(off - ref)) <= 1e-6
    # a run started from the state recorded at t_k = 0.5 continues the recorded run
    k5 = 5
    rest = _quiet(simulate, d, T[k5:], 0.0, one.states[:, k5])
    assert np.max(np.abs(rest.outputs - one.outputs[:, k5:])) <= 1e-6


def test_bad_sampled_blocks_are_named():
    src = ct.nlsys(lambda t, x, u, p: -x, lambda t, x, u, p: x, inputs=[], outputs=["w"],
                   states=1, name="src")

    def update(t, x, u, p):
        if t > 0.25:
            raise ZeroDivisionError("boom")
        return x + u

    acc = ct.nlsys(update, lambda t, x, u, p: x, inputs=["w"], outputs=["z"], states=1,
                   dt=0.1, name="acc")
    d = ct.interconnect([src, sampled(acc)], inputs=[], outputs=["z"])
    for engine in ENGINES:
        with pytest.raises(BlockError, match=r"block 'acc' \(sampled\) raised at t = 0.3 s"):
            _quiet(simulate, d, 1.0, 0.0, [1.0, 0.0], engine=engine)
    unspecified = ct.nlsys(update, None, inputs=["w"], outputs=["z"], states=1, dt=True,
                           name="u")
    with pytest.raises(ValueError, match="positive, finite sample period"):
        sampled(unspecified)


@pytest.mark.parametrize("engine", ENGINES)
def test_mixed_loop_equals_its_zoh_discretization(engine):
    """A continuous plant under a held input equals its zero-order-hold discretization at
    the samples: the mixed loop (continuous plant, summing junction, discrete tf with
    feedthrough) equals python-control's run of the wholly discrete loop (ct.c2d)."""
    h = 0.05
    C = ct.tf([0.5, -0.4], [1, -0.9], dt=h, inputs="e", outputs="u", name="C")
    A, B = [[-1.0, 0.5], [0.0, -2.0]], [[0.0], [1.0]]
    P = ct.ss(A, B, [[1.0, 0.0]], [[0.0]], inputs="u", outputs="y", name="P")
    mixed = ct.interconnect([P, sampled(C), ct.summing_junction(["r", "-y"], "e", name="S")],
                            inputs=["r"], outputs=["y", "u"])
    Pd = ct.ss(ct.c2d(ct.ss(A, B, [[1.0, 0.0]], [[0.0]]), h, "zoh"), inputs="u",
               outputs="y", name="P")
    discrete = ct.interconnect([Pd, C, ct.summing_junction(["r", "-y"], "e", name="S", dt=h)],
                               inputs=["r"], outputs=["y", "u"])
    T = np.arange(0, 2 + 1e-9, h)
    r = _quiet(simulate, mixed, T, np.sin(T), engine=engine, rtol=1e-11, atol=1e-13)
    ref = ct.input_output_response(discrete, T, np.sin(T))
    assert np.max(np.abs(r.outputs - ref.outputs)) <= 1e-9


def test_direct_chain_through_a_continuous_gain():
    """Sampled A (direct) -> continuous static gain -> sampled B (direct): B's input at t_k
    reads A's new output through the gain, as python-control's discrete loop (the gain a
    static dt = h system there) computes it."""
    h = 0.1
    f = lambda t, x, u, p: 0.5 * x + u       # noqa: E731
    g = lambda t, x, u, p: x + 2.0 * u       # noqa: E731

    def blocks(gain_dt):
        a = ct.nlsys(f, g, inputs=["w"], outputs=["a"], states=["xa"], dt=h, name="A")
        b = ct.nlsys(f, g, inputs=["c"], outputs=["b"], states=["xb"], dt=h, name="B")
        k = ct.ss([], [], [], [[-3.0]], inputs="a", outputs="c", name="K", dt=gain_dt)
        return a, k, b
    a, k, b = blocks(0)
    mixed = ct.interconnect([sampled(a), k, sampled(b)], inputs=["w"], outputs=["b", "c"])
    discrete = ct.interconnect(list(blocks(h)), inputs=["w"], outputs=["b", "c"])
    T = np.arange(0, 1.5 + 1e-9, h)
    ref = ct.input_output_response(discrete, T, np.cos(T), [1.0, -0.5])
    for engine in ENGINES:
        r = _quiet(simulate, mixed, T, np.cos(T), [1.0, -0.5], engine=engine)
        assert np.max(np.abs(r.outputs - ref.outputs)) <= 1e-12, engine
