"""One generic suite for every row of the method registry (ivdrem.sim.methods).

Each test is parametrized over ``methods.all_methods()`` (the stepper-internal Bogacki-Shampine
3(2) too, run through ``Simulator`` with its registry row), so a new method is covered by
adding its row: nothing here names a method.  The reference problems are shared and have
known solutions:

* logistic ``x' = r x (1 - x)`` (closed form), nonlinear and autonomous (Rodas5P's df/dt by
  a forward difference in t is then exact: 0);
* spring-mass ``x'' = -w^2 x`` (closed form), linear;
* Prothero-Robinson ``y' = -L (y - g(t)) + g'(t)``, solution ``g`` for every ``L``: stiff
  at ``L = 1e6``;
* Robertson's chemical kinetics (stiff, no closed form: scipy's Radau at rtol 1e-10).

What the registry says of a method and what is measured:

* ``order``: the global error at a fixed end time, steps ``h`` halved (an adaptive method
  with ``h_max = h`` and tolerances no step can fail: every step is ``h``);
* ``error_order``: the error estimate of one step from the exact state, ``O(h^(q+1))``, or
  identically 0 for a method without one;
* ``dense_order``: the interpolant inside a step, read at the step's middle through a
  transport delay's history (``O(h^(min(order, dense_order) + 1))`` for one step);
* ``adaptive``: a fixed-step method is priced by the cost guards from its real step count;
* ``l_stable``: the stiff problems in a few dozen steps at the default tolerances;
* a dispatch id the stepper has no step function for is an error, never another method.
"""
from __future__ import annotations

import dataclasses
import re
import warnings

import control as ct
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ivdrem.blocks import transport_delay
from ivdrem.sim import Simulator, simulate
from ivdrem.sim import methods
from ivdrem.sim.guards import estimate_cost

ROWS = methods.all_methods()
IDS = [m.name for m in ROWS]

R_LOG, X0_LOG = 1.5, 0.1           # logistic
W_SPRING = 2.0                     # spring-mass
L_PR = 1e6                         # Prothero-Robinson
LOOSE = dict(rtol=1e-300, atol=1e6)   # tolerances no step fails: every step is h_max


def logistic_exact(t):
    return 1.0 / (1.0 + (1.0 / X0_LOG - 1.0) * np.exp(-R_LOG * t))


def _logistic_upd(t, x, u, params):
    return np.array([R_LOG * x[0] * (1.0 - x[0])])


def _logistic_out(t, x, u, params):
    return np.array([x[0], R_LOG * x[0] * (1.0 - x[0])])


def logistic_block():
    """The logistic ODE, outputs x and dx/dt."""
    return ct.nlsys(_logistic_upd, _logistic_out, inputs=0, outputs=["x[0]", "dx[0]"],
                    states=["x"], name="logistic")


def logistic_with_delay(T):
    """The logistic ODE and x delayed by T, its history the cubic Hermite of x and dx/dt
    (or the method's own dense output at the points pushed from it)."""
    dly = transport_delay(1, T, input="x", derivative="dx", output="y", name="delay")
    return ct.interconnect([logistic_block(), dly], inplist=[], outlist=["x[0]", "y[0]"],
                           name="log_delay")


def spring_loop():
    A = [[0.0, 1.0], [-W_SPRING ** 2, 0.0]]
    blk = ct.ss(A, np.zeros((2, 1)), np.eye(2), np.zeros((2, 1)), inputs=["u"],
                outputs=["x", "v"], states=["x", "v"], name="spring")
    with warnings.catch_warnings():      # its input (a zero B column) stays unconnected
        warnings.simplefilter("ignore", UserWarning)
        return ct.interconnect([blk], inplist=[], outlist=["x", "v"], name="spring_mass")


def spring_exact(t):
    return np.array([np.cos(W_SPRING * t), -W_SPRING * np.sin(W_SPRING * t)])


def _pr_upd(t, x, u, params):
    return np.array([-L_PR * (x[0] - np.cos(t)) - np.sin(t)])


def _pr_out(t, x, u, params):
    return np.array([x[0]])


def _rob_upd(t, x, u, params):
    return np.array([-0.04 * x[0] + 1e4 * x[1] * x[2],
                     0.04 * x[0] - 1e4 * x[1] * x[2] - 3e7 * x[1] * x[1],
                     3e7 * x[1] * x[1]])


def _rob_out(t, x, u, params):
    return np.array([x[0], x[1], x[2]])


def _diagram(blk, name):
    return ct.interconnect([blk], inplist=[], outlist=list(blk.output_labels), name=name)


_LOOPS = {}


def loop(name):
    """The reference diagrams, built once per session (each compiles once)."""
    if name not in _LOOPS:
        if name == "logistic":
            _LOOPS[name] = _diagram(logistic_block(), "logistic_loop")
        elif name == "spring":
            _LOOPS[name] = spring_loop()
        elif name == "prothero":
            _LOOPS[name] = _diagram(ct.nlsys(_pr_upd, _pr_out, inputs=0, outputs=["y"],
                                             states=["y"], name="prothero"), "prothero_loop")
        elif name == "robertson":
            _LOOPS[name] = _diagram(ct.nlsys(_rob_upd, _rob_out, inputs=0,
                                             outputs=["y1", "y2", "y3"],
                                             states=["y1", "y2", "y3"], name="robertson"),
                                    "robertson_loop")
        else:
            _LOOPS[name] = logistic_with_delay(float(name.split(":")[1]))
    return _LOOPS[name]


def run(row, diagram, t_end, x0, *, h, t_eval=None, **kw):
    """(output rows at t_eval, stats) of `row` on `diagram` from x0 over [0, t_end], steps
    h (h_max = h for an adaptive method unless given)."""
    t_eval = np.array([0.0, t_end]) if t_eval is None else np.asarray(t_eval, float)
    if row.adaptive:
        kw = {**LOOSE, "h_max": h, **kw}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim = Simulator(diagram, method=row, h=h, x0=np.asarray(x0, float), **kw)
    out_y = np.full((t_eval.size, diagram.noutputs), np.nan)
    try:
        n = sim.advance(t_end, out_t=t_eval.copy(), out_y=out_y)
    finally:
        sim.close()
    assert n == t_eval.size
    return out_y, sim.stats_dict()


def orders(errors, factor=2.0):
    e = np.asarray(errors)
    return np.log(e[:-1] / e[1:]) / np.log(factor)


# --------------------------------------------------------------------------- the registry
def test_every_row_is_consistent_and_in_the_c_header():
    from ivdrem.sim._cstepper import header_source
    hdr = header_source()
    assert len({m.id for m in ROWS}) == len(ROWS)
    for m in ROWS:
        assert re.search(rf"^#define {m.name.upper()} {m.id}$", hdr, flags=re.M), m.name
        assert (m.error_order == 0) == m.fixed_step, m.name   # only adaptive steps estimate
        assert 0 < m.error_order < m.order or m.fixed_step
        assert 0 < m.dense_order <= m.order
        assert m.rtol > 0 and m.atol > 0
    assert methods.DEFAULT_METHOD in methods.METHODS
    assert methods.method_info(methods.STIFF_METHOD).l_stable
    assert methods.method_info(methods.REFERENCE_METHOD).fixed_step


def test_unknown_names_are_refused():
    with pytest.raises(ValueError, match="unknown method 'nosuch'; choose one of"):
        methods.method_info("nosuch")
    with pytest.raises(ValueError, match="unknown method"):
        estimate_cost(1.0, noutputs=1, method="nosuch")


@pytest.mark.parametrize("engine", ["compiled", "reference"])
def test_an_id_without_a_step_function_is_an_error_not_another_method(engine):
    """A registry row whose id the stepper's method_step has no branch for stops the run
    (it used to run RK4 bit for bit under the new name)."""
    fake = dataclasses.replace(methods.method_info("rk4"), name="heun", id=99)
    sim = Simulator(loop("spring"), method=fake, engine=engine, h=0.01, x0=[1.0, 0.0])
    try:
        with pytest.raises(NotImplementedError, match=r"'heun' \(dispatch id 99"):
            sim.advance(0.1)
    finally:
        sim.close()


# --------------------------------------------------------------------------- order
# steps per unit time for the three refinements, per order: errors in the asymptotic range
# and above rounding.  Measured orders (logistic / spring-mass): Rodas5P 4.98, 4.97 /
# 5.80, 5.82 (a linear problem satisfies more of its order conditions), DP45 4.83, 4.93 /
# 4.62, 4.82, RK4 4.06, 4.03 / 4.13, 4.07, BS23 3.07, 3.03 / 2.93, 2.97
def _steps_per_unit_time(order):
    return (16, 32, 64) if order <= 3 else (8, 16, 32) if order <= 5 else (4, 8, 16)


@pytest.mark.parametrize("row", ROWS, ids=IDS)
@pytest.mark.parametrize("problem", ["logistic", "spring"])
def test_observed_order_from_step_refinement(row, problem):
    t_end = 4.0 if problem == "logistic" else 2.0
    x0 = [X0_LOG] if problem == "logistic" else [1.0, 0.0]
    exact = logistic_exact(t_end) if problem == "logistic" else spring_exact(t_end)
    errs = []
    for n in _steps_per_unit_time(row.order):
        h = 1.0 / n
        y, st = run(row, loop(problem), t_end, x0, h=h)
        assert st["steps"] == round(t_end / h) and st["rejected"] == 0, st
        x = y[-1, :1] if problem == "logistic" else y[-1]
        errs.append(float(np.max(np.abs(x - exact))))
    p = orders(errs)
    assert np.all(p > row.order - 0.45), (row.name, errs, p)
    if problem == "logistic":                  # nonlinear: the order, not more
        assert np.all(p < row.order + 0.4), (row.name, errs, p)
    assert errs[-1] > 1e-13, errs              # measured above rounding


# --------------------------------------------------------------------------- error estimate
@pytest.mark.parametrize("row", ROWS, ids=IDS)
def test_error_estimate_is_of_the_registered_order(row):
    """One step h from the exact state: the error estimate (weighted RMS norm times atol,
    rtol negligible) is O(h^(error_order + 1)); 0 for a method without one.  Measured:
    Rodas5P 5.22, 5.10, DP45 4.93, 4.97, BS23 3.04, 3.02."""
    ests = []
    for h in (0.1, 0.05, 0.025):
        _, st = run(row, loop("logistic"), h, [X0_LOG], h=h)
        assert st["steps"] == 1
        ests.append(st["last_error"] * LOOSE["atol"])
    if row.fixed_step:
        assert ests == [0.0, 0.0, 0.0]
        return
    p = orders(ests)
    assert np.all(np.abs(p - (row.error_order + 1)) < 0.4), (row.name, ests, p)


# --------------------------------------------------------------------------- dense output
@pytest.mark.parametrize("row", ROWS, ids=IDS)
def test_dense_output_is_of_the_registered_order(row):
    """x at the middle of the first step, read by a transport delay (T = 1.5 h) at t = 2 h:
    the delay's history is the method's dense output there (the step's midpoint pushed
    from it) or the cubic Hermite of the step's end values and slopes; one step from the
    exact state, so the error is O(h^(min(order, dense_order) + 1)).

    The error at the middle sums the interpolant's own error and a share of the step end's
    (one order higher, of the other sign for RK4 here: measured 1.3e-7, 1.5e-9, 1.7e-10,
    2.0e-11, pre-asymptotic), so the test bounds e / h^p over three halvings: an
    interpolant one order lower makes it grow 8x.  Measured orders of the last halving:
    Rodas5P 5.06, DP45 4.25, BS23 3.97."""
    errs, hs = [], np.array([0.2, 0.1, 0.05, 0.025])
    for h in hs.tolist():
        T = 1.5 * h
        y, _ = run(row, loop(f"delay:{T!r}"), 2 * h, [X0_LOG], h=h)
        errs.append(abs(float(y[-1, 1]) - float(logistic_exact(0.5 * h))))
    want = min(row.order, row.dense_order) + 1
    c = np.array(errs) / hs ** want
    assert c[-1] <= 2.0 * c[:-1].max() and errs[-1] > 1e-13, (row.name, errs, c)


# --------------------------------------------------------------------------- cost guard
@pytest.mark.parametrize("row", [m for m in ROWS if m.user], ids=[m.name for m in ROWS
                                                                   if m.user])
@pytest.mark.parametrize("t_end, h", [(1.0, 0.1), (1.0, 0.3), (0.5, 0.01)])
def test_guards_price_a_method_from_its_step_count(row, t_end, h):
    """A fixed-step method's estimate is its real step count; an adaptive one's a lower
    bound (its steps never exceed h_max)."""
    est = estimate_cost(t_end, noutputs=2, method=row.name, h=h, h_max=h)
    _, st = run(row, loop("spring"), t_end, [1.0, 0.0], h=h,
                **({} if row.fixed_step else dict(rtol=1e-8, atol=1e-10)))
    if row.fixed_step:
        assert est.steps_min == st["steps"], (est, st["steps"])
    else:
        assert est.steps_min <= st["steps"], (est, st["steps"])


# --------------------------------------------------------------------------- stiff problems
@pytest.mark.parametrize("row", [m for m in ROWS if m.l_stable],
                         ids=[m.name for m in ROWS if m.l_stable])
def test_l_stable_methods_solve_stiff_problems_in_few_steps(row):
    """Prothero-Robinson at L = 1e6 (an explicit method needs ~L steps per unit time) and
    Robertson to t = 40 against scipy's Radau, at the method's default tolerances."""
    r = simulate(loop("prothero"), 2.0, initial_state=[1.0], method=row.name,
                 t_eval=[0.0, 1.0, 2.0], progress=False)
    assert r.stats["steps"] < 100, r.stats
    # the step ends to ~1e-9, the dense output inside a step to the tolerance (measured
    # 1.1e-4 at t = 1 at rtol 2e-4: the error control bounds the step's end only)
    assert np.max(np.abs(r.outputs - np.cos([0.0, 1.0, 2.0]))) < 2 * row.rtol
    ref = solve_ivp(lambda t, y: _rob_upd(t, y, None, None), (0.0, 40.0), [1.0, 0.0, 0.0],
                    method="Radau", rtol=1e-10, atol=[1e-12, 1e-16, 1e-12])
    assert ref.success
    r = simulate(loop("robertson"), 40.0, initial_state=[1.0, 0.0, 0.0], method=row.name,
                 t_eval=[0.0, 40.0], h=1e-6, progress=False)
    assert r.stats["steps"] < 300, r.stats
    got, want = np.asarray(r.outputs)[:, -1], ref.y[:, -1]
    assert np.all(np.abs(got - want) <= 1e-3 * np.abs(want) + 1e-12), (got, want)
