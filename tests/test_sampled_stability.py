"""The sampled design at the robot's rate with the controller FMU's one-sample delay
(docs/controller.md, "Sampled designs"): the gain rule of ``inertia_scaled_gains`` and the
prediction of ``ivdrem.controller.stability`` along the closed loop itself."""
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from ivdrem.controller.loop import ModelPlant, disturbance_at, sampled_loop  # noqa: E402
from ivdrem.controller.sampled import (GAIN_FLOOR, GRADIENT_GAIN, SampledController,  # noqa: E402
                                       gain_budget, inertia_scaled_gains)
from ivdrem.controller.stability import UNSTABLE_GROWTH, sampled_stability  # noqa: E402
from ivdrem.diagrams import arm_reference as arm  # noqa: E402
from ivdrem.models import get_model, two_link  # noqa: E402

ARMS = ("panda", "ur5", "iiwa", "xarm7")
MU_MAX, DELTA_MU = 135.0, 0.8


def _experiment(name):
    """The real-arm experiment's model, reference, start, disturbance, window, joint gains
    (N m s) and M(q0)."""
    m = get_model(name)
    traj = arm.design_trajectory(m)
    q0, _ = arm.initial_state(traj)
    dist = arm.design_disturbance(m, traj)
    T = arm.design_window(traj, dist)
    Kj = np.array(arm.design_gains(m, q0))
    M = np.empty((m.n, m.n))
    m.functions.M(np.asarray(q0, float), m.theta_values, M)
    return m, traj, q0, dist, T, Kj, M


def _last_session_gains(Kj, M, h):
    """The rule the iiwa and the xArm7 diverged with: K_i / M_ii(q0), capped at
    h (K_i + δ_μ μ_max) <= 0.5, no floor, the observer's injection not counted."""
    return np.minimum(Kj / np.diag(M), 0.5 / h - DELTA_MU * MU_MAX)


# ----------------------------------------------------------------------------- the rule
def _limit(delay):
    """The largest g for which z - 1 + g = 0 (delay 0) or z² - z + g = 0 (delay 1) has its
    roots inside the unit circle, by bisection on numpy's roots (independent of the rule)."""
    def stable(g):
        poly = [1.0, -1.0 + g] if delay == 0 else [1.0, -1.0, g]
        return np.max(np.abs(np.roots(poly))) < 1.0
    lo, hi = 1e-6, 4.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stable(mid) else (lo, mid)
    return lo


@pytest.mark.parametrize("delay", [0, 1])
def test_budget_is_half_the_discrete_loops_limit(delay):
    assert _limit(delay) == pytest.approx(2.0 if delay == 0 else 1.0, abs=1e-9)
    assert gain_budget(delay) == pytest.approx(0.5 * _limit(delay), abs=1e-9)


@pytest.mark.parametrize("name", ARMS)
@pytest.mark.parametrize("h, delay", [(1e-3, 1), (2e-3, 1), (1e-3, 0)])
def test_gain_rule_budget_floor_and_inertia(name, h, delay):
    """Every joint's per-step gain h (K_i + (1 + δ_μ) μ_max) is within the budget; no K is
    below the floor the cap leaves; between floor and cap K_i = K_joint,i / M_ii(q0)."""
    m, _, q0, _, _, Kj, M = _experiment(name)
    K = inertia_scaled_gains(m, Kj, q0, h, delay=delay)
    cap = gain_budget(delay) / h - (1 + DELTA_MU) * MU_MAX
    assert np.all(h * (K + (1 + DELTA_MU) * MU_MAX) <= gain_budget(delay) * (1 + 1e-12))
    assert np.all(K >= min(GAIN_FLOOR, cap) * (1 - 1e-12))
    raw = Kj / np.diag(M)
    inside = (raw > GAIN_FLOOR) & (raw < cap)
    np.testing.assert_allclose(K[inside], raw[inside], rtol=1e-12)
    if h == 1e-3:
        # the heavy joints (raw ~2 1/s) are raised to the floor, the light wrist capped
        assert np.sum(raw < GAIN_FLOOR) >= 3 and np.all(K[raw < GAIN_FLOOR] == GAIN_FLOOR)


def test_gain_rule_refuses_no_room():
    m, _, q0, _, _, Kj, _ = _experiment("ur5")
    with pytest.raises(ValueError, match="mu_max") as exc:
        inertia_scaled_gains(m, Kj, q0, 4e-3, delay=1)
    assert "\n" not in str(exc.value) and "0.972" in str(exc.value)


# ----------------------------------------------------------------------------- prediction
def test_delay_halves_the_two_link_boundary():
    """The paper's 2-link design at 1 ms: K = 480 holds without delay (0.999 per step,
    tests/test_controller_export.py); with the torque held one sample the discrete limit
    halves and the same K is predicted unstable, and the loop diverges within 0.5 s; K = 200
    holds with the delay."""
    from ivdrem.controller.clib import CController
    zero = {k: [0.0, 0.0] for k in ("amplitude", "omega", "phase", "offset")}
    for K, delay, stable in ((480.0, 0, True), (480.0, 1, False), (200.0, 1, True)):
        st = sampled_stability(two_link(), "iv-drem", K=K, h=1e-3, t_end=0.0, points=1,
                               suggest=False, delay=delay)
        assert st.stable is stable, st.reason()
        c = CController(two_link(), "iv-drem", K=K, h=1e-3, delay=delay)
        q0, dq0, _ = c_ref = SampledController(two_link(), "none").reference(0.0)
        del c_ref
        try:
            rec = sampled_loop(c, ModelPlant(two_link(), q0, dq0), 0.5, disturbance=zero)
            ok = bool(np.all(np.isfinite(rec["q"])) and np.abs(rec["q"]).max() < 10)
        except (FloatingPointError, ValueError, RuntimeError):
            ok = False
        assert ok is stable, (K, delay)


def _predict(name, K, prefix, Gamma=0.01, *, T=None, t_end=300.0, points=2, **kw):
    m, traj, _, dist, T0, _, _ = _experiment(name)
    return sampled_stability(
        m, "iv-drem", t_end=t_end, points=points, prefix=prefix, suggest=False,
        disturbance=lambda t: disturbance_at(t, dist), h=1e-3, K=K, T=T0 if T is None else T,
        trajectory=traj, delay=1, Gamma=Gamma, gamma=0.5 / Gamma, mixing="eigen",
        mix_every=10, **kw)


def test_xarm7_last_sessions_gains_predicted_unstable_new_rule_stable():
    """The xArm7 with last session's gains and the FMU's delay diverged at 1.9 s around
    its plant FMU (the observer's injection at θ̂, as then); the prediction runs the loop
    itself and says so, in one line; with the rule's gains the same prediction holds over
    the same 3 s."""
    m, _, q0, _, _, Kj, M = _experiment("xarm7")
    old = _predict("xarm7", _last_session_gains(Kj, M, 1e-3), 3.0, injection="estimate")
    assert not old.stable and old.diverged is not None and old.diverged < 2.5
    line = old.reason()
    assert "\n" not in line and "diverged at t = 1." in line and "delay 1" in line
    new = _predict("xarm7", inertia_scaled_gains(m, Kj, q0, 1e-3), 3.0, Gamma=GRADIENT_GAIN)
    assert new.stable and new.diverged is None, new.reason()
    assert any(w.startswith("theta_hat(t) of the run") for _, w, _ in new.points)


@pytest.mark.parametrize("name, t_end", [("iiwa", 3.0), ("xarm7", 5.0)])
def test_short_delay_one_run_stays_on_the_reference(name, t_end):
    """3-5 s of the C controller (IV-DREM) with the rule's gains, its torque one sample late,
    around the arm's own dynamics by one RK4 step per 1 ms (the plant FMU's): past the
    1.9 s where the xArm7 used to diverge (and the 4.9 s where it does with Γ = 0.01), it
    stays within 0.75 rad of the reference (measured 0.50 xArm7, 0.51 iiwa: θ̂ is still
    near 0, no feedforward, and α = 1 1/s lets a velocity error linger; the last session's
    gains leave it by far more before diverging)."""
    from ivdrem.controller.clib import CController
    m, traj, q0, dist, T, Kj, _ = _experiment(name)
    K = inertia_scaled_gains(m, Kj, q0, 1e-3)
    c = CController(m, "iv-drem", h=1e-3, K=K, T=T, trajectory=traj, delay=1,
                    Gamma=GRADIENT_GAIN, gamma=0.5 / GRADIENT_GAIN, mixing="eigen",
                    mix_every=10)
    ref = SampledController(m, "none", trajectory=traj)
    qd0, dqd0, _ = ref.reference(0.0)
    rec = sampled_loop(c, ModelPlant(m, qd0, dqd0, substeps=1), t_end, disturbance=dist,
                       every=50)
    qd = np.array([ref.reference(t)[0] for t in rec["t"]])
    assert np.all(np.isfinite(rec["theta_hat"]))
    assert np.abs(rec["q"] - qd).max() < 0.75


def test_xarm7_past_the_window_injection_at_theta_hat_flagged_at_nominal_holds():
    """The xArm7 diverged 2.79 s past T = 40 s once the composite term (21) drove θ̂ to
    where M(q, θ̂) is indefinite, with the observer's injection of (8) at θ̂; with a window
    of T = 10 s it does so at 11.2 s.  The prediction's default prefix (1.25 T: the loop
    itself, the composite term from T on) flags that design in one line naming the
    injection, and passes the injection at θ_nominal (the design's default), whose loop
    holds over the same 12.5 s (docs/controller.md, "The observer on the nominal
    inertia")."""
    from ivdrem.controller.stability import PREFIX_PAST_T
    m, _, q0, _, _, Kj, _ = _experiment("xarm7")
    K = inertia_scaled_gains(m, Kj, q0, 1e-3)
    assert PREFIX_PAST_T * 10.0 > 11.5
    old = _predict("xarm7", K, None, GRADIENT_GAIN, T=10.0, t_end=12.5, points=1,
                   injection="estimate")
    assert not old.stable and old.diverged is not None and 10.5 < old.diverged < 12.5, \
        old.reason()
    line = old.reason()
    assert "\n" not in line and "injection = 'nominal'" in line and "diverged at t = 11." in line
    new = _predict("xarm7", K, None, GRADIENT_GAIN, T=10.0, t_end=12.5, points=1)
    assert SampledController(m, "none", K=K).injection == "nominal"
    assert new.stable and new.diverged is None, new.reason()
    assert max(t for t, _, _ in new.points) >= 12.4       # the run went past T
    assert new.growth < 1.0, new.reason()


def test_prediction_with_the_robots_gravity_is_the_loop_without_it():
    """gravity = "robot": the controller commands τ − ĝ(q) and the robot adds G(q) itself,
    so the prediction's plant adds it too (the run over the prefix and the linearised
    step): the loop is the one without the option up to ĝ(q_k) held over a sample where
    the robot's G(q(t)) moves (measured: q within 2.6e-4 rad over 1 s), and so is its
    growth per step.  Without the robot's G(q) in the plant the arm falls (the UR5's
    shoulder holds 59 N m): q leaves the other run by far more."""
    from ivdrem.controller.stability import closed_loop_prefix
    m, traj, q0, dist, _, Kj, _ = _experiment("ur5")
    K = inertia_scaled_gains(m, Kj, q0, 1e-3)
    gains = dict(h=1e-3, K=K, trajectory=traj, delay=1, Gamma=GRADIENT_GAIN, T=0.01)
    runs = {}
    for gravity in ("controller", "robot"):
        pts, div = closed_loop_prefix(m, "none", m.theta_values, 1.0, checkpoints=2,
                                      gravity=gravity, **gains)
        assert div is None
        runs[gravity] = pts
        st = sampled_stability(m, "none", t_end=2.0, points=2, prefix=1.0, prefix_points=2,
                               suggest=False, gravity=gravity, **gains)
        runs[gravity + " growth"] = [g for _, _, g in st.points]
    for a, b in zip(runs["controller"], runs["robot"]):
        assert a[0] == b[0] and np.abs(a[1] - b[1]).max() < 1e-3
    np.testing.assert_allclose(runs["robot growth"], runs["controller growth"], atol=1e-5)
    # the check can fail: the command τ − ĝ(q) around a plant that does not add G(q)
    from ivdrem.controller.clib import CController
    qd0, dqd0, _ = SampledController(m, "none", trajectory=traj).reference(0.0)
    try:
        rec = sampled_loop(CController(m, "none", gravity="robot", **gains),
                           ModelPlant(m, qd0, dqd0, substeps=1), 1.0, every=1000)
        fell = np.abs(rec["q"][-1] - runs["robot"][-1][1]).max()
    except (FloatingPointError, ValueError, RuntimeError):
        fell = np.inf
    assert fell > 1e-2


# ------------------------------------------------- the prefix's loop in one compiled call
def _same_prefix(a, b):
    """Two results of closed_loop_prefix equal to the last bit: every point's t, q, q̇, u,
    θ̂, and the divergence's time and state."""
    (pa, da), (pb, db) = a, b
    assert len(pa) == len(pb)
    for x, y in zip(pa, pb):
        assert x[0] == y[0]
        for u, v in zip(x[1:], y[1:]):
            assert np.array_equal(u, v), (x[0], u, v)
    assert (da is None) == (db is None)
    if da is not None:
        assert da[0] == db[0]
        _same_prefix(([da[1]], None), ([db[1]], None))


@pytest.mark.parametrize("K, delay, diverges", [(200.0, 1, False), (480.0, 0, False),
                                                (480.0, 1, True)])
def test_compiled_prefix_is_the_python_loop_two_link(K, delay, diverges):
    """The C library's loop in one compiled call (the default) against the same C
    controller stepped from Python around the same RK4: the same points, bit for bit, with
    the paper's disturbance, either delay, and a loop that diverges (K = 480 with the delay,
    test_delay_halves_the_two_link_boundary), whose time and state 0.1-0.2 s before are
    the same too."""
    from ivdrem.controller.loop import PAPER_DISTURBANCE
    from ivdrem.controller.stability import closed_loop_prefix
    m = two_link()
    kw = dict(disturbance=lambda t: disturbance_at(t, PAPER_DISTURBANCE), checkpoints=5,
              h=1e-3, K=K, delay=delay)
    fast = closed_loop_prefix(m, "iv-drem", m.theta_values, 1.5, **kw)
    slow = closed_loop_prefix(m, "iv-drem", m.theta_values, 1.5, compiled=False, **kw)
    assert (fast[1] is not None) is diverges
    assert len(fast[0]) == (5 if not diverges else len(slow[0]))
    _same_prefix(fast, slow)


@pytest.mark.parametrize("K, delay, diverges", [(200.0, 1, False), (480.0, 1, True)])
def test_prefix_in_pieces_is_the_prefix_in_one_call(K, delay, diverges):
    """The compiled prefix runs in pieces of about PIECE_S s (between which Python handles
    Ctrl-C and SIGTERM); in one call, in pieces of 1 step, of 7 steps (boundaries that fall
    on records, checkpoints and the divergence's step or not) and of the default size:
    the same points, bit for bit, through a divergence too."""
    from ivdrem.controller import stability
    from ivdrem.controller.loop import PAPER_DISTURBANCE
    from ivdrem.controller.stability import FIRST_PIECE, closed_loop_prefix
    m = two_link()
    kw = dict(disturbance=lambda t: disturbance_at(t, PAPER_DISTURBANCE), checkpoints=5,
              h=1e-3, K=K, delay=delay)
    N = 1500
    calls = {}
    real = stability.run_in_pieces

    def counted(piece, progress, stop, pieces=None, **k):
        def one(k_stop):
            calls.setdefault(pieces, []).append(k_stop)
            return piece(k_stop)
        return real(one, progress, stop, pieces, **k)
    stability.run_in_pieces = counted
    try:
        runs = {p: closed_loop_prefix(m, "iv-drem", m.theta_values, N * 1e-3, pieces=p, **kw)
                for p in (N + 1, 1, 7, None)}
    finally:
        stability.run_in_pieces = real
    assert (runs[None][1] is not None) is diverges
    assert calls[N + 1] == [N + 1]                  # one call: the whole loop
    assert calls[None][0] == FIRST_PIECE          # the default: pieces (K = 480 diverges
    assert len(calls[None]) > 1 or diverges       # within the first)
    for p in (1, 7, None):
        _same_prefix(runs[p], runs[N + 1])


def test_the_prefix_progress_bar_changes_nothing(monkeypatch, capsys):
    """On a terminal the prefix draws a bar of its steps on stderr, updated between the
    pieces; the points are those of a run without it, bit for bit."""
    import ivdrem._progress as progress_rule
    from ivdrem.controller.stability import closed_loop_prefix
    m = two_link()
    kw = dict(checkpoints=4, h=1e-3, delay=1, pieces=100)
    quiet = closed_loop_prefix(m, "iv-drem", m.theta_values, 1.0, progress=False, **kw)
    assert "stability prediction" not in capsys.readouterr().err
    monkeypatch.setattr(progress_rule, "want_progress", lambda requested=None, stream=None:
                        requested is not False)
    shown = closed_loop_prefix(m, "iv-drem", m.theta_values, 1.0, **kw)
    err = capsys.readouterr().err
    assert "stability prediction, the loop's first 1 s" in err and "/1000" in err
    _same_prefix(shown, quiet)


def test_run_in_pieces_sizes_pieces_by_wall_time():
    """run_in_pieces: the first piece FIRST_PIECE steps, then sized to piece_s from the
    last piece's speed (at most 4 times the last), and the last piece ends at stop; a
    status other than "go on" is returned at once."""
    import time

    from ivdrem.controller.stability import FIRST_PIECE, run_in_pieces
    progress = [0]
    sizes = []

    def piece(k_stop):                  # 1 ms a step
        sizes.append(k_stop - progress[0])
        time.sleep(1e-3 * (k_stop - progress[0]))
        progress[0] = k_stop
        return 0 if k_stop == 2000 else 3
    assert run_in_pieces(piece, progress, 2000, piece_s=0.05) == 0
    assert sizes[0] == FIRST_PIECE and progress[0] == 2000
    assert all(b <= 4 * a for a, b in zip(sizes, sizes[1:]))
    assert 25 <= min(sizes[1:-1]) and max(sizes[1:-1]) <= 50      # ~50 steps of 1 ms
    progress[0] = 0

    def refused(k_stop):
        progress[0] = 5
        return 1
    assert run_in_pieces(refused, progress, 2000) == 1


def test_compiled_prefix_prediction_rows_unchanged_panda(monkeypatch):
    """The Panda's prediction as the export makes it (its configuration's design, the
    FMU's delay 1, the configuration's disturbance), over a short prefix past a short
    window (the law's composite term runs in the C library): every row (t, which θ̂, ρ)
    the same with the prefix run step by step from Python."""
    import functools

    from ivdrem.controller import stability
    from ivdrem.controller.fmu_export import controller_design, predict
    from ivdrem.experiments.config import read_config
    from ivdrem.experiments.experiment import Experiment
    experiment = Experiment.from_config(read_config("examples/panda.toml",
                                                    {"iv_drem.gamma": 500.0}))
    design = {**controller_design(experiment, "iv-drem", h=experiment.h), "T": 0.4}
    model = experiment.model
    fast = predict(model, "iv-drem", design, experiment)
    monkeypatch.setattr(stability, "closed_loop_prefix",
                        functools.partial(stability.closed_loop_prefix, compiled=False))
    slow = predict(model, "iv-drem", design, experiment)
    assert sum(w.startswith("theta_hat(t) of the run") for _, w, _ in fast.points) == 8
    assert fast.points == slow.points and fast.growth == slow.growth


def test_prefix_library_at_o3_is_o2_bit_for_bit():
    """The prefix's C library is built with -O3 (PREFIX_FLAGS: 1.3-1.6 times as fast on the
    Panda, benchmarks/bench_predict.py); its points are -O2's to the last bit (the UR5's
    IV-DREM past a short window, so the composite term (21) and the mixing (17) run)."""
    from ivdrem.controller.stability import PREFIX_FLAGS, closed_loop_prefix
    m, traj, q0, dist, _, Kj, _ = _experiment("ur5")
    gains = dict(h=1e-3, K=inertia_scaled_gains(m, Kj, q0, 1e-3), trajectory=traj,
                 delay=1, Gamma=GRADIENT_GAIN, gamma=0.5 / GRADIENT_GAIN, T=0.2,
                 mixing="eigen", mix_every=10)
    kw = dict(disturbance=lambda t: disturbance_at(t, dist), checkpoints=4, **gains)
    assert PREFIX_FLAGS == ("-O3",)
    o3 = closed_loop_prefix(m, "iv-drem", m.theta_values, 0.3, **kw)
    o2 = closed_loop_prefix(m, "iv-drem", m.theta_values, 0.3, flags=("-O2",), **kw)
    assert o3[1] is None and len(o3[0]) == 4
    assert np.abs(o3[0][-1][4]).max() > 0            # θ̂ moved
    _same_prefix(o3, o2)
