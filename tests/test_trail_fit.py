"""The trail-fitting restorer: its model against the renderer, its fit against the Cramer-Rao bound, its output."""

import math

import gymnasium as gym
import numpy as np
import pytest

import starenv  # noqa: F401  (registers the environments)
from starenv.agents.base import step_input
from starenv.agents.detect import CentroidDetector
from starenv.agents.restore.trail_fit import TrailFitDeblurrer, fit_trail, trail_model
from starenv.scoring import match
from starenv.sim.render import StarTruth, still_image

SIGMA = 0.8


def rendered_trail(shape, centre, offsets, flux):
    """A trail drawn by the renderer's still-star code (tabulated bands, np.add.at): ``flux`` split equally over the
    samples ``centre + offsets``; independent of the model's erf evaluation."""
    return still_image(np.asarray(centre) + offsets, np.full(len(offsets), flux / len(offsets)), shape, SIGMA)


def line(length_px: float, angle_rad: float, m: int = 41) -> np.ndarray:
    t = (np.arange(m) + 0.5) / m - 0.5
    return length_px * t[:, None] * np.array([math.cos(angle_rad), math.sin(angle_rad)])


def test_model_is_the_renderers_trail_and_its_derivative_is_the_finite_difference():
    offsets = line(12.0, 0.4)
    centre = np.array([20.3, 17.8])
    xs, ys = np.arange(40.0), np.arange(36.0)
    t, tx, ty = trail_model(xs, ys, centre, offsets, SIGMA)
    np.testing.assert_allclose(t, rendered_trail((36, 40), centre, offsets, 1.0), atol=1e-7)
    assert t.sum() == pytest.approx(1.0, abs=1e-9)  # the whole trail is inside the box
    h = 1e-5
    for k, d in enumerate((tx, ty)):
        step = np.zeros(2)
        step[k] = h
        fd = (trail_model(xs, ys, centre + step, offsets, SIGMA)[0]
              - trail_model(xs, ys, centre - step, offsets, SIGMA)[0]) / (2 * h)
        np.testing.assert_allclose(d, fd, atol=1e-8)


def test_fit_is_unbiased_and_its_covariance_is_the_scatter():
    # 200 seeded frames of one 15 px trail (flux 3000 DN, white noise 5 DN, background 100 DN): the fitted mid-exposure
    # position scatters as the covariance the fit reports (J^T J)^-1 sigma^2, which for white Gaussian noise is the
    # Cramer-Rao bound: chi-square of the 2-D errors averages 2 (95 % band of the mean of 200: 2 +- 0.28).
    offsets = line(15.0, -0.7)
    truth = np.array([24.4, 23.1])
    clean = 100.0 + rendered_trail((48, 48), truth, offsets, 3000.0)
    rng = np.random.default_rng(7)
    xs = ys = np.arange(48.0)
    usable = np.ones((48, 48), dtype=bool)
    chi2, errors = [], []
    for _ in range(200):
        frame = clean + rng.normal(0.0, 5.0, clean.shape)
        c, flux, level, cov, ok = fit_trail(frame, xs, ys, truth + [0.8, -0.6], offsets, SIGMA, 5.0, usable)
        assert ok
        e = c - truth
        chi2.append(e @ np.linalg.solve(cov[:2, :2], e))
        errors.append(e)
    assert np.mean(chi2) == pytest.approx(2.0, abs=0.28)
    assert np.all(np.abs(np.mean(errors, axis=0)) < 3 * np.std(errors, axis=0) / math.sqrt(200))


def test_a_hot_pixel_on_the_trail_is_left_out():
    offsets = line(15.0, 0.0)
    truth = np.array([24.0, 20.3])
    frame = 100.0 + rendered_trail((40, 48), truth, offsets, 3000.0) + np.random.default_rng(1).normal(0, 5, (40, 48))
    xs, ys = np.arange(48.0), np.arange(40.0)
    usable = np.ones(frame.shape, dtype=bool)
    clean_fit = fit_trail(frame, xs, ys, truth, offsets, SIGMA, 5.0, usable)[0]
    frame[20, 29] += 2000.0  # a hot pixel 5 px along the trail from its centre
    c = fit_trail(frame, xs, ys, truth, offsets, SIGMA, 5.0, usable)[0]
    np.testing.assert_allclose(c, clean_fit, atol=0.01)
    kept = fit_trail(frame, xs, ys, truth, offsets, SIGMA, 5.0, usable, outlier_sigma=1e6)[0]
    assert np.hypot(*(kept - clean_fit)) > 0.1  # without the rejection it moves 0.2 px (measured)


def frames(rate_dps: float, axis, seed: int = 0, n: int = 3):
    env = gym.make("StarEnv/Paper000-v0", overrides={"motion.rate_dps": list(rate_dps * np.asarray(axis))})
    env.reset(seed=seed)
    base = env.unwrapped
    for _ in range(n):
        obs, _, _, _, info = env.step(None)
        truth = StarTruth(**{k: np.asarray(v) for k, v in info["truth"]["stars"][0].items()})
        yield base, step_input(obs, base.sensor_info), truth


def test_a_still_frame_comes_back_unchanged():
    for _, step, _ in frames(0.0, [1, 0, 0], n=1):
        image = step.images[0]
        agent = TrailFitDeblurrer()
        np.testing.assert_array_equal(agent.deblur(image, 0, step), image)
        assert agent.last_info["kept"] > 10  # every star was fitted: its trail and its still star are the same


def test_fast_frames_give_more_stars_and_smaller_errors_than_the_blurred_ones():
    # paper_000 at 60 deg/s about X (26 px trails), seed 0, frames 1-3, the scenario's detector, 3 px gate against
    # xy_mid.  Measured: blurred 40 stars matched, mean error 0.62 px; trail fit 66 stars, mean 0.51 px.
    detector = CentroidDetector()
    counts, errors = {"blurred": 0, "fitted": 0}, {"blurred": [], "fitted": []}
    for base, step, truth in frames(60.0, [1, 0, 0]):
        image = step.images[0]
        for name, img in (("blurred", image), ("fitted", TrailFitDeblurrer().deblur(image, 0, step))):
            _, _, d = match(detector.detect(img, base.cameras[0]).xy, truth.xy_mid)
            counts[name] += len(d)
            errors[name] += list(d)
    assert counts["fitted"] >= 1.5 * counts["blurred"]
    assert np.mean(errors["fitted"]) < 0.9 * np.mean(errors["blurred"])


def test_bad_options_name_the_field():
    with pytest.raises(ValueError, match="min_snr"):
        TrailFitDeblurrer(min_snr=-1.0)
    with pytest.raises(ValueError, match="threshold_sigma"):
        TrailFitDeblurrer(threshold_sigma=0.0)
