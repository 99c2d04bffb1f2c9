"""The paper 002 comparison's condition generator sets what it says: rate magnitude and axes, position noise of sigma
px, magnitude noise of sigma mag, boresights off the catalogue stars; and its scoring tells a right attitude from a
wrong one."""

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from starenv.agents.base import StarMeasurements

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("paper002_comparison", ROOT / "benchmarks" / "paper002_comparison.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)

SEED = 7


@pytest.mark.parametrize("mode", ["two", "three"])
def test_condition_rate_has_the_stated_magnitude_and_axes(mode):
    for index in range(20):
        for w in (0.0, 4.0, 12.0):
            rate = bench.condition_rate(mode, w, SEED, index)
            assert np.linalg.norm(rate) == pytest.approx(w, abs=1e-12)
            if mode == "two":
                assert rate[2] == 0.0
            else:  # the paper's test set 2: three equal components
                assert np.allclose(np.abs(rate), w / math.sqrt(3.0), atol=1e-12)
    with pytest.raises(ValueError):
        bench.condition_rate("one", 1.0, SEED, 0)


def test_rendered_trails_have_the_stated_rate():
    # A star near the boresight moves f * w * T px during the exposure (small angles: the pinhole's 1/cos^2 stretch
    # stays below 1 % within 6 % of the focal length of the axis); a rate mis-set by axis or unit misses by far more.
    spec = bench.condition_spec(SEED)
    for mode, w in (("two", 6.0), ("three", 12.0)):
        params, frame, step = bench.condition_frame(spec, mode, w, 0)
        truth = frame.heads[0].truth
        cam = step.cameras[0]
        in_plane = float(np.linalg.norm(params["rate_cam_dps"][:2]))
        centre = np.array([(cam.width - 1) / 2, (cam.height - 1) / 2])
        near = np.linalg.norm(truth.xy_mid - centre, axis=1) < 0.06 * cam.fx
        length = np.linalg.norm(truth.xy_end - truth.xy_start, axis=1)[near]
        assert near.sum() >= 1
        roll_reach = np.radians(abs(params["rate_cam_dps"][2])) * step.exposure_s * 0.06 * cam.fx  # roll adds <= this
        expected = cam.fx * np.radians(in_plane) * step.exposure_s
        assert np.all(np.abs(length - expected) <= 0.01 * expected + roll_reach + 0.05)


def _paired_truth(sigma_px: float, sigma_mag: float, index: int):
    quiet = bench.condition_frame(bench.condition_spec(SEED), "two", 0.0, index)[1].heads[0].truth
    noisy = bench.condition_frame(bench.condition_spec(SEED, sigma_px, sigma_mag), "two", 0.0, index)[1].heads[0].truth
    common, a, b = np.intersect1d(quiet.catalog_id, noisy.catalog_id, return_indices=True)
    keep = common >= 0
    return quiet, noisy, a[keep], b[keep]


def _variance_within(samples: np.ndarray, sigma: float):
    # n independent N(0, sigma^2) samples: n s^2 / sigma^2 ~ chi2(n); a two-sided 1e-4 test
    n = samples.size
    statistic = float(np.sum(samples**2)) / sigma**2
    assert chi2.ppf(5e-5, n) <= statistic <= chi2.ppf(1 - 5e-5, n), (statistic, n)


def test_position_noise_moves_each_star_by_sigma_px_per_axis():
    sigma = 3.0
    shifts = []
    for index in range(2):
        quiet, noisy, a, b = _paired_truth(sigma, 0.0, index)
        shifts.append(noisy.xy_mid[b] - quiet.xy_mid[a])
    shifts = np.concatenate(shifts).ravel()
    assert shifts.size >= 40
    _variance_within(shifts, sigma)


def test_magnitude_noise_adds_sigma_mag():
    sigma = 1.0
    quiet, noisy, a, b = _paired_truth(0.0, sigma, 0)
    assert np.array_equal(quiet.xy_mid[a], noisy.xy_mid[b])  # magnitude noise leaves the positions alone
    _variance_within(noisy.magnitude[b] - quiet.magnitude[a], sigma)


def test_boresights_are_uniform_over_the_sky_not_on_stars():
    # Uniform boresights: z = cos(colatitude) is uniform on [-1, 1] (mean 0, sd 1/sqrt(3)), and the distance to the
    # nearest navigation star is spread over its cell, not zero as for frames centred on a star.
    spec = bench.condition_spec(SEED)
    from starenv.datasets.samples import draw

    sc = spec.load_scenario()
    cam = sc.heads[0].camera
    axes = np.array([cam.inertial_to_camera(draw(spec, i)["attitude"]).inv().apply([0.0, 0.0, 1.0])
                     for i in range(300)])
    assert abs(axes[:, 2].mean()) <= 4.0 / math.sqrt(3.0 * 300)
    w = bench._pipeline()
    nearest = np.degrees(np.arccos(np.clip((axes @ w["nav_unit"].T).max(axis=1), -1.0, 1.0)))
    assert np.median(nearest) > 0.2


def test_score_tells_a_right_attitude_from_a_wrong_one():
    w = bench._pipeline()
    cam, catalog = w["camera"], w["catalog"]
    params, frame, _ = bench.condition_frame(bench.condition_spec(SEED), "two", 0.0, 1)
    truth = frame.heads[0].truth
    keep = truth.detectable & (truth.catalog_id >= 0)
    right = StarMeasurements(xy=truth.xy_mid[keep], catalog_id=truth.catalog_id[keep])
    assert keep.sum() >= 3
    args = (cam, catalog, w["nav_unit"], w["nav_hip"], params["attitude"], truth)
    assert bench.score(right, *args) == {"main": True, "wrong_main": False, "wrong_label": False, "solved": True}
    # the same labels read under a 180 deg roll about the boresight: every detection far from its star's trail;
    # the boresight, and so the paper's main star, stays where it was
    centre = np.array([(cam.width - 1) / 2, (cam.height - 1) / 2])
    flipped = StarMeasurements(xy=2 * centre - truth.xy_mid[keep], catalog_id=truth.catalog_id[keep])
    assert bench.score(flipped, *args) == {"main": True, "wrong_main": False, "wrong_label": True, "solved": False}
    # the labels moved across the frame: the solved boresight lands a field away, on another navigation star
    moved = StarMeasurements(xy=truth.xy_mid[keep] + [cam.width, 0.0], catalog_id=truth.catalog_id[keep])
    assert bench.score(moved, *args) == {"main": False, "wrong_main": True, "wrong_label": True, "solved": False}
    # nothing labelled: neither identified nor wrong
    none = StarMeasurements(xy=truth.xy_mid[keep], catalog_id=np.full(keep.sum(), -1))
    assert bench.score(none, *args) == {"main": False, "wrong_main": False, "wrong_label": False, "solved": False}


def test_identified_counts_labelled_frames_without_a_wrong_label():
    # frames: right attitude and labels; a wrong label under the right main star; a wrong attitude; nothing labelled
    flags = {"main": "1100", "wrong_main": "0010", "wrong_label": "0110", "solved": "1000"}
    assert bench.identified(flags) == {"identified": 1, "wrong": 2, "wrong_attitude": 1}
