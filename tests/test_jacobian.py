"""The generated Jacobian (ivdrem/sim/jacobian.py) and the static-pattern LU
(ivdrem/sim/sparse_lu.py) against independent evaluations.

* a tiny hand-made diagram whose df/dx is known in closed form (chain rule through a
  direct-feedthrough block, a negative gain and a sum of two outputs in the connection map);
* the paper's closed loops: the generated J against careful central differences of the
  whole right-hand side at random states (after a short run, so delays and holds are live);
* c I - J solved with the sparse LU against numpy's dense solve, and the SINGULAR guard.
"""
from __future__ import annotations

import numpy as np
import pytest

from ivdrem.blocks import BlockSpec, make_block
from ivdrem.diagrams import assemble
from ivdrem.sim.simulator import Simulator
from ivdrem.sim._stepper_codes import SINGULAR

from conftest import paper_loop

TINY_A, TINY_B = 2.5, 0.75


# ---------------------------------------------------------------- tiny diagram kernels
def osc_update(t, x, u, dx, a):
    # states x[2]; input u[1]; dx = [x1, -a x0 + u]
    dx[0] = x[1]
    dx[1] = -a * x[0] + u[0]


def osc_output(t, x, u, y, a):
    # outputs y = [x0 x1, sin x0]
    y[0] = x[0] * x[1]
    y[1] = np.sin(x[0])


def osc_jacobian(t, x, u, jac, a):
    # the block's own Jacobian: rows [y0, y1, dx0, dx1], columns [x0, x1, u0]
    jac[0, 0] = x[1]
    jac[0, 1] = x[0]
    jac[1, 0] = np.cos(x[0])
    jac[2, 1] = 1.0
    jac[3, 0] = -a
    jac[3, 2] = 1.0


def mix_output(t, x, u, y):
    # direct feedthrough: w = v0^2 + 3 v1
    y[0] = u[0] * u[0] + 3.0 * u[1]


def decay_update(t, x, u, dx):
    dx[0] = -x[0] * u[0]


def decay_output(t, x, u, y):
    y[0] = x[0]


def grow_update(t, x, u, dx, b):
    dx[0] = b * x[0]


def grow_output(t, x, u, y, b):
    y[0] = x[0]


def source_update(t, x, u, dx):
    dx[0] = -x[0]


def leaky_output(t, x, u, y):
    # uses its input but declares no direct feedthrough (a wrong declaration)
    y[0] = x[0] + u[0]


def tiny_diagram():
    blocks = [
        make_block(BlockSpec("osc", [("u", 1)], [("y", 2)], [("x", 2)], np.array([0.3, -0.2]),
                             ("a",), osc_output, osc_update, jacobian=osc_jacobian),
                   {"a": TINY_A}),
        make_block(BlockSpec("mix", [("v", 2)], [("w", 1)], [], np.zeros(0), (), mix_output,
                             direct=("v",))),
        make_block(BlockSpec("decay", [("w", 1)], [("zo", 1)], [("z", 1)], np.ones(1), (),
                             decay_output, decay_update)),
        make_block(BlockSpec("grow", [], [("g", 1)], [("g", 1)], np.ones(1), ("b",),
                             grow_output, grow_update), {"b": TINY_B}),
    ]
    conns = [["osc.u[0]", "-decay.zo[0]", "grow.g[0]"],
             ["mix.v[0]", "osc.y[0]"], ["mix.v[1]", "osc.y[1]"],
             ["decay.w[0]", "mix.w[0]"]]
    return assemble(blocks, ["zo"], name="tiny_jacobian", connections=conns)


def tiny_exact(x):
    x0, x1, z, g = x
    s = x0 ** 2 * x1 ** 2 + 3.0 * np.sin(x0)
    return np.array([[0.0, 1.0, 0.0, 0.0],
                     [-TINY_A, 0.0, -1.0, 1.0],
                     [-z * (2 * x0 * x1 ** 2 + 3 * np.cos(x0)), -z * 2 * x0 ** 2 * x1, -s, 0.0],
                     [0.0, 0.0, 0.0, TINY_B]])


def central_fd(engine, t, x, W):
    """Central differences of the whole right-hand side, step 1e-5 max(|x_j|, 1)."""
    n = x.size
    J = np.zeros((n, n))
    for j in range(n):
        h = 1e-5 * max(abs(x[j]), 1.0)
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        J[:, j] = (engine.rhs(t, xp, W) - engine.rhs(t, xm, W)) / (xp[j] - xm[j])
    return J


def assert_jacobian_close(J, Jfd, rtol=1e-6):
    scale = np.abs(Jfd).max()
    assert np.linalg.norm(J - Jfd) <= rtol * np.linalg.norm(Jfd)
    big = np.abs(Jfd) >= 1e-3 * scale
    rel = np.abs(J - Jfd)[big] / np.abs(Jfd)[big]
    assert rel.max() <= rtol, f"worst entry-wise relative error {rel.max():.2e}"
    # the structural pattern holds every entry the whole-system differences see
    assert np.abs(Jfd[J == 0.0]).max(initial=0.0) <= 1e-9 * scale


@pytest.fixture(scope="module")
def tiny():
    return Simulator(tiny_diagram())


def test_chain_rule_on_tiny_diagram(tiny):
    """osc supplies its own Jacobian kernel; mix, decay and grow are differenced alone."""
    rng = np.random.default_rng(3)
    for _ in range(3):
        x = rng.uniform(-1.5, 1.5, size=4)
        J = tiny.engine.jacobian(0.4, x, tiny.W)
        # mix and decay are forward-differenced (step sqrt(eps) max(|v|, 1)): ~1e-8 relative
        np.testing.assert_allclose(J, tiny_exact(x), rtol=1e-7, atol=1e-9)
        # osc's rows come from its own kernel, exactly (differences would be ~1e-8 off)
        assert J[0, 1] == 1.0 and J[1, 0] == -TINY_A
        # and the whole-system dense fallback agrees to its own (forward-difference) accuracy
        np.testing.assert_allclose(tiny.engine.jacobian(0.4, x, tiny.W, dense=True),
                                   tiny_exact(x), rtol=1e-5, atol=1e-6)


def added_osc_jacobian(t, x, u, jac, a):
    # osc_jacobian with its rows added into the buffer (kernels may), raising part-way
    # through for x0 > 10 (a kernel that fails after it wrote)
    jac[0, 0] += x[1]
    jac[0, 1] += x[0]
    jac[1, 0] += np.cos(x[0])
    if x[0] > 10.0:
        raise ValueError("x0 above 10 for the test")
    jac[2, 1] += 1.0
    jac[3, 0] += -a
    jac[3, 2] += 1.0


def test_a_jacobian_kernel_that_raised_leaves_no_stale_entries():
    """A Jacobian kernel's buffer holds 0 at every entry read before the kernel runs (it
    may add into them: cleared as it is read).  A kernel that raises after writing leaves
    entries behind: the next Jacobian of the same workspace clears the whole buffer first,
    so it equals one from a fresh workspace; and repeated Jacobians do not accumulate."""
    from ivdrem.sim.errors import BlockError
    blocks = [
        make_block(BlockSpec("osc", [("u", 1)], [("y", 2)], [("x", 2)], np.array([0.3, -0.2]),
                             ("a",), osc_output, osc_update, jacobian=added_osc_jacobian),
                   {"a": TINY_A}),
        make_block(BlockSpec("grow", [], [("g", 1)], [("g", 1)], np.ones(1), ("b",),
                             grow_output, grow_update), {"b": TINY_B})]
    d = assemble(blocks, ["y"], name="tiny_raising_jacobian", connections=[["osc.u[0]", "grow.g[0]"]])
    sim = Simulator(d)
    x = np.array([0.4, -0.3, 1.2])
    first = sim.engine.jacobian(0.4, x, sim.W)
    np.testing.assert_array_equal(sim.engine.jacobian(0.4, x, sim.W), first)
    assert first[0, 1] == 1.0 and first[1, 0] == -TINY_A
    with pytest.raises(BlockError, match="block .osc. raised .*x0 above 10 for the test.*jacobian"):
        sim.engine.jacobian(0.4, np.array([11.0, -0.3, 1.2]), sim.W)
    assert sim.W.jac_dirty[0] == 1
    np.testing.assert_array_equal(sim.engine.jacobian(0.4, x, sim.W), first)
    assert sim.W.jac_dirty[0] == 0
    np.testing.assert_array_equal(sim.engine.jacobian(0.4, x, Simulator(d).W), first)


def test_singular_pivot_is_reported(tiny):
    x = np.array([0.4, -0.3, 0.8, 1.2])
    J = tiny.engine.jacobian(0.0, x, tiny.W)
    # the row of g holds only d(dg)/dg = b (differenced: b to ~1e-8): c = J[3, 3] makes
    # c I - J exactly singular
    assert J[3, 3] == pytest.approx(TINY_B, rel=1e-7)
    st, _, _ = tiny.engine.factor(J, J[3, 3])
    assert st == SINGULAR
    st, _, _ = tiny.engine.factor(J, J[3, 3], dense=True)
    assert st == SINGULAR
    Jnan = J.copy()
    Jnan[2, 0] = np.nan
    assert tiny.engine.factor(Jnan, 10.0)[0] == SINGULAR
    st, LU, piv = tiny.engine.factor(J, 10.0)
    assert st == 0
    b = np.array([1.0, -2.0, 0.5, 3.0])
    np.testing.assert_allclose(tiny.engine.solve(LU, piv, b),
                               np.linalg.solve(10.0 * np.eye(4) - J, b), rtol=1e-13)


def test_undeclared_feedthrough_is_an_error():
    from ivdrem.sim.compiled import generate_source
    from ivdrem.sim.jacobian import DeclarationError
    from ivdrem.sim.plan import DiagramPlan
    src = make_block(BlockSpec("src", [], [("s", 1)], [("s", 1)], np.ones(1), (),
                               decay_output, source_update))
    leaky = make_block(BlockSpec("leaky", [("s", 1)], [("o", 1)], [("o", 1)], np.ones(1), (),
                                 leaky_output, decay_update))
    d = assemble([src, leaky], ["o"], name="leaky",
                 connections=[["leaky.s[0]", "src.s[0]"]])
    with pytest.raises(DeclarationError, match="direct feedthrough"):
        generate_source(DiagramPlan.from_diagram(d))


def _loop_at_random_states(diagram, seeds, t_run=1.5):
    sim = Simulator(diagram)
    sim.advance(t_run)
    out = []
    for s in seeds:
        rng = np.random.default_rng(s)
        x = sim.x * rng.uniform(0.8, 1.2, sim.x.size) + 0.05 * rng.standard_normal(sim.x.size)
        out.append(x)
    return sim, out


@pytest.mark.parametrize("law", ["iv-drem", "composite-learning"])
def test_generated_jacobian_matches_whole_system_differences(law):
    sim, states = _loop_at_random_states(paper_loop(law), seeds=[0, 1])
    # the robot-model blocks are not differenced: their own kernels are compiled and called
    with_jac = {name for name, role, _ in sim.engine.wrappers if role == "jacobian"}
    model_blocks = {"plant", "torque_observer", "regression_filter"}
    model_blocks |= {"instrument"} if law == "iv-drem" else set()
    assert model_blocks <= with_jac, sorted(model_blocks - with_jac)
    for x in states:
        J = sim.engine.jacobian(sim.t, x, sim.W)
        assert_jacobian_close(J, central_fd(sim.engine, sim.t, x, sim.W))


@pytest.mark.slow
def test_generated_jacobian_planar_arm_3():
    loop = _planar3_loop()
    sim, states = _loop_at_random_states(loop, [5], t_run=0.5)
    J = sim.engine.jacobian(sim.t, states[0], sim.W)
    assert_jacobian_close(J, central_fd(sim.engine, sim.t, states[0], sim.W))


def test_sparse_lu_matches_dense_solve():
    sim, (x,) = _loop_at_random_states(paper_loop("iv-drem"), seeds=[7])
    J = sim.engine.jacobian(sim.t, x, sim.W)
    rng = np.random.default_rng(11)
    for c in (10.0, 1e2, 1e3, 1e5):
        st, LU, piv = sim.engine.factor(J, c)
        assert st == 0
        for _ in range(2):
            b = rng.standard_normal(x.size)
            ref = np.linalg.solve(c * np.eye(x.size) - J, b)
            got = sim.engine.solve(LU, piv, b)
            assert np.linalg.norm(got - ref) <= 1e-12 * np.linalg.norm(ref)
            # the dense fallback (partial pivoting) agrees as well
            st_d, LUd, pivd = sim.engine.factor(J, c, dense=True)
            assert st_d == 0
            assert np.linalg.norm(sim.engine.solve(LUd, pivd, b, dense=True) - ref) \
                <= 1e-12 * np.linalg.norm(ref)


def test_symbolic_lu_is_computed_once_per_pattern_and_equals_a_fresh_one():
    from ivdrem.sim import sparse_lu
    rng = np.random.default_rng(5)
    pat = rng.random((40, 40)) < 0.08
    sparse_lu._SYMBOLIC.clear()
    first = sparse_lu.symbolic_lu(pat)
    assert sparse_lu.symbolic_lu(pat.copy()) is first          # same pattern: no new work
    fresh = sparse_lu._symbolic_lu(pat)
    for f in ("perm", "rowptr", "colidx", "diagp"):
        assert np.array_equal(getattr(first, f), getattr(fresh, f))
        assert not getattr(first, f).flags.writeable
    other = pat.copy()
    other[0, 39] = not other[0, 39]
    assert sparse_lu.symbolic_lu(other) is not first           # another pattern: its own


def test_unprobeable_block_is_dense_within_its_declaration():
    """A plant whose parameters make M(q) indefinite everywhere gives no finite probe: the
    block is taken as dense over its states and declared inputs, with no false
    declaration error, and the run itself reports the model's problem."""
    import pytest
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import two_link
    from ivdrem.sim import SimulationError, simulate
    from ivdrem.sim.jacobian import block_pattern
    from ivdrem.sim.plan import DiagramPlan
    from ivdrem.blocks._core import kernel_args
    theta = [-1.3, 0.28, 0.32, 0.4, 1.4]
    diagram = closed_loop("iv-drem", two_link(), theta=theta)
    plan = DiagramPlan.from_diagram(diagram)
    plant = next(b for b in plan.blocks if b.sys.name == "plant")
    args = kernel_args(plant.spec, plan.block_params(plant))
    assert block_pattern(plant.spec, args, plant.sys.nstates, plant.sys.ninputs,
                         plant.sys.noutputs) is None
    with pytest.raises(SimulationError, match="positive definite"):
        simulate(diagram, 0.1)


def _user_lag_update(t, x, u, params):
    return -x + u


def _user_lag_output(t, x, u, params):
    return x


def test_pattern_cache_returns_the_probe_and_keys_on_what_the_probe_reads(tmp_path,
                                                                          monkeypatch):
    """The in-process pattern cache gives what a fresh probe gives, a copy each time, and
    probes again for another parameter value or a block ivdrem did not write."""
    import control as ct
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import two_link
    from ivdrem.sim import jacobian as jac
    from ivdrem.sim.foreign import adapt_block
    from ivdrem.sim.plan import DiagramPlan
    from ivdrem.blocks._core import kernel_args
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))     # no pattern on disk yet
    plan = DiagramPlan.from_diagram(closed_loop("iv-drem", two_link()))
    calls = []
    real = jac.block_pattern

    def counted(*a, **k):
        calls.append(a[0])
        return real(*a, **k)

    jac._PATTERNS.clear()
    jac.block_pattern, saved = counted, jac.block_pattern
    try:
        for b in plan.blocks:
            if b.spec.kind != "ode" or b.sys.nstates + b.sys.ninputs == 0:
                continue
            args = kernel_args(b.spec, plan.block_params(b))
            sizes = (b.sys.nstates, b.sys.ninputs, b.sys.noutputs)
            first = jac.cached_block_pattern(b.spec, args, *sizes, seed=3)
            n = len(calls)
            again = jac.cached_block_pattern(b.spec, args, *sizes, seed=3)
            assert len(calls) == n                       # no second probe
            assert np.array_equal(again, first) and again is not first
            assert np.array_equal(again, real(b.spec, args, *sizes, seed=3))
            again[...] = ~again                           # a copy: the cache is untouched
            assert np.array_equal(jac.cached_block_pattern(b.spec, args, *sizes, seed=3),
                                  first)
            if any(np.asarray(a).dtype.kind == "f" for a in args):  # another value: probed again
                other = [np.asarray(a) * 1.5 + 0.25
                         if np.asarray(a).dtype.kind == "f" else a for a in args]
                jac.cached_block_pattern(b.spec, other, *sizes, seed=3)
                assert len(calls) == n + 1
        # a user's nlsys is probed every time
        user = ct.nlsys(_user_lag_update, _user_lag_output, inputs=1, states=1, outputs=1,
                        name="user")
        spec = adapt_block(user, {})
        uargs = kernel_args(spec, {})
        n = len(calls)
        for _ in range(2):
            assert jac.cached_block_pattern(spec, uargs, 1, 1, 1) is not None
        assert len(calls) == n + 2
    finally:
        jac.block_pattern = saved


def _plan_blocks():
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import two_link
    from ivdrem.sim.plan import DiagramPlan
    from ivdrem.blocks._core import kernel_args
    plan = DiagramPlan.from_diagram(closed_loop("iv-drem", two_link()))
    for b in plan.blocks:
        if b.spec.kind == "ode" and b.sys.nstates + b.sys.ninputs:
            yield (b.spec, kernel_args(b.spec, plan.block_params(b)),
                   (b.sys.nstates, b.sys.ninputs, b.sys.noutputs))


def test_probed_patterns_are_kept_on_disk_for_the_next_process(tmp_path, monkeypatch):
    """A pattern probed in one process is read back from the cache by the next (no probe),
    equal to the probe; a changed ivdrem source, parameter value or seed, and a damaged
    file, are probed again; a block whose kernels are not ivdrem's is never kept."""
    from ivdrem.sim import jacobian as jac
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    real, calls = jac.block_pattern, []

    def counted(*a, **k):
        calls.append(a[0])
        return real(*a, **k)

    monkeypatch.setattr(jac, "block_pattern", counted)
    blocks = list(_plan_blocks())
    jac._PATTERNS.clear()
    first = [jac.cached_block_pattern(spec, args, *sizes, seed=5) for spec, args, sizes in blocks]
    assert len(calls) == len(blocks)
    files = sorted((tmp_path / "patterns").glob("*.npy"))
    assert len(files) == len(blocks)

    jac._PATTERNS.clear()                                # as a new process starts
    again = [jac.cached_block_pattern(spec, args, *sizes, seed=5) for spec, args, sizes in blocks]
    assert len(calls) == len(blocks)                     # read, not probed
    for a, b in zip(first, again):
        assert (a is None and b is None) or np.array_equal(a, b)

    spec, args, sizes = next(x for x in blocks if any(np.asarray(a).dtype.kind == "f"
                                                      for a in x[1]))
    other = [np.asarray(a) * 1.5 + 0.25 if np.asarray(a).dtype.kind == "f" else a
             for a in args]
    for call in (lambda: jac.cached_block_pattern(spec, other, *sizes, seed=5),
                 lambda: jac.cached_block_pattern(spec, args, *sizes, seed=6)):
        jac._PATTERNS.clear()
        n = len(calls)
        call()
        assert len(calls) == n + 1                       # another value or seed: probed

    monkeypatch.setattr(jac, "_package_digest", lambda: "another ivdrem")
    jac._PATTERNS.clear()
    n = len(calls)
    jac.cached_block_pattern(spec, args, *sizes, seed=5)
    assert len(calls) == n + 1                           # another source: probed
    monkeypatch.undo()
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(jac, "block_pattern", counted)

    for f in files:
        f.write_bytes(b"not a pattern")
    jac._PATTERNS.clear()
    n = len(calls)
    mended = [jac.cached_block_pattern(s, a, *z, seed=5) for s, a, z in blocks]
    assert len(calls) == n + len(blocks)                 # damaged: probed again
    for a, b in zip(first, mended):
        assert (a is None and b is None) or np.array_equal(a, b)
    jac._PATTERNS.clear()
    n = len(calls)
    [jac.cached_block_pattern(s, a, *z, seed=5) for s, a, z in blocks]
    assert len(calls) == n                               # and rewritten whole

    user = BlockSpec(name="user_lag", inputs=[("u", 1)], outputs=[("y", 1)],
                     states=[("x", 1)], x0=np.zeros(1), param_names=(),
                     update=_user_spec_update, output=_user_spec_output)
    assert jac._pattern_path(user, ()) is None           # a user's kernels: memory only


def _user_spec_update(t, x, u, dx):
    dx[0] = u[0] - x[0]


def _user_spec_output(t, x, u, y):
    y[0] = x[0]


def test_two_processes_filling_the_pattern_cache_at_once_both_succeed(tmp_path, monkeypatch):
    """Two processes probing the same blocks into one empty cache both finish, and the
    cache then holds whole patterns equal to a probe."""
    import os
    import subprocess
    import sys
    code = ("import numpy as np, sys; sys.path.insert(0, %r); import test_jacobian as t; "
            "from ivdrem.sim import jacobian as jac; "
            "[jac.cached_block_pattern(s, a, *z, seed=5) for s, a, z in t._plan_blocks()]"
            % str(__import__("pathlib").Path(__file__).parent))
    env = {**os.environ, "IVDREM_CACHE_DIR": str(tmp_path)}
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env) for _ in range(2)]
    assert [p.wait(timeout=600) for p in procs] == [0, 0]
    from ivdrem.sim import jacobian as jac
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    for spec, args, sizes in _plan_blocks():
        path = jac._pattern_path(spec, jac._probe_inputs(spec, args, *sizes, 5))
        ok, pat = jac._read_pattern(path, (sizes[2] + sizes[0], sizes[0] + sizes[1]))
        assert ok
        probe = jac.block_pattern(spec, args, *sizes, seed=5)
        assert (pat is None and probe is None) or np.array_equal(pat, probe)
    assert not list((tmp_path / "patterns").glob(".*.tmp"))


def test_a_second_run_of_a_diagram_is_bit_for_bit_the_first(monkeypatch):
    """The second simulate() of a diagram reuses the tables the first kept in the process
    (nothing probed, built or read from disk again): same steps, same numbers."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import two_link
    from ivdrem.sim import compiled, simulate
    compiled._TABLES.clear()
    d = closed_loop("iv-drem", two_link())
    first = simulate(d, 3.0, progress=False)
    assert len(compiled._TABLES) == 1

    def again(*a, **k):
        raise AssertionError("built or read again")
    monkeypatch.setattr(compiled, "JacobianProgram", again)
    monkeypatch.setattr(compiled, "load_tables", again)
    second = simulate(d, 3.0, progress=False)
    assert first.stats["steps"] == second.stats["steps"]
    assert np.array_equal(first.outputs, second.outputs)
    assert np.array_equal(first.states, second.states)


# ------------------------------------------------- the blocks' own analytic Jacobians
def _flat(spec, role):
    """The block's kernel as f(t, x, u, out, *params) of flat vectors (named-port kernels
    get their views from the block framework, where it offers them)."""
    from ivdrem.blocks import _core
    if hasattr(_core, "flat_kernel"):
        return _core.flat_kernel(spec, role)
    return _core.bind_model(getattr(spec, role), spec.model)


def _block_central_fd(spec, args, t, v):
    """Central differences (step 1e-5 max(|v_j|, 1)) of the block's own update/output
    kernels: the local Jacobian [(ny + nx), (nx + nu)]."""
    nx, nu, ny = spec.nstates, spec.ninputs, spec.noutputs
    out, upd = _flat(spec, "output"), _flat(spec, "update") if nx else None

    def ev(w):
        yf = np.zeros(ny + nx)
        out(t, w[:nx].copy(), w[nx:].copy(), yf[:ny], *args)
        if upd is not None:
            upd(t, w[:nx].copy(), w[nx:].copy(), yf[ny:], *args)
        return yf
    J = np.zeros((ny + nx, nx + nu))
    for c in range(nx + nu):
        h = 1e-5 * max(abs(v[c]), 1.0)
        vp, vm = v.copy(), v.copy()
        vp[c] += h
        vm[c] -= h
        J[:, c] = (ev(vp) - ev(vm)) / (vp[c] - vm[c])
    return J


def _blocks_with_jacobians(loop):
    from ivdrem.blocks._core import kernel_args
    for sysb in loop.syslist:
        spec = getattr(sysb, "ivdrem", None)
        if spec is not None and spec.jacobian is not None:
            yield spec, kernel_args(spec, spec.validate(dict(sysb.params))
                                    if spec.validate else dict(sysb.params))


def _planar3_loop(law="iv-drem", **kw):
    """The loop of `law` on a 3-link planar arm (its own reference and disturbance);
    `kw` over the pinned mixing and γ."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import planar_arm
    ones = np.ones(3)
    traj = dict(amplitude=0.5 * ones, omega=[1.0, 0.7, 0.4], phase=0 * ones, offset=0.2 * ones)
    dist = dict(amplitude=[2.0, 1.0, 0.5], omega=[0.5, 0.3, 0.2], phase=0 * ones,
                offset=0 * ones)
    # the paper's mixing (17) and γ (every arm but the paper's defaults to "eigen", "auto")
    pinned = dict(mixing="paper", gamma=1e10) if law == "iv-drem" else {}
    gains = {**pinned, **{k: v for k, v in kw.items() if k in ("mixing", "gamma")}}
    loop = {k: v for k, v in kw.items() if k not in gains}
    return closed_loop(law, model=planar_arm(3), trajectory=traj, disturbance=dist,
                       gains=gains, **loop)


@pytest.mark.parametrize("case", ["iv-drem", "composite-learning", "planar3-iv-drem",
                                  "planar3-composite-learning", "literal-observer",
                                  "inertia-scaled"])
def test_block_jacobian_kernels_match_their_own_differences(case):
    """Every block that supplies an analytic Jacobian (ivdrem/blocks/jacobians.py) against
    central differences of its own update/output kernels, at random states and inputs,
    including a singular Psi (rank nθ - 1) for the mixing step (17) and Psi = 0 (its
    value at t0).  The robot-model blocks (plant, torque observer in both variants,
    regression filter, instrument) use the regressors' generated derivatives; the
    inertia-scaled design's observer and law with the injection at θ_nominal too."""
    if case.startswith("planar3"):
        loop = _planar3_loop(case[len("planar3-"):])
    elif case == "literal-observer":
        from ivdrem.diagrams import closed_loop
        loop = closed_loop("iv-drem", observer_variant="literal")
    elif case == "inertia-scaled":
        from ivdrem.diagrams import closed_loop
        loop = closed_loop("iv-drem", design="inertia-scaled", K=3.0)
        obs = next(b for b in loop.syslist if b.name == "torque_observer")
        assert [p for p, _ in obs.ivdrem.outputs][-1] == "chi"      # the nominal injection
    else:
        loop = paper_loop(case)
    rng = np.random.default_rng(42)
    seen = set()
    for spec, args in _blocks_with_jacobians(loop):
        seen.add(spec.name)
        nx, nu, ny = spec.nstates, spec.ninputs, spec.noutputs
        for trial in range(4):
            v = rng.standard_normal(nx + nu)
            if spec.name == "mixing":
                nth = (ny - 2) if spec.outputs[0][1] == 1 else ny // 3
                if trial == 2:          # singular Psi: adj is nonzero, det is zero
                    B = rng.standard_normal((nth, nth - 1))
                    v[nth:] = (B @ B.T).ravel()
                if trial == 3:          # Psi = 0 (the start of every run)
                    v[nth:] = 0.0
            if spec.model is not None:
                # a plausible robot input: mu > 0 (the observer divides by it)
                for name, sl in spec.port_slices("inputs").items():
                    if name == "mu":
                        v[nx + sl.start] = 2.0 + abs(v[nx + sl.start])
            jac = np.zeros((ny + nx, nx + nu))
            _flat(spec, "jacobian")(0.37, v[:nx].copy(), v[nx:].copy(), jac, *args)
            ref = _block_central_fd(spec, args, 0.37, v)
            if spec.name == "mixing" and trial >= 2:
                # log10|Delta| is singular where Delta = 0: compare Delta and calY only
                k = spec.outputs[0][1]
                jac, ref = jac[:k + nth], ref[:k + nth]
            scale = max(np.abs(ref).max(), 1e-300)
            if spec.name == "mixing" and trial == 3:
                # ||Psi||_F has a kink at 0: compare the columns of Y only there
                np.testing.assert_allclose(jac[:, :nth], ref[:, :nth], rtol=0, atol=1e-9)
                continue
            err = np.abs(jac - ref).max() / scale
            assert err <= 1e-7, f"{spec.name} (trial {trial}): {err:.2e}"
            if spec.model is not None:
                # entry by entry too: the regressors' derivatives carry gains such as mu
                big = np.abs(ref) >= 1e-6 * scale
                rel = (np.abs(jac - ref)[big] / np.abs(ref)[big]).max()
                assert rel <= 1e-6, f"{spec.name} (trial {trial}): entry-wise {rel:.2e}"
    want = {"control_law", "adaptation_law", "extension", "plant", "torque_observer",
            "regression_filter"}
    want |= ({"composite_learning_term"} if case.endswith("composite-learning")
             else {"mixing", "drem_term", "instrument"})
    assert want <= seen, f"blocks without their analytic Jacobian: {sorted(want - seen)}"


# ------------------------------------------- the probe's numba-compiled kernels
def _python_only(i):
    return i


def _fallback_update(t, x, u, dx):
    # a model-free kernel numba cannot compile (it calls a plain Python function): probed
    # in Python instead
    for i in range(x.shape[0]):
        dx[i] = -x[i] + u[_python_only(i)]


def _fallback_output(t, x, u, y):
    for i in range(x.shape[0]):
        y[i] = x[i]


@pytest.mark.parametrize("arm, mixing", [("two-link", "eigen"),
                                         pytest.param("planar-3", "paper", marks=pytest.mark.slow)])
def test_compiled_probe_gives_the_python_probes_pattern(monkeypatch, arm, mixing):
    """The large model-free blocks of a real arm's loop (window integrator, averaging,
    mixing) are probed with numba-compiled kernels: on a small loop, with these blocks
    made 'large', the compiled probe finds exactly the Python probe's entries."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import planar_arm
    from ivdrem.sim import jacobian as jac
    from ivdrem.sim.compiled import _check_kernels
    from ivdrem.sim.plan import DiagramPlan
    from ivdrem.blocks._core import kernel_args
    if arm == "two-link":
        loop = closed_loop("iv-drem", gains=dict(mixing=mixing, gamma=1.0))
    else:
        ones = np.ones(3)
        traj = dict(amplitude=0.5 * ones, omega=[1.0, 0.7, 0.4], phase=0 * ones,
                    offset=0.2 * ones)
        dist = dict(amplitude=[2.0, 1.0, 0.5], omega=[0.5, 0.3, 0.2], phase=0 * ones,
                    offset=0 * ones)
        loop = closed_loop("iv-drem", model=planar_arm(3), trajectory=traj,
                           disturbance=dist, gains=dict(mixing=mixing, gamma=1.0))
    plan = DiagramPlan.from_diagram(loop)
    _check_kernels(plan)
    names = {"window_integrator", "averaging", "mixing"}
    seen = set()
    for b in plan.blocks:
        if b.sys.name not in names:
            continue
        args = kernel_args(b.spec, plan.block_params(b))
        sizes = (b.sys.nstates, b.sys.ninputs, b.sys.noutputs)
        monkeypatch.setattr(jac, "PROBE_COMPILE_WORK", 10 ** 18)
        python = jac._difference_pattern(b.spec, args, *sizes, seed=b.index, n_points=3)
        assert not hasattr(jac._probe_kernels(b.spec, args, *sizes)[0], "py_func")
        monkeypatch.setattr(jac, "PROBE_COMPILE_WORK", 0)
        assert hasattr(jac._probe_kernels(b.spec, args, *sizes)[0], "py_func")  # numba's
        compiled = jac._difference_pattern(b.spec, args, *sizes, seed=b.index, n_points=3)
        assert python is not None and python.any()
        assert np.array_equal(compiled, python), b.sys.name
        seen.add(b.sys.name)
    assert seen == names


def _arm_plan(arm):
    """The plan of the IV-DREM loop of examples/<arm>.toml (the run's loop)."""
    from pathlib import Path
    from ivdrem.experiments.config import read_config, resolve_config
    from ivdrem.experiments.experiment import Experiment
    from ivdrem.sim.plan import DiagramPlan
    root = Path(__file__).resolve().parents[1]
    c = resolve_config(read_config(root / "examples" / f"{arm}.toml",
                    overrides={"experiment.t_end": 1.0, "experiment.laws": ["iv-drem"]}))[0]
    return DiagramPlan.from_diagram(Experiment.from_config(c).loop("iv-drem"))


@pytest.mark.parametrize("case", [
    "iv-drem", "composite-learning", "literal-observer", "planar3-iv-drem",
    "planar3-eigen", "planar3-composite-learning",
    pytest.param("ur5", marks=pytest.mark.slow), pytest.param("panda", marks=pytest.mark.slow)])
def test_a_jacobian_kernel_gives_the_difference_probe_s_pattern(case):
    """A block with its own Jacobian kernel and no robot model takes its local pattern from
    that kernel at three random points (one call each) instead of 2 (nx + nu) kernel calls
    per point: on every such block of the paper's loops, planar-3 and the real arms' loops
    it is the difference probe's pattern entry by entry (so the Jacobian program, the LU
    and the run are unchanged)."""
    from ivdrem.sim import jacobian as jac
    from ivdrem.sim.plan import DiagramPlan
    from ivdrem.blocks._core import kernel_args
    if case in ("ur5", "panda"):
        plan = _arm_plan(case)
    elif case.startswith("planar3"):
        law = case[len("planar3-"):]
        plan = DiagramPlan.from_diagram(_planar3_loop("iv-drem", mixing="eigen")
                                        if law == "eigen" else _planar3_loop(law))
    elif case == "literal-observer":
        from ivdrem.diagrams import closed_loop
        plan = DiagramPlan.from_diagram(closed_loop("iv-drem", observer_variant="literal"))
    else:
        plan = DiagramPlan.from_diagram(paper_loop(case))
    seen = set()
    for b in plan.blocks:
        if (b.spec.kind != "ode" or b.spec.jacobian is None or b.spec.model is not None):
            continue
        args = kernel_args(b.spec, plan.block_params(b))
        sizes = (b.sys.nstates, b.sys.ninputs, b.sys.noutputs)
        from_kernel = jac._jacobian_pattern(b.spec, args, *sizes, seed=b.index, n_points=3)
        differences = jac._difference_pattern(b.spec, args, *sizes, seed=b.index, n_points=3)
        assert from_kernel is not None and differences.any()
        assert np.array_equal(from_kernel, differences), (
            f"{b.sys.name}: {int((differences & ~from_kernel).sum())} entries missing, "
            f"{int((from_kernel & ~differences).sum())} more")
        # whichever of the two the probe takes (the kernel's, unless calling it would first
        # make numba compile a helper)
        assert np.array_equal(jac.block_pattern(b.spec, args, *sizes, seed=b.index),
                              from_kernel)
        seen.add(b.sys.name)
    want = {"control_law", "adaptation_law", "extension", "tracking_error"}
    if "composite-learning" not in case:
        want |= {"mixing", "drem_term"}
    assert want <= seen, sorted(want - seen)


def _coupled_update(t, x, u, dx):
    # dx0 = -x0 + u0 u1, dx1 = -x1 + u1
    dx[0] = -x[0] + u[0] * u[1]
    dx[1] = -x[1] + u[1]


def _coupled_output(t, x, u, y):
    y[0] = x[0]
    y[1] = x[1]


def _coupled_jacobian_forgetting_u1(t, x, u, jac):
    # rows y0, y1, dx0, dx1; columns x0, x1, u0, u1: d(dx0)/du1 = u0 left out
    jac[0, 0] = 1.0
    jac[1, 1] = 1.0
    jac[2, 0] = -1.0
    jac[2, 2] = u[1]
    jac[3, 1] = -1.0
    jac[3, 3] = 1.0


def _coupled_jacobian_without_dx1(t, x, u, jac):
    # the row of dx1 left empty: a dependence forgotten that the check along w sees
    jac[0, 0] = 1.0
    jac[1, 1] = 1.0
    jac[2, 0] = -1.0
    jac[2, 2] = u[1]
    jac[2, 3] = u[0]


def test_a_jacobian_kernel_that_forgets_a_dependence_is_caught():
    """A wrong (too small) pattern from a Jacobian kernel: an empty row is caught at probe
    time (the difference along a random direction moves it; the block is probed by
    differences instead, which finds the whole pattern); an entry left out of a row that
    has others is what the comparison above fails on (and the kernel's own values, checked
    against differences by test_block_jacobian_kernels_match_their_own_differences)."""
    from ivdrem.sim import jacobian as jac
    true = np.zeros((4, 4), dtype=bool)
    true[[0, 1, 2, 2, 2, 3, 3], [0, 1, 0, 2, 3, 1, 3]] = True

    def spec(jacobian):
        return BlockSpec("coupled", [("u", 2)], [("y", 2)], [("x", 2)], np.zeros(2),
                         param_names=(), update=_coupled_update, output=_coupled_output,
                         jacobian=jacobian)

    diff = jac._difference_pattern(spec(None), [], 2, 2, 2, seed=0, n_points=3)
    assert np.array_equal(diff, true)
    # the empty row: back to the differences, the whole pattern
    s = spec(_coupled_jacobian_without_dx1)
    assert jac._jacobian_pattern(s, [], 2, 2, 2, seed=0, n_points=3) is None
    assert np.array_equal(jac.block_pattern(s, [], 2, 2, 2), true)
    # the entry left out: the kernel's pattern is smaller, and differs from the probe's
    s = spec(_coupled_jacobian_forgetting_u1)
    small = jac._jacobian_pattern(s, [], 2, 2, 2, seed=0, n_points=3)
    assert small is not None and not small[2, 3] and np.array_equal(small | (diff & ~small), diff)
    assert not np.array_equal(small, diff)


def _slope(u1):
    return u1


_SLOPE = None           # a numba dispatcher of _slope, made fresh by the test below


def _coupled_jacobian_with_helper(t, x, u, J):
    J[0, 0] = 1.0
    J[1, 1] = 1.0
    J[2, 0] = -1.0
    J[2, 2] = _SLOPE(u[1])
    J[2, 3] = u[0]
    J[3, 1] = -1.0
    J[3, 3] = 1.0


def test_a_jacobian_kernel_whose_helper_is_not_compiled_yet_is_probed_by_differences(
        monkeypatch):
    """On a first run a Jacobian kernel calling a numba helper that is neither compiled
    in this process nor in numba's cache would cost that compile to probe: the block is
    probed by differences of its kernels then, by its kernel once the helper is compiled;
    the pattern is the same."""
    from numba import njit
    from ivdrem.sim import jacobian as jac
    monkeypatch.setitem(globals(), "_SLOPE", njit(cache=False)(_slope))
    kernel = _coupled_jacobian_with_helper
    spec = BlockSpec("coupled", [("u", 2)], [("y", 2)], [("x", 2)], np.zeros(2),
                     param_names=(), update=_coupled_update, output=_coupled_output,
                     jacobian=kernel)
    assert jac._compiles_first(kernel) and not jac._kernel_probe_applies(spec)
    by_differences = jac.block_pattern(spec, [], 2, 2, 2)
    _SLOPE(0.5)
    assert not jac._compiles_first(kernel) and jac._kernel_probe_applies(spec)
    assert np.array_equal(jac.block_pattern(spec, [], 2, 2, 2), by_differences)


def test_probe_falls_back_to_python_for_kernels_numba_refuses(monkeypatch):
    from ivdrem.sim import jacobian as jac
    spec = BlockSpec("fallback", [("u", 3)], [("y", 3)], [("x", 3)], np.zeros(3),
                     param_names=(), update=_fallback_update, output=_fallback_output)
    monkeypatch.setattr(jac, "PROBE_COMPILE_WORK", 0)
    out, upd = jac._probe_kernels(spec, [], 3, 3, 3)
    assert out is _fallback_output and upd is _fallback_update
    pat = jac.block_pattern(spec, [], 3, 3, 3)
    expect = np.zeros((6, 6), dtype=bool)
    expect[:3, :3] = np.eye(3, dtype=bool)               # y = x
    expect[3:, :3] = expect[3:, 3:] = np.eye(3, dtype=bool)   # dx = -x + u
    assert np.array_equal(pat, expect)


def _expand(dst, f, src, length):
    """The runs of the Jacobian chain as single multiply-adds again (dst, f, src)."""
    out = []
    for d, g, s, m in zip(dst, f, src, length):
        for k in range(abs(m)):
            if s == -1:                         # factors alone
                out.append((d + k, g + k, -1))
            elif s < -1:                        # a factor and a source each
                out.append((d + k, g + k, -2 - s + k))
            else:                               # one factor, consecutive sources
                out.append((d + k, g, s + k))
    return out


def test_chain_runs_hold_the_same_multiply_adds_in_the_same_order():
    from ivdrem.sim.jacobian import _runs
    ins = [(0, 5, 10), (1, 5, 11), (2, 5, 12),      # one factor, consecutive: one run
           (3, 5, 14),                               # the source jumps: a new run
           (4, 7, -1), (5, 8, -1), (6, 9, -1),       # factors alone, consecutive: one run
           (7, 9, -1),                               # the factor repeats: a new run
           (8, 6, 20), (9, 7, 21)]                   # the factor changes: two runs
    a = np.array(ins, dtype=np.int64)
    dst, f, src, length = _runs(a[:, 0], a[:, 1], a[:, 2])
    assert list(length) == [3, 1, 3, 1, 2]
    assert list(src) == [10, 14, -1, -1, -2 - 20]   # the last two: a factor and source each
    assert _expand(dst, f, src, length) == ins


def test_single_multiply_adds_consecutive_in_every_index_make_one_run():
    """A row read through single-entry rows (the mixing's derivatives with respect to the
    averaged Psi): destination, factor and source all consecutive, one run; a break in any
    of the three, or a term that a run of one factor already holds, ends it."""
    from ivdrem.sim.jacobian import _runs
    ins = [(0, 3, 50), (1, 4, 51), (2, 5, 52), (3, 6, 53),     # one elementwise run
           (4, 7, 60),                                         # the source jumps
           (5, 9, 61),                                         # the factor jumps
           (7, 10, 62),                                        # the destination jumps
           (8, 11, 70), (9, 11, 71),                           # one factor: its own kind
           (10, 12, 72), (11, 13, -1)]                         # an alone term ends it
    a = np.array(ins, dtype=np.int64)
    dst, f, src, length = _runs(a[:, 0], a[:, 1], a[:, 2])
    assert list(length) == [4, 1, 1, 1, 2, 1, 1]
    assert list(src) == [-2 - 50, 60, 61, 62, 70, 72, -1]
    assert _expand(dst, f, src, length) == ins


def test_chain_as_runs_reproduces_the_sums_of_single_multiply_adds():
    """The runs of the planar-3 loop, run as written and one multiply-add at a time: the
    same slots bit for bit (the order in which a slot receives its terms is kept)."""
    from ivdrem.sim.jacobian import JacobianProgram
    from ivdrem.sim.plan import DiagramPlan
    loop = _planar3_loop(mixing="eigen", gamma=50.0)
    prog = JacobianProgram(DiagramPlan.from_diagram(loop))
    # (planar-3: 5,740 multiply-adds in 2,159 runs; the UR5 loop: 2.08 million in 128,721)
    assert np.abs(prog.run_len).sum() >= prog.n_ins and prog.run_len.size < prog.n_ins / 2
    rng = np.random.default_rng(2)
    F = rng.standard_normal(prog.n_jb + prog.gains.size)
    F[prog.n_jb:] = prog.gains
    S1 = _chain(prog, F)
    S2 = np.zeros(prog.n_slots)
    for d, g, s in _expand(prog.run_dst, prog.run_f, prog.run_src, prog.run_len):
        S2[d] += F[g] if s < 0 else F[g] * S2[s]
    assert np.array_equal(S1, S2) and np.count_nonzero(S1) > 0


def test_each_slots_first_term_is_stored_so_the_slots_need_no_clearing():
    """A run of first terms (negative length) holds the first term each of its
    destinations receives and nothing else; every slot, those no term reaches included, is
    stored before it is read or added to, so that the chain run over slots left holding
    anything (here NaN: the last Jacobian's values) gives the sums from +0 bit for bit."""
    from ivdrem.sim.jacobian import JacobianProgram, _runs
    from ivdrem.sim.plan import DiagramPlan
    ins = np.array([(0, 5, 10), (1, 5, 11), (2, 5, 12),     # first terms of 0, 1, 2
                    (1, 6, 13), (2, 6, 14),                  # second terms: a run of their own
                    (3, 7, -1), (4, 8, -1)], dtype=np.int64)
    first = np.array([1, 1, 1, 0, 0, 1, 1], dtype=bool)
    dst, f, src, length = _runs(ins[:, 0], ins[:, 1], ins[:, 2], first)
    assert list(length) == [-3, 2, -2]
    assert _expand(dst, f, src, length) == [tuple(r) for r in ins.tolist()]
    prog = JacobianProgram(DiagramPlan.from_diagram(_planar3_loop(mixing="eigen",
                                                                  gamma=50.0)))
    written = np.zeros(prog.n_slots, dtype=bool)
    for d, g, s, m in zip(prog.run_dst, prog.run_f, prog.run_src, prog.run_len):
        rng_ = np.arange(d, d + abs(m))
        # a gain that is 0 (the unreached slots' runs) reads no source (jac_chain)
        zero = g >= prog.n_jb and prog.gains[g - prog.n_jb] == 0.0
        reads = (np.arange(-2 - s, -2 - s + abs(m)) if s < -1 else
                 np.arange(s, s + abs(m)) if s >= 0 and not zero else
                 np.zeros(0, dtype=np.int64))
        assert written[reads].all()             # a source is complete when read
        assert (m < 0) == (not written[rng_].any()) and (m > 0) == written[rng_].all()
        written[rng_] = True
    assert written.all()
    rng = np.random.default_rng(3)
    F = rng.standard_normal(prog.n_jb + prog.gains.size)
    F[prog.n_jb:] = prog.gains
    F[:prog.n_jb][rng.random(prog.n_jb) < 0.2] = 0.0  # exact zeros among the factors
    assert np.array_equal(_chain(prog, F, start=np.nan), _chain(prog, F))


def _chain(prog, F, start=0.0):
    """The chain's slots S from the factors F, run by run as jac_chain runs them, over
    slots that held `start` before (a run of first terms, m < 0, stores 0.0 + term)."""
    S = np.full(prog.n_slots, start)
    for d, g, s, m in zip(prog.run_dst, prog.run_f, prog.run_src, prog.run_len):
        first, m = m < 0, abs(m)
        if first:
            S[d:d + m] = 0.0
        if s == -1:
            S[d:d + m] += F[g:g + m]
        elif s < -1:
            S[d:d + m] += F[g:g + m] * S[-2 - s:-2 - s + m]
        elif F[g] != 0.0:
            S[d:d + m] += F[g] * S[s:s + m]
    return S


@pytest.mark.parametrize("Gamma", ["diagonal", "full"])
def test_factors_the_parameters_make_zero_are_left_out_and_change_no_value(Gamma,
                                                                          monkeypatch):
    """A diagonal Gamma makes the adaptation law's off-diagonal entries exactly zero: the
    program leaves their multiply-adds out, and df/dx is the same bit for bit as the
    program that keeps them (those factors zero there too) over random factors; the
    pattern of df/dx, and so the LU's, is the same.  A full Gamma: nothing of the law is
    left out (the control law's diagonal K still is)."""
    from ivdrem.sim import jacobian
    from ivdrem.sim.plan import DiagramPlan
    rng = np.random.default_rng(5)
    if Gamma == "full":
        A = rng.standard_normal((6, 6))
        G = 0.01 * (A @ A.T + 6 * np.eye(6))
    else:
        G = np.diag(rng.uniform(0.5, 2.0, 6))
    plan = DiagramPlan.from_diagram(_planar3_loop(mixing="eigen", gamma=50.0, Gamma=G))
    monkeypatch.setattr(jacobian, "_program_path", lambda key: None)
    jacobian._PROGRAMS.clear()
    left_out = jacobian.JacobianProgram(plan)
    zeros = jacobian._parameter_zeros(plan, left_out.patterns)
    jacobian._PROGRAMS.clear()
    with monkeypatch.context() as m:
        m.setattr(jacobian, "_parameter_zeros", lambda *a, **k: {})
        kept = jacobian.JacobianProgram(plan)
    jacobian._PROGRAMS.clear()
    (law,) = [b.index for b in plan.blocks if b.sys.name == "adaptation_law"]
    (ctl,) = [b.index for b in plan.blocks if b.sys.name == "control_law"]
    # the control law's diagonal K (the default): d tau_i / d r_j = K_ij, j != i; with a
    # diagonal Gamma, each row i of the law: d/dtheta_c_j = Gamma_ij and d/dPi^T[k, j] =
    # Gamma_ij r_k, for j != i
    assert zeros[ctl].sum() == 3 * 2
    if Gamma == "full":
        assert set(zeros) == {ctl}
    else:
        assert set(zeros) == {law, ctl} and zeros[law].sum() == 6 * 5 * (1 + 3)
    assert left_out.n_ins < kept.n_ins
    assert np.array_equal(left_out.pattern, kept.pattern)
    assert np.array_equal(left_out.j_slot, kept.j_slot)
    assert np.array_equal(left_out.e_slot, kept.e_slot)
    F = rng.standard_normal(kept.n_jb + kept.gains.size)
    F[kept.n_jb:] = kept.gains
    # the left-out factors' slots, zero here as in a run with these parameters
    for kb, b in enumerate(kept.fd_blocks):
        if b.index not in zeros:
            continue
        c0, c1 = kept.gc_ptr[kept.g_ptr[kb]], kept.gc_ptr[kept.g_ptr[kb + 1]]
        for cc in range(c0, c1):
            for e in range(kept.e_ptr[cc], kept.e_ptr[cc + 1]):
                if zeros[b.index][kept.e_row[e], kept.col[cc]]:
                    F[kept.e_slot[e]] = 0.0
    # the same factors; each program's own constant gains after them (the left-out
    # program has runs of its own that store +0 into the slots no term reaches)
    assert left_out.n_jb == kept.n_jb
    F_left = np.concatenate([F[:kept.n_jb], left_out.gains])
    S1, S2 = _chain(left_out, F_left), _chain(kept, F)
    assert np.array_equal(S1[left_out.j_slot], S2[kept.j_slot])
    assert np.count_nonzero(S1[left_out.j_slot]) > 0


def test_a_jacobian_kernels_entries_are_read_row_by_row_into_consecutive_factors():
    """A block with its own Jacobian kernel is read from its buffer in the buffer's order,
    one entry per column entry of the program, into consecutive slots: the mixing's rows
    (its derivatives with respect to the averaged Psi, each read through a single-entry
    row) become elementwise runs, a handful instead of one per entry."""
    from ivdrem.sim.jacobian import JacobianProgram
    from ivdrem.sim.plan import DiagramPlan
    plan = DiagramPlan.from_diagram(_planar3_loop(mixing="eigen", gamma=50.0))
    prog = JacobianProgram(plan)
    for kb, b in enumerate(prog.fd_blocks):
        c0, c1 = prog.gc_ptr[prog.g_ptr[kb]], prog.gc_ptr[prog.g_ptr[kb + 1]]
        rows = np.concatenate([prog.e_row[prog.e_ptr[c]:prog.e_ptr[c + 1]]
                               for c in range(c0, c1)])
        slots = np.concatenate([prog.e_slot[prog.e_ptr[c]:prog.e_ptr[c + 1]]
                                for c in range(c0, c1)])
        if b.spec.jacobian is not None:
            ncol = b.sys.nstates + b.sys.ninputs
            flat = rows * ncol + prog.col[c0:c1]
            assert np.all(np.diff(flat) > 0) and np.all(np.diff(slots) == 1)
    assert (prog.run_src < -1).sum() > 0
    nth = 6
    # the mixing's 1 + nθ + 1 rows over nθ² Psi entries: far fewer runs than entries
    assert (np.abs(prog.run_len[prog.run_src < -1]) >= nth * nth).sum() >= nth


def test_the_jacobian_sits_in_the_lu_pattern_and_comes_back_dense():
    from ivdrem.sim.tables import dense_to_sparse, jacobian_positions, sparse_to_dense
    from ivdrem.sim.sparse_lu import symbolic_lu

    class Prog:        # what jacobian_positions reads of a JacobianProgram
        pass
    rng = np.random.default_rng(4)
    pat = rng.random((30, 30)) < 0.1
    slu = symbolic_lu(pat)
    prog = Prog()
    prog.j_row, prog.j_col = np.nonzero(pat)
    pos = jacobian_positions(prog, slu)
    J = np.where(pat, rng.standard_normal(pat.shape), 0.0)
    values = np.zeros(slu.nnz_lu)
    values[pos] = J[pat]
    assert np.array_equal(sparse_to_dense(values, slu.perm, slu.rowptr, slu.colidx), J)
    assert np.array_equal(dense_to_sparse(J, slu.perm, slu.rowptr, slu.colidx), values)
    assert slu.nnz_lu > pat.sum()            # fill: positions no entry of J maps to stay 0


def test_a_jacobian_program_is_kept_on_disk_for_the_next_process(tmp_path, monkeypatch):
    """A program built in one process is read back by the next one (no build), equal to a
    fresh build array by array and count by count; a damaged file, or another ivdrem
    source, is built again."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import jacobian
    from ivdrem.sim.plan import DiagramPlan
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    plan = DiagramPlan.from_diagram(closed_loop("iv-drem"))
    jacobian._PROGRAMS.clear()
    built = jacobian.JacobianProgram(plan)
    files = list((tmp_path / "jacobian-programs").glob("*.npz"))
    assert len(files) == 1
    real_build, builds = jacobian.JacobianProgram._build, []

    def counted(self, *a):
        builds.append(1)
        return real_build(self, *a)

    monkeypatch.setattr(jacobian.JacobianProgram, "_build", counted)
    jacobian._PROGRAMS.clear()                          # as a new process starts
    read = jacobian.JacobianProgram(plan)
    assert not builds
    for name in jacobian._PROGRAM_ARRAYS:
        a, b = getattr(built, name), getattr(read, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
        assert not b.flags.writeable
    for name in jacobian._PROGRAM_COUNTS:
        assert type(getattr(read, name)) is int and getattr(read, name) == getattr(built, name)
    assert [b.index for b in read.fd_blocks] == [b.index for b in built.fd_blocks]
    assert all(b in plan.blocks for b in read.fd_blocks) and read.plan is plan
    files[0].write_bytes(b"damaged")
    jacobian._PROGRAMS.clear()
    jacobian.JacobianProgram(plan)
    assert len(builds) == 1                             # damaged: built again, rewritten
    jacobian._PROGRAMS.clear()
    jacobian.JacobianProgram(plan)
    assert len(builds) == 1
    monkeypatch.setattr(jacobian, "_package_digest", lambda: "another ivdrem")
    jacobian._PROGRAMS.clear()
    jacobian.JacobianProgram(plan)
    assert len(builds) == 2                             # another source: built


def test_a_jacobian_program_is_built_once_per_structure_and_equals_a_fresh_one():
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import jacobian
    from ivdrem.sim.plan import DiagramPlan
    plan1 = DiagramPlan.from_diagram(closed_loop("iv-drem"))
    plan2 = DiagramPlan.from_diagram(closed_loop("iv-drem"))
    p1, p2 = jacobian.JacobianProgram(plan1), jacobian.JacobianProgram(plan2)
    assert p2.run_dst is p1.run_dst                    # the second is the cached one
    assert p2.plan is plan2 and all(b in plan2.blocks for b in p2.fd_blocks)
    fresh = object.__new__(jacobian.JacobianProgram)
    patterns = jacobian._local_patterns(plan2, 0)
    fresh._build(plan2, patterns, jacobian._parameter_zeros(plan2, patterns))
    for name, v in vars(fresh).items():
        if isinstance(v, np.ndarray):
            assert np.array_equal(v, getattr(p2, name)), name
    # a changed gain in the connection map, or another diagram, is another program
    key = jacobian._program_key(plan2, p2.patterns)
    k = next(i for i, row in enumerate(plan2.conn) if row)
    j, g = plan2.conn[k][0]
    plan2.conn[k] = [(j, 2.0 * g)] + plan2.conn[k][1:]
    assert jacobian._program_key(plan2, p2.patterns) != key
    other = DiagramPlan.from_diagram(closed_loop("composite-learning"))
    assert jacobian.JacobianProgram(other).run_dst is not p1.run_dst


def test_the_program_cache_keeps_no_diagram():
    """The process-wide cache of programs keeps each program without the plan it was built
    from: a simulated diagram (python-control's dense connection map: 1.2 GiB on the Panda)
    is freed once its caller drops it, and the next diagram of that structure still gets
    the cached program, bound to its own plan."""
    import gc
    import weakref
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim import jacobian
    from ivdrem.sim.plan import DiagramPlan
    jacobian._PROGRAMS.clear()
    diagram = closed_loop("iv-drem")
    first = jacobian.JacobianProgram(DiagramPlan.from_diagram(diagram))
    gone = weakref.ref(diagram)
    run_dst = first.run_dst
    del diagram, first
    gc.collect()
    assert gone() is None
    plan = DiagramPlan.from_diagram(closed_loop("iv-drem"))
    again = jacobian.JacobianProgram(plan)
    assert again.run_dst is run_dst and again.plan is plan
    assert all(b in plan.blocks for b in again.fd_blocks)


def test_column_groups_are_the_greedy_first_fit_groups():
    """_color (a table of rows x groups) against the greedy grouping written plainly: each
    column, by decreasing row count, into the first group it shares no row with; the same
    groups on random patterns (so the Jacobian program is unchanged)."""
    import random
    from ivdrem.sim.jacobian import _color

    def first_fit(rows_of_col):
        groups = []
        for c in sorted(rows_of_col, key=lambda c: -len(rows_of_col[c])):
            for rows, cols in groups:
                if not rows & rows_of_col[c]:
                    rows.update(rows_of_col[c])
                    cols.append(c)
                    break
            else:
                groups.append((set(rows_of_col[c]), [c]))
        return [sorted(cols) for _, cols in groups]

    rng = random.Random(0)
    for trial in range(200):
        n_rows = rng.randint(1, 40)
        cols = rng.sample(range(300), rng.randint(0, 60))
        pattern = {c: set(rng.sample(range(n_rows), rng.randint(0 if trial % 5 == 0 else 1,
                                                                 min(n_rows, 6))))
                   for c in cols}
        assert _color(pattern) == first_fit(pattern)
    many = {c: set(range(45)) for c in range(100)}          # the mixing's shape: one each
    assert _color(many) == [[c] for c in range(100)]


def test_the_probes_way_reads_numbas_cache_as_it_was_before_the_compile_child(monkeypatch):
    """The engine starts its compile child before the probe; within helpers_cache_as_now a
    helper the child writes to numba's cache meanwhile still counts as not compiled, so the
    block's way (differences here) does not depend on how far the child has come."""
    from numba import njit
    from ivdrem.blocks import _kernels
    from ivdrem.sim import jacobian as jac
    helper = njit(cache=True)(_slope)
    monkeypatch.setattr(_kernels, "slope_for_the_probe_test", helper, raising=False)
    monkeypatch.setitem(globals(), "_SLOPE", helper)
    kernel = _coupled_jacobian_with_helper
    in_cache = {"now": False}
    # the probe's module reads numba's cache through its own binding of index_exists
    monkeypatch.setattr(jac, "index_exists", lambda cache: in_cache["now"])
    with jac.helpers_cache_as_now():
        assert jac._compiles_first(kernel)
        in_cache["now"] = True                 # the child has compiled it meanwhile
        assert jac._compiles_first(kernel)
    assert not jac._compiles_first(kernel)     # outside: numba's cache as it is now
    with jac.helpers_cache_as_now():
        assert not jac._compiles_first(kernel)
    in_cache["now"] = False
    helper(0.5)                                # compiled in this process: as outside
    with jac.helpers_cache_as_now():
        assert not jac._compiles_first(kernel)
