"""The sampled controller on real arms: the inertia-scaled design, the robot's contract
(gravity "robot", torque and torque-rate limits, a first command of zero), the Fourier
reference, the mixing variants and the multi-rate mixing, in the Python reference and the
C library (docs/controller.md, "Sampled designs" and "The robot's contract").

Independent checks: M(q) x by the model's own M (a second evaluation path of the
inertia-scaled feedback); a plant that adds its own gravity against a controller that
compensates it (the same loop two ways); the C library against the Python reference (two
implementations of the same algorithm, LAPACK against a Jacobi SVD, the Fourier series
written twice); the per-step growth of the sampled loop's feedback (an eigenvalue bound,
h k / lambda_min(M) < 2); each option's test fails without the option.
"""
import math
import os

import numpy as np
import pytest

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ivdrem.controller.sampled import SampledController  # noqa: E402
from ivdrem.models import get_model, two_link  # noqa: E402


def _experiment(model):
    """The real-arm experiment of docs/experiment.md: reference, q0, disturbance, window."""
    from ivdrem.diagrams import arm_reference as arm
    traj = arm.design_trajectory(model)
    q0, dq0 = arm.initial_state(traj)
    dist = arm.design_disturbance(model, traj)
    return traj, q0, dq0, dist, arm.design_window(traj, dist) or 20.0


def _measurements(ctl, k):
    """A smooth measured motion near the controller's own reference (no plant needed)."""
    t = k * ctl.h
    qd, dqd, _ = ctl.reference(t)
    return t, qd + 0.05 * np.sin(3 * t) + 0.02, dqd + 0.15 * np.cos(3 * t)


# ----------------------------------------------------------------------- the design
def test_inertia_scaled_feedback_is_the_nominal_inertia_times_the_papers():
    """M(q, theta_nominal)(K + delta_mu mu) r through Phi_M (Property 1) equals the model's
    own M(q) times the paper's feedback."""
    m = get_model("panda")
    ctl = SampledController(m, "none", K=np.arange(1.0, 8.0), design="inertia-scaled")
    paper = SampledController(m, "none", K=np.arange(1.0, 8.0), design="paper")
    rng = np.random.default_rng(1)
    M = np.empty((m.n, m.n))
    for _ in range(5):
        q, r, mu = rng.uniform(-1, 1, m.n), rng.standard_normal(m.n), rng.uniform(15, 135)
        m.functions.M(q, m.theta_values, M)
        want = M @ paper.feedback(q, r, mu)
        assert np.abs(ctl.feedback(q, r, mu) - want).max() <= 1e-12 * np.abs(want).max()


@pytest.mark.parametrize("name", ["panda", "xarm7"])
def test_per_step_growth_of_the_feedback(name):
    """The feedback applied once per step h = 1 ms, r+ = (I - h M^-1 F) r: the paper's
    F = (K + delta_mu mu) grows on the light wrists (spectral radius > 1: h k/lambda_min(M)
    > 2), the inertia-scaled F = M(q)(K + delta_mu mu) contracts by 1 - h (k + delta_mu mu)
    whatever M(q) (here at 200 random configurations within the joint limits)."""
    m = get_model(name)
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(m.position_limits).T
    h, k, mu = 1e-3, 2.0, 135.0
    M = np.empty((m.n, m.n))
    worst_paper = worst_scaled = 0.0
    for _ in range(200):
        q = rng.uniform(np.maximum(lo, -3), np.minimum(hi, 3))
        m.functions.M(q, m.theta_values, M)
        Minv = np.linalg.inv(M)
        F = (k + 0.8 * mu) * np.eye(m.n)
        worst_paper = max(worst_paper, np.abs(np.linalg.eigvals(np.eye(m.n) - h * Minv @ F)).max())
        worst_scaled = max(worst_scaled,
                           np.abs(np.linalg.eigvals(np.eye(m.n) - h * Minv @ (M @ F))).max())
    assert worst_paper > 2.0                       # measured: Panda 24, xArm7 820
    assert worst_scaled == pytest.approx(1 - h * (k + 0.8 * mu), abs=1e-9)


def _closed_loop(model, design, t_end, law="none", K=2.0, **kw):
    from ivdrem.controller.loop import ModelPlant, sampled_loop
    traj, q0, dq0, dist, T = _experiment(model)
    ctl = SampledController(model, law, K=K, T=kw.pop("T", T), trajectory=traj,
                            design=design, **kw)
    return ctl, sampled_loop(ctl, ModelPlant(model, q0, dq0), t_end, disturbance=dist,
                             every=100)


@pytest.mark.parametrize("name", ["panda", "xarm7"])
def test_inertia_scaled_loop_holds_at_1_khz_where_the_papers_diverges(name):
    """The real-arm experiment at h = 1 ms around the arm's own dynamics (RK4, torque held):
    the paper's design (K = 2 N m s) diverges within 0.3 s, the inertia-scaled one with the
    bandwidth K = 400 1/s (h (K + delta_mu mu) about 0.41) tracks within 0.1 rad for 3 s
    (measured 0.016-0.049 rad on the xArm7; with K = 2 1/s the xArm7's designed disturbance
    of 5-10 N m on its heavy joints throws it off in 0.9 s)."""
    m = get_model(name)
    with pytest.raises((FloatingPointError, ValueError)):
        _closed_loop(m, "paper", 0.3)
    ctl, rec = _closed_loop(m, "inertia-scaled", 3.0, K=400.0)
    assert np.all(np.isfinite(rec["q"])) and np.abs(rec["q"][-1] - ctl.q_d).max() < 0.1


# ----------------------------------------------------------------------- the robot's contract
def _gravity_pair(option):
    from ivdrem.controller.loop import ModelPlant, sampled_loop
    m = get_model("planar-3")
    out = []
    for robot_adds in (False, True):
        traj = dict(amplitude=[0.3] * 3, omega=[0.5, 0.75, 1.0], phase=[0.0] * 3,
                    offset=[0.0] * 3)
        ctl = SampledController(m, "iv-drem", T=0.3, gamma=1e6, mu_max=135.0,
                                trajectory=traj, gravity=option if robot_adds else "controller")
        plant = ModelPlant(m, [0.0] * 3, [0.15, 0.225, 0.3], gravity=robot_adds, substeps=8)
        rec = sampled_loop(ctl, plant, 1.0, disturbance=dict(
            amplitude=[1.0, 0.5, 0.2], omega=[1.3, 0.7, 2.1], phase=[0.0] * 3,
            offset=[0.0] * 3), every=50)
        g = np.array([_gravity(m, q) if robot_adds else np.zeros(3) for q in rec["q"]])
        out.append((rec, rec["tau"] + g))              # the torque acting on the arm
    return out


def _gravity(model, q):
    g = np.empty(model.n)
    model.functions.G(np.asarray(q, float), model.theta_values, g)
    return g


def test_gravity_robot_gives_the_loop_of_a_controller_that_compensates_it():
    """A plant that adds G(q) itself, with gravity = "robot": theta_hat and the torque
    acting on the arm as the plain plant with the law's torque (the robot's G(q(t)) moves
    within a sample where the controller's g_hat(q_k) is held: O(h) apart, measured
    ~1e-5 relative); with gravity = "controller" gravity counts twice."""
    (a, ta), (b, tb) = _gravity_pair("robot")
    assert np.abs(a["theta_hat"] - b["theta_hat"]).max() <= 1e-3 * np.abs(a["theta_hat"]).max()
    assert np.abs(ta - tb).max() <= 1e-3 * np.abs(ta).max()
    assert np.abs(a["q"] - b["q"]).max() < 1e-4
    (a, ta), (b, tb) = _gravity_pair("controller")
    assert np.abs(a["q"] - b["q"]).max() > 1e-2


def _knocked(ctl, k):
    """The smooth motion, knocked by 0.1 rad at t = 0.2 s (a torque jump of about 2 N m)."""
    t, q, dq = _measurements(_paper_reference(), k)
    return t, q + (0.1 if k >= 200 else 0.0), dq


_PAPER = []


def _paper_reference():
    if not _PAPER:
        _PAPER.append(SampledController())
    return _PAPER[0]


def test_torque_rate_limit_first_zero_and_torque_limit_in_python_and_c():
    """|tau_k - tau_k-1| <= h tau_rate_max (0.1 N m) at every step, tau_0 = 0, |tau_i| <= tau_max_i,
    the C library as the Python reference; without the options the torque jumps."""
    from ivdrem.controller.clib import CController
    lim = dict(tau_rate_max=100.0, first_zero=True, tau_max=[30.0, 8.0])
    for cls in (SampledController, CController):
        for opts, holds in ((lim, True), ({}, False)):
            ctl = cls(law="iv-drem", mu_max=135.0, T=0.5, **opts)
            taus = np.array([ctl.step(*_knocked(ctl, k)) for k in range(400)])
            rate_ok = np.abs(np.diff(taus, axis=0)).max() <= 0.1 + 1e-12
            assert rate_ok == holds
            assert (np.all(taus[0] == 0.0)) == holds
            assert (np.abs(taus[:, 1]).max() <= 8.0) == holds
    py = SampledController(law="iv-drem", mu_max=135.0, T=0.5, **lim)
    c = CController(law="iv-drem", mu_max=135.0, T=0.5, **lim)
    for k in range(400):
        a, b = py.step(*_knocked(py, k)), c.step(*_knocked(c, k))
        assert np.abs(a - b).max() <= 1e-12 * max(1.0, np.abs(a).max())


# ----------------------------------------------------------------------- C = Python
@pytest.mark.parametrize("opts", [
    dict(design="inertia-scaled", gravity="robot", mixing="eigen", mix_every=7),
    dict(design="inertia-scaled", mixing="channel", tau_rate_max=500.0, delay=1),
    dict(design="paper", mixing="eigen", first_zero=True)])
def test_c_library_equals_python_reference_with_the_real_arm_options(opts):
    """planar-3 (nθ = 6), a Fourier reference, the options of a real arm: the C library
    equals the Python reference to 1e-10 relative over 1500 steps (the 0.3 s window wraps
    five times, the scale-free mixings start at t = T)."""
    from ivdrem.controller.clib import CController
    m = get_model("planar-3")
    traj = dict(kind="fourier", omega_f=2 * math.pi / 1.5,
                a=[[0.3, -0.1, 0.05], [0.1, 0.2, -0.1], [-0.2, 0.1, 0.1]],
                b=[[0.0, 0.1, 0.0], [-0.1, 0.0, 0.05], [0.1, 0.0, -0.05]],
                offset=[0.1, 0.5, -0.3])
    kw = dict(mu_max=135.0, T=0.3, gamma=50.0, K=[3.0, 4.0, 5.0], trajectory=traj, **opts)
    py, c = SampledController(m, "iv-drem", **kw), CController(m, "iv-drem", **kw)
    worst = 0.0
    for k in range(1500):
        t, q, dq = _measurements(py, k)
        a, b = py.step(t, q, dq), c.step(t, q, dq)
        worst = max(worst, np.abs(a - b).max() / max(1.0, np.abs(a).max()))
        if k % 250 == 0:
            qd, dqd = c.last_reference()
            assert np.abs(qd - py.q_d).max() <= 1e-13 and np.abs(dqd - py.dq_d).max() <= 1e-13
    assert worst <= 1e-10
    th = py.theta_hat
    assert np.abs(th - c.theta_hat).max() <= 1e-10 * max(1.0, np.abs(th).max())
    assert py.Delta != 0.0 and abs(py.Delta - c.Delta) <= 1e-9 * abs(py.Delta)


def test_multi_rate_mixing_holds_delta_between_mixing_samples():
    """mix_every = m: Delta changes only at the samples k = 0, m, 2m, ...; m = 1 is the
    single-rate controller."""
    m = get_model("planar-3")
    ctl = SampledController(m, "iv-drem", T=0.3, gamma=50.0, mixing="eigen", mix_every=5)
    one = SampledController(m, "iv-drem", T=0.3, gamma=50.0, mixing="eigen")
    deltas, singles = [], []
    for k in range(700):
        ctl.step(*_measurements(ctl, k))
        one.step(*_measurements(one, k))
        deltas.append(ctl.Delta)
        singles.append(one.Delta)
    d = np.array(deltas)
    changed = np.flatnonzero(np.diff(d) != 0) + 1
    assert changed.size > 50 and np.all(changed % 5 == 0)
    assert np.unique(np.array(singles)[400:]).size > 250


def test_multi_rate_mixing_is_applied_one_period_after_its_sample():
    """mix_every = m > 1: the mixing (17) of the averaged (Y, Psi) at t_k (k a multiple of
    m) is held over [t_k+m, t_k+2m) (the C library spreads its work over the m samples
    between); m = 1 applies it at once.  Checked against mixing_values on the recorded
    (Y, Psi), per channel ("channel") and scalar ("eigen")."""
    from ivdrem.blocks._kernels import MIXING_VARIANTS, mixing_values
    m = get_model("planar-3")
    nth = m.ntheta
    for mixing in ("eigen", "channel"):
        ctl = SampledController(m, "iv-drem", T=0.3, gamma=50.0, mixing=mixing, mix_every=4)
        snaps, held = {}, {}
        for k in range(600):
            if k % 4 == 0:
                snaps[k] = ctl.Yavg.copy()
            ctl.step(*_measurements(ctl, k))
            held[k] = (ctl.D_held.copy(), ctl.calY_held.copy())
        D, calY, logD = np.zeros(nth), np.zeros(nth), np.zeros(nth)
        for k in range(8, 600, 4):
            mixing_values(MIXING_VARIANTS.index(mixing), snaps[k - 4][:nth],
                          snaps[k - 4][nth:], ctl.f_rel, ctl.guard, D, calY, logD)
            want = D if mixing == "channel" else np.full(nth, D[0])
            for j in range(k, min(k + 4, 600)):
                assert np.array_equal(held[j][0], want) and np.array_equal(held[j][1], calY)
        assert np.all(held[599][0] != 0.0)


def _composite_run(model, steps, **kw):
    """Composite learning's Python reference over `steps` samples of the measured motion,
    with every window output y = (Y_b, Psi_b) its max-hold sees and the hold after each step."""
    ctl = SampledController(model, "composite-learning", gamma=50.0, **kw)
    seen, held = {}, []
    orig = ctl._max_hold_sample

    def probe(y):
        seen[ctl.k] = y.copy()
        orig(y)
    ctl._max_hold_sample = probe
    for k in range(steps):
        ctl.step(*_measurements(ctl, k))
        held.append((ctl.lambda_min_held, ctl.held.copy()))
    return ctl, seen, held


def test_multi_rate_max_hold_decides_one_period_after_its_sample():
    """Composite learning with mix_every = m > 1: the max-hold of (35) samples the window at
    t_k, k a multiple of m, and decides at t_k+m (the C library spreads lambda_min over the
    m samples between); m = 1 decides at once.  Checked against LAPACK's eigvalsh on the
    recorded window outputs: the hold changes only at multiples of m, to the window of m
    samples before, when its lambda_min beat the running maximum and epsilon."""
    model = get_model("planar-3")
    nth = model.ntheta

    def lam(y):
        P = y[nth:].reshape(nth, nth)
        return np.linalg.eigvalsh(0.5 * (P + P.T))[0]
    for m in (1, 4):
        ctl, seen, held = _composite_run(model, 800, T=0.2, mix_every=m)
        best, changes = 0.0, 0
        for k in range(800):
            if k % m == 0 and k >= (m if m > 1 else 0):
                y = seen[k - m if m > 1 else k]
                if lam(y) > best and lam(y) > ctl.epsilon:
                    best = lam(y)
                    assert held[k][0] == best and np.array_equal(held[k][1], y)
            changes += k > 0 and held[k][0] != held[k - 1][0]
            assert held[k][0] == best, k
        assert changes > (100 if m == 1 else 30)


@pytest.mark.parametrize("mix_every", [1, 20])
def test_c_library_composite_learning_max_hold_equals_python_reference(mix_every):
    """Composite learning on the UR5 (nθ = 36), T = 0.5 s, 1500 steps: C (lambda_min of the
    hold by Householder tridiagonalization and bisection, a job sliced over the m samples)
    equals the Python reference (LAPACK) to 1e-10 on tau and theta_hat, and the hold took
    new windows along the way (lambda_min beat epsilon), at m = 1 and m = 20."""
    from ivdrem.controller.clib import CController
    m = get_model("ur5")
    kw = dict(T=0.5, gamma=50.0, trajectory=_experiment(m)[0], gravity="robot",
              mix_every=mix_every)
    py, c = SampledController(m, "composite-learning", **kw), CController(m, "composite-learning", **kw)
    worst, changes, last = 0.0, 0, 0.0
    for k in range(1500):
        t, q, dq = _measurements(py, k)
        a, b = py.step(t, q, dq), c.step(t, q, dq)
        worst = max(worst, np.abs(a - b).max() / max(1.0, np.abs(a).max()))
        changes += py.lambda_min_held != last
        last = py.lambda_min_held
    assert worst <= 1e-10
    th = py.theta_hat
    assert np.abs(th - c.theta_hat).max() <= 1e-10 * max(1.0, np.abs(th).max())
    assert changes >= (100 if mix_every == 1 else 8)


def test_c_max_hold_lambda_min_job_equals_lapack(tmp_path):
    """The C library's lambda_min of the symmetric part (Householder tridiagonalization and
    Sturm bisection, ivdrem_controller.c) against LAPACK's eigvalsh, n = 43 (the Panda's
    nθ): general, graded positive definite (eigenvalues 1e-10 .. 1e4), rank-deficient and
    phi^T phi-like matrices within 1e-14 ||S||; the job sliced in small budgets gives the
    same bits as at once, and its work never exceeds the budget the period is given."""
    import ctypes
    from ivdrem._cc import compile_shared
    from ivdrem.controller.codegen import generate_controller_sources
    panda = get_model("panda")
    for fn, text in generate_controller_sources(panda).items():
        (tmp_path / fn).write_text(text)
    (tmp_path / "lam_driver.c").write_text(
        '#include "ivdrem_controller.c"\n'
        "/* lambda_min of y's Psi part at once and in slices of `budget` units */\n"
        "double lam_once_and_sliced(const double *y, double budget, double *sliced, double *units,\n"
        "                           double *total) {\n"
        "    static ivc_controller c;\n"
        "    double once;\n"
        "    lam_begin(&c, y); lam_work(&c, -1.0); once = c.s.lam_value;\n"
        "    lam_begin(&c, y); *units = 0;\n"
        "    while (c.s.lam_phase != LAM_DONE) *units += lam_work(&c, budget);\n"
        "    *sliced = c.s.lam_value; *total = lam_job_units();\n"
        "    return once;\n"
        "}\n")
    lib_path = tmp_path / "lam.so"
    compile_shared([tmp_path / "lam_driver.c", tmp_path / "controller_model.c"], lib_path,
                   what="the lambda_min test driver", include_dirs=[tmp_path],
                   extra_flags=())
    lib = ctypes.CDLL(str(lib_path))
    dp = ctypes.POINTER(ctypes.c_double)
    lib.lam_once_and_sliced.restype = ctypes.c_double
    lib.lam_once_and_sliced.argtypes = [dp, ctypes.c_double, dp, dp, dp]
    n = panda.ntheta
    rng = np.random.default_rng(7)
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    X = rng.standard_normal((n, 30)) * 1e5
    Z = rng.standard_normal((200, n)) * np.logspace(-3, 2, n)
    mats = [rng.standard_normal((n, n)), Q @ np.diag(np.logspace(-10, 4, n)) @ Q.T,
            X @ X.T, Z.T @ Z + 1e-3 * rng.standard_normal((n, n)), np.zeros((n, n)),
            1e-200 * rng.standard_normal((n, n)), 1e200 * rng.standard_normal((n, n))]
    for A in mats:
        y = np.concatenate([np.zeros(n), A.reshape(-1)])
        sliced, units, total = ctypes.c_double(), ctypes.c_double(), ctypes.c_double()
        once = lib.lam_once_and_sliced(y.ctypes.data_as(dp), 37.0, ctypes.byref(sliced),
                                       ctypes.byref(units), ctypes.byref(total))
        ev = np.linalg.eigvalsh(0.5 * (A + A.T))
        assert abs(once - ev[0]) <= 1e-14 * np.abs(ev).max() + 1e-300, (once, ev[0])
        assert once == sliced.value
        assert units.value <= total.value


_SLICED_JOB_DRIVER = r"""
#include "ivdrem_controller.c"
/* `steps` samples of a smooth motion with the mixing every m samples and window T: at each
 * mixing sample the new job is also run at once on a copy of the state; when the period ends
 * the job run in slices must have finished and match it bit for bit.  Returns the number of
 * jobs compared, or -1 - k at the first sample k where not; *capped: jobs that ended at the
 * sweep cap; *sweeps: the cap. */
long sliced_equals_at_once(long steps, double m, double T, double mixing, long *capped,
                           double *sweeps) {
    static ivc_state once;
    double par[IVC_NPAR], q[IVC_NQ], dq[IVC_NQ], tau[IVC_NQ], qd[IVC_NQ], dqd[IVC_NQ];
    char msg[256];
    long k, jobs = 0;
    int i, have = 0;
    ivc_controller *c;
    ivc_default_params(par);
    par[IVC_P_MIX_EVERY] = m; par[IVC_P_T] = T; par[IVC_P_MIXING] = mixing;
    c = ivc_init(par, msg, sizeof msg);
    if (!c) return -1;
    *capped = 0;
    *sweeps = c->mix_sweeps;
    for (k = 0; k < steps; k++) {
        double t = k * c->h;
        for (i = 0; i < IVC_NQ; i++) qd[i] = dqd[i] = 0.0;
        if (k > 0) ivc_reference(c, qd, dqd);
        for (i = 0; i < IVC_NQ; i++) {
            q[i] = qd[i] + 0.05 * sin(3.0 * t + i) + 0.02;
            dq[i] = dqd[i] + 0.15 * cos(3.0 * t + i);
        }
        if (k % (long)m == 0 && have) {          /* the period's job must be done, as at once */
            if (c->s.mix_phase != MIX_DONE
                || memcmp(c->s.mix_D, once.mix_D, sizeof once.mix_D)
                || memcmp(c->s.mix_calY, once.mix_calY, sizeof once.mix_calY)
                || memcmp(c->s.mix_V, once.mix_V, sizeof once.mix_V)) { ivc_free(c); return -1 - k; }
            jobs++;
            *capped += once.mix_sweep == c->mix_sweeps;
        }
        if (ivc_step(c, t, q, dq, tau) != IVC_OK) { ivc_free(c); return -1 - k; }
        if (k % (long)m == 0) {                  /* the job begun now, run at once */
            ivc_state keep = c->s;
            mix_work(c, -1.0);
            once = c->s;
            c->s = keep;
            have = 1;
        }
    }
    ivc_free(c);
    return jobs;
}
"""


def test_c_mixing_job_sliced_over_the_period_equals_the_job_at_once(tmp_path):
    """The C library's multi-rate mixing on the UR5 (nθ = 36), T = 0.5 s, "eigen" and
    "channel", every 20 and 7 samples, 1500 samples: every job run in its per-sample slices
    has finished when its period ends (no sample finishes a long job at once) and its result
    (Δ, 𝒴 and the rotations V, the next warm start) equals the same job run at once, bit for
    bit; the sweep cap is reached by some jobs while the window starts."""
    import ctypes
    from ivdrem._cc import compile_shared
    from ivdrem.controller.codegen import generate_controller_sources
    ur5 = get_model("ur5")
    for fn, text in generate_controller_sources(ur5).items():
        (tmp_path / fn).write_text(text)
    (tmp_path / "job_driver.c").write_text(_SLICED_JOB_DRIVER)
    lib_path = tmp_path / "job.so"
    compile_shared([tmp_path / "job_driver.c", tmp_path / "controller_model.c"], lib_path,
                   what="the mixing job's test driver", include_dirs=[tmp_path])
    lib = ctypes.CDLL(str(lib_path))
    lib.sliced_equals_at_once.restype = ctypes.c_long
    lib.sliced_equals_at_once.argtypes = [ctypes.c_long, ctypes.c_double, ctypes.c_double,
                                          ctypes.c_double, ctypes.POINTER(ctypes.c_long),
                                          ctypes.POINTER(ctypes.c_double)]
    capped_total = 0
    for m, mixing in ((20, 1.0), (7, 2.0)):
        capped, sweeps = ctypes.c_long(), ctypes.c_double()
        jobs = lib.sliced_equals_at_once(1500, m, 0.5, mixing, ctypes.byref(capped),
                                         ctypes.byref(sweeps))
        assert jobs == 1500 // m - (1500 % m == 0), (m, mixing, jobs)
        # the cap: as many sweeps (11 units a pair, 630 pairs) as m x IVC_MIX_BUDGET hold
        assert sweeps.value == (16 if m == 20 else 8)
        capped_total += capped.value
    assert capped_total > 0


def test_scale_free_mixings_default_gamma_by_the_auto_rule():
    """gamma not given: 0.5 / max(Gamma) with the scale-free mixings (the rule of gamma
    "auto" at Delta = 1; 50 at the default Gamma = 0.01), the law's registry value with the
    paper's mixing (the 2-link's paper design unchanged) and for composite learning."""
    from ivdrem.diagrams.gamma_auto import DEFAULT_RATE
    from ivdrem.laws import get_law
    ur5 = get_model("ur5")
    assert SampledController(ur5, "iv-drem").gamma == 50.0                  # eigen (default)
    assert SampledController(ur5, "drem", mixing="channel",
                             Gamma=np.linspace(0.01, 0.04, ur5.ntheta)).gamma \
        == DEFAULT_RATE / 0.04
    assert SampledController(ur5, "iv-drem", gamma=7.0).gamma == 7.0         # given: kept
    paper = get_law("iv-drem").defaults["gamma"]
    assert SampledController(ur5, "iv-drem", mixing="paper").gamma == paper
    assert SampledController(law="iv-drem").gamma == paper                   # the 2-link
    assert SampledController(ur5, "composite-learning").gamma == \
        get_law("composite-learning").defaults["gamma"]


# ----------------------------------------------------------------------- refusals
def test_refusals_name_the_number_and_the_option():
    from ivdrem.controller.parameters import param_layout, param_vector
    from ivdrem.controller.clib import load_library
    import ctypes
    for bad, match in ((dict(T=0.0105), r"T / h = 10\.5"), (dict(design="fast"), "design"),
                       (dict(gravity="arm"), "gravity"), (dict(mixing="svd"), "mixing"),
                       (dict(mix_every=0), "mix_every"), (dict(tau_rate_max=0.0), "tau_rate_max"),
                       (dict(tau_max=[1.0, -1.0]), "tau_max")):
        with pytest.raises(ValueError, match=match):
            SampledController(**bad)
    m = two_link()
    lib = load_library(m)
    lib.ivc_check_params.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.c_char_p,
                                     ctypes.c_size_t]
    idx, off = {}, 0
    for name, size, _ in param_layout(m):
        idx[name] = off
        off += size
    good = param_vector(SampledController(mu_max=135.0))
    for name, value, match in (("T", 0.0105, "T / h = 10.5"), ("design", 3.0, "design = 3"),
                               ("gravity", 0.5, "gravity = 0.5"), ("mixing", 4.0, "mixing = 4"),
                               ("tau_rate_max", 0.0, "tau_rate_max"),
                               ("mix_every", 1.5, "mix_every = 1.5")):
        par = good.copy()
        par[idx[name]] = value
        msg = ctypes.create_string_buffer(256)
        assert lib.ivc_check_params(par.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
                                    msg, 256) != 0
        assert match in msg.value.decode() and "\n" not in msg.value.decode()
    msg = ctypes.create_string_buffer(256)
    assert lib.ivc_check_params(good.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
                                msg, 256) == 0


@pytest.mark.parametrize("name", ["ur5", pytest.param("panda", marks=pytest.mark.slow)])
def test_c_library_equals_python_reference_on_real_arms(name):
    """Every law with a sampled form on the UR5 (nθ = 36) and the Panda (43; slow), with the
    real arm's defaults (inertia-scaled design, "eigen" mixing, the Fourier reference),
    gravity "robot" and the mixing every 3 samples: C = Python to 1e-10 relative on tau and
    theta_hat over 0.5 s (500 steps; the 0.1 s window wraps, the composite term is on from
    t = T; shorter than 10 s: the Python reference takes 1-2 ms a step here, and measured
    with 1000 steps and T = 0.25 s on both arms the result is the same)."""
    from ivdrem.controller.clib import CController
    from ivdrem.controller.sampled import SAMPLED_LAWS
    m = get_model(name)
    traj = _experiment(m)[0]
    for law in SAMPLED_LAWS:
        kw = dict(T=0.1, gamma=50.0, trajectory=traj, gravity="robot", mix_every=3)
        py, c = SampledController(m, law, **kw), CController(m, law, **kw)
        worst = 0.0
        for k in range(500):
            t, q, dq = _measurements(py, k)
            a, b = py.step(t, q, dq), c.step(t, q, dq)
            worst = max(worst, np.abs(a - b).max() / max(1.0, np.abs(a).max()))
        th = py.theta_hat
        assert worst <= 1e-10, (law, worst)
        assert np.abs(th - c.theta_hat).max() <= 1e-10 * max(1.0, np.abs(th).max()), law
        assert np.abs(th - kw.get("theta_hat0", 0.0)).max() > 1e-6     # the estimate moved


@pytest.mark.parametrize("name, law", [("panda", "iv-drem"), ("ur5", "drem")])
def test_c_library_equals_python_reference_over_3_windows(name, law):
    """6 s (6,000 samples, three windows T = 2 s: filling, the composite term from T on,
    learning) of benchmarks/check_c_equals_python.py, one law per arm (that script runs
    every law on both arms over 10 s): the real arm's options, the mixing every 20 samples
    (one period late, the C library's job sliced over the period); C = Python to 1e-10
    relative on tau and theta_hat at every sample (measured over 6 s: 1.6e-12 and 9.4e-13
    on the Panda, as over 10 s; 7.4e-14 and 3.6e-13 on the UR5, 2.1e-13 on tau over 10 s)."""
    import importlib.util
    from pathlib import Path
    spec = importlib.util.spec_from_file_location(
        "check_c_equals_python",
        Path(__file__).parents[1] / "benchmarks" / "check_c_equals_python.py")
    check = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check)
    r = check.compare(name, law, t_end=6.0)
    assert r["steps"] == 6000
    assert r["tau"] <= 1e-10 and r["theta_hat"] <= 1e-10, r
    assert r["moved"] > 1e-3 and r["Delta_c"] != 0.0            # the estimate and Delta moved
    assert abs(r["Delta_py"] - r["Delta_c"]) <= 1e-9 * abs(r["Delta_py"])


def test_inertia_scaled_loop_converges_at_first_order_in_h_on_the_ur5():
    """The sampled loop (C library, inertia-scaled, IV-DREM "eigen", the real-arm reference
    and disturbance) around the UR5's own dynamics: theta_hat and q at t = 0.5 s approach
    the loop at h = 1/16 ms like O(h) (h = 1, 0.5, 0.25 ms: the continuous design's limit
    by step refinement; the errors halve with h)."""
    from ivdrem.controller.clib import CController
    from ivdrem.controller.loop import ModelPlant, sampled_loop
    m = get_model("ur5")
    traj, q0, dq0, dist, _ = _experiment(m)
    K = [4.0, 4.0, 4.0, 8.0, 8.0, 16.0]

    def final(h):
        ctl = CController(m, "iv-drem", h=h, K=K, T=0.25, gamma=50.0, trajectory=traj,
                          theta_hat0=0.5 * np.asarray(m.theta_values))
        rec = sampled_loop(ctl, ModelPlant(m, q0, dq0, substeps=2), 0.5, disturbance=dist,
                           every=10 ** 7)
        return np.concatenate([rec["theta_hat"][-1], rec["q"][-1]])
    ref = final(6.25e-5)
    errs = [np.abs(final(h) - ref).max() for h in (1e-3, 5e-4, 2.5e-4)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all((orders > 0.8) & (orders < 1.4)), (errs, orders)
