"""Blur kernels against the renderer's truth (same motion, independent code path) and against closed forms."""

import math

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import starenv  # noqa: F401  (registers the environments)
from starenv.agents.restore.kernels import (
    ExposureMotion,
    boresight_blur,
    cross_boresight_blur,
    gyro_rotation,
    path_kernel,
    path_kernels,
    star_paths,
)
from starenv.sim.gyro import GyroSamples

NOISE_FREE_GYRO = {"gyro.arw_deg_rthr": 0.0, "gyro.rrw_deg_hr_rthr": 0.0, "gyro.bias_instability_deg_hr": 0.0}


def second_frame(scenario: str, head: int = 0, **overrides):
    """Observation and truth of frame 1 (its gyro record covers the whole exposure) of a noise-free-gyro scenario."""
    env = gym.make(f"StarEnv/{scenario}-v0", overrides={**NOISE_FREE_GYRO, **overrides})
    env.reset(seed=0)
    obs, _, _, _, info = env.step(None)
    base = env.unwrapped
    n = int(obs["gyro"]["count"])
    gyro = GyroSamples(obs["gyro"]["t"][:n], obs["gyro"]["rate"][:n], 1.0 / base.scenario.gyro.rate_hz)
    stars = {k: np.asarray(v) for k, v in info["truth"]["stars"][head].items()}
    return base, gyro, float(obs["time_s"]), base.scenario.exposure_s, stars


def ends_and_mid(cam, gyro, t_mid, exposure, xy_mid, **kw):
    """Path samples at exactly the start, middle and end of the exposure: 3 midpoint instants of a window 1.5 T long
    fall at t_mid - T/2, t_mid, t_mid + T/2."""
    return star_paths(cam, gyro, t_mid - 0.75 * exposure, t_mid + 0.75 * exposure, xy_mid, n_samples=3, **kw)


@pytest.mark.parametrize(
    ("scenario", "head", "overrides"),
    [
        ("Paper002", 0, {}),  # 5 deg/s three-axis, no distortion
        ("Paper000", 0, {"motion.rate_dps": [3.0, -2.0, 4.0]}),  # paper 000's radial distortion
        ("Paper004", 1, {"motion.rate_dps": [2.0, -1.0, 3.0]}),  # a head mounted at 90 deg to the body
    ],
)
def test_star_paths_match_renderer_truth(scenario, head, overrides):
    base, gyro, t_mid, exposure, truth = second_frame(scenario, head, **overrides)
    cam = base.cameras[head]
    assert len(truth["xy_mid"]) >= 5
    p = ends_and_mid(cam, gyro, t_mid, exposure, truth["xy_mid"])
    # A constant rate is integrated exactly from its average samples: the renderer's exact attitude is reproduced.
    np.testing.assert_allclose(p[:, 0], truth["xy_start"], atol=1e-6)
    np.testing.assert_allclose(p[:, 1], truth["xy_mid"], atol=1e-9)
    np.testing.assert_allclose(p[:, 2], truth["xy_end"], atol=1e-6)
    full = star_paths(cam, gyro, t_mid - 0.5 * exposure, t_mid + 0.5 * exposure, truth["xy_mid"])
    assert full.shape[1] % 2 == 1
    np.testing.assert_array_equal(full[:, full.shape[1] // 2], p[:, 1])
    # Mean of the midpoint samples = the renderer's trail centroid (both midpoint sums of the same integral).
    np.testing.assert_allclose(full.mean(axis=1), truth["xy_centroid"], atol=1e-4)


def test_one_exposures_motion_gives_each_set_of_stars_its_own_paths():
    # The rotations are found once and kept: stars asked for afterwards, elsewhere, get their own paths, as from
    # star_paths, bit for bit (the trail fit asks again for each round's candidates).
    base, gyro, t_mid, exposure, truth = second_frame("Paper000", **{"motion.rate_dps": [30.0, -20.0, 40.0]})
    cam = base.cameras[0]
    window = (t_mid - 0.5 * exposure, t_mid + 0.5 * exposure)
    motion = ExposureMotion(cam, gyro, *window)
    first, then = truth["xy_mid"][:4], np.array([[10.0, 20.0], [500.0, 480.0], [256.0, 256.0]])
    for xy in (first, then, np.zeros((0, 2))):
        np.testing.assert_array_equal(motion.paths(xy), star_paths(cam, gyro, *window, xy))


def test_star_paths_rolling_shutter_windows_match_renderer():
    line_time = 1e-5  # 5 ms readout across 512 rows, comparable to the 4 ms exposure
    base, gyro, _, exposure, truth = second_frame("Paper000", **{"motion.rate_dps": [3.0, -2.0, 4.0],
                                                                 "exposure_s": 0.004,
                                                                 "heads.0.detector.line_time_s": line_time})
    cam = base.cameras[0]
    t_start = 1.0 / base.scenario.frame_rate_hz  # frame 1 opens row 0 here
    p = star_paths(cam, gyro, t_start - 0.25 * exposure, t_start + 1.25 * exposure, truth["xy_mid"], n_samples=3,
                   line_time_s=line_time)
    # The renderer's row (found by fixed-point iteration) is the one xy_mid sits on to well under a row.
    np.testing.assert_allclose(p[:, 0], truth["xy_start"], atol=2e-3)
    np.testing.assert_allclose(p[:, 2], truth["xy_end"], atol=2e-3)
    # (Under a constant rate a path relative to its mid point does not depend on when the window opens, so this
    # checks the per-row window bookkeeping, not the size of the rolling-shutter effect.)


def test_boresight_blur_is_the_chord_of_the_roll():
    rate = math.radians(8.0)
    base, gyro, t_mid, exposure, truth = second_frame("Paper002", **{"motion.rate_dps": [0.0, 0.0, 8.0]})
    cam = base.cameras[0]
    blur = boresight_blur(truth["xy_mid"], rate, exposure, cam)
    np.testing.assert_allclose(blur.start, truth["xy_start"], atol=1e-6)
    np.testing.assert_allclose(blur.end, truth["xy_end"], atol=1e-6)
    r = np.linalg.norm(truth["xy_mid"] - [cam.cx, cam.cy], axis=1)
    chord = 2.0 * r * math.sin(rate * exposure / 2.0)
    np.testing.assert_allclose(blur.length, chord, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(truth["xy_end"] - truth["xy_start"], axis=1), chord, rtol=1e-8)
    # Eq. 18 (|w| T r) is the arc length, longer than the chord by (wT)^2 / 24 relative.
    np.testing.assert_allclose(rate * exposure * r / blur.length - 1.0, (rate * exposure) ** 2 / 24.0, rtol=1e-3)


def test_cross_boresight_blur_exact_on_the_axis_and_first_order_elsewhere():
    rate = math.radians(6.0)
    base, gyro, t_mid, exposure, truth = second_frame("Paper002", **{"motion.rate_dps": [6.0, 0.0, 0.0]})
    cam = base.cameras[0]
    # A star on the column of the principal point moves in the Y-Z plane only: Eq. 9 is exact there.
    on_axis = np.array([[cam.cx, 100.0], [cam.cx, 900.0]])
    exact = ends_and_mid(cam, gyro, t_mid, exposure, on_axis)
    blur = cross_boresight_blur(on_axis, [rate, 0.0], exposure, cam)
    np.testing.assert_allclose(blur.start, exact[:, 0], atol=1e-6)
    np.testing.assert_allclose(blur.end, exact[:, 2], atol=1e-6)
    # Elsewhere the model drops the w_x x y term of du/dt: the u error is f * w T * |x y|, at most ~0.2 px here.
    blur = cross_boresight_blur(truth["xy_mid"], [rate, 0.0], exposure, cam)
    x = (truth["xy_mid"][:, 0] - cam.cx) / cam.fx
    y = (truth["xy_mid"][:, 1] - cam.cy) / cam.fy
    bound = cam.fx * rate * exposure * np.abs(x * y) * 1.05 + 1e-3
    assert np.all(np.abs((blur.end - blur.start) - (truth["xy_end"] - truth["xy_start"]))[:, 0] <= bound)
    np.testing.assert_allclose(blur.end[:, 1] - blur.start[:, 1], truth["xy_end"][:, 1] - truth["xy_start"][:, 1],
                               rtol=2e-3)
    # Eq. 11 to first order, and the direction of Eq. 14 (rotation about X alone moves stars along +v).
    alpha = np.arctan(y)
    np.testing.assert_allclose(blur.length, cam.fy * (np.tan(alpha) ** 2 + 1) * rate * exposure, rtol=5e-3)
    np.testing.assert_allclose(blur.angle, math.pi / 2, atol=1e-12)


def test_path_kernel_moments_closed_form():
    sigma, length, m = 1.0, 30.0, 61
    # A horizontal path through a pixel centre: a discrete uniform of m points spaced L/m convolved with the
    # pixel-integrated Gaussian, whose variance on the pixel grid is sigma^2 + 1/12 (aliasing < 1e-8; the band cut
    # at 4.5 sigma drops 7e-6 of the light, which moves moments by ~1e-6 relative).
    path = np.stack([100.0 + length * ((np.arange(m) + 0.5) / m - 0.5), np.full(m, 50.0)], axis=1)
    kernel, origin = path_kernel(path, sigma)
    assert kernel.dtype == np.float64 and kernel.shape[0] % 2 == 1 and kernel.shape[1] % 2 == 1
    np.testing.assert_array_equal(origin, [kernel.shape[1] // 2, kernel.shape[0] // 2])
    assert kernel.sum() == pytest.approx(1.0, abs=1e-12)
    yy, xx = np.mgrid[: kernel.shape[0], : kernel.shape[1]]
    mx, my = (kernel * xx).sum(), (kernel * yy).sum()
    assert (mx, my) == pytest.approx(tuple(origin), abs=1e-9)
    var_x = (kernel * (xx - mx) ** 2).sum()
    var_y = (kernel * (yy - my) ** 2).sum()
    assert var_x == pytest.approx((length / m) ** 2 * (m * m - 1) / 12.0 + sigma**2 + 1 / 12, rel=1e-5)
    assert var_y == pytest.approx(sigma**2 + 1 / 12, rel=1e-5)


@settings(max_examples=30, deadline=None)
@given(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.0, 40.0), st.floats(-math.pi, math.pi))
def test_path_kernel_centroid_is_the_path_mean_relative_to_mid(fx, fy, length, angle):
    m = 41
    mid = np.array([300.0 + fx, 200.0 + fy])
    s = length * ((np.arange(m) + 0.5) / m - 0.5)
    path = mid + np.outer(s, [math.cos(angle), math.sin(angle)]) + np.outer(s**2, [0.0, 0.01])  # slightly curved
    kernel, origin = path_kernel(path, 0.7)
    yy, xx = np.mgrid[: kernel.shape[0], : kernel.shape[1]]
    centroid = np.array([(kernel * xx).sum(), (kernel * yy).sum()])
    # Up to the 4.5-sigma band cut: 7e-6 of the light, cut unevenly (the band starts on a whole pixel) at ~3.5 px.
    np.testing.assert_allclose(centroid - origin, path.mean(axis=0) - mid, atol=3e-5)


def test_gyro_rotation_constant_and_piecewise_rates():
    dt = 0.005
    t = 0.1 + dt * np.arange(1, 9)
    w = np.array([0.3, -0.2, 0.5])
    const = GyroSamples(t, np.tile(w, (8, 1)), dt)
    times = np.array([0.09, 0.1, 0.1234, 0.14, 0.15])  # before, inside and after the samples
    got = gyro_rotation(const, times, 0.12)
    want = Rotation.from_rotvec(-np.outer(times - 0.12, w))
    assert np.allclose((got * want.inv()).magnitude(), 0.0, atol=1e-14)
    # Two different samples: the rotation over both intervals is the product of the per-interval rotations.
    rates = np.array([[0.1, 0.0, 0.0], [0.0, 0.4, 0.0]])
    two = GyroSamples(np.array([1.0, 1.0 + dt]), rates, dt)
    got = gyro_rotation(two, np.array([1.0 + dt]), 1.0 - dt)
    want = Rotation.from_rotvec(-rates[1] * dt) * Rotation.from_rotvec(-rates[0] * dt)
    assert (got * want.inv()).magnitude()[0] < 1e-15


def test_bad_input_names_the_field():
    gyro = GyroSamples(np.array([0.1]), np.zeros((1, 3)), 0.01)
    base, *_ = second_frame("Paper000")
    cam = base.cameras[0]
    with pytest.raises(ValueError, match="xy_mid"):
        star_paths(cam, gyro, 0.0, 0.01, np.zeros(3))
    with pytest.raises(ValueError, match="t_end"):
        star_paths(cam, gyro, 0.02, 0.01, np.zeros((1, 2)))
    with pytest.raises(ValueError, match="gyro"):
        star_paths(cam, GyroSamples(np.zeros(0), np.zeros((0, 3)), 0.01), 0.0, 0.01, np.zeros((1, 2)))
    with pytest.raises(ValueError, match="path"):
        path_kernel(np.zeros((4, 3)), 1.0)
    with pytest.raises(ValueError, match="sigma_px"):
        path_kernel(np.zeros((4, 2)), 0.0)
    with pytest.raises(ValueError, match="exposure_s"):
        boresight_blur(np.zeros((1, 2)), 0.1, -1.0, cam)


def test_linear_blur_kernel_is_the_uniform_line_psf():
    # Paper 000's Eqs. 15/21: light spread evenly along the trail; rasterised, its variance along the trail is that of
    # m evenly spaced points over the length L plus the pixel-integrated Gaussian's sigma^2 + 1/12.
    cam_like = type("Cam", (), {"cx": 511.5, "cy": 511.5})()
    blur = boresight_blur(np.array([[811.5, 511.5]]), math.radians(20.0), 0.1, cam_like)  # vertical ~10.5 px chord
    length = float(blur.length[0])
    m = blur.paths().shape[1]
    kernel, origin = blur.kernels(1.0)[0]
    assert kernel.sum() == pytest.approx(1.0, abs=1e-12)
    yy, xx = np.mgrid[: kernel.shape[0], : kernel.shape[1]]
    my = (kernel * yy).sum()
    assert my == pytest.approx(origin[1], abs=1e-5)
    var_y = (kernel * (yy - my) ** 2).sum()
    assert var_y == pytest.approx((length / m) ** 2 * (m * m - 1) / 12.0 + 1.0 + 1 / 12, rel=1e-5)
    assert blur.angle[0] == pytest.approx(-math.pi / 2, abs=1e-12)  # roll about +Z moves a star on +u towards -v


def test_path_kernels_of_many_paths_are_each_path_kernel():
    # One scatter for all paths (the region-of-interest restorers' kernels) must give each path's own kernel, bit for
    # bit, whatever the paths' lengths and directions.
    rng = np.random.default_rng(3)
    steps = rng.normal(0.0, 0.6, (5, 41, 2)) + rng.normal(0.0, 1.0, (5, 1, 2))
    paths = np.cumsum(steps, axis=1) + rng.uniform(20.0, 80.0, (5, 1, 2))
    kernels, origins = path_kernels(paths, 0.9)
    for path, kernel, origin in zip(paths, kernels, origins, strict=True):
        one, one_origin = path_kernel(path, 0.9)
        np.testing.assert_array_equal(kernel, one)
        np.testing.assert_array_equal(origin, one_origin)
    assert len({k.shape for k in kernels}) > 1
    with pytest.raises(ValueError, match="paths must be an"):
        path_kernels(paths[0], 0.9)
