"""Tests of the gyro model (starenv.sim.gyro): Allan signatures of each error term, exact interval averaging, state
carried across calls and argument checks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from starenv.sim.conventions import ARCSEC, DEG
from starenv.sim.gyro import (
    GM_PEAK_TAU_PER_T,
    IEEE_FLICKER_FLOOR,
    Gyro,
    GyroSpec,
    allan_deviation,
    gauss_markov_allan_variance,
)

NOISE_FREE = {"arw_deg_rthr": 0.0, "rrw_deg_hr_rthr": 0.0, "bias_instability_deg_hr": 0.0}


def zero_rate(t):
    """Body at rest: (n, 3) rad/s of zeros."""
    return np.zeros((np.size(t), 3))


def constant_rate(w):
    """Callable returning the constant body rate ``w`` (3,) rad/s at every time."""
    return lambda t: np.broadcast_to(w, (np.size(t), 3))


SINE_AMPLITUDE = np.array([0.2, -0.1, 0.05])  # rad/s
SINE_OMEGA = np.array([0.7, 3.0, 12.0])  # rad/s
SINE_PHASE = np.array([0.3, -1.0, 2.0])  # rad


def sine_rate(t):
    """Body rate a sin(omega t + phase) per axis, (n, 3) rad/s."""
    return SINE_AMPLITUDE * np.sin(SINE_OMEGA * np.asarray(t)[:, None] + SINE_PHASE)


def sine_interval_mean(t, dt):
    """Exact mean of :func:`sine_rate` over (t - dt, t]: a sin(omega (t - dt/2) + phase) sin(h) / h, h = omega dt/2."""
    half_angle = SINE_OMEGA * dt / 2
    centre_phase = SINE_OMEGA * (t[:, None] - dt / 2) + SINE_PHASE
    return SINE_AMPLITUDE * np.sin(centre_phase) * np.sin(half_angle) / half_angle


def test_arw_and_rrw_recovered_from_allan_deviation():
    # N = 0.02 deg/sqrt(h) and K = 100 deg/h/sqrt(h) cross at tau_c = sqrt(3) N / K = 1.25 s: at 100 Hz the -1/2 slope
    # (ARW) rules tau in [0.01, 0.1] s with millions of clusters, and a 4 h record leaves the +1/2 slope (RRW) two and
    # a half decades, [10, 720] s = L/20, before clusters get too few.  sigma^2 = N^2/tau + K^2 tau/3 is fitted to
    # relative residuals weighted by sqrt(L / tau), the inverse of each point's expected relative scatter.
    spec = GyroSpec(rate_hz=100.0, arw_deg_rthr=0.02, rrw_deg_hr_rthr=100.0, bias_instability_deg_hr=0.0)
    duration_s = 4 * 3600.0
    samples = Gyro(spec, np.random.default_rng(20240611)).sample_until(zero_rate, duration_s)
    taus = np.unique(np.rint(np.logspace(-2, np.log10(duration_s / 20), 30) * spec.rate_hz)) / spec.rate_hz
    avar = allan_deviation(samples.rate, spec.sample_interval_s, taus) ** 2
    weight = np.sqrt(duration_s / taus)
    arw_si = spec.arw_deg_rthr * DEG / 60.0
    rrw_si = spec.rrw_deg_hr_rthr * DEG / 3600.0 / 60.0
    for axis in range(3):
        design = np.stack([1.0 / taus, taus / 3.0], axis=1) / avar[:, axis, None] * weight[:, None]
        (n_squared, k_squared), *_ = np.linalg.lstsq(design, weight, rcond=None)
        assert np.sqrt(n_squared) == pytest.approx(arw_si, rel=0.10), f"ARW axis {axis}"
        assert np.sqrt(k_squared) == pytest.approx(rrw_si, rel=0.10), f"RRW axis {axis}"


def test_allan_deviation_of_white_noise_and_ramps():
    rng = np.random.default_rng(5)
    sigma, dt, n = 2.0, 0.01, 400_000
    white = sigma * rng.standard_normal((n, 3))
    cluster_sizes = np.array([1, 10, 100])
    adev = allan_deviation(white, dt, cluster_sizes * dt)
    assert adev.shape == (3, 3)
    np.testing.assert_allclose(adev, (sigma / np.sqrt(cluster_sizes))[:, None] * np.ones(3), rtol=0.03)
    assert allan_deviation(white[:, 0], dt, cluster_sizes * dt).shape == (3,)

    t = np.arange(10_000) * dt
    taus = np.array([0.01, 0.5, 20.0])
    assert np.all(allan_deviation(np.full_like(t, 0.37), dt, taus) < 1e-12)  # constant rate: the angle is a ramp
    ramp = 1e-3  # rad/s^2: a rate ramp R has the closed form R tau / sqrt(2)
    np.testing.assert_allclose(allan_deviation(ramp * t, dt, taus), ramp * taus / np.sqrt(2), rtol=1e-9)


@pytest.mark.parametrize("tau", [0.1, 1.0, 3.785, 10.0, 100.0])
def test_gauss_markov_allan_variance_matches_autocorrelation_integral(tau):
    # AVAR = Var(mean over tau) - Cov(adjacent means), each an integral of R(u) = sigma^2 exp(-u/T).
    sigma, correlation_s = 0.3, 2.0

    def autocorrelation(u):
        return sigma**2 * np.exp(-u / correlation_s)

    variance = 2.0 / tau**2 * quad(lambda u: (tau - u) * autocorrelation(u), 0.0, tau, epsabs=0)[0]
    covariance = quad(lambda u: (tau - abs(u - tau)) * autocorrelation(u), 0.0, 2 * tau, points=[tau],
                      epsabs=0)[0] / tau**2
    assert gauss_markov_allan_variance(tau, sigma, correlation_s) == pytest.approx(variance - covariance, rel=1e-9)


def test_bias_instability_peak_is_0664_b():
    spec = GyroSpec(rate_hz=100.0, arw_deg_rthr=0.0, rrw_deg_hr_rthr=0.0, bias_instability_deg_hr=1.0,
                    bias_correlation_s=1.0)
    samples = Gyro(spec, np.random.default_rng(3)).sample_until(zero_rate, 10_000.0)
    taus = np.geomspace(0.2, 20.0, 25) * spec.bias_correlation_s
    adev_deg_hr = allan_deviation(samples.rate, spec.sample_interval_s, taus) / (DEG / 3600.0)
    plateau = adev_deg_hr.max(axis=0)
    np.testing.assert_allclose(plateau, IEEE_FLICKER_FLOOR * spec.bias_instability_deg_hr, rtol=0.15)
    peak_taus = taus[adev_deg_hr.argmax(axis=0)]
    peak_tau_expected = GM_PEAK_TAU_PER_T * spec.bias_correlation_s  # 1.89 T
    assert np.all((peak_taus > peak_tau_expected / 2) & (peak_taus < peak_tau_expected * 2))


def test_quantization_is_unbiased_and_in_whole_quanta():
    spec = GyroSpec(rate_hz=100.0, quantization_arcsec=1.0, **NOISE_FREE)
    quantum_per_sample = spec.quantization_arcsec * ARCSEC * spec.rate_hz  # rad/s of one LSB per sample
    true_rate = np.array([0.3737, -2.71828, 17.0123456]) * quantum_per_sample
    samples = Gyro(spec, np.random.default_rng(0)).sample_until(constant_rate(true_rate), 100.0)
    quanta = samples.rate / quantum_per_sample
    np.testing.assert_allclose(quanta, np.rint(quanta), rtol=0, atol=1e-9)
    mean_error_quanta = np.abs(samples.rate.mean(axis=0) - true_rate) / quantum_per_sample
    assert np.all(mean_error_quanta < 1e-3)


def test_quantization_allan_signature():
    # Angle noise of half a quantum per sample randomises the carried remainder, which then adds q^2 / (4 tau^2) to
    # the ARW's N^2 / tau (IEEE Std 952: 3 Q^2 / tau^2 with Q = q / sqrt(12)).
    quantum_arcsec = 10.0
    spec = GyroSpec(rate_hz=100.0, arw_deg_rthr=quantum_arcsec / 2 / 3600.0 * 60.0 / np.sqrt(0.01),
                    rrw_deg_hr_rthr=0.0, bias_instability_deg_hr=0.0, quantization_arcsec=quantum_arcsec)
    samples = Gyro(spec, np.random.default_rng(11)).sample_until(zero_rate, 3000.0)
    taus = np.array([1, 2, 4]) * spec.sample_interval_s
    avar = allan_deviation(samples.rate, spec.sample_interval_s, taus) ** 2
    arw_si = spec.arw_deg_rthr * DEG / 60.0
    quantum_estimate = 2.0 * taus[:, None] * np.sqrt(avar - arw_si**2 / taus[:, None])
    np.testing.assert_allclose(quantum_estimate / ARCSEC, quantum_arcsec, rtol=0.10)


def test_noise_free_output_is_misaligned_scaled_biased_interval_mean():
    spec = GyroSpec(rate_hz=250.0, time_offset_s=0.0013, bias_deg_hr=(30.0, -12.0, 5.0),
                    scale_factor_ppm=(300.0, -150.0, 80.0),
                    misalignment_mrad=[[0.0, 0.3, -0.2], [0.1, 0.0, 0.4], [-0.5, 0.2, 0.0]], **NOISE_FREE)
    sensor_matrix = np.eye(3) + np.diag(np.array(spec.scale_factor_ppm) * 1e-6) + np.array(spec.misalignment_mrad) / 1e3
    bias = np.array(spec.bias_deg_hr) * DEG / 3600.0

    w = np.array([0.1, -0.05, 0.02])
    constant = Gyro(spec, np.random.default_rng(0)).sample_until(constant_rate(w), 2.0)
    assert constant.rate.shape == (499, 3)  # the 500th sample falls at 2.0013 s
    np.testing.assert_allclose(constant.rate, np.broadcast_to(sensor_matrix @ w + bias, (499, 3)), rtol=0, atol=1e-16)

    sine = Gyro(spec, np.random.default_rng(0)).sample_until(sine_rate, 20.0)
    expected = sine_interval_mean(sine.t, spec.sample_interval_s) @ sensor_matrix.T + bias
    np.testing.assert_allclose(sine.rate, expected, rtol=0, atol=1e-12)


FULL_SPEC = GyroSpec(rate_hz=200.0, arw_deg_rthr=0.05, rrw_deg_hr_rthr=2.0, bias_instability_deg_hr=0.5,
                     bias_correlation_s=20.0, bias_deg_hr=(1.0, 2.0, -3.0), scale_factor_ppm=(100.0, 0.0, -50.0),
                     misalignment_mrad=[[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.5, 0.0, 0.0]], quantization_arcsec=0.1)


def test_chunked_sampling_equals_one_shot_bit_for_bit():
    duration_s = 400.0  # 80 000 samples: crosses the internal block boundary
    one_shot = Gyro(FULL_SPEC, np.random.default_rng(7)).sample_until(sine_rate, duration_s)
    chunked_gyro = Gyro(FULL_SPEC, np.random.default_rng(7))
    chunks = [chunked_gyro.sample_until(sine_rate, t_end) for t_end in [0.0, 0.003, 0.005, 1.2345, 1.2345, 37.0,
                                                                       333.3, duration_s]]
    assert np.array_equal(np.concatenate([c.t for c in chunks]), one_shot.t)
    assert np.array_equal(np.concatenate([c.rate for c in chunks]), one_shot.rate)

    again = Gyro(FULL_SPEC, np.random.default_rng(7)).sample_until(sine_rate, duration_s)
    assert np.array_equal(again.rate, one_shot.rate)
    other_seed = Gyro(FULL_SPEC, np.random.default_rng(8)).sample_until(sine_rate, duration_s)
    assert not np.array_equal(other_seed.rate, one_shot.rate)


def test_timestamps_on_grid_and_inside_requested_window():
    spec = GyroSpec(rate_hz=300.0, time_offset_s=0.002)
    gyro = Gyro(spec, np.random.default_rng(1))
    delivered = 0
    previous_end = 0.0
    for t_end in [0.001, 0.002, 1 / 300 + 0.002, 0.5, 0.5, 0.49, 1.0, 7.77]:
        samples = gyro.sample_until(zero_rate, t_end)
        n = samples.t.size
        assert samples.rate.shape == (n, 3)
        np.testing.assert_array_equal(samples.t, np.arange(delivered + 1, delivered + n + 1) / 300.0 + 0.002)
        assert np.all(samples.t <= t_end) and np.all(samples.t > previous_end)
        assert (delivered + n + 1) / 300.0 + 0.002 > t_end  # nothing left behind
        delivered += n
        previous_end = max(previous_end, t_end)
        assert gyro.last_time_s == delivered / 300.0 + 0.002
    assert delivered == 2330


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("rate_hz", 50.0),
        ("rate_hz", 5000.0),
        ("arw_deg_rthr", float("nan")),
        ("arw_deg_rthr", -0.01),
        ("bias_deg_hr", (1.0, 2.0)),
        ("scale_factor_ppm", (0.0, np.inf, 0.0)),
        ("misalignment_mrad", np.eye(3)),
        ("bias_correlation_s", 0.0),
        ("time_offset_s", 1 / 200.0),
        ("quantization_arcsec", -1.0),
    ],
)
def test_bad_spec_raises_naming_field(field, value):
    with pytest.raises(ValueError, match=field):
        GyroSpec(**{field: value})


def test_bad_call_arguments_raise():
    gyro = Gyro(GyroSpec(), np.random.default_rng(0))
    with pytest.raises(ValueError, match="t_end"):
        gyro.sample_until(zero_rate, float("nan"))
    with pytest.raises(ValueError, match="body_rate"):
        gyro.sample_until(lambda t: np.zeros((np.size(t), 2)), 1.0)
    with pytest.raises(ValueError, match="taus"):
        allan_deviation(np.zeros(100), 0.01, np.array([0.6]))


def test_the_bias_truth_is_what_the_samples_carry():
    """A static gyro with only a constant bias and a rate random walk (no ARW, scale factor or quantization) reads
    exactly its bias: the truth after a record is the record's last sample."""
    spec = GyroSpec(rate_hz=200.0, arw_deg_rthr=0.0, rrw_deg_hr_rthr=5.0, bias_instability_deg_hr=0.0,
                    bias_deg_hr=(10.0, -20.0, 30.0))
    gyro = Gyro(spec, np.random.default_rng(4))
    np.testing.assert_allclose(gyro.bias_rad_s, np.radians([10.0, -20.0, 30.0]) / 3600.0, rtol=1e-12)
    record = gyro.sample_until(lambda t: np.zeros((len(t), 3)), 1.0)
    np.testing.assert_array_equal(gyro.bias_rad_s, record.rate[-1])
    assert not np.allclose(record.rate[0], record.rate[-1])  # the walk moved it
