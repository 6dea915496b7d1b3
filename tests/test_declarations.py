"""Direct feedthrough: every library block's declaration (BlockSpec.direct) against its own
python-control output function, and the feedthrough of blocks ivdrem did not write
(StateSpace D, declare_feedthrough, the numerical probe)."""
import numpy as np
import pytest
import control as ct

from ivdrem.diagrams import closed_loop
from ivdrem.models import two_link, planar_arm
from ivdrem.sim import DiagramPlan, AlgebraicLoopError
from ivdrem.sim import declare_feedthrough
from ivdrem.sim.foreign import direct_inputs, probe_feedthrough


def _library_blocks():
    """Every block of both default laws' loops on the 2-link arm, and the 3-link arm's."""
    blocks = {}
    m2 = two_link()
    for law in ("iv-drem", "composite-learning"):
        for sys in closed_loop(law, m2).syslist:
            blocks.setdefault(f"2link:{sys.name}", sys)
    m3 = planar_arm(3)
    n = m3.n
    traj = dict(amplitude=[0.3] * n, omega=[1.0, 0.5, 0.3], phase=[0.0] * n,
                offset=[0.1] * n)
    dist = dict(amplitude=[1.0] * n, omega=[0.5] * n, phase=[0.0] * n, offset=[0.0] * n)
    # γ a number: "auto" (the 3-link arm's rule) would choose one first, same blocks
    for sys in closed_loop("iv-drem", m3, gains={"gamma": 1.0}, trajectory=traj,
                           disturbance=dist).syslist:
        blocks.setdefault(f"3link:{sys.name}", sys)
    return blocks


BLOCKS = _library_blocks()


def _moves(sys, inputs, rng, n_points=4):
    """For each input index: does moving it alone (random points) move an output?"""
    nx, nu = sys.nstates, sys.ninputs
    p = dict(sys.params)
    hit = np.zeros(nu, dtype=bool)
    good = 0
    for _ in range(20):
        if good >= n_points:
            break
        t = rng.uniform(0.1, 3.0)
        x = sys.ivdrem.x0 + rng.uniform(0.2, 1.2, nx)
        u = rng.uniform(0.2, 1.2, nu) * rng.choice([-1.0, 1.0], nu)
        with np.errstate(all="ignore"):
            y0 = np.asarray(sys.output(t, x, u, p), float)
        if not np.all(np.isfinite(y0)):
            continue
        for i in inputs:
            up = u.copy()
            up[i] += rng.uniform(0.5, 1.5)
            y1 = np.asarray(sys.output(t, x, up, p), float)
            hit[i] |= bool(np.any(y1 != y0))
        good += 1
    assert good == n_points, f"{sys.name}: no finite output at random points"
    return hit


@pytest.mark.parametrize("key", sorted(BLOCKS))
def test_inputs_not_declared_direct_move_no_output(key):
    sys = BLOCKS[key]
    spec = sys.ivdrem
    direct = set(direct_inputs(sys))
    if spec.kind != "ode":
        # delay / max-hold outputs come from the simulator's history, never from u(t)
        assert direct == set(), key
        return
    rng = np.random.default_rng(abs(hash(key)) % 2**32)
    others = [i for i in range(sys.ninputs) if i not in direct]
    hit = _moves(sys, others, rng)
    moved = [sys.input_labels[i] for i in others if hit[i]]
    assert not moved, f"{key}: outputs move with {moved}, not declared in BlockSpec.direct"


def test_declared_direct_inputs_do_move_an_output():
    """The check above can fail: for every block declaring direct ports, moving those
    ports moves an output (so the same probe would see an undeclared dependence)."""
    checked = 0
    for key, sys in sorted(BLOCKS.items()):
        if sys.ivdrem.kind != "ode" or not sys.ivdrem.direct:
            continue
        direct = direct_inputs(sys)
        hit = _moves(sys, direct, np.random.default_rng(1))
        assert hit[list(direct)].any(), f"{key}: no declared-direct input moves an output"
        checked += 1
    assert checked >= 5


# ---- blocks ivdrem did not write
def test_statespace_feedthrough_from_the_nonzero_columns_of_D():
    g = ct.ss([[-1.0]], [[1.0, 0.0, 2.0]], [[1.0], [0.5]], [[0.0, 0.0, 3.0], [0.0, 0.0, 0.0]],
              inputs=["a", "b", "c"], outputs=["y[0]", "y[1]"], name="lin")
    assert direct_inputs(g) == (2,)
    assert direct_inputs(ct.tf([1.0], [1.0, 1.0])) == ()          # strictly proper
    assert direct_inputs(ct.tf([2.0, 1.0], [1.0, 1.0])) == (0,)   # proper: D = 2
    sj = ct.summing_junction(inputs=["a", "b"], output="c")
    assert direct_inputs(sj) == (0, 1)


def _plain(outfcn, nu=3):
    return ct.nlsys(lambda t, x, u, p: -x + u[0], outfcn, inputs=nu, outputs=1, states=1,
                    name="plain")


def test_probe_finds_the_inputs_the_output_function_reads():
    sys = _plain(lambda t, x, u, p: np.array([x[0] + p["k"] * u[2]]), nu=3)
    sys.params = {"k": 0.5}
    assert probe_feedthrough(sys) == (2,)
    assert direct_inputs(sys) == (2,)
    assert probe_feedthrough(_plain(lambda t, x, u, p: np.array([np.sin(x[0] * t)]))) == ()
    # deterministic: the same block gets the same answer
    assert probe_feedthrough(sys) == probe_feedthrough(sys)


def test_probe_of_an_output_that_fails_everywhere_assumes_every_input():
    def bad(t, x, u, p):
        raise ValueError("no")
    assert probe_feedthrough(_plain(bad)) == (0, 1, 2)


def test_declare_feedthrough_overrides_the_probe_and_checks_names():
    sys = _plain(lambda t, x, u, p: np.array([x[0] + u[1]]))
    sys2 = ct.nlsys(None, lambda t, x, u, p: u[:2] * 2, inputs=["w[0]", "w[1]", "v"],
                    outputs=2, name="gain")
    assert declare_feedthrough(sys2, ["w"]) is sys2
    assert direct_inputs(sys2) == (0, 1)
    declare_feedthrough(sys, [])
    assert direct_inputs(sys) == ()
    with pytest.raises(ValueError, match="no input 'q'"):
        declare_feedthrough(sys, ["q"])
    with pytest.raises(TypeError):
        declare_feedthrough(ct.ss([[-1.0]], [[1.0]], [[1.0]], [[0.0]]), [])


def test_plain_plant_no_longer_makes_a_false_algebraic_loop():
    """A user plant written as a plain nlsys (outputs = states) in the paper's loop: the
    plan probes it, finds no feedthrough, and orders the loop."""
    model = two_link()
    ref = next(s for s in closed_loop("iv-drem", model).syslist if s.name == "plant")

    def upd(t, x, u, p):
        return ref.updfcn(t, x, u, ref.params)
    user = ct.nlsys(upd, lambda t, x, u, p: x.copy(), inputs=ref.input_labels,
                    outputs=ref.output_labels, states=ref.state_labels, name="plant")
    diagram = closed_loop("iv-drem", model, replace={"plant": user})
    plan = DiagramPlan.from_diagram(diagram)
    assert len(plan.order) == len(diagram.syslist)
    # and a genuine loop is still found: the same plant declaring feedthrough of tau
    declare_feedthrough(user, ["tau"])
    with pytest.raises(AlgebraicLoopError, match="plant"):
        DiagramPlan.from_diagram(closed_loop("iv-drem", model, replace={"plant": user}))


def test_vector_of_the_wrong_size_is_an_error_naming_both_signals():
    from ivdrem.blocks import disturbance
    from ivdrem.sim.plan import SignalSizeError
    d3 = disturbance(3, amplitude=[0, 0, 0], omega=[0, 0, 0], offset=[1.0, 2.0, 3.0])
    with pytest.raises(SignalSizeError, match=r"'disturbance' output 'tau_d' has 3 .*"
                                              r"'plant' input 'tau_d', which has 2"):
        closed_loop("iv-drem", two_link(), disturbance=d3)
    # the same check at plan level, for a diagram built with ct.interconnect directly
    src = ct.nlsys(None, lambda t, x, u, p: np.ones(3), inputs=0,
                   outputs=["s[0]", "s[1]", "s[2]"], name="src")
    snk = ct.nlsys(lambda t, x, u, p: u - x, None, inputs=["s[0]", "s[1]"],
                   outputs=["o[0]", "o[1]"], states=2, name="snk")
    d = ct.interconnect([src, snk], outputs=["o"], check_unused=False)
    with pytest.raises(SignalSizeError, match="'src' output 's' has 3"):
        DiagramPlan.from_diagram(d)


def test_the_experiments_start_reaches_a_replaced_plant():
    """closed_loop(q0=...) with a user's plant: a plain nlsys gets q(0), q̇(0) by its state
    names; an ivdrem block that starts elsewhere (an FMU plant's start values) is refused,
    naming both states; a plain plant without q/dq states cannot take a nonzero q0."""
    model = two_link()
    ref = next(s for s in closed_loop("iv-drem", model).syslist if s.name == "plant")

    def upd(t, x, u, p):
        return ref.updfcn(t, x, u, ref.params)
    user = ct.nlsys(upd, lambda t, x, u, p: x.copy(), inputs=ref.input_labels,
                    outputs=ref.output_labels, states=ref.state_labels, name="plant")
    d = closed_loop("iv-drem", model, q0=[0.1, 0.7], dq0=[0.0, -0.2], replace={"plant": user})
    plan = DiagramPlan.from_diagram(d)
    entry = next(b for b in plan.blocks if b.sys is user)
    np.testing.assert_array_equal(plan.x0[entry.x], [0.1, 0.7, 0.0, -0.2])
    # the paper's own q(0) when q0 is not given
    plan = DiagramPlan.from_diagram(closed_loop("iv-drem", model, replace={"plant": user}))
    entry = next(b for b in plan.blocks if b.sys is user)
    np.testing.assert_allclose(plan.x0[entry.x], [0.0, 0.3 * np.pi, 0.0, 0.0])
    # the user's system itself is not changed
    assert not hasattr(user, "ivdrem_start")
    # states named otherwise: a nonzero q0 cannot reach it
    other = ct.nlsys(upd, lambda t, x, u, p: x.copy(), inputs=ref.input_labels,
                     outputs=ref.output_labels, states=["a", "b", "c", "d"], name="plant")
    with pytest.raises(ValueError, match=r"has no states named q\[0\.\.1\], dq\[0\.\.1\]"):
        closed_loop("iv-drem", model, replace={"plant": other})
    closed_loop("iv-drem", model, q0=[0.0, 0.0], replace={"plant": other})   # zero: fine
