"""The sampled controller's building blocks: window (15a) and exact filter updates."""
import math

import numpy as np
import pytest
from scipy.integrate import quad, solve_ivp

from ivdrem.controller import (BlockWindow, averaging_factor, filter_step, mu_integral,
                               observer_decay)


def _trapezoid_window(G, h, N):
    """Full-memory reference: trapezoid over the last N intervals, g = 0 before t0."""
    c = np.zeros_like(G)
    c[1:] = 0.5 * h * (G[1:] + G[:-1])
    cs = np.cumsum(c, axis=0)
    out = cs.copy()
    out[N:] -= cs[:-N]
    return out


def test_window_block1_equals_full_trapezoid():
    rng = np.random.default_rng(1)
    h, T = 1e-3, 0.05
    G = rng.standard_normal((400, 3))
    w = BlockWindow(3, T, h, block=1)
    Y = np.array([w.push(g) for g in G])
    assert np.max(np.abs(Y - _trapezoid_window(G, h, 50))) < 1e-13


def test_window_blocks_exact_at_boundaries_and_close_between():
    h, T, B = 1e-3, 0.2, 10
    t = h * np.arange(2000)
    G = np.stack([np.sin(3 * t), np.cos(0.5 * t) + t], axis=1)
    w = BlockWindow(2, T, h, block=B)
    Y = np.array([w.push(g) for g in G])
    ref = _trapezoid_window(G, h, 200)
    k = np.arange(len(t))
    assert np.max(np.abs(Y[k % B == 0] - ref[k % B == 0])) < 1e-12
    # between boundaries: the interpolated oldest block, error <= B h max|g'| B h
    assert np.max(np.abs(Y - ref)) < (B * h) ** 2 * 3.0
    # the window of a smooth g approaches the exact integral (h -> 0 would be O(h^2))
    exact = np.array([quad(lambda s: math.sin(3 * s), max(0, tk - T), tk)[0] for tk in t[::97]])
    assert np.max(np.abs(Y[::97, 0] - exact)) < 1e-4


def _window_errors(naive, K=200000, h=1e-3, T=0.02, B=5):
    """Max error of the window at block boundaries early and late in a long run of random
    g ~ 1e6, against the exact trapezoid over the window's 20 intervals."""
    G = 1e6 + np.random.default_rng(0).random(K)
    c = np.zeros(K)
    c[1:] = 0.5 * h * (G[1:] + G[:-1])
    w = BlockWindow(1, T, h, block=B)
    early = late = 0.0
    for k in range(K):
        if naive:
            w.nshadow = 0                   # never reset: the plain running sum
        y = w.push(G[k:k + 1])
        if k % B == 0 and (100 < k < 2100 or k > K - 2000):
            err = abs(y[0] - math.fsum(c[k - 19:k + 1]))
            if k < 2100:
                early = max(early, err)
            else:
                late = max(late, err)
    return early, late


def test_window_running_sum_does_not_drift():
    """The shadow sum keeps the error at its early level over 10,000 window lengths; the
    plain running sum S += new - old (same class, reset disabled) drifts."""
    early, late = _window_errors(naive=False)
    assert late <= 1.5 * early
    n_early, n_late = _window_errors(naive=True)
    assert n_late > 2 * late                  # measured: 5.8e-11 against 7.3e-12


def test_window_memory_and_bad_sizes():
    w = BlockWindow(30, 20.0, 1e-3, block=10)          # paper's arm: m = nθ + nθ² = 30
    assert w.ring.shape == (2000, 30)
    assert w.nbytes < 0.5 * 2 ** 20
    with pytest.raises(ValueError, match="whole number"):
        BlockWindow(3, 0.0105, 1e-3, block=10)


def test_filter_step_is_exact_for_held_input_at_any_gain():
    # x_f' = a (x - x_f), x held: the exact solution; Euler with a h = 50 would explode
    a, h, x, xf = 5e4, 1e-3, 2.0, -1.0
    d = math.exp(-a * h)
    assert filter_step(xf, x, d) == pytest.approx(x + math.exp(-a * h) * (xf - x), rel=1e-15)
    for _ in range(10):
        xf = filter_step(xf, x, d)
    assert abs(xf - x) < 1e-12


@pytest.mark.parametrize("t", [0.0, 80.0, 84.9995, 85.0, 200.0])
def test_observer_decay_against_ode(t):
    """Factors of (7) with saturated mu (mu0 = 1, mu1 = 15, mu_max = 100: kink at 85 s)
    against the ODE x_f' = a(t)(x - x_f) solved by scipy."""
    h, mu0, mu1, mumax = 1e-3, 1.0, 15.0, 100.0
    mu = lambda s: min(mu0 * s + mu1, mumax)                       # noqa: E731
    dmu = lambda s: mu0 if mu0 * s + mu1 < mumax else 0.0          # noqa: E731
    assert mu_integral(t, h, mu0, mu1, mumax) == pytest.approx(
        quad(mu, t, t + h, points=[85.0] if t < 85 < t + h else None)[0], rel=1e-12)
    d_f, d_m = observer_decay(t, h, mu0, mu1, mumax)
    for gain, d in ((mu, d_f), (lambda s: mu(s) + dmu(s) / mu(s), d_m)):
        sol = solve_ivp(lambda s, y: [gain(s) * (1.0 - y[0])], (t, t + h), [0.0],
                        method="DOP853", rtol=1e-13, atol=1e-15)
        assert 1.0 - d == pytest.approx(sol.y[0, -1], rel=1e-9)


def test_averaging_factor_solves_15b():
    p, F0, t, h, y = 2.0, 1.0, 3.0, 0.01, 0.7
    F = lambda s: s ** p + F0                                      # noqa: E731
    sol = solve_ivp(lambda s, Y: [-(p * s ** (p - 1) / F(s)) * (Y[0] - y)], (t, t + h), [2.0],
                    method="DOP853", rtol=1e-13, atol=1e-15)
    assert y + averaging_factor(t, h, p, F0) * (2.0 - y) == pytest.approx(sol.y[0, -1], rel=1e-11)
    with pytest.raises(ValueError, match="E3"):
        averaging_factor(t, h, p, 0.0)
