"""StarSensor: seeded determinism, frame / truth / gyro timing, dropped frames, the background level and noise of real
scenarios against photometry, and star signal in the image against the truth."""

from __future__ import annotations

import math
import os
import threading
from unittest import mock

import numpy as np
import pytest

from starenv.parallel import POOL_WORKER_ENV
from starenv.scenario import load
from starenv.sim.conventions import ARCSEC_PER_RAD, angle_between
from starenv.sim.imager import Detector
from starenv.sim.sensor import StarSensor, noise_thread_default


def quiet(n_heads: int) -> dict:
    """Overrides switching off cosmic rays and hot pixels on every head."""
    keys = ("cosmic_ray_rate_per_cm2_s", "hot_pixel_fraction")
    return {f"heads.{h}.detector.{k}": 0.0 for h in range(n_heads) for k in keys}


def run(sensor: StarSensor, seed, n: int):
    sensor.reset(seed)
    return [sensor.next_frame() for _ in range(n)]


def assert_identical(frames_a, frames_b) -> None:
    """Bit-identical images, drop flags, truth, gyro samples and attitudes."""
    for fa, fb in zip(frames_a, frames_b, strict=True):
        assert (fa.index, fa.t_start, fa.t_mid) == (fb.index, fb.t_start, fb.t_mid)
        np.testing.assert_array_equal(fa.attitude.as_quat(), fb.attitude.as_quat())
        np.testing.assert_array_equal(fa.gyro.t, fb.gyro.t)
        np.testing.assert_array_equal(fa.gyro.rate, fb.gyro.rate)
        for ha, hb in zip(fa.heads, fb.heads, strict=True):
            assert ha.image.dtype == np.uint16 and hb.image.dtype == np.uint16
            np.testing.assert_array_equal(ha.image, hb.image)
            assert ha.dropped == hb.dropped
            for key, value in ha.truth.as_dict().items():
                np.testing.assert_array_equal(value, getattr(hb.truth, key))


# ---------------------------------------------------------------------------------------------------------------
# Determinism.


def test_same_seed_gives_bit_identical_frames():
    # Two sensors of one scenario with one seed agree bit for bit over 10 frames on every head (drops included);
    # a reset with the same seed replays the episode; another seed gives other images.
    sc = load("paper_004", {"drops.probability": 0.3})
    a, b = StarSensor(sc), StarSensor(sc)
    first = run(a, 123, 10)
    assert_identical(first, run(b, 123, 10))
    assert_identical(first, run(a, 123, 10))
    flags = [h.dropped for f in first for h in f.heads]
    assert any(flags) and not all(flags)  # the drop channel really ran
    other = run(b, 124, 10)
    kept = [(ha.image, hb.image) for fa, fb in zip(first, other, strict=True)
            for ha, hb in zip(fa.heads, fb.heads, strict=True) if not ha.dropped and not hb.dropped]
    assert kept and all(not np.array_equal(x, y) for x, y in kept)
    assert not np.array_equal(first[-1].gyro.rate, other[-1].gyro.rate)


@pytest.mark.parametrize("name", ["paper_004", "hot_sensor", "stress_tumble"])
def test_noise_drawn_beside_the_render_gives_the_same_frames(name):
    # Each head's background frame drawn on the noise thread while the stars render (counted: every head of every
    # frame, none drawn on this thread) gives the frames drawn after the render bit for bit, with hot pixels, cosmic
    # rays, drops, three heads (paper_004) and a varying dark current (hot_sensor): the draw neither moves within a
    # head's noise stream nor races the read-out that uses it.
    sc = load(name, {"drops.probability": 0.3})
    serial = run(StarSensor(sc, noise_thread=False), 31, 6)
    threads = []
    draw = Detector.draw_background

    def counted(*args, **kwargs):
        threads.append(threading.current_thread() is threading.main_thread())
        return draw(*args, **kwargs)

    with mock.patch.object(Detector, "draw_background", autospec=True, side_effect=counted):
        threaded = run(StarSensor(sc, noise_thread=True), 31, 6)
    assert threads == [False] * (6 * len(sc.heads))
    assert_identical(serial, threaded)


def test_noise_thread_default_and_setting():
    # The thread is taken by default only with two cores or more, outside a pool's worker process (a multiprocessing
    # child, or a Ray worker marked by the runners); a setting that is not a bool or None is refused by name.
    with mock.patch("os.sched_getaffinity", return_value={0, 1}), mock.patch.dict(os.environ):
        os.environ.pop(POOL_WORKER_ENV, None)
        assert noise_thread_default()
        with mock.patch("multiprocessing.parent_process", return_value=object()):
            assert not noise_thread_default()
        os.environ[POOL_WORKER_ENV] = "1"
        assert not noise_thread_default()
    with mock.patch("os.sched_getaffinity", return_value={0}):
        assert not noise_thread_default()
    with pytest.raises(ValueError, match="noise_thread"):
        StarSensor(load("paper_000"), noise_thread="yes")


def test_appending_a_head_leaves_the_others_unchanged():
    # The documented stream layout: head 0's images, drops and the gyro do not depend on how many heads follow.
    three = load("paper_004", {"drops.probability": 0.5})
    one = load(three.data | {"heads": three.data["heads"][:1]})
    frames3, frames1 = run(StarSensor(three), 7, 4), run(StarSensor(one), 7, 4)
    for f3, f1 in zip(frames3, frames1, strict=True):
        np.testing.assert_array_equal(f3.heads[0].image, f1.heads[0].image)
        assert f3.heads[0].dropped == f1.heads[0].dropped
        np.testing.assert_array_equal(f3.gyro.rate, f1.gyro.rate)


# ---------------------------------------------------------------------------------------------------------------
# Timing of frames, truth and gyro samples.


@pytest.mark.parametrize(
    ("name", "overrides", "n_frames"),
    [
        ("paper_001", {}, 6),  # 10 Hz, 60 ms, gyro 200 Hz
        ("stress_tumble", {}, 8),  # 100 Hz, 10 ms, gyro 1000 Hz, non-uniform rate
        ("paper_000", {"gyro.time_offset_s": 0.0013, "gyro.rate_hz": 300.0}, 8),  # grid not aligned with frames
    ],
)
def test_frame_truth_and_gyro_timing(name, overrides, n_frames):
    # Frame starts, truth instants and the gyro samples handed over with each frame follow the documented timing.
    sc = load(name, overrides)
    sensor = StarSensor(sc)
    frames = run(sensor, 5, n_frames)
    rate_hz, offset = sc.gyro.rate_hz, sc.gyro.time_offset_s
    delivered = offset  # sample 0 (at the grid origin) is never delivered
    indices = []
    for k, frame in enumerate(frames):
        # Frame k opens at k / frame_rate_hz; a global shutter's truth is at mid-exposure.
        assert frame.index == k
        assert frame.t_start == pytest.approx(k / sc.frame_rate_hz, rel=1e-12, abs=1e-15)
        assert frame.t_mid == pytest.approx(frame.t_start + sc.exposure_s / 2, rel=1e-12, abs=1e-15)
        assert all(h.t_mid == frame.t_mid for h in frame.heads)
        assert angle_between(frame.attitude, sc.trajectory.attitude(frame.t_mid)) < 1e-12
        np.testing.assert_allclose(frame.body_rate, sc.trajectory.body_rate(frame.t_mid), rtol=1e-12)
        # Gyro samples: stamped in (previous delivery, end of this exposure], all of them, on the grid.
        t = frame.gyro.t
        window_end = frame.t_start + sc.exposure_s
        assert frame.gyro.rate.shape == (len(t), 3)
        assert len(t) > 0 and np.all(t > delivered) and np.all(t <= window_end)
        grid = (t - offset) * rate_hz
        np.testing.assert_allclose(grid, np.rint(grid), atol=1e-6)
        last = int(np.rint(grid[-1]))
        assert (last + 1) / rate_hz + offset > window_end  # nothing left behind that was already due
        indices.extend(np.rint(grid).astype(int).tolist())
        delivered = t[-1]
        # Measured rates are the true mean rate over each sample interval, up to the gyro's noise.
        np.testing.assert_allclose(frame.gyro.rate, sc.trajectory.body_rate(t - 0.5 / rate_hz), atol=2e-3)
    assert indices == list(range(1, len(indices) + 1))  # no gap, no repeat across frames


# ---------------------------------------------------------------------------------------------------------------
# Dropped frames.


def test_dropped_frames_are_black_but_keep_truth():
    # A lost frame delivers zeros and dropped=True, but its truth and the gyro samples are still there.
    lossy = StarSensor(load("stress_drops", {"drops.probability": 1.0}))
    clean = StarSensor(load("stress_drops", {"drops.probability": 0.0, "drops.p_good_to_bad": 0.0}))
    for f_lossy, f_clean in zip(run(lossy, 3, 3), run(clean, 3, 3), strict=True):
        head, ref = f_lossy.heads[0], f_clean.heads[0]
        assert head.dropped and not ref.dropped
        assert head.image.dtype == np.uint16 and head.image.shape == (512, 512) and not head.image.any()
        assert ref.image.any()
        assert len(head.truth) > 0
        for key, value in head.truth.as_dict().items():
            np.testing.assert_array_equal(value, getattr(ref.truth, key))
        assert len(f_lossy.gyro.t) > 0


def test_bursty_drops_per_head():
    # With a bursty (Gilbert-Elliott) channel on each of three heads, exactly the lost frames are all zeros.
    sc = load("paper_004", {"drops.p_good_to_bad": 0.5, "drops.p_bad_to_good": 0.5})
    frames = run(StarSensor(sc), 9, 8)
    for frame in frames:
        for head in frame.heads:
            assert head.image.any() != head.dropped
    assert 0 < sum(h.dropped for f in frames for h in f.heads) < 24


# ---------------------------------------------------------------------------------------------------------------
# Background level and noise against photometry.


def expected_background(sc, head) -> tuple[float, float]:
    """Mean (DN) and standard deviation (DN, with the ADC's 1/12 DN^2) of a star-free pixel."""
    cam, det = head.camera, head.detector
    pixel_arcsec = cam.pixel_pitch_m / cam.focal_length_m * ARCSEC_PER_RAD
    sky = head.photometry.electrons_per_s_mag0 * 10.0 ** (-0.4 * sc.sky_mag_per_arcsec2) * pixel_arcsec**2
    assert sky == pytest.approx(head.photometry.sky_electrons_per_px_s(sc.sky_mag_per_arcsec2, pixel_arcsec**2))
    electrons = (sky + det.dark_current_e_per_s) * sc.exposure_s
    mean = det.bias_dn + electrons / det.gain_e_per_dn
    return mean, math.sqrt((electrons + det.read_noise_e**2) / det.gain_e_per_dn**2 + 1.0 / 12.0)


@pytest.mark.parametrize(
    ("name", "overrides"),
    [
        ("paper_000", {}),
        ("paper_001", {}),
        ("paper_002", {}),
        ("paper_003", {}),
        ("paper_004", {}),
        ("stress_tumble", {}),
        # A bright sky and a hot sensor make the background hundreds of DN: a wrong term would show.
        ("paper_002", {"sky_mag_per_arcsec2": 16.0, "heads.0.detector.dark_current_e_per_s": 2000.0}),
        ("paper_000", {"sky_mag_per_arcsec2": 14.0, "heads.0.detector.gain_e_per_dn": 1.5}),
    ],
)
def test_background_median_and_noise(name, overrides):
    # Median = bias + (sky + dark) * exposure / gain within 1 DN; the spread is shot + read noise within 10 %.
    sc = load(name, overrides)
    frame = run(StarSensor(sc), 2, 1)[0]
    for head, out in zip(sc.heads, frame.heads, strict=True):
        assert not out.dropped
        mean, sigma = expected_background(sc, head)
        image = out.image.astype(np.float64)
        median = float(np.median(image))
        assert median == pytest.approx(mean, abs=1.0)
        core = image[np.abs(image - median) < 6.0 * sigma]  # leave out stars, hot pixels and cosmic rays
        assert core.size > 0.98 * image.size
        assert core.std() == pytest.approx(sigma, rel=0.1)


# ---------------------------------------------------------------------------------------------------------------
# Star signal in the image against the truth.


def trail_mask(shape, origin, start, end, radius) -> np.ndarray:
    """Pixels (in a window of ``shape`` at ``origin`` (x, y)) within ``radius`` px of the segment start -> end."""
    ys, xs = np.indices(shape, dtype=np.float64)
    px, py = xs + origin[0] - start[0], ys + origin[1] - start[1]
    dx, dy = end[0] - start[0], end[1] - start[1]
    along = np.clip((px * dx + py * dy) / max(dx * dx + dy * dy, 1e-12), 0.0, 1.0)
    return np.hypot(px - along * dx, py - along * dy) <= radius


@pytest.mark.parametrize(("name", "n_heads"), [("paper_002", 1), ("paper_000", 1), ("paper_004", 3)])
def test_star_signal_matches_truth_electrons(name, n_heads):
    # Along each bright, unsaturated, isolated truth trail, the background-subtracted image holds truth.electrons
    # (within 10 %) and its intensity centroid sits on truth.xy_centroid: image and truth agree in flux and place.
    sc = load(name, quiet(n_heads))
    frame = run(StarSensor(sc), 1, 1)[0]
    checked = sum(check_star_signal(sc, head, out) for head, out in zip(sc.heads, frame.heads, strict=True))
    assert checked >= 2


def check_star_signal(sc, head, out) -> int:
    """Check every qualifying star of one head's frame; returns how many were checked."""
    cam, det, sigma = head.camera, head.detector, head.psf_sigma_px
    image, truth = out.image.astype(np.float64), out.truth
    saturation = min(det.full_well_e, (det.max_dn - det.bias_dn) * det.gain_e_per_dn)
    _, noise_dn = expected_background(sc, head)
    radius = 4.5 * sigma + 1.0  # the renderer's PSF footprint plus a pixel
    pad = math.ceil(radius) + 1
    ends = np.stack([truth.xy_start, truth.xy_end, truth.xy_centroid], axis=1)  # (stars, 3, 2)
    lo = np.floor(ends.min(axis=1)).astype(int) - pad
    hi = np.ceil(ends.max(axis=1)).astype(int) + pad
    # Background: mean of every pixel away from all trails (the ADC's rounding down is shared with the stars).
    free = np.ones(image.shape, bool)
    for (x0, y0), (x1, y1) in zip(lo, hi, strict=True):
        free[max(y0, 0) : y1 + 1, max(x0, 0) : x1 + 1] = False
    background = image[free & (np.abs(image - np.median(image)) < 6 * noise_dn)].mean()
    checked = 0
    for i in np.argsort(truth.electrons)[::-1]:
        electrons = truth.electrons[i]
        if electrons / (2 * math.pi * sigma**2) > 0.8 * saturation:
            continue  # might saturate
        if np.any(lo[i] < 0) or hi[i, 0] >= cam.width or hi[i, 1] >= cam.height:
            continue  # too close to an edge
        shape, origin = (hi[i, 1] - lo[i, 1] + 1, hi[i, 0] - lo[i, 0] + 1), lo[i]
        mask = trail_mask(shape, origin, truth.xy_start[i], truth.xy_end[i], radius)
        noise_e = math.sqrt(mask.sum() * (noise_dn * det.gain_e_per_dn) ** 2 + electrons)
        if electrons < 30 * noise_e:
            continue  # too faint for a 10 % test to be 3 sigma
        near = [j for j in range(len(truth)) if j != i and truth.electrons[j] > 0.005 * electrons
                and np.all(lo[j] <= hi[i]) and np.all(hi[j] >= lo[i])]
        if any((mask & trail_mask(shape, origin, truth.xy_start[j], truth.xy_end[j], 2 * radius)).any() for j in near):
            continue  # not isolated
        window = image[lo[i, 1] : hi[i, 1] + 1, lo[i, 0] : hi[i, 0] + 1] - background
        star = np.where(mask, window, 0.0)
        assert star.sum() * det.gain_e_per_dn == pytest.approx(electrons, rel=0.1)
        ys, xs = np.indices(shape)
        centroid = np.array([(xs * star).sum(), (ys * star).sum()]) / star.sum() + origin
        np.testing.assert_allclose(centroid, truth.xy_centroid[i], atol=0.5)
        checked += 1
    return checked
