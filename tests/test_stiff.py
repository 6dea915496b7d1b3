"""The stiff method (Rodas5P) and the integrator loop, tested apart from the paper's diagram.

Small problems whose solutions are known, through the stepper: Rodas5P's tableau against
the Rosenbrock order conditions, its stability function (and one step of the stepper
against it), a stiff problem with an analytic solution through the loop, the explicit
methods on a smooth one.  The loop's checks (growth-rate divergence,
the stiffness warning, unknown method names, compile/simulation time) run on small
diagrams.  Oracles: Hairer & Wanner, Solving ODEs II, sec. IV.7 (order conditions of
Rosenbrock methods through rooted trees; transformed coefficients), closed-form solutions.
"""
from __future__ import annotations

import dataclasses
import math
import re
import warnings
from pathlib import Path

import control as ct
import numpy as np
import pytest

import ivdrem.sim as sim
from ivdrem.sim import _stepper_codes as tpl
from ivdrem.sim.tables import pack, with_fill_runs
from ivdrem.sim import (METHODS, METHOD_TABLE, SimulationError, StiffnessWarning, simulate)

from conftest import LAB_OUTPUTS, build_lab, lab_blocks, paper_loop, sig


# ----------------------------------------------------------------- the tableau, symbolically
def _original_coefficients():
    """alpha, Gamma, b, b_hat of Rodas5P from its transformed coefficients (HW IV.7:
    C = diag(1/gamma) - Gamma^-1, a = alpha Gamma^-1, m = b Gamma^-1)."""
    g = tpl.RODAS5P_GAMMA
    s = 8
    Gam = np.linalg.inv(np.eye(s) / g - tpl.RODAS5P_C)
    alpha = tpl.RODAS5P_A @ Gam
    b = tpl.RODAS5P_B @ Gam
    bhat = (tpl.RODAS5P_B - np.eye(s)[s - 1]) @ Gam     # embedded: x_new - U_8
    return alpha, Gam, b, bhat


def _trees(n):
    """Rooted trees with n vertices as sorted tuples of subtrees."""
    if n == 1:
        return [()]
    found = set()

    def forests(rem, maxsz):
        if rem == 0:
            yield []
            return
        for k in range(min(rem, maxsz), 0, -1):
            for tr in _trees(k):
                for rest in forests(rem - k, k):
                    yield [tr] + rest
    for f in forests(n - 1, n - 1):
        found.add(tuple(sorted(f)))
    return sorted(found)


def _density(tr):
    order = lambda t: 1 + sum(order(c) for c in t)     # noqa: E731
    return order(tr) * math.prod(_density(c) for c in tr)


def _phi(tr, alpha, beta):
    """Elementary weights of a Rosenbrock method: a vertex with one child carries beta =
    alpha + Gamma (the linear J terms), a vertex with several children alpha (HW IV.7)."""
    if not tr:
        return np.ones(alpha.shape[0])
    if len(tr) == 1:
        return beta @ _phi(tr[0], alpha, beta)
    return np.prod([alpha @ _phi(c, alpha, beta) for c in tr], axis=0)


def test_rodas5p_order_conditions():
    """All 17 order conditions up to order 5 hold to rounding for the solution, the 8 up to
    order 4 for the embedded solution; order 6 fails (so the check discriminates).
    The time nodes and time-derivative weights are the row sums of alpha and Gamma, as the
    non-autonomous form requires.  Measured: max residual 1.6e-14 (order <= 5)."""
    alpha, Gam, b, bhat = _original_coefficients()
    beta = alpha + Gam
    assert np.abs(np.triu(alpha)).max() < 1e-13            # explicit in alpha
    assert np.abs(np.diag(Gam) - tpl.RODAS5P_GAMMA).max() < 1e-13
    assert np.allclose(alpha.sum(axis=1), tpl.RODAS5P_CT, rtol=0, atol=1e-13)
    assert np.allclose(Gam.sum(axis=1), tpl.RODAS5P_D, rtol=0, atol=1e-13)
    res = {n: [b @ _phi(t, alpha, beta) - 1 / _density(t) for t in _trees(n)]
           for n in range(1, 7)}
    res_hat = {n: [bhat @ _phi(t, alpha, beta) - 1 / _density(t) for t in _trees(n)]
               for n in range(1, 6)}
    assert [len(res[n]) for n in range(1, 7)] == [1, 1, 2, 4, 9, 20]
    for n in range(1, 6):
        assert np.abs(res[n]).max() < 1e-12, (n, res[n])
    for n in range(1, 5):
        assert np.abs(res_hat[n]).max() < 1e-12, (n, res_hat[n])
    assert np.abs(res[6]).max() > 1e-4                     # a fifth-order method
    assert np.abs(res_hat[5]).max() > 1e-4                 # a fourth-order embedding
    # stiffly accurate: b is the last row of beta (the solution is the last stage)
    assert np.allclose(b, beta[-1], rtol=0, atol=1e-12)


def _stability_function(z):
    alpha, Gam, b, _ = _original_coefficients()
    beta = alpha + Gam
    s = b.size
    return 1 + z * b @ np.linalg.solve(np.eye(s) - z * beta, np.ones(s))


def test_rodas5p_is_l_stable():
    """R(z) -> 0 as z -> -inf, |R| <= 1 on the imaginary axis and in the left half plane
    (A-stable), and one step of the template's rodas5p_step on y' = lambda y gives R(h lambda)."""
    assert abs(_stability_function(-1e12)) < 1e-9
    # R(z) = O(1/z): |z R(z)| stays bounded as z -> -inf
    r6, r9 = abs(_stability_function(-1e6)), abs(_stability_function(-1e9))
    assert r6 < 1e-4 and r9 < 1e-7 and 0.5 < (r6 * 1e6) / (r9 * 1e9) < 2
    for y in np.concatenate([np.logspace(-3, 6, 200), -np.logspace(-3, 6, 50)]):
        assert abs(_stability_function(1j * y)) <= 1 + 1e-12
    rng = np.random.default_rng(1)
    z = -np.abs(rng.normal(size=300)) * np.logspace(-2, 4, 300) + 1j * rng.normal(size=300) * 1e2
    assert max(abs(_stability_function(zz)) for zz in z) <= 1 + 1e-12
    for hl in (-0.5, -3.0, -50.0, -1e4):
        # one step h = 1 of the stepper on y' = hl y (a StateSpace block: its Jacobian is
        # exact), tolerances no step fails
        lin = ct.ss([[hl]], np.zeros((1, 1)), np.eye(1), np.zeros((1, 1)), inputs=["u"],
                    outputs=["y"], states=["s"], name="lin")
        loop = ct.interconnect([lin], inplist=["u"], outlist=["y"], name="lambda_y")
        s1 = sim.Simulator(loop, method="rodas5p", h=1.0, h_max=1.0, rtol=1e-300, atol=1e6,
                           x0=[1.0])
        s1.advance(1.0, u=[0.0])
        assert s1.stats_dict()["steps"] == 1
        x1 = s1.x
        assert abs(x1[0] - _stability_function(hl).real) < 1e-12 * max(1, abs(x1[0])), hl


# ------------------------------------------------- the stepper on problems with known solutions
# (the order of every method, of its error estimate and of its dense output, on shared
# reference problems: tests/test_methods.py)
LAM_PR = -1e6
A_PAIR = np.array([[-1.0, 0.0], [1e4 - 1.0, -1e4]])   # eigenvalues -1, -1e4


def _f_stiff(t, x, u, params):
    """Prothero-Robinson y' = lambda (y - sin t) + cos t, and the stiff linear pair."""
    return np.array([LAM_PR * (x[0] - math.sin(t)) + math.cos(t),
                     A_PAIR[0, 0] * x[1] + A_PAIR[0, 1] * x[2],
                     A_PAIR[1, 0] * x[1] + A_PAIR[1, 1] * x[2]])


# y1 = sin t, y2 = exp(-t) sin(t)-coupled, non-autonomous and nonlinear
def _f_smooth(t, x, u, params):
    return np.array([-x[0] ** 2 + math.sin(t) ** 2 + math.cos(t),
                     -2.0 * x[1] + x[0] * x[1] + (1.0 - math.sin(t)) * x[1]])


def _state_out(t, x, u, params):
    return x


def _exact_smooth(t):
    return np.array([math.sin(t), math.exp(-t)])


def _loop(f, n, name):
    blk = ct.nlsys(f, _state_out, inputs=0, outputs=n, states=n, name=name)
    return ct.interconnect([blk], inplist=[], outlist=list(blk.output_labels),
                           name=f"{name}_loop")


def _run(loop, method, x0, out_t, **kw):
    """(x at the end, outputs at out_t, stats) of the stepper; method a name or a row."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = sim.Simulator(loop, method=method, x0=np.asarray(x0, float), **kw)
    out_y = np.full((out_t.size, loop.noutputs), np.nan)
    try:
        assert s.advance(float(out_t[-1]), out_t=out_t.copy(), out_y=out_y) == out_t.size
    finally:
        s.close()
    return s.x.copy(), out_y, s.stats_dict()


def test_rodas5p_loop_on_a_stiff_problem_with_analytic_solution():
    """Prothero-Robinson y' = lambda (y - g(t)) + g'(t), g = sin t, lambda = -1e6, plus a
    stiff linear pair with eigenvalues -1 and -1e4: the adaptive loop follows the exact
    solutions over 10 s with steps far beyond 2/|lambda| (few hundred steps), and the
    outputs read from the dense output match too (the interpolant drops to order 3 on the
    Prothero-Robinson component in the stiff limit)."""
    def exact(t):
        # x2 = e^-t, x3 = e^-t (the fast mode is not excited from (1, 1))
        return np.array([math.sin(t), math.exp(-t), math.exp(-t)])
    loop = _loop(_f_stiff, 3, "stiff")
    out_t = np.linspace(0.0, 10.0, 41)
    x, out_y, st = _run(loop, "rodas5p", exact(0.0), out_t, rtol=1e-6, atol=1e-9)
    assert np.abs(x - exact(10.0)).max() < 1e-6
    ex = np.array([exact(t) for t in out_t])
    assert np.abs(out_y[:, 1:] - ex[:, 1:]).max() < 1e-6
    assert np.abs(out_y[:, 0] - ex[:, 0]).max() < 5e-5
    assert st["steps"] < 300 and st["jacobians"] >= st["steps"]
    # the same problem perturbed off the slow manifold: the fast transient is damped (L-stable)
    x, _, _ = _run(loop, "rodas5p", exact(0.0) + np.array([1.0, 0.0, 0.5]), out_t,
                   rtol=1e-6, atol=1e-9)
    assert np.abs(x - exact(10.0)).max() < 1e-6


def test_dp45_through_the_loop_matches_the_smooth_solution():
    """The loop with DP45 and BS23 (landing on outputs; BS23 as a loop method only here,
    through its registry row) and RK4 (fixed step) on the smooth problem: each within its
    accuracy of the exact solution at the outputs."""
    from ivdrem.sim import methods
    loop = _loop(_f_smooth, 2, "smooth")
    out_t = np.linspace(0.0, 2.0, 21)
    ex = np.array([_exact_smooth(t) for t in out_t])
    _, y, _ = _run(loop, "dp45", _exact_smooth(0.0), out_t, rtol=1e-9, atol=1e-12)
    assert np.abs(y - ex).max() < 1e-8
    bs23 = next(m for m in methods.all_methods() if m.id == methods.BS23)
    _, y, st = _run(loop, dataclasses.replace(bs23, dense_outputs=False), _exact_smooth(0.0),
                    out_t, rtol=1e-8, atol=1e-11, h_max=np.inf)
    assert np.abs(y - ex).max() < 1e-7 and st["rejected"] < st["steps"] / 10
    _, y, st = _run(loop, "rk4", _exact_smooth(0.0), out_t, h=1e-2)
    assert st["steps"] == 200
    assert np.abs(y - ex).max() < 1e-8


# ---------------------------------------------------------------- the simulator's API
def test_method_table_is_the_one_source_of_names():
    """Names come from one table; each row's step function exists in the C stepper and
    method_step dispatches its id to it; an unknown name is an error naming the valid ones."""
    assert METHODS == tuple(METHOD_TABLE) and isinstance(METHODS, tuple)
    assert {"rodas5p", "dp45", "rk4"} <= set(METHODS)
    assert sim.STIFF_METHOD in METHODS and METHOD_TABLE[sim.STIFF_METHOD].l_stable
    src = (Path(tpl.__file__).parent / "stepper.c").read_text()
    for name, info in METHOD_TABLE.items():
        assert re.search(rf"^static double {info.step}\(", src, flags=re.M), info.step
        assert re.search(rf"if \(mid == {name.upper()}\) return {info.step}\(", src), name
    assert len({info.id for info in METHOD_TABLE.values()}) == len(METHOD_TABLE)
    assert set(sim.DEFAULT_TOLERANCES) == set(METHODS)
    # BS23 only takes a Rodas5P run's pinned steps: no user method
    assert tpl.BS23 not in {info.id for info in METHOD_TABLE.values()}
    from ivdrem.experiments.config import SOLVER_METHODS
    assert tuple(SOLVER_METHODS) == METHODS
    d = build_lab()
    with pytest.raises(ValueError, match=r"unknown method 'rodas'; choose one of rodas5p, dp45"):
        simulate(d, 1.0, method="rodas", engine="reference", progress=False)


# h_max: the plain delay's history slopes come from quadratics through history points,
# accurate only when those are close (both methods alike)
LAB_RODAS5P = dict(method="rodas5p", engine="reference", rtol=1e-7, atol=1e-10, h_max=2e-3,
                   dt_out=0.01, progress=False)


@pytest.fixture(scope="module")
def lab_rodas5p():
    """The lab diagram on Rodas5P, reference engine, over 2 s (2.7 windows LAB_T; the hold
    fires at 0.47 s): run once for the two tests below, which read it (13.6 s of the
    module's time)."""
    return simulate(build_lab(), 2.0, **LAB_RODAS5P)


def test_rodas5p_and_dp45_agree_on_the_lab_diagram_reference_engine(lab_rodas5p):
    """Delays (Hermite and plain) and the max-hold on the reference engine: Rodas5P with
    tight tolerances matches DP45; the hold fires at the same sampling time t_e."""
    d = build_lab()
    a = simulate(d, 2.0, method="dp45", engine="reference", rtol=1e-9, atol=1e-11,
                 h_max=LAB_RODAS5P["h_max"], dt_out=LAB_RODAS5P["dt_out"], progress=False)
    b = lab_rodas5p
    A, Bo = np.asarray(a.outputs), np.asarray(b.outputs)
    assert np.abs(A - Bo).max() <= 1e-6 * max(1.0, np.abs(A).max())
    assert a.hold_times[0] == b.hold_times[0]
    # t_e is a sampling time (multiple of dt_sample = 1 ms)
    assert abs(a.hold_times[0] * 1e3 - round(a.hold_times[0] * 1e3)) < 1e-6
    # steps pinned to the sampling grid by hold updates may be explicit (BS23) steps
    assert b.stats["jacobians"] + b.stats["explicit_steps"] >= b.stats["steps"] > 0


def test_pinned_explicit_steps_give_way_to_rodas5p_on_a_stiff_mode(lab_rodas5p):
    """The lab diagram plus a Prothero-Robinson block with a mode at -1e4, outside BS23's
    stability region at the 1 ms grid (h*lambda = -10): while the hold pins the steps, the
    explicit steps are rejected and Rodas5P takes them; the stiff state stays on sin t
    and the hold fires at the same sampling time as without that block."""
    import control as ct

    from ivdrem.diagrams import assemble

    def upd(t, x, u, params):
        return [-1e4 * (x[0] - np.sin(t)) + np.cos(t)]
    pr = ct.nlsys(upd, lambda t, x, u, params: x, states=1, outputs=["pr_y"], inputs=0,
                  name="pr")
    d = assemble(lab_blocks() + [pr], LAB_OUTPUTS + ["pr_y"], name="lab_pr")
    a = lab_rodas5p                                        # the lab alone, the same options
    b = simulate(d, 2.0, **LAB_RODAS5P)
    assert b.hold_times[0] == a.hold_times[0]
    assert a.stats["explicit_steps"] > 100                # the lab alone: BS23 steps
    assert b.stats["explicit_steps"] < a.stats["explicit_steps"] / 10
    assert b.stats["rejected"] >= 1
    t = np.asarray(b.time)
    assert np.abs(sig(b, "pr_y")[0] - np.sin(t)).max() < 1e-6
    A, Bo = np.asarray(a.outputs), np.asarray(b.outputs)[:-1]
    assert np.abs(A - Bo).max() <= 1e-6 * max(1.0, np.abs(A).max())


def test_growth_rate_divergence_is_reported_before_the_absolute_limit():
    """A state growing like e^{40 t} is stopped when it has grown 1e6-fold within a second,
    long before 1e10, with the state, the time and the rate in the message."""
    from conftest import lab_source
    from ivdrem.diagrams import assemble
    d = assemble([lab_source(a_grow=40.0)], ["blow"], name="blow")
    with pytest.raises(SimulationError, match=r"diverged at t = 0\.3\d* s: state "
                       r"lab_source\.blow\[?0?\]? = .* grew by more than 1e\+06x within 1 s "
                       r"\(e-folding rate 4\d\.?\d* /s\)"):
        simulate(d, 5.0, method="dp45", engine="reference", progress=False)


def test_stiffness_warning_names_the_stiff_method():
    """DP45 on a loop whose fastest mode is -1e4 (Prothero-Robinson block on the reference
    engine): one StiffnessWarning naming the time and method="rodas5p"; Rodas5P: none."""
    import control as ct

    def upd(t, x, u, params):
        return [-1e4 * (x[0] - np.sin(t)) + np.cos(t)]
    sysm = ct.nlsys(upd, lambda t, x, u, params: x, states=1, outputs=["y"], inputs=0,
                    name="pr")
    d = ct.interconnect([sysm], outlist=["pr.y"], outputs=["y"], name="pr_loop")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        r = simulate(d, 1.0, method="dp45", engine="reference", rtol=1e-6, atol=1e-8,
                     h_max=1.0, progress=False)
    stiff = [w for w in rec if issubclass(w.category, StiffnessWarning)]
    assert len(stiff) == 1, [str(w.message) for w in rec]
    assert re.search(r'stiff at t = [0-9.e-]+ s.*method="rodas5p"', str(stiff[0].message))
    assert r.stats["stiff_at"] is not None
    with warnings.catch_warnings():
        warnings.simplefilter("error", StiffnessWarning)
        r2 = simulate(d, 1.0, method="rodas5p", engine="reference", h_max=1.0, progress=False)
    assert r2.stats["steps"] < r.stats["steps"] / 10
    assert abs(sig(r2, "y")[0, -1] - np.sin(1.0)) < 1e-6


def test_stats_split_compile_and_simulation_time():
    """wall_s = sim_s + compile_s, both measured (non-negative), and the counters are there."""
    r = simulate(build_lab(), 0.5, method="rodas5p", engine="reference", progress=False)
    s = r.stats
    assert s["compile_s"] >= 0 and s["sim_s"] > 0
    assert s["wall_s"] == pytest.approx(s["sim_s"] + s["compile_s"])
    for k in ("jacobians", "factorizations", "hold_cuts", "hold_samples"):
        assert isinstance(s[k], int)





# ------------------------------------------------------------- the paper's loop (compiled)
def _rel_end(a, b, name="theta_hat"):
    A, Bv = sig(a, name)[:, -1], sig(b, name)[:, -1]
    return np.abs(A - Bv).max() / np.abs(Bv).max()


def test_rodas5p_error_follows_its_tolerance_on_the_paper_loop_over_10s():
    """IV-DREM over 10 s against RK4 h = 1 ms (itself 1e-8 from a tight DP45, see test_sim):
    theta_hat's largest error over all outputs (read from the dense output) at the default
    tolerances (rtol 2e-4, atol 2e-6) and at 100x tighter ones shrinks with the tolerance,
    in far fewer steps than RK4.  Measured: 3.2e-5 and 5.5e-7 relative (140 and 411 steps).
    (At 300 s the default's theta_hat is within 5.0e-7 of the tighter run: the benchmark.)"""
    from conftest import paper_run
    from ivdrem.sim.simulator import DEFAULT_TOLERANCES
    rtol, atol = DEFAULT_TOLERANCES["rodas5p"]
    rk = paper_run("iv-drem", 10.0, "rk4", "compiled")
    lo = paper_run("iv-drem", 10.0, "rodas5p", "compiled", rtol=None, atol=None)
    hi = paper_run("iv-drem", 10.0, "rodas5p", "compiled", rtol=rtol / 100, atol=atol / 100)
    th = sig(rk, "theta_hat")
    e_lo = np.abs(sig(lo, "theta_hat") - th).max() / np.abs(th).max()
    e_hi = np.abs(sig(hi, "theta_hat") - th).max() / np.abs(th).max()
    assert e_lo <= 1e-4 and e_hi <= 2e-6 and e_hi < e_lo / 20, (e_lo, e_hi)
    assert lo.stats["steps"] < hi.stats["steps"] < rk.stats["steps"] / 10
    assert lo.stats["jacobians"] >= lo.stats["steps"]


@pytest.mark.parametrize("t_end", [25.0, pytest.param(300.0, marks=pytest.mark.slow)])
def test_composite_learning_theta_hat_and_hold_time_do_not_depend_on_the_method(t_end):
    """The max-hold samples lambda_min on its 1 ms grid from the dense output and each step
    ends at an update, so DP45 and Rodas5P (default tolerances) agree on theta_hat to 1e-6
    relative and on the hold time t_e exactly (the window fills until T = 20 s: the hold
    updates on every sample until then)."""
    from conftest import paper_run
    a = paper_run("composite-learning", t_end, "dp45", "compiled")
    b = paper_run("composite-learning", t_end, "rodas5p", "compiled", rtol=None, atol=None)
    assert _rel_end(b, a) <= 1e-6, _rel_end(b, a)
    assert a.hold_times[0] == b.hold_times[0]
    assert 19.0 < a.hold_times[0] < 21.0
    assert abs(sig(a, "lambda_min_held")[0, -1] / sig(b, "lambda_min_held")[0, -1] - 1) < 1e-6


def _restricted_and_full_sweep(loop, full_sweep):
    """Two simulators of `loop`: one with its own tables, one whose tables are changed by
    full_sweep(tables) -> {field: table} to evaluate every block where the first evaluates
    only what a probe, an output or a history point reads."""
    from ivdrem.sim.simulator import Simulator
    fast = Simulator(loop)
    full = Simulator(loop)
    ints, floats = pack(with_fill_runs(
        fast.engine.tables._replace(**full_sweep(fast.engine.tables))))
    full.W = full.W._replace(table_ints=ints, table_floats=floats)
    full._Wref[0] = full.W
    return fast, full


def test_probing_a_hold_evaluates_only_what_feeds_it():
    """While the loop probes composite learning's max-hold at interpolated points, the
    table-driven diagram evaluates only the blocks the hold's inputs depend on, followed
    output entry by output entry through the blocks' local patterns (the window
    I - I(t - T) needs the integrator and the delay, not the regressor chain behind the
    integrand g); the run is bit for bit the one that sweeps every block at every probe."""
    loop = paper_loop("composite-learning")
    fast, full = _restricted_and_full_sweep(loop, lambda tb: dict(
        probe_order=tb.order, probe_fill=np.concatenate([tb.fill_order, tb.fill_rest])))
    names = {loop.syslist[k].name for k in fast.engine.tables.probe_order}
    assert names == {"window_delay", "window_integrator"}, names
    t_out = np.linspace(0.0, 25.0, 26)
    a = np.array([fast.advance(t) or fast.outputs_at_current() for t in t_out[1:]])
    b = np.array([full.advance(t) or full.outputs_at_current() for t in t_out[1:]])
    assert fast.stats[tpl.S_PROBES] > 1000 and fast.stats[tpl.S_PROBES] == full.stats[tpl.S_PROBES]
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(fast.hold_times(), full.hold_times())


def test_recording_evaluates_only_what_the_outputs_read():
    """Outputs recorded inside Rodas5P's steps (from its dense output) evaluate only the
    blocks the diagram's output map reads, through the blocks' local patterns; the
    recorded outputs are bit for bit those of a full sweep."""
    loop = paper_loop("iv-drem")
    fast, full = _restricted_and_full_sweep(loop, lambda tb: dict(
        record_order=tb.order, record_fill=tb.fill_rest))
    names = {loop.syslist[k].name for k in fast.engine.tables.record_order}
    # the window, its delay, the extension and the DREM term feed no recorded output
    assert {"window_integrator", "window_delay", "extension", "drem_term"}.isdisjoint(names)
    assert {"plant", "mixing", "torque_observer", "adaptation_law"} <= names
    t_out = np.linspace(0.0, 6.0, 601)
    ys = []
    for s in (fast, full):
        y = np.zeros((t_out.size, loop.noutputs))
        assert s.advance(6.0, out_t=t_out, out_y=y) == t_out.size
        ys.append(y)
    assert fast.stats[tpl.S_STEPS] < 300           # outputs from inside the steps
    np.testing.assert_array_equal(ys[0], ys[1])


def test_history_points_inside_steps_evaluate_only_what_the_delays_read():
    """The midpoint of each Rodas5P step that feeds the delays' history evaluates only the
    blocks the delay inputs (the window integral and its slope) depend on; the run is bit
    for bit the one with a full sweep there."""
    loop = paper_loop("iv-drem")
    fast, full = _restricted_and_full_sweep(loop, lambda tb: dict(
        history_order=tb.order, history_fill=tb.fill_rest))
    names = {loop.syslist[k].name for k in fast.engine.tables.history_order}
    assert names == {"plant", "regression_filter", "instrument", "extension",
                     "window_integrator"}, names
    t_out = np.linspace(0.0, 25.0, 26)
    a = np.array([fast.advance(t) or fast.outputs_at_current() for t in t_out[1:]])
    b = np.array([full.advance(t) or full.outputs_at_current() for t in t_out[1:]])
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(fast.x, full.x)
