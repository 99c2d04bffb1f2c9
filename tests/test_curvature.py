"""Paper 001's gated curvature filter and its centroid-stopped Richardson-Lucy deblurrer."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage

from starenv.agents.base import StepInput
from starenv.agents.restore.algorithms import (
    curvature_energy,
    curvature_filter,
    gating_energy,
    nearest_plane_step,
    plane_distances,
    resharpen,
    richardson_lucy,
    richardson_lucy_batch,
)
from starenv.agents.restore.curvature import CentroidStop, CurvatureRLDeblurrer, patch_centroids, window_centroids
from starenv.agents.restore.kernels import path_kernel, star_paths
from starenv.sim.gyro import GyroSamples
from starenv.sim.optics import Camera

images = arrays(np.float64, st.tuples(st.integers(3, 14), st.integers(3, 14)),
                elements=st.floats(0.0, 4000.0, allow_nan=False, allow_infinity=False))


def star_field(rng, shape=(96, 112), n=12, sigma=1.3, level=100.0):
    """Noise-free Gaussian stars on a flat sky (grey levels) and their exact centres."""
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    img = np.full(shape, level)
    centres = rng.uniform(8, np.array(shape[::-1]) - 8, (n, 2))
    for (x0, y0), amp in zip(centres, rng.uniform(80.0, 600.0, n), strict=True):
        img += amp * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * sigma**2))
    return img, centres


def test_plane_distances_match_eq17_written_out():
    f = np.arange(25.0).reshape(5, 5) ** 1.5  # no symmetry to hide a swapped offset
    d = plane_distances(f)
    y, x = 2, 2
    v = lambda dy, dx: f[y + dy, x + dx]  # noqa: E731  f(x + dx, y + dy) in the paper's notation
    eq17 = [
        (v(0, -1) + v(0, 1) + v(1, 0)) / 3,
        (v(-1, 0) + v(-1, 1) + v(0, 1)) / 3,
        (v(-1, -1) + v(0, -1) + v(-1, 0)) / 3,
        (v(1, 0) + v(0, 1) + v(1, 1)) / 3,
        (v(-1, 0) + v(1, 0) + v(0, 1)) / 3,
        (v(0, -1) + v(1, 0) + v(1, -1)) / 3,
        (v(-1, 0) + v(1, 0) + v(0, -1)) / 3,
        (v(0, -1) + v(-1, 0) + v(0, 1)) / 3,
    ]
    np.testing.assert_allclose(d[:, y, x], np.array(eq17) - f[y, x], rtol=1e-12)
    m = nearest_plane_step(f)[y, x]
    assert abs(m) == pytest.approx(min(abs(e - f[y, x]) for e in eq17), rel=1e-12)
    # Eq. 19-23 with alpha = 1: |d_m| + the 4 smallest |f - f_nb| of the 8 neighbours.
    nb = np.sort([abs(f[y, x] - f[y + a, x + b]) for a in (-1, 0, 1) for b in (-1, 0, 1) if (a, b) != (0, 0)])
    assert gating_energy(f)[y, x] == pytest.approx(abs(m) + nb[:4].sum(), rel=1e-12)


@settings(max_examples=150, deadline=None)
@given(images, st.one_of(st.just(0.0), st.floats(0.0, 3000.0)), st.floats(1.0, 2.0))
def test_curvature_energy_never_increases(f, threshold, alpha):
    energies = [curvature_energy(f)]
    for _ in range(3):
        f = curvature_filter(f, threshold, iterations=1, alpha=alpha)
        energies.append(curvature_energy(f))
    assert np.all(np.diff(energies) <= 1e-9 * max(energies[0], 1.0))


def test_gate_keeps_the_energy_falling_where_plain_projection_raises_it():
    """Why the acceptance matters: moving every pixel onto its nearest plane at once, pass after pass (Eq. 18
    alone), raises sum |d_m| on a bright star over noise; the filter's gated passes never do."""
    yy, xx = np.mgrid[:16, :16]
    raised = 0
    for seed in range(10):
        start = np.random.default_rng(seed).normal(100.0, 10.0, (16, 16))
        start += 3000.0 * np.exp(-((xx - 8.3) ** 2 + (yy - 6.6) ** 2) / 4.0)
        plain, ours = start, start
        plain_e, ours_e = [curvature_energy(start)], [curvature_energy(start)]
        for _ in range(6):
            plain = plain + nearest_plane_step(plain)
            ours = curvature_filter(ours, threshold=0.0, iterations=1)
            plain_e.append(curvature_energy(plain))
            ours_e.append(curvature_energy(ours))
        raised += np.any(np.diff(plain_e) > 1e-9)
        assert np.all(np.diff(ours_e) <= 1e-9 * ours_e[0])
    assert raised >= 3


@settings(max_examples=40, deadline=None)
@given(st.floats(-1e4, 1e4), st.integers(3, 20), st.integers(3, 20), st.floats(0.0, 100.0), st.floats(1.0, 2.0))
def test_flat_images_are_fixed_points(value, h, w, threshold, alpha):
    f = np.full((h, w), value)
    np.testing.assert_array_equal(curvature_filter(f, threshold, iterations=3, alpha=alpha), f)


def test_threshold_above_every_energy_leaves_the_image_alone():
    f = np.random.default_rng(0).normal(100.0, 8.0, (30, 40))
    np.testing.assert_array_equal(curvature_filter(f, threshold=gating_energy(f).max() + 1.0), f)


def test_denoising_a_star_field_raises_psnr():
    rng = np.random.default_rng(11)
    clean, _ = star_field(rng)
    noisy = clean + rng.normal(0.0, np.sqrt(50.0), clean.shape)  # the paper's variance 50
    out = curvature_filter(noisy)  # T = 3 sigma of the noise (the default)
    var_in, var_out = np.var(noisy - clean), np.var(out - clean)
    psnr = lambda img: 10 * np.log10(clean.max() ** 2 / np.mean((img - clean) ** 2))  # noqa: E731
    assert var_out < 0.9 * var_in
    assert psnr(out) > psnr(noisy) + 0.4
    # Every pixel gated on (T = 0): stronger smoothing, still closer to the truth than the noisy frame.
    assert np.var(curvature_filter(noisy, threshold=0.0) - clean) < 0.5 * var_in


def test_bad_input_names_the_field():
    with pytest.raises(ValueError, match="image"):
        curvature_filter(np.zeros(5))
    with pytest.raises(ValueError, match="alpha"):
        curvature_filter(np.zeros((5, 5)), alpha=3.0)
    with pytest.raises(ValueError, match="threshold"):
        curvature_filter(np.zeros((5, 5)), threshold=-1.0)
    with pytest.raises(ValueError, match="eps_px"):
        CentroidStop(np.zeros((1, 4)), [-1.0, 0.0], 10)
    with pytest.raises(ValueError, match="psf_sigma_px"):
        CurvatureRLDeblurrer(psf_sigma_px=-1.0)


def reference_stop(estimates, boxes, eps, floor):
    """Eq. 25 written independently: centroids by scipy, the first iterate k + 1 (1-based) that satisfies it."""
    cents = []
    for k, est in enumerate(estimates, start=1):
        c = []
        for x0, y0, x1, y1 in boxes:
            patch = est[y0:y1, x0:x1]
            cy, cx = ndimage.center_of_mass(np.clip(patch - floor * patch.max(), 0.0, None))
            c.append((x0 + cx, y0 + cy))
        cents.append(np.array(c))
        if k >= 3:
            step_now, step_before = np.abs(cents[-1] - cents[-2]), np.abs(cents[-2] - cents[-3])
            if np.all(np.abs(step_now - step_before) <= eps):
                return k
    return None


def test_stop_rule_fires_at_the_first_iterate_satisfying_eq25():
    # A spot settling geometrically on its final place, as RL iterates do: step sizes 1.5 * 0.6^k px.
    yy, xx = np.mgrid[:40, :40]
    estimates = []
    for k in range(1, 30):
        x = 20.0 + 1.5 * 0.6**k
        y = 18.0 - 0.8 * 0.6**k
        estimates.append(500.0 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 2.0))
    boxes = np.array([[12, 10, 29, 27]])
    eps = np.array([0.01, 0.01])
    expected = reference_stop(estimates, boxes, eps, 0.2)
    stop = CentroidStop(boxes, eps, max_iterations=100, floor_fraction=0.2)
    fired = next(k for k, est in enumerate(estimates, start=1) if stop(k, est))
    assert fired == expected == stop.iterations and stop.converged
    assert 4 < fired < 20  # neither immediately nor never: the test discriminates


def test_stop_rule_inside_richardson_lucy_matches_an_independent_loop():
    rng = np.random.default_rng(5)
    sharp, _ = star_field(rng, shape=(80, 90), n=6, level=0.0)
    kernel = np.zeros((1, 15))
    kernel[0] = 1.0 / 15  # a 15 px horizontal trail
    blurred = ndimage.convolve(sharp, kernel, mode="constant") + 20.0
    noisy = np.clip(blurred + rng.normal(0.0, 2.0, blurred.shape), 0.0, None)
    boxes = np.array([[0, 0, 45, 40], [45, 40, 90, 80]])
    eps = np.array([0.02, 0.02])
    stop = CentroidStop(boxes, eps, max_iterations=200, floor_fraction=0.2)
    restored = richardson_lucy(noisy, kernel, 200, background=20.0, callback=stop)
    every = []
    richardson_lucy(noisy, kernel, 60, background=20.0, callback=lambda k, f: every.append(f.copy()) and False)
    expected = reference_stop(every, boxes, eps, 0.2)
    assert expected is not None and stop.iterations == expected and stop.converged
    np.testing.assert_array_equal(restored, every[expected - 1])


def test_window_centroids_of_a_symmetric_spot_and_an_empty_window():
    img = np.zeros((20, 20))
    img[9:12, 4:7] = [[1, 2, 1], [2, 4, 2], [1, 2, 1]]
    c = window_centroids(img, np.array([[0, 0, 10, 20], [10, 0, 20, 20]]))
    np.testing.assert_allclose(c[0], [5.0, 10.0])
    assert np.all(np.isnan(c[1]))


def test_deblurrer_restores_a_smeared_star_to_its_mid_exposure_position():
    camera = Camera.from_focal_length(0.06, 7.86e-6, 160, 120)
    rate = np.radians([2.0, 2.0, 0.0])  # 16 px trail in each axis over 60 ms
    exposure, t_mid = 0.06, 1.0
    ts = np.arange(0.9, 1.04, 0.005)
    gyro = GyroSamples(ts, np.tile(rate, (len(ts), 1)), 0.005)
    stars = np.array([[60.3, 50.6], [110.7, 80.2]])
    paths = star_paths(camera, gyro, t_mid - exposure / 2, t_mid + exposure / 2, stars)
    img = np.full((120, 160), 100.0)
    for xy, path, flux in zip(stars, paths, (6000.0, 3000.0), strict=True):
        pixel = np.round(xy)
        k, origin = path_kernel(path, 1.0, xy_mid=pixel)  # the trail drawn about the star's pixel, sub-pixel kept
        x0, y0 = (pixel - origin).astype(int)
        img[y0 : y0 + k.shape[0], x0 : x0 + k.shape[1]] += flux * k
    rng = np.random.default_rng(2)
    noisy = np.clip(np.round(img + rng.normal(0.0, 5.0, img.shape)), 0, 4095).astype(np.uint16)
    step = StepInput([noisy], np.ones(1, bool), t_mid, exposure, gyro, [camera])
    agent = CurvatureRLDeblurrer(max_iterations=60)
    estimate, kernel = agent.restore(noisy, 0, step)  # the paper's restored image, DN above the background
    info = agent.last_info
    assert estimate.shape == noisy.shape and estimate.dtype == np.float64
    assert info["stars_watched"] == 2 and info["converged"] and 3 <= info["iterations"] < 60
    boxes = np.column_stack([np.round(stars) - 5, np.round(stars) + 6]).astype(int)
    err = window_centroids(estimate, boxes, 0.2) - stars
    assert np.all(np.abs(err) < 0.15)  # the blurred trail spans 16 px per axis
    # deblur() is resharpen() of that estimate: the raw frame, each trail replaced by its still star.
    out = agent.deblur(noisy, 0, step)
    assert agent.last_info["iterations"] == info["iterations"]
    np.testing.assert_allclose(out, resharpen(noisy.astype(np.float64), estimate, kernel, camera.psf_sigma_px))


def test_a_stack_is_filtered_image_by_image_and_batched_rl_stops_on_its_callback():
    rng = np.random.default_rng(4)
    stack = rng.normal(100.0, 10.0, (4, 23, 31))
    stack[:, 11, 15] += 400.0
    np.testing.assert_array_equal(curvature_filter(stack, 20.0), np.stack([curvature_filter(x, 20.0) for x in stack]))
    # patch_centroids: each image one window, as window_centroids over the whole image.
    boxes = np.array([[0, 0, 31, 23]])
    np.testing.assert_allclose(patch_centroids(stack, 0.2), [window_centroids(x, boxes, 0.2)[0] for x in stack])
    psfs = np.tile(np.full((1, 5), 0.2), (4, 1, 1))
    seen = []
    out = richardson_lucy_batch(np.maximum(stack, 0), psfs, 50, background=90.0, initial=np.maximum(stack - 90.0, 1.0),
                                callback=lambda k, f: seen.append(k) or k == 7)
    assert seen == list(range(1, 8)) and out.shape == stack.shape
    with pytest.raises(ValueError, match="initial must be a positive array"):
        richardson_lucy_batch(np.maximum(stack, 0), psfs, 5, initial=np.zeros(stack.shape))
