"""A robot's sensors and actuator limits (ivdrem.plants.sensing): each applied as documented,
and nothing changed when everything is off.  No MuJoCo needed."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lfilter

from ivdrem.plants.sensing import REALISTIC, Imperfections

H = 1e-3


def _trajectory(n=3, N=2000, seed=4):
    rng = np.random.default_rng(seed)
    t = np.arange(N) * H
    A, w = rng.uniform(0.2, 1.0, n), rng.uniform(0.5, 3.0, n)
    return t, np.sin(np.outer(t, w)) * A, np.cos(np.outer(t, w)) * A * w


def test_everything_off_passes_the_numbers_through_untouched():
    t, q, dq = _trajectory()
    r = Imperfections().start(3, H, q[0], dq[0])
    assert Imperfections().active == []
    for k in range(len(t)):
        qk, dqk = q[k], dq[k]
        qm, dqm = r.measure(qk, dqk)
        assert qm is qk and dqm is dqk              # the very arrays: bit for bit
        tau = np.array([1e3, -2e3, 0.5]) * np.sin(k)
        assert r.actuate(tau) is tau


def test_quantized_positions_are_multiples_of_the_count():
    counts = 2.0 ** 12
    quantum = 2 * math.pi / counts
    t, q, dq = _trajectory()
    r = Imperfections(encoder_counts=counts).start(3, H, q[0], dq[0])
    m = np.array([r.measure(q[k], dq[k])[0] for k in range(len(t))])
    steps = m / quantum
    assert np.abs(steps - np.round(steps)).max() < 1e-9
    assert np.abs(m - q).max() <= 0.5 * quantum * (1 + 1e-12)
    assert np.abs(m - q).max() > 0.3 * quantum          # it did quantize


def test_filtered_difference_is_the_low_pass_of_the_measured_differences():
    """Second path: scipy's lfilter of the differences, same pole and start."""
    fc = 150.0
    t, q, dq = _trajectory()
    spec = Imperfections(encoder_counts=2.0 ** 16, velocity="difference", velocity_cutoff=fc)
    r = spec.start(3, H, q[0], dq[0])
    out = np.array([r.measure(q[k], dq[k])[1] for k in range(len(t))])
    quantum = 2 * math.pi / 2.0 ** 16
    qm = quantum * np.round(q / quantum)
    raw = np.diff(qm, axis=0, prepend=qm[:1]) / H
    p = math.exp(-2 * math.pi * fc * H)
    ref, _ = lfilter([1 - p], [1, -p], raw, axis=0, zi=(p * dq[0])[None, :])
    assert np.abs(out - ref).max() < 1e-9
    # it tracks the true velocity after the transient: one count over h is 0.096 rad/s in
    # the raw difference, about a third of it after the low-pass
    assert np.abs(out[500:] - dq[500:]).max() < 0.1


def test_velocity_noise_has_the_given_sigma_and_follows_the_seed():
    sigma = 0.01
    t, q, dq = _trajectory(N=20000)
    outs = []
    for seed in (1, 1, 2):
        r = Imperfections(velocity="noise", velocity_noise=sigma, seed=seed).start(
            3, H, q[0], dq[0])
        outs.append(np.array([r.measure(q[k], dq[k])[1] for k in range(len(t))]) - dq)
    assert np.array_equal(outs[0], outs[1])              # same seed, same noise
    assert not np.array_equal(outs[0], outs[2])
    assert abs(outs[0].std() / sigma - 1) < 0.02
    assert abs(outs[0].mean()) < 5 * sigma / math.sqrt(outs[0].size)


def test_encoder_noise_is_rounded_by_the_encoder_and_follows_the_seed():
    """White noise of σ counts before the encoder: the measured angles stay multiples of
    the count; their error is the noise plus the rounding (dithered, uniform): variance
    σ² + 1/12 counts²; σ = 0 is the plain encoder, bit for bit."""
    counts, sigma = 2.0 ** 12, 1.0
    quantum = 2 * math.pi / counts
    t, q, dq = _trajectory(N=20000)
    outs = []
    for seed in (5, 5, 6):
        spec = Imperfections(encoder_counts=counts, encoder_noise=sigma, seed=seed)
        assert spec.random and "encoder noise σ = 1 counts" in spec.active
        r = spec.start(3, H, q[0], dq[0])
        outs.append(np.array([r.measure(q[k], dq[k])[0] for k in range(len(t))]))
    steps = outs[0] / quantum
    assert np.abs(steps - np.round(steps)).max() < 1e-9
    assert np.array_equal(outs[0], outs[1]) and not np.array_equal(outs[0], outs[2])
    err = (outs[0] - q) / quantum
    assert abs(err.std() / math.sqrt(sigma ** 2 + 1 / 12) - 1) < 0.02
    assert abs(err.mean()) < 5 * err.std() / math.sqrt(err.size)
    plain = Imperfections(encoder_counts=counts).start(3, H, q[0], dq[0])
    zero = Imperfections(encoder_counts=counts, encoder_noise=0.0, seed=5).start(
        3, H, q[0], dq[0])
    assert not Imperfections(encoder_counts=counts).random
    for k in range(100):
        assert np.array_equal(plain.measure(q[k], dq[k])[0], zero.measure(q[k], dq[k])[0])
    # a noise level scales the count and so the noise in radians; σ in counts stays
    big = Imperfections(encoder_counts=counts, encoder_noise=sigma).scaled(10.0)
    assert big.encoder_noise == sigma
    assert big.start(3, H, q[0], dq[0]).jitter == pytest.approx(10 * sigma * quantum)


def test_one_sample_delay_gives_the_previous_measurement():
    t, q, dq = _trajectory(N=50)
    r = Imperfections(measurement_delay=1).start(3, H, q[0], dq[0])
    got = [r.measure(q[k], dq[k]) for k in range(len(t))]
    assert np.array_equal(got[0][0], q[0])
    for k in range(1, len(t)):
        assert np.array_equal(got[k][0], q[k - 1]) and np.array_equal(got[k][1], dq[k - 1])


def test_torque_saturation_and_rate_limit_hold():
    rate, limit = 1000.0, np.array([87.0, 87.0, 12.0])
    r = Imperfections(tau_limit=limit, tau_rate_limit=rate).start(3, H, np.zeros(3),
                                                                   np.zeros(3))
    rng = np.random.default_rng(0)
    prev = np.zeros(3)
    out = []
    for k in range(3000):
        cmd = rng.uniform(-200, 200, 3) if k % 500 < 250 else np.array([100.0, -100.0, 50.0])
        tau = r.actuate(cmd)
        assert np.all(np.abs(tau - prev) <= rate * H * (1 + 1e-12))
        assert np.all(np.abs(tau) <= limit)
        prev = tau
        out.append(tau)
    out = np.array(out)
    # a held command is reached at the rate, then the limit holds it
    assert np.allclose(out[499], [87.0, -87.0, 12.0])
    # joint 0 goes from out[249] to 87 at exactly rate h per sample (1 N·m), then stays
    need = math.ceil((87.0 - out[249, 0]) / (rate * H))
    assert np.all(np.diff(out[249:249 + need, 0]) == pytest.approx(rate * H))
    assert out[249 + need, 0] == 87.0 and out[249 + need - 1, 0] < 87.0


def test_scaled_noise_level_and_realistic_defaults():
    s = REALISTIC.scaled(100.0)
    assert s.encoder_counts == pytest.approx(2.0 ** 18 / 100)
    assert s.velocity == "difference" and s.measurement_delay == 1
    assert Imperfections(velocity="noise", velocity_noise=1e-3).scaled(10).velocity_noise == \
        pytest.approx(1e-2)
    assert len(REALISTIC.active) == 3


@pytest.mark.parametrize("kw, word", [
    (dict(encoder_counts=0), "encoder_counts"), (dict(encoder_counts=float("nan")), "encoder"),
    (dict(velocity="kalman"), "velocity"), (dict(velocity_cutoff=-1), "velocity_cutoff"),
    (dict(velocity_noise=-0.1), "velocity_noise"), (dict(measurement_delay=2), "delay"),
    (dict(seed=1.5), "seed"), (dict(encoder_noise=-1.0), "encoder_noise"),
    (dict(encoder_noise=1.0), "needs encoder_counts")])
def test_bad_options_are_refused_by_name(kw, word):
    with pytest.raises(ValueError, match=word):
        Imperfections(**kw)


def test_bad_limits_are_refused_when_the_run_starts():
    with pytest.raises(ValueError, match="tau_limit"):
        Imperfections(tau_limit=[1.0, -2.0, 3.0]).start(3, H, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="tau_rate_limit"):
        Imperfections(tau_rate_limit=[1.0, 2.0]).start(3, H, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="noise level"):
        REALISTIC.scaled(0)


@pytest.mark.parametrize("kwargs, fragment", [
    (dict(encoder_counts=2 ** 18, encoder_noise=-0.5), "encoder_noise must be"),
    (dict(encoder_counts=2 ** 18, encoder_noise=math.nan), "encoder_noise must be"),
    (dict(encoder_noise=1.0), "it needs encoder_counts"),
])
def test_bad_encoder_noise_is_refused_naming_it(kwargs, fragment):
    """Encoder noise is σ in counts of the encoder: negative, NaN or without an encoder's
    counts is refused at construction, naming the option."""
    with pytest.raises(ValueError, match=fragment):
        Imperfections(**kwargs)
