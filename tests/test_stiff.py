"""The stiff method (Rodas5P) and the integrator loop, tested apart from the paper's diagram.

The stepping template is executed in Python here (as the reference engine does) with small
problems whose solutions are known: its tableau against the Rosenbrock order conditions,
its stability function, its order by step refinement, its dense output, a stiff problem
with an analytic solution through the loop.  The loop's checks (growth-rate divergence,
the stiffness warning, unknown method names, compile/simulation time) run on small
diagrams.  Oracles: Hairer & Wanner, Solving ODEs II, sec. IV.7 (order conditions of
Rosenbrock methods through rooted trees; transformed coefficients), closed-form solutions.
"""
from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

import ivdrem.sim as sim
from ivdrem.sim import _template as tpl
from ivdrem.sim.tables import empty_tables, pack, with_fill_runs
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
        ns = _template_ns(lambda t, x, out: out.__setitem__(0, hl * x[0]),
                          lambda t, x, J: J.__setitem__((0, 0), hl))
        x1, _, _ = _one_step(ns, "rodas5p_step", 0.0, 1.0, np.array([1.0]))
        assert abs(x1[0] - _stability_function(hl).real) < 1e-12 * max(1, abs(x1[0])), hl


# ------------------------------------------------------ the template, run in Python
def _template_ns(f, jac):
    """The stepping template with diagram_eval = f (mode RHS), RECORD = the state."""
    src = Path(tpl.__file__).read_text()
    ns = {"__name__": "test_template"}
    exec(compile(src, tpl.__file__, "exec"), ns)

    def diagram_eval(mode, t, x, P, W, out):
        if mode == tpl.RHS:
            f(t, x, out)
        elif mode == tpl.RECORD:
            out[:] = x
        return tpl.OK

    def diagram_jacobian(t, x, P, W, J):
        jac(t, x, J)
        return tpl.OK
    ns.update(diagram_eval=diagram_eval, diagram_jacobian=diagram_jacobian,
              newton_factor=lambda W, J, c, LU, piv: ns["dense_factor"](J, c, LU, piv),
              newton_solve=lambda W, LU, piv, b: ns["dense_solve"](LU, piv, b))
    return ns


def _workspace(n):
    z = np.zeros
    return sim.Workspace(z(4), z((4, 0)), z((4, 0)), np.array([0, 0, 4, 0], dtype=np.int64),
                         z(0), z(0), z(0), z(0), z(0), z(0), z(0, dtype=np.int64), z(0),
                         z((0, 1)), z(1, dtype=np.int64), z(1), z(0), z((0, 0)),
                         z(1, dtype=np.int64), z(2), *pack(empty_tables()), z(0),
                         z(1, dtype=np.int64), z(2, dtype=np.uint8), z(8, dtype=np.int32))


def _one_step(ns, step, t, h, x):
    n = x.size
    K = np.zeros((tpl.K_ROWS, n))
    ns["diagram_eval"](tpl.RHS, t, x, None, None, K[0])
    xn = np.zeros(n)
    stats = np.zeros(tpl.N_STATS, dtype=np.int64)
    err = ns[step](t, h, x, xn, K, np.zeros((n, n)), np.zeros((n, n)),
                   np.zeros(n, dtype=np.int64), None, _workspace(n), 1e-6, 1e-8, stats)
    return xn, err, K


# y1 = sin t, y2 = exp(-t) sin(t)-coupled, non-autonomous and nonlinear
def _f_smooth(t, x, out):
    out[0] = -x[0] ** 2 + math.sin(t) ** 2 + math.cos(t)
    out[1] = -2.0 * x[1] + x[0] * x[1] + (1.0 - math.sin(t)) * x[1]


def _j_smooth(t, x, J):
    J[0, 0] = -2.0 * x[0]
    J[0, 1] = 0.0
    J[1, 0] = x[1]
    J[1, 1] = -2.0 + x[0] + 1.0 - math.sin(t)


def _exact_smooth(t):
    return np.array([math.sin(t), math.exp(-t)])


def _refinement(ns, step, nsteps):
    """Errors at t = 2 of fixed steps of `step` from the exact value at 0 (the smooth
    problem), one per number of steps, and the ratios of consecutive errors."""
    errs = []
    for nstep in nsteps:
        h = 2.0 / nstep
        x = _exact_smooth(0.0)
        for k in range(nstep):
            x, _, _ = _one_step(ns, step, k * h, h, x)
        errs.append(np.abs(x - _exact_smooth(2.0)).max())
    return errs, [errs[i] / errs[i + 1] for i in range(len(errs) - 1)]


def test_rodas5p_converges_with_order_5():
    """Fixed steps on a nonlinear, time-dependent problem (exact solution y = (sin t, e^-t)):
    the error at t = 2 falls by ~2^5 per halving.  Measured ratios 31-33."""
    errs, ratios = _refinement(_template_ns(_f_smooth, _j_smooth), "rodas5p_step",
                               (10, 20, 40, 80))
    assert all(26 < r < 40 for r in ratios), (errs, ratios)


def test_rodas5p_error_estimate_and_dense_output_orders():
    """From the exact value at t = 0.3: the local error is O(h^6), the embedded error
    estimate O(h^5), the dense output at s = 0.4 O(h^5) (an order-4 interpolant)."""
    ns = _template_ns(_f_smooth, _j_smooth)
    loc, est, den = [], [], []
    t0 = 0.3
    for h in (0.2, 0.1, 0.05):
        x0 = _exact_smooth(t0)
        xn, err, K = _one_step(ns, "rodas5p_step", t0, h, x0)
        loc.append(np.abs(xn - _exact_smooth(t0 + h)).max())
        est.append(np.abs(K[8]).max())
        out = np.zeros(2)
        ns["dense_eval"](tpl.RODAS5P, h, 0.4, x0, xn, K[0], None, K, out)
        den.append(np.abs(out - _exact_smooth(t0 + 0.4 * h)).max())
    for e, p in ((loc, 6), (est, 5), (den, 5)):
        r = [math.log2(e[i] / e[i + 1]) for i in range(2)]
        assert all(p - 0.6 < ri < p + 1.0 for ri in r), (p, e, r)
    # the dense output reproduces both ends
    out = np.zeros(2)
    ns["dense_eval"](tpl.RODAS5P, 0.05, 1.0, x0, xn, K[0], None, K, out)
    assert np.allclose(out, xn, rtol=0, atol=1e-15)


def _run_loop(ns, mid, x0, t_end, out_t, rtol, atol, h0=1e-3, h_max=np.inf,
              adaptive=True, dense=True):
    n = x0.size
    x = x0.copy()
    tf = np.zeros(tpl.N_TF)
    tf[tpl.F_H] = h0
    out_y = np.full((out_t.size, n), np.nan)
    io = np.array([0, out_t.size], dtype=np.int64)
    stats = np.zeros(tpl.N_STATS, dtype=np.int64)
    ctl = np.array([rtol, atol, h_max, 1e7, 1e10, float(adaptive), float(dense), 0.0])
    st = ns["integrate"](mid, tf, t_end, x, None, _workspace(n), out_t.copy(), out_y,
                         np.zeros((out_t.size, 0)), io, stats, ctl)
    assert st == tpl.OK
    return x, out_y, stats


def test_rodas5p_loop_on_a_stiff_problem_with_analytic_solution():
    """Prothero-Robinson y' = lambda (y - g(t)) + g'(t), g = sin t, lambda = -1e6, plus a
    stiff linear pair with eigenvalues -1 and -1e4: the adaptive loop follows the exact
    solutions over 10 s with steps far beyond 2/|lambda| (30 steps), and the outputs read
    from the dense output match too.  Measured: end-point errors 1e-7; outputs 1e-7 on the
    non-stiff pair, 1.3e-5 on the Prothero-Robinson component, where the interpolant drops
    to order 3 in the stiff limit (single steps: 6.6e-6, 3.9e-7, 2.4e-8 at h = 0.4, 0.2, 0.1)."""
    lam = -1e6
    A = np.array([[-1.0, 0.0], [1e4 - 1.0, -1e4]])   # eigenvalues -1, -1e4

    def f(t, x, out):
        out[0] = lam * (x[0] - math.sin(t)) + math.cos(t)
        out[1:] = A @ x[1:]

    def jac(t, x, J):
        J[:] = 0.0
        J[0, 0] = lam
        J[1:, 1:] = A

    def exact(t):
        # x2 = e^-t, x3 = e^-t (the fast mode is not excited from (1, 1))
        return np.array([math.sin(t), math.exp(-t), math.exp(-t)])
    ns = _template_ns(f, jac)
    out_t = np.linspace(0.0, 10.0, 41)[1:]
    x, out_y, stats = _run_loop(ns, tpl.RODAS5P, exact(0.0), 10.0, out_t, 1e-6, 1e-9)
    assert np.abs(x - exact(10.0)).max() < 1e-6
    ex = np.array([exact(t) for t in out_t])
    assert np.abs(out_y[:, 1:] - ex[:, 1:]).max() < 1e-6
    assert np.abs(out_y[:, 0] - ex[:, 0]).max() < 5e-5
    assert stats[tpl.S_STEPS] < 300 and stats[tpl.S_JAC] >= stats[tpl.S_STEPS]
    # the same problem perturbed off the slow manifold: the fast transient is damped (L-stable)
    x0 = exact(0.0) + np.array([1.0, 0.0, 0.5])
    x, _, _ = _run_loop(ns, tpl.RODAS5P, x0, 10.0, out_t, 1e-6, 1e-9)
    assert np.abs(x - exact(10.0)).max() < 1e-6


def test_bs23_converges_with_order_3_and_estimates_its_error_with_order_3():
    """Bogacki-Shampine 3(2), fixed steps on the smooth problem: the error at t = 2 falls by
    ~2^3 per halving, and one step's error estimate (x_new minus the order-2 solution) is
    O(h^3) and bounds the true local error (O(h^4)) from above."""
    ns = _template_ns(_f_smooth, _j_smooth)
    errs, ratios = _refinement(ns, "bs23_step", (20, 40, 80, 160))
    assert all(6.5 < r < 9.5 for r in ratios), (errs, ratios)
    est, loc = [], []
    for h in (0.2, 0.1, 0.05):
        x0 = _exact_smooth(0.3)
        xn, err, K = _one_step(ns, "bs23_step", 0.3, h, x0)
        loc.append(np.abs(xn - _exact_smooth(0.3 + h)).max())
        # the weighted norm back to the largest component: estimate = err * scale
        f0, f1 = K[0], K[6]
        e = h * (-5 / 72 * f0 + 1 / 12 * K[1] + 1 / 9 * K[5] - 1 / 8 * f1)
        est.append(np.abs(e).max())
        sc = 1e-8 + 1e-6 * np.maximum(np.abs(x0), np.abs(xn))
        assert err == pytest.approx(np.sqrt(np.mean((e / sc) ** 2)), rel=1e-12)
        # FSAL: the last stage is f at the new point
        out = np.zeros(2)
        _f_smooth(0.3 + h, xn, out)
        assert np.array_equal(out, f1)
    for e, p in ((est, 3), (loc, 4)):
        r = [math.log2(e[i] / e[i + 1]) for i in range(2)]
        assert all(p - 0.6 < ri < p + 0.8 for ri in r), (p, e, r)
    assert all(a > b for a, b in zip(est, loc))


def test_dp45_through_the_loop_matches_the_smooth_solution():
    """The same loop with DP45 and BS23 (landing on outputs; BS23 as a loop method only
    here) and RK4 (fixed step) on the smooth problem: each within its accuracy of the exact
    solution at the outputs."""
    ns = _template_ns(_f_smooth, _j_smooth)
    out_t = np.linspace(0.0, 2.0, 21)[1:]
    ex = np.array([_exact_smooth(t) for t in out_t])
    _, y, _ = _run_loop(ns, tpl.DP45, _exact_smooth(0.0), 2.0, out_t, 1e-9, 1e-12, dense=False)
    assert np.abs(y - ex).max() < 1e-8
    _, y, st = _run_loop(ns, tpl.BS23, _exact_smooth(0.0), 2.0, out_t, 1e-8, 1e-11,
                         dense=False)
    assert np.abs(y - ex).max() < 1e-7 and st[tpl.S_REJECTED] < st[tpl.S_STEPS] / 10
    _, y, st = _run_loop(ns, tpl.RK4, _exact_smooth(0.0), 2.0, out_t, 1e-9, 1e-12, h0=1e-2,
                         adaptive=False, dense=False)
    assert st[tpl.S_STEPS] == 200
    assert np.abs(y - ex).max() < 1e-8


# ---------------------------------------------------------------- the simulator's API
def test_method_table_is_the_one_source_of_names():
    """Names come from one table; each row's step function exists in the template and
    method_step dispatches its id to it; an unknown name is an error naming the valid ones."""
    assert METHODS == tuple(METHOD_TABLE) and isinstance(METHODS, tuple)
    assert {"rodas5p", "dp45", "rk4"} <= set(METHODS)
    assert sim.STIFF_METHOD in METHODS and METHOD_TABLE[sim.STIFF_METHOD].l_stable
    src = Path(tpl.__file__).read_text()
    for name, info in METHOD_TABLE.items():
        assert f"def {info.step}(" in src
        assert info.id in (tpl.RK4, tpl.DP45, tpl.RODAS5P)
    assert len({info.id for info in METHOD_TABLE.values()}) == len(METHOD_TABLE)
    assert set(sim.DEFAULT_TOLERANCES) == set(METHODS)
    # BS23 only takes a Rodas5P run's pinned steps: no user method
    assert tpl.BS23 not in {info.id for info in METHOD_TABLE.values()}
    from ivdrem.experiments.config import SOLVER_METHODS
    assert tuple(SOLVER_METHODS) == METHODS
    d = build_lab()
    with pytest.raises(ValueError, match=r"unknown method 'rodas'; choose one of rodas5p, dp45"):
        simulate(d, 1.0, method="rodas", engine="reference", progress=False)


def test_rodas5p_and_dp45_agree_on_the_lab_diagram_reference_engine():
    """Delays (Hermite and plain) and the max-hold on the reference engine: Rodas5P with
    tight tolerances matches DP45; the hold fires at the same sampling time t_e."""
    d = build_lab()
    # h_max: the plain delay's history slopes come from quadratics through history points,
    # accurate only when those are close (both methods alike)
    a = simulate(d, 2.0, method="dp45", engine="reference", rtol=1e-9, atol=1e-11,
                 h_max=2e-3, progress=False)
    b = simulate(d, 2.0, method="rodas5p", engine="reference", rtol=1e-7, atol=1e-10,
                 h_max=2e-3, progress=False)
    A, Bo = np.asarray(a.outputs), np.asarray(b.outputs)
    assert np.abs(A - Bo).max() <= 1e-6 * max(1.0, np.abs(A).max())
    assert a.hold_times[0] == b.hold_times[0]
    # t_e is a sampling time (multiple of dt_sample = 1 ms)
    assert abs(a.hold_times[0] * 1e3 - round(a.hold_times[0] * 1e3)) < 1e-6
    # steps pinned to the sampling grid by hold updates may be explicit (BS23) steps
    assert b.stats["jacobians"] + b.stats["explicit_steps"] >= b.stats["steps"] > 0


def test_pinned_explicit_steps_give_way_to_rodas5p_on_a_stiff_mode():
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
    lab = build_lab()
    d = assemble(lab_blocks() + [pr], LAB_OUTPUTS + ["pr_y"], name="lab_pr")
    kw = dict(engine="reference", rtol=1e-7, atol=1e-10, h_max=2e-3, dt_out=0.01,
              progress=False)
    a = simulate(lab, 2.0, method="rodas5p", **kw)
    b = simulate(d, 2.0, method="rodas5p", **kw)
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
