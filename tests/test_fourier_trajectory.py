"""The finite-Fourier-series reference trajectory (ivdrem.blocks.sources.fourier_trajectory):
analytic derivatives against finite differences, the block kernel against the numpy series,
the bounds it is scaled by, and the compiled path against python-control's."""
import numpy as np
import pytest

from ivdrem.blocks import ParameterError
from ivdrem.blocks.sources import fourier_bounds, fourier_series, fourier_trajectory

RNG = np.random.default_rng(7)
N, H = 3, 4
OMEGA_F = 2 * np.pi / 10
A = RNG.standard_normal((N, H))
B = RNG.standard_normal((N, H))
C = RNG.standard_normal(N)


def test_derivatives_against_central_differences():
    t = np.linspace(0.0, 25.0, 301)
    h = 1e-5
    q, dq, ddq = fourier_series(t, OMEGA_F, A, B, C)
    qp, dqp, _ = fourier_series(t + h, OMEGA_F, A, B, C)
    qm, dqm, _ = fourier_series(t - h, OMEGA_F, A, B, C)
    # central differences: error O(h^2 |q'''|) + round-off O(eps/h) ~ 1e-10 here
    np.testing.assert_allclose((qp - qm) / (2 * h), dq, rtol=0, atol=1e-8)
    np.testing.assert_allclose((dqp - dqm) / (2 * h), ddq, rtol=0, atol=1e-8)
    # the check can fail: a wrong sign of the cosine part breaks it
    _, wrong, _ = fourier_series(t, OMEGA_F, A, -B, C)
    assert np.max(np.abs((qp - qm) / (2 * h) - wrong)) > 1e-2


def test_one_harmonic_is_the_closed_form_sinusoid():
    """H = 1: q = c + (a sin wt − b cos wt)/w = c + (|(a, b)|/w) sin(wt − atan2(b, a))."""
    a, b, c, w = np.array([[0.7]]), np.array([[-0.4]]), np.array([0.2]), 1.3
    t = np.linspace(0, 10, 57)
    q, dq, ddq = fourier_series(t, w, a, b, c)
    amp, phi = np.hypot(0.7, -0.4) / w, np.arctan2(-0.4, 0.7)
    np.testing.assert_allclose(q[:, 0], 0.2 + amp * np.sin(w * t - phi), atol=1e-14)
    np.testing.assert_allclose(dq[:, 0], amp * w * np.cos(w * t - phi), atol=1e-14)
    np.testing.assert_allclose(ddq[:, 0], -amp * w * w * np.sin(w * t - phi), atol=1e-14)


def test_block_output_equals_the_series():
    blk = fourier_trajectory(N, OMEGA_F, A, B, C)
    assert blk.name == "trajectory" and blk.ninputs == 0
    assert [s.split("[")[0] for s in blk.output_labels[::N]] == ["q_d", "dq_d", "ddq_d"]
    for t in (0.0, 0.37, 3.1, 17.0):
        y = np.asarray(blk.output(t, [], []), float)
        q, dq, ddq = fourier_series([t], OMEGA_F, A, B, C)
        np.testing.assert_allclose(y, np.concatenate([q[0], dq[0], ddq[0]]), rtol=1e-13,
                                   atol=1e-13)


def test_bounds_hold_and_are_reached_by_one_harmonic():
    t = np.linspace(0.0, 2 * np.pi / OMEGA_F, 20001)
    q, dq, _ = fourier_series(t, OMEGA_F, A, B, C)
    pos, vel = fourier_bounds(OMEGA_F, A, B)
    assert np.all(np.max(np.abs(q - C), axis=0) <= pos + 1e-12)
    assert np.all(np.max(np.abs(dq), axis=0) <= vel + 1e-12)
    # one harmonic: the bound is the amplitude, reached
    a, b = np.array([[0.3]]), np.array([[0.4]])
    q1, dq1, _ = fourier_series(np.linspace(0, 2 * np.pi, 40001), 1.0, a, b, [0.0])
    p1, v1 = fourier_bounds(1.0, a, b)
    assert np.max(np.abs(q1)) == pytest.approx(p1[0], rel=1e-8)
    assert np.max(np.abs(dq1)) == pytest.approx(v1[0], rel=1e-8)


@pytest.mark.parametrize("kw, fragment", [
    (dict(a=np.ones((2, 3)), b=np.ones((3, 3))), "'q_d_a' must be an 3 x H matrix"),
    (dict(a=np.ones((3, 3)), b=np.ones((3, 2))), "must have the same shape"),
    (dict(a=np.ones(3), b=np.ones(3)), "'q_d_a' must be an 3 x H matrix"),
    (dict(omega_f=0.0), "'q_d_omega_f' must be > 0"),
    (dict(offset=[0.0, 1.0]), "'q_d_offset' must have length 3"),
    (dict(a=np.full((3, 2), np.nan), b=np.ones((3, 2))), "non-finite"),
])
def test_bad_parameters_name_the_parameter(kw, fragment):
    args = dict(omega_f=OMEGA_F, a=A, b=B, offset=C) | kw
    with pytest.raises(ParameterError, match=fragment.replace("(", r"\(")):
        fourier_trajectory(N, **args)


def test_compiled_loop_equals_reference_loop():
    """The kernel compiled by numba inside a closed loop gives python-control's result."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import planar_arm
    from ivdrem.sim import simulate
    m = planar_arm(2)
    a, b = 0.5 * A[:2, :2], 0.5 * B[:2, :2]
    traj = fourier_trajectory(2, 1.0, a, b, [0.1, 0.2])
    dist = dict(amplitude=[0.5, 0.2], omega=[1.5, 0.7], phase=[0.0, 0.0], offset=[0.0, 0.0])
    q0 = fourier_series([0.0], 1.0, a, b, [0.1, 0.2])[0][0]
    loop = closed_loop("none", m, trajectory=traj, disturbance=dist, q0=q0)
    out = {}
    for engine in ("compiled", "reference"):
        r = simulate(loop, 0.5, dt_out=0.05, engine=engine, method="rk4", h=1e-3,
                     progress=False)
        out[engine] = np.asarray(r.outputs)
    np.testing.assert_allclose(out["compiled"], out["reference"], rtol=1e-10, atol=1e-10)
    qd = fourier_series(np.asarray(r.time), 1.0, a, b, [0.1, 0.2])[0]
    idx = [i for i, lab in enumerate(r.output_labels) if lab.startswith("q_d[")]
    np.testing.assert_allclose(out["compiled"][idx].T, qd, atol=1e-13)
