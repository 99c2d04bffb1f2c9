"""The datasheet estimators (starenv.datasheet) on synthetic error series whose split is known by construction."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import binomtest

from starenv.datasheet import acquisition_times, binomial_interval, bootstrap_interval, error_split


def synthetic(n, bias, sigma, amplitude, period, seed):
    """bias + white noise (deviation sigma) + a slow sine (amplitude, period in frames: whole periods over n)."""
    k = np.arange(n)
    return bias + np.random.default_rng(seed).normal(0.0, sigma, n) + amplitude * np.sin(2 * np.pi * k / period)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_split_recovers_bias_noise_and_drift(seed):
    n, bias, sigma, amplitude, period = 4000, 2.0, 0.5, 1.5, 1000
    split = error_split(synthetic(n, bias, sigma, amplitude, period, seed))
    # bias: the sine averages to 0 over whole periods; the mean of n white samples has standard error sigma/sqrt(n)
    assert abs(split["bias"] - bias) < 5 * sigma / np.sqrt(n)
    # NEA: first differences of white noise are MA(1) with lag-1 correlation -1/2, so the sample deviation's
    # standard error is sigma * sqrt((1 + 2 * 0.25) / (2 n)); the sine's differences add (2 pi A / P)^2 / 4 to the
    # variance, under 1e-3 of sigma^2 here.  A missing 1/sqrt(2) would give sigma sqrt(2), the plain deviation
    # sqrt(sigma^2 + A^2 / 2).
    assert abs(split["nea"] - sigma) < 5 * sigma * np.sqrt(1.5 / (2 * n))
    # low frequency: the sine's deviation A/sqrt(2); its error is the NEA's scaled by sigma / (A/sqrt(2))
    assert split["low_frequency"] == pytest.approx(amplitude / np.sqrt(2), abs=0.03)
    total = np.sqrt(bias**2 + sigma**2 + amplitude**2 / 2)
    assert split["total_1s"] == pytest.approx(total, rel=0.02)
    assert split["total_3s"] == pytest.approx(3 * split["total_1s"], rel=1e-12)


def test_white_noise_alone_has_no_low_frequency_part():
    split = error_split(synthetic(20000, 0.0, 1.0, 0.0, 1000, 3))
    # var(e) - NEA^2 is the difference of two estimates of sigma^2 = 1, each with standard error ~ sqrt(2/n): the
    # low-frequency part is the square root of what is left, under sqrt(5 standard errors)
    assert split["low_frequency"] < np.sqrt(5 * np.sqrt(2 / 20000))


def test_signs_survive_and_missing_steps_are_left_out():
    e = np.array([-3.0, np.nan, -3.0, -3.0, np.nan])
    split = error_split(e)
    assert split["bias"] == -3.0 and split["nea"] == 0.0 and split["total_1s"] == 3.0
    assert np.isnan(error_split([np.nan])["bias"]) and np.isnan(error_split([1.0])["nea"])
    assert np.isnan(error_split([])["bias"])


@given(st.integers(1, 80).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n))))
@settings(max_examples=60, deadline=None)
def test_binomial_interval_is_clopper_pearson(k_n):
    k, n = k_n
    low, high = binomial_interval(k, n)
    ref = binomtest(k, n).proportion_ci(0.95, method="exact")
    assert low == pytest.approx(ref.low, abs=1e-9) and high == pytest.approx(ref.high, abs=1e-9)
    assert low <= k / n <= high


def test_bootstrap_interval_width_follows_the_spread_between_runs():
    rng = np.random.default_rng(4)
    runs_count, tau = 40, 2.0
    runs = [rng.normal(m, 0.1, 50) for m in rng.normal(0.0, tau, runs_count)]
    low, high = bootstrap_interval(runs, lambda r: np.concatenate(r).mean())
    # the mean of R run means varies by tau / sqrt(R): a 95 % interval spans about 2 * 1.96 of that
    expected = 2 * 1.96 * tau / np.sqrt(runs_count)
    assert 0.6 * expected < high - low < 1.4 * expected
    assert low < np.mean(np.concatenate(runs)) < high
    same = [np.full(10, 1.5)] * 5
    assert bootstrap_interval(same, lambda r: np.concatenate(r).mean()) == (1.5, 1.5)
    assert all(np.isnan(bootstrap_interval(runs[:1], lambda r: np.concatenate(r).mean())))


def test_differences_are_taken_within_runs():
    """Two still runs with different biases: pooled, their NEA is 0 (no frame-to-frame change inside a run), while
    differences across the boundary would report the bias step as noise."""
    split = error_split([np.full(50, 1.0), np.full(50, 5.0)])
    assert split["nea"] == 0.0 and split["bias"] == 3.0
    assert split["low_frequency"] == pytest.approx(np.std(np.r_[np.full(50, 1.0), np.full(50, 5.0)], ddof=1))


def test_acquisition_and_reacquisition_times():
    t = np.arange(10) * 0.5
    fixed = [0, 0, 1, 1, 0, 0, 0, 1, 0, 1]
    assert acquisition_times(fixed, t) == {"first": [1.0], "reacquisition": [1.5, 0.5]}
    assert acquisition_times([0, 0, 0], t[:3]) == {"first": [], "reacquisition": []}
    assert acquisition_times([1, 1], t[:2]) == {"first": [0.0], "reacquisition": []}
