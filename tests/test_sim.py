"""Correctness of ivdrem's simulator: engines, methods, convergence, errors, results.

Compiled diagrams used here: closed_loop("iv-drem") and closed_loop("composite-learning")
with default arguments (the same modules the rest of the test suite compiles) and the lab
diagram of conftest.py.  Every other diagram runs on the reference engine or fails before
compiling.
"""
from __future__ import annotations

import math
import re

import control as ct
import numpy as np
import pandas as pd
import pytest

import ivdrem.blocks as block_library
from ivdrem.blocks import BlockSpec, ParameterError, make_block
from ivdrem.diagrams import assemble, closed_loop
from ivdrem.sim import AlgebraicLoopError, SimulationError, Simulator, simulate
from ivdrem.sim.compiled import CompileError

from conftest import LAB_T, build_lab, lab_source, paper_loop, paper_run, sig, state

TH = np.array([1.3, 0.28, 0.32, 0.4, 1.4])


# ============================================================ fixed step vs adaptive (10 s)
def test_rk4_and_dp45_agree_over_10s():
    """RK4 h = 1e-3 and DP45 (rtol 1e-9, atol 1e-11) on the paper loop agree on theta_hat, q.

    Measured: |theta_hat diff| 1.0e-8, |q diff| 2.1e-10 (|theta_hat| <= 2.3, |q| <= 1.9)."""
    a = paper_run("iv-drem", 10.0, "rk4", "compiled")
    b = paper_run("iv-drem", 10.0, "dp45", "compiled", rtol=1e-9, atol=1e-11)
    assert np.allclose(a.time, b.time, rtol=0, atol=1e-9)
    assert b.stats["method"] == "dp45" and b.stats["steps"] > 100
    assert a.stats["method"] == "rk4" and a.stats["steps"] == 10000
    # 4 per step, plus f(t, x) at each entry into the loop (the start, and after each of the
    # delay history's (at most two) regrowths within 10 s)
    assert 1 <= a.stats["rhs_calls"] - 4 * a.stats["steps"] <= 3
    d_th = np.abs(sig(a, "theta_hat") - sig(b, "theta_hat")).max()
    d_q = np.abs(sig(a, "q") - sig(b, "q")).max()
    assert d_th <= 1e-7, d_th
    assert d_q <= 2e-9, d_q
    # the parameters really move (the comparison is not between two zeros)
    assert np.abs(sig(a, "theta_hat")[:, -1]).max() > 0.5


def test_rk4_is_fourth_order_on_the_paper_loop():
    """Errors of RK4 at h = 2 ms and 1 ms against h/8 = 0.25 ms over 5 s (outputs every 10 ms,
    a multiple of every step): ratio ~16.  Measured 16.6 (theta_hat), 16.8 (q, states)."""
    runs = {h: paper_run("iv-drem", 5.0, "rk4", "compiled", h=h) for h in (2e-3, 1e-3, 2.5e-4)}
    ref = runs[2.5e-4]
    for name in ("theta_hat", "q", "dq", "tau"):
        e1 = np.abs(sig(runs[2e-3], name) - sig(ref, name)).max()
        e2 = np.abs(sig(runs[1e-3], name) - sig(ref, name)).max()
        assert 10.0 <= e1 / e2 <= 22.0, (name, e1, e2)
    e1 = np.abs(np.asarray(runs[2e-3].states) - np.asarray(ref.states)).max()
    e2 = np.abs(np.asarray(runs[1e-3].states) - np.asarray(ref.states)).max()
    assert 10.0 <= e1 / e2 <= 22.0, (e1, e2)


def test_dp45_error_control_tracks_tolerance():
    """Tighter rtol/atol gives a smaller error against a fine RK4 run over 5 s
    (measured |q| error 7.0e-9 at rtol 1e-6, 8.1e-12 at rtol 1e-9)."""
    ref = paper_run("iv-drem", 5.0, "rk4", "compiled", h=2.5e-4)
    errs = []
    for rtol in (1e-6, 1e-9):
        r = paper_run("iv-drem", 5.0, "dp45", "compiled", rtol=rtol, atol=rtol * 1e-2)
        errs.append(np.abs(sig(r, "q") - sig(ref, "q")).max())
    assert errs[1] < errs[0] / 30, errs
    assert errs[1] <= 1e-9, errs


def test_dp45_stays_stable_where_fixed_rk4_diverges():
    """docs/simulation.md: the fastest mode grows like (K + delta_mu mu)/m_min.  With mu(0) = 2000
    (param override, same compiled module) it is ~1.5e4 /s: RK4 at 1 ms diverges with a
    clear error, DP45 with default tolerances adapts its step and stays accurate.

    Measured DP45 vs RK4 h = 5e-5: |q| 8.5e-10, |theta_hat| 5.8e-8."""
    d = paper_loop("iv-drem")
    p = {"mu1": 2000.0}
    with pytest.raises(SimulationError, match=r"diverged at t = .* mu\(t\)"):
        simulate(d, 1.0, method="rk4", h=1e-3, params=p, progress=False)
    a = simulate(d, 1.0, method="dp45", params=p, progress=False)
    ref = simulate(d, 1.0, method="rk4", h=5e-5, params=p, progress=False)
    assert a.stats["steps"] > 1000                       # it did have to shorten its steps
    assert np.abs(sig(a, "q") - sig(ref, "q")).max() <= 1e-8
    assert np.abs(sig(a, "theta_hat") - sig(ref, "theta_hat")).max() <= 5e-7
    assert np.all(np.isfinite(np.asarray(a.outputs)))


# ============================================================== reference vs compiled (1 s)
@pytest.mark.parametrize("law", ["iv-drem", "composite-learning"])
def test_reference_and_compiled_engines_agree(law):
    """All outputs (and states) agree to 1e-9 relative to each signal's scale (measured:
    bit-identical, both engines run the same stepping template on the same kernels).
    1 s (1,000 RK4 steps, every block of the loop evaluated at each): the reference engine
    runs Python per step, and an equivalence of the same kernels does not need more; the
    max-hold of composite learning engages at 0.01 s, so its held path is compared too."""
    a = paper_run(law, 1.0, "rk4", "reference")
    b = paper_run(law, 1.0, "rk4", "compiled")
    assert a.stats["engine"] == "reference" and b.stats["engine"] == "compiled"
    assert list(a.output_labels) == list(b.output_labels)
    A, Bo = np.asarray(a.outputs), np.asarray(b.outputs)
    assert np.all(np.isfinite(A))
    scale = np.maximum(np.abs(A).max(axis=1), 1e-300)
    rel = np.abs(A - Bo).max(axis=1) / scale
    assert rel.max() <= 1e-9, dict(zip(a.output_labels, rel))
    Xa, Xb = np.asarray(a.states), np.asarray(b.states)
    assert np.abs(Xa - Xb).max() <= 1e-9 * max(1.0, np.abs(Xa).max())
    if law == "composite-learning":
        # the max-hold has engaged within the 2 s, so the held path is compared too
        assert sig(a, "lambda_min_held")[0, -1] > 0


def test_mixing_outputs_match_averaging_states():
    """Delta and calY of the paper loop equal det(Psi_n) and adj(Psi_n) Y / s computed with
    numpy (LU determinants of cofactors) from the averaging states [Y, Psi],
    s = 1 + ||Psi||_F: the (15b)-(17) chain is wired as specified.
    Measured relative differences: Delta 2.3e-12, calY 3.0e-11."""
    r = paper_run("iv-drem", 10.0, "rk4", "compiled")
    X = state(r, "averaging_avg")
    D, calY = sig(r, "Delta")[0], sig(r, "calY")
    for k in range(0, r.time.size, 50):
        Y, Psi = X[:5, k], X[5:, k].reshape(5, 5)
        s = 1.0 + np.linalg.norm(Psi)
        Pn = Psi / s
        d = np.linalg.det(Pn)
        adj = np.array([[(-1) ** (i + j) * np.linalg.det(np.delete(np.delete(Pn, j, 0), i, 1))
                         for j in range(5)] for i in range(5)])
        assert D[k] == pytest.approx(d, rel=1e-8, abs=1e-14)
        assert np.allclose(calY[:, k], adj @ Y / s, rtol=1e-8, atol=1e-14)
    assert np.abs(D).max() > 1e-5       # Delta does become non-zero within 10 s


def test_composite_learning_max_hold_in_the_loop():
    """For t < T the baseline window is Psi_b = int_0^t phi phi^T, whose lambda_min never
    decreases (PSD increments), so the max-hold follows it at every step once it exceeds
    epsilon = 1e-9: lambda_min_held = lambda_min(Psi_b(t)) from the window states."""
    r = paper_run("composite-learning", 2.0, "rk4", "compiled")
    I = state(r, "window_integrator_window_I")          # [int phi z (5), int phi phi^T (25)]
    lam = np.array([np.linalg.eigvalsh(0.5 * (P + P.T))[0]
                    for P in I[5:].T.reshape(-1, 5, 5)])
    held = sig(r, "lambda_min_held")[0]
    on = lam > 1e-9
    assert on.sum() > 10 and (~on).sum() >= 1           # starts at Psi_b = 0
    assert np.all(held[~on] == 0.0)
    assert np.allclose(held[on], lam[on], rtol=1e-10, atol=1e-15)
    assert np.all(np.diff(held) >= 0)


# ============================================================== Simulator.advance
def test_simulator_advance_in_chunks_equals_one_shot(lab):
    """The delay/max-hold history carries over between advance() calls (RK4: identical)."""
    one = simulate(lab, 2.0, method="rk4", h=1e-3, engine="compiled", dt_out=0.5,
                   progress=False)
    sim = Simulator(lab, method="rk4", h=1e-3, engine="compiled")
    for t_to in (0.3, 0.7305, 1.1, 2.0):
        sim.advance(t_to)
    assert sim.t == pytest.approx(2.0, abs=1e-12)
    row = sim.outputs_at_current()
    assert np.array_equal(row, np.asarray(one.outputs)[:, -1])
    with pytest.raises(ValueError, match="cannot go back in time"):
        sim.advance(1.0)
    sim.close()


# ============================================================== errors
def test_input_output_response_refuses_delay_and_max_hold():
    for extra in (block_library.transport_delay(3, 0.5, input="ext_g", output="g_delayed"),
                  block_library.max_hold(2, 2, input="mh_in", output="held")):
        d = assemble([lab_source(), extra], [extra.output_labels[0].split("[")[0]])
        with pytest.raises(Exception, match=r"ivdrem\.sim\.simulate") as ei:
            ct.input_output_response(d, T=np.linspace(0, 0.1, 5))
        assert ("TransportDelay" in str(ei.value)) or ("MaxHold" in str(ei.value))


@pytest.mark.parametrize("kw,pattern", [
    (dict(K=-2.0), r"'K' must be positive definite"),
    (dict(K=[[2.0, 3.0], [3.0, 2.0]]), r"'K' must be positive definite"),
    (dict(delta_mu=0.0), r"'delta_mu' must be in \(0.0, 1.0\)"),
    (dict(delta_mu=1.0), r"'delta_mu' must be in \(0.0, 1.0\)"),
    (dict(l=0.0), r"'l' must be > 0"),
    (dict(l=-1.0), r"'l' must be > 0"),
    (dict(T=0.0), r"'T' must be > 0"),
    (dict(T=-20.0), r"'T' must be > 0"),
    (dict(p=0.5), r"'p' must be >= 1"),
    (dict(F0=0.0), r"'F0' must be > 0"),
    (dict(F0=-1.0), r"'F0' must be > 0"),
    (dict(Gamma=-0.01), r"'Gamma' must be positive definite"),
    (dict(Gamma=np.diag([0.01, 0.01, -0.01, 0.01, 0.01])), r"'Gamma' must be positive definite"),
    (dict(theta=[1.3, 0.28]), r"'theta' must have length 5"),
    (dict(q0=[0.0]), r"'q0' must have length 2"),
    (dict(theta_hat0=np.zeros(4)), r"'theta_hat0' must have length 5"),
    (dict(alpha=0.0), r"'alpha' must be > 0"),
    (dict(observer_variant="paper"), r"unknown observer variant"),
])
def test_closed_loop_rejects_bad_arguments(kw, pattern):
    from ivdrem.diagrams.closed_loop import LOOP_ARGUMENTS
    loop = {k: v for k, v in kw.items() if k in LOOP_ARGUMENTS}    # the law's gains apart
    gains = {k: v for k, v in kw.items() if k not in LOOP_ARGUMENTS}
    with pytest.raises(ParameterError, match=pattern):
        closed_loop("iv-drem", gains=gains, **loop)


def test_closed_loop_rejects_unknown_law_and_replacement():
    with pytest.raises(ValueError, match=r"unknown law 'ivdrem'.*iv-drem"):
        closed_loop("ivdrem")
    with pytest.raises(ValueError, match="replace: no block named 'plnt'"):
        closed_loop("none", replace={"plnt": lab_source()})


def test_simulate_rejects_bad_options(lab):
    with pytest.raises(ValueError, match=r"unknown method 'euler'.*dp45.*rk4"):
        simulate(lab, 1.0, method="euler")
    with pytest.raises(ValueError, match=r"unknown engine 'numba'.*compiled.*reference"):
        simulate(lab, 1.0, engine="numba")
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['not_a_param'\]"):
        simulate(lab, 1.0, params={"not_a_param": 1.0}, engine="reference")
    with pytest.raises(ValueError, match="shortest transport delay"):
        simulate(lab, 1.0, method="rk4", h=LAB_T, engine="reference")
    with pytest.raises(ValueError, match="shortest transport delay"):
        simulate(lab, 1.0, method="rk4", h=2 * LAB_T, engine="reference")
    with pytest.raises(ValueError, match="shortest transport delay"):
        simulate(lab, 1.0, method="dp45", h_max=LAB_T, engine="reference")
    with pytest.raises(ValueError, match="t_end must be a finite number > 0"):
        simulate(lab, 0.0, engine="reference")
    with pytest.raises(ValueError, match="h must be a finite number > 0"):
        simulate(lab, 1.0, method="rk4", h=-1e-3, engine="reference")
    with pytest.raises(ValueError, match="x0 has 3 entries"):
        simulate(lab, 1.0, x0=np.zeros(3), engine="reference")
    # a single continuous-time block runs (tests/test_user_round_two.py); what simulate
    # cannot run is refused naming the drop-in that can
    with pytest.raises(TypeError, match="ivdrem.pycontrol.input_output_response"):
        simulate(ct.nlsys(lambda t, x, u, p: -x, None, states=1, dt=0.1), 1.0)


def test_simulate_validates_parameter_overrides():
    d = paper_loop("iv-drem")
    with pytest.raises(ParameterError, match="'K' must be positive definite"):
        simulate(d, 1.0, params={"K": -1.0})
    with pytest.raises(ParameterError, match=r"'delta_mu' must be in \(0.0, 1.0\)"):
        simulate(d, 1.0, params={"delta_mu": 2.0})
    with pytest.raises(ParameterError, match="'T' must be > 0"):
        simulate(d, 1.0, params={"T": 0.0})
    with pytest.raises(ParameterError, match="'theta' must have length 5"):
        simulate(d, 1.0, params={"theta": np.ones(3)})
    with pytest.raises(ParameterError, match="'Gamma' must be positive definite"):
        simulate(d, 1.0, params={"Gamma": -1.0})


def _feedthrough_output(t, x, u, y):
    y[0] = 2.0 * u[0]


def _feedthrough(name, inp, out):
    spec = BlockSpec(name=name, inputs=[(inp, 1)], outputs=[(out, 1)], states=[],
                     x0=np.zeros(0), param_names=(), output=_feedthrough_output, direct=(inp,))
    return make_block(spec, {})


def test_algebraic_loop_is_reported_with_block_names():
    d = assemble([_feedthrough("amplifier_a", "sig_b", "sig_a"),
                  _feedthrough("amplifier_b", "sig_a", "sig_b")], ["sig_a"])
    for engine in ("reference", "compiled"):
        with pytest.raises(AlgebraicLoopError, match="algebraic loop") as ei:
            simulate(d, 1.0, engine=engine)
        assert "amplifier_a" in str(ei.value) and "amplifier_b" in str(ei.value)


# DP45 is compiled for the paper loop only (compile budget); the reference engine runs
# the same stepping template
@pytest.mark.parametrize("engine,method", [("reference", "rk4"), ("reference", "dp45"),
                                           ("compiled", "rk4")])
def test_diverging_run_raises_with_time_and_state(lab, engine, method):
    """blow' = 100 blow, blow(0) = 1 grows 1e6-fold within 1 s at t = ln(1e6)/100 = 0.138 s
    (the growth-rate check, with the rate in the message); with x_limit = 1e4 the absolute
    limit is crossed first, at t = ln(1e4)/100 = 0.092 s."""
    with pytest.raises(SimulationError) as ei:
        simulate(lab, 1.0, method=method, engine=engine, params={"a_grow": 100.0},
                 progress=False)
    msg = str(ei.value)
    assert "diverged" in msg and "lab_source.blow[0]" in msg and "grew by more than" in msg
    t_msg = float(re.search(r"diverged at t = ([0-9.eE+-]+) s", msg).group(1))
    assert t_msg == pytest.approx(math.log(1e6) / 100.0, abs=0.02)
    rate = float(re.search(r"e-folding rate ([0-9.eE+-]+) /s", msg).group(1))
    assert rate == pytest.approx(100.0, rel=0.1)
    with pytest.raises(SimulationError, match=r"blow\[0\] is .*\(limit 10000\)") as ei:
        simulate(lab, 1.0, method=method, engine=engine, params={"a_grow": 100.0},
                 x_limit=1e4, progress=False)
    t_msg = float(re.search(r"diverged at t = ([0-9.eE+-]+) s", str(ei.value)).group(1))
    assert t_msg == pytest.approx(math.log(1e4) / 100.0, abs=0.02)


@pytest.mark.parametrize("engine", ["reference", "compiled"])
def test_singular_inertia_raises(engine):
    """theta3 = 0 makes M(q) indefinite (det M = -theta2^2 c2^2 <= 0)."""
    th = TH.copy()
    th[2] = 0.0
    with pytest.raises(SimulationError, match="inertia") as ei:
        simulate(paper_loop("iv-drem"), 1.0, method="rk4", engine=engine,
                 params={"theta": th}, progress=False)
    assert "t = 0 s" in str(ei.value)


@pytest.mark.parametrize("engine", [
    "compiled",
    # regression: on the reference engine a NaN used to surface as python-control's
    # "algebraic loop detected" instead of a SimulationError naming the time and state
    "reference"])
def test_nan_state_is_reported(engine):
    """A kernel producing NaN stops the run with the state named (not NaNs in the result)."""
    with pytest.raises(SimulationError, match=r"lab_source\.blow\[0\] is (np\.float64\()?nan"):
        simulate(build_lab(), 1.0, method="rk4", engine=engine,
                 params={"a_grow": float("nan")}, progress=False)


def test_plain_nlsys_runs_on_both_engines():
    """A lambda numba cannot compile: on the compiled engine that block alone is called
    back into Python (with a notice), and both engines give y = t."""
    from ivdrem.sim.foreign import PythonBlockNotice
    ramp = ct.nlsys(lambda t, x, u, p: np.array([1.0]), lambda t, x, u, p: x,
                    states=["x"], outputs=["y"], inputs=0, name="ramp")
    d = assemble([ramp], ["y"])
    with pytest.warns(PythonBlockNotice, match=r"'ramp' \(its update function is a lambda\)"):
        c = simulate(d, 1.0, method="rk4", h=1e-2, engine="compiled", dt_out=0.25,
                     progress=False)
    r = simulate(d, 1.0, method="rk4", h=1e-2, engine="reference", dt_out=0.25,
                 progress=False)
    assert np.allclose(sig(r, "y")[0], r.time, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sig(c, "y")[0], sig(r, "y")[0], rtol=0, atol=1e-12)


_HIDDEN_GAIN = 3.0


def _global_kernel(t, x, u, y):
    y[0] = _HIDDEN_GAIN * t


def test_kernel_with_foreign_global_is_refused_by_the_compiler():
    spec = BlockSpec(name="hidden", inputs=[], outputs=[("h", 1)], states=[], x0=np.zeros(0),
                     param_names=(), output=_global_kernel)
    d = assemble([make_block(spec, {})], ["h"])
    with pytest.raises(CompileError, match="_HIDDEN_GAIN"):
        simulate(d, 1.0, engine="compiled")
    r = simulate(d, 1.0, method="rk4", h=0.1, engine="reference", dt_out=0.5, progress=False)
    assert np.allclose(sig(r, "h")[0], 3.0 * r.time)


# ============================================================== results
def test_to_pandas_has_named_columns():
    r = paper_run("iv-drem", 2.0, "rk4", "compiled")
    df = r.to_pandas()
    assert isinstance(df, pd.DataFrame)
    assert len(df) == r.time.size == 201
    for col in ("time", "q[0]", "q[1]", "theta_hat[4]", "Delta", "calY[0]", "tau_d_hat[1]",
                "plant_q[0]", "adaptation_law_theta_hat[0]"):
        assert col in df.columns, col
    assert np.allclose(df["time"], r.time)
    assert np.allclose(df["theta_hat[2]"], sig(r, "theta_hat")[2])
    assert r.stats["engine"] == "compiled" and r.stats["steps"] == 2000


def test_output_sampling_and_stats(lab):
    r = simulate(lab, 1.0, method="dp45", engine="reference", dt_out=0.1, progress=False)
    assert np.allclose(r.time, np.linspace(0, 1, 11), rtol=0, atol=1e-12)
    s = r.stats
    assert s["rejected"] >= 0 and s["rhs_calls"] >= 6 * s["steps"]
    assert 0 < s["h_max"] <= LAB_T / 4


# ------------------------------------------------------------------ structure of ivdrem.sim
def _sim_imports():
    """{module: (modules of ivdrem.sim it imports at its top level, those it imports inside
    a function)}, read from the sources."""
    import ast
    from pathlib import Path
    import ivdrem.sim
    root = Path(ivdrem.sim.__file__).parent
    mods = {p.stem for p in root.glob("*.py")}
    out = {}
    for p in root.glob("*.py"):
        tree = ast.parse(p.read_text())
        top, inner = set(), set()

        def names(node):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level == 1:
                    if base:
                        return {base.split(".")[0]}
                    return {a.name for a in node.names}
                if base.startswith("ivdrem.sim."):
                    return {base.split(".")[2]}
                if base == "ivdrem.sim":
                    return {"__init__"}
            return set()
        for node in tree.body:
            top |= names(node)
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for sub in ast.walk(node):
                    inner |= names(sub)
        out[p.stem] = (top & mods, inner & mods)
    return out


def test_no_import_circle_in_sim():
    """The modules of ivdrem.sim import each other without a circle, and no import of
    another module of ivdrem.sim sits inside a function to dodge one."""
    graph = _sim_imports()
    state = {}

    def visit(m, path):
        if state.get(m) == 1:
            raise AssertionError("import circle: " + " -> ".join(path + [m]))
        if state.get(m) == 2:
            return
        state[m] = 1
        for d in sorted(graph.get(m, ((), ()))[0] - {"__init__"}):
            visit(d, path + [m])
        state[m] = 2
    for m in sorted(graph):
        if m != "__init__":
            visit(m, [])
    inner = {m: sorted(v[1]) for m, v in graph.items() if v[1]}
    assert inner == {}, inner
