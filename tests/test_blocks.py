"""The agents' building blocks (starenv.agents.blocks), each against a closed form or an independent computation."""

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage
from scipy.spatial.transform import Rotation
from scipy.special import ndtr, ndtri

from starenv.agents import blocks
from starenv.agents.blocks import (
    background,
    background_maps,
    component_peaks,
    components,
    components_above,
    frame_background,
    frame_span_s,
    pixels_above,
    row_window,
    streak_candidates,
    wahba_svd,
)
from starenv.agents.blocks.background import censored_mean_std

EPS = np.finfo(np.float64).eps


def test_the_door_names_every_block():
    assert sorted(blocks.__all__) == sorted(set(blocks.__all__))
    for name in blocks.__all__:
        assert getattr(blocks, name).__doc__


# --- Wahba's problem -------------------------------------------------------------------------------------------------


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_wahba_svd_recovers_a_rotation_exactly_from_noise_free_vectors():
    # With b_i = A r_i the profile matrix is A sum r r^T, whose polar factor is A: the SVD returns it to rounding.
    # A backward-stable SVD of a matrix with singular values of order 1 (vectors spread over the sphere) errs by a
    # few eps in each entry; 64 eps bounds that with room for the products.
    rng = np.random.default_rng(0)
    truth = Rotation.random(200, random_state=1).as_matrix()
    inertial = unit(rng.normal(size=(200, 6, 3)))
    body = np.einsum("kij,knj->kni", truth, inertial)
    attitude = wahba_svd(body, inertial)
    assert np.abs(attitude - truth).max() < 64 * EPS
    np.testing.assert_allclose(np.linalg.det(attitude), 1.0, atol=64 * EPS)
    # A problem gives the same bits alone as in a batch (the identifiers solve both ways).
    alone = np.stack([wahba_svd(b, r) for b, r in zip(body, inertial, strict=True)])
    np.testing.assert_array_equal(alone, attitude)


def test_wahba_svd_agrees_with_scipys_align_vectors_on_noisy_weighted_vectors():
    # Both minimise sum w |b - A r|^2 over rotations (scipy by its own SVD); with 1 mrad noise on six spread vectors
    # the minimum is unique and well separated (singular values of order 1), so the two agree to rounding: 1e-12 rad
    # leaves a factor of a thousand over eps.
    rng = np.random.default_rng(2)
    truth = Rotation.random(100, random_state=3)
    inertial = unit(rng.normal(size=(100, 6, 3)))
    body = unit(np.einsum("kij,knj->kni", truth.as_matrix(), inertial) + rng.normal(0.0, 1e-3, (100, 6, 3)))
    weights = rng.uniform(0.1, 2.0, (100, 6))
    attitude = Rotation.from_matrix(wahba_svd(body, inertial, weights))
    for k in range(100):
        scipy_attitude, _ = Rotation.align_vectors(body[k], inertial[k], weights=weights[k])
        assert (attitude[k] * scipy_attitude.inv()).magnitude() < 1e-12
    # ... and the noise moves the solution by about 1 mrad / sqrt(6) from the truth, far less than 10 mrad.
    assert (attitude * truth.inv()).magnitude().max() < 1e-2


def test_wahba_svd_returns_a_rotation_where_the_best_orthogonal_fit_is_a_reflection():
    # Body vectors mirrored through a plane (b = M r, det M = -1): the nearest orthogonal matrix is the reflection,
    # and the answer must be the best proper rotation instead, as scipy finds it: the same loss to rounding.
    rng = np.random.default_rng(4)
    inertial = unit(rng.normal(size=(5, 3)))
    mirror = np.diag([1.0, 1.0, -1.0])
    body = inertial @ mirror
    attitude = wahba_svd(body, inertial)
    assert np.linalg.det(attitude) == pytest.approx(1.0, abs=64 * EPS)
    np.testing.assert_allclose(attitude @ attitude.T, np.eye(3), atol=64 * EPS)
    scipy_attitude, _ = Rotation.align_vectors(body, inertial)

    def loss(a):
        return float(np.sum((body - inertial @ a.T) ** 2))

    assert loss(attitude) == pytest.approx(loss(scipy_attitude.as_matrix()), abs=1e-12)
    assert loss(attitude) > 1e-3  # a rotation cannot undo the mirror
    # The flip of the last axis gives the same bits alone as in a batch (here beside problems that need none).
    batch = np.stack([body, inertial @ Rotation.random(random_state=5).as_matrix().T])
    together = wahba_svd(batch, np.stack([inertial, inertial]))
    np.testing.assert_array_equal(together[0], attitude)
    np.testing.assert_array_equal(together[1], wahba_svd(batch[1], inertial))


# --- background and noise --------------------------------------------------------------------------------------------

LEVEL_DN, NOISE_DN, SIZE = 100.3, 3.0, 512
LEVEL_SAMPLE = SIZE * SIZE // 4  # every other pixel of every other row
DIFFERENCES = (SIZE // 4) * (SIZE - 1)  # horizontal neighbours on every fourth row
# Standard errors for Gaussian noise: the clipped mean of n values ~ sigma / sqrt(n) (a 3-sigma clip keeps 99.7 % and
# shrinks the spread by 1.3 %); the standard deviation's relative error ~ sqrt(1.5 / (2 n)) for n differences of
# neighbours (adjacent differences share a pixel, correlation -1/2, which raises the variance of their sample variance
# by 1 + 2 (1/2)^2).  The tests allow 5 of them (a chance below 1e-6 for each).
LEVEL_SE = NOISE_DN / math.sqrt(LEVEL_SAMPLE)
NOISE_REL_SE = math.sqrt(1.5 / (2 * DIFFERENCES))


def noisy_frame(seed: int, stars: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    frame = LEVEL_DN + rng.normal(0.0, NOISE_DN, (SIZE, SIZE))
    hit = rng.random(frame.shape) < stars  # single bright pixels (hot pixels, cosmic rays, faint stars' cores)
    frame[hit] += rng.uniform(20.0, 500.0, hit.sum())
    return frame


@pytest.mark.parametrize("stars", [0.0, 0.02])
def test_frame_background_of_a_flat_frame_is_its_level_and_noise_within_their_standard_errors(stars):
    # Outliers 20-500 DN above (7 noise sigmas and more) on 2 % of the pixels lie beyond the clip: they drop out of
    # both statistics and leave the bounds as they are.
    level, noise = frame_background(noisy_frame(1, stars))
    assert abs(level - LEVEL_DN) < 5 * LEVEL_SE
    assert abs(noise / NOISE_DN - 1.0) < 5 * NOISE_REL_SE


def test_frame_background_noise_is_blind_to_a_gradient():
    # A plane rising 40 DN across the frame adds a constant 40 / 511 DN to every horizontal difference: their spread
    # and so the noise stay as on a flat frame (the pixels' own spread would be sqrt(9 + 40^2 / 12) = 12 DN).
    frame = noisy_frame(2) + np.linspace(0.0, 40.0, SIZE)[None, :]
    _, noise = frame_background(frame)
    assert abs(noise / NOISE_DN - 1.0) < 5 * NOISE_REL_SE


def test_the_noise_of_an_integer_read_out_is_its_standard_deviation_not_its_rounded_mad():
    # 2 DN of Gaussian noise rounded to whole DN has the standard deviation sqrt(4 + 1/12) = 2.02 DN (rounding adds
    # 1/12 DN^2, independent from pixel to pixel); a median absolute deviation moves in whole DN and reads 1.48 DN.
    rng = np.random.default_rng(5)
    frame = np.round(100.3 + rng.normal(0.0, 2.0, (SIZE, SIZE))).astype(np.uint16)
    level, noise = frame_background(frame)
    assert abs(level - 100.3) < 5 * 2.02 / math.sqrt(LEVEL_SAMPLE)
    assert abs(noise / math.sqrt(4.0 + 1.0 / 12.0) - 1.0) < 5 * NOISE_REL_SE


def test_background_maps_of_one_tile_are_the_frame_background():
    # A tile larger than the frame leaves one tile: the maps hold the scalar estimate everywhere (float32).
    frame = noisy_frame(3, 0.01)
    level, noise = frame_background(frame)
    level_map, noise_map = background_maps(frame.astype(np.float32), tile_px=4 * SIZE)
    np.testing.assert_allclose(level_map, level, rtol=1e-6)
    np.testing.assert_allclose(noise_map, noise, rtol=1e-6)


def test_the_noise_map_stays_at_the_quantisation_floor_where_its_extrapolation_would_cross_it():
    # A noiseless first column of tiles (its noise at the floor) beside tiles of 8 DN: extrapolated linearly across
    # the border, the map would fall below zero there.  Its tiles are cut at the floor first, and every map value
    # mixes tile values with weights in [0, 1]: none below the floor, to float32 rounding.
    sigma = np.where(np.arange(SIZE) < 32, 0.0, 8.0)
    frame = (LEVEL_DN + np.random.default_rng(9).normal(0.0, 1.0, (SIZE, SIZE)) * sigma).astype(np.float32)
    _, noise_map = background_maps(frame, tile_px=32)
    assert noise_map.min() >= np.float32(background.QUANTISATION_NOISE_DN) * (1 - 1e-6)
    assert noise_map[:, :16].max() < 1.0 and noise_map[:, 48:].min() > 6.0


def test_background_maps_follow_a_plane_within_the_tiles_standard_error():
    # Tiles of 32 px: 256 level samples each, a standard error of 3 / 16 DN.  A map value is a bilinear mix of tile
    # values, or a linear extrapolation from two (weights up to 1.5 and -0.5: at most twice a tile's error), of a
    # plane that the mixing reproduces exactly; 5 standard errors of a tile, doubled.
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    plane = LEVEL_DN + 0.05 * cols - 0.03 * rows
    frame = (plane + np.random.default_rng(6).normal(0.0, NOISE_DN, plane.shape)).astype(np.float32)
    level_map, noise_map = background_maps(frame, tile_px=32)
    assert np.abs(level_map - plane).max() < 2 * 5 * NOISE_DN / 16
    # The noise of a tile comes from 8 x 31 differences: relative standard error sqrt(1.5 / 496).
    assert np.abs(noise_map / NOISE_DN - 1.0).max() < 2 * 5 * math.sqrt(1.5 / 496)



def _censored_population(mean: float, std: float, probability: float) -> float:
    """The quantile ``censored_mean_std`` reads at ``probability`` from a whole population of Gaussian values rounded
    to integers: the bin ``[v - 1/2, v + 1/2)`` holding it, interpolated linearly in the Gaussian's CDF at its edges."""
    v = math.ceil(mean + std * ndtri(probability) - 0.5)
    lo, hi = ndtr((v - 0.5 - mean) / std), ndtr((v + 0.5 - mean) / std)
    return v - 0.5 + (probability - lo) / (hi - lo)


def _censored_expectation(mean: float, std: float, n: int, integer: bool) -> tuple[float, float, float, float]:
    """What ``censored_mean_std`` should give on ``n`` Gaussian values cut at 0 (rounded first if ``integer``): the
    mean and sigma it tends to, and their standard errors.  The quantiles' asymptotic variances are
    ``p (1 - p) / (n phi(z)^2) sigma^2``, their covariance ``p_a (1 - p_b) / (n phi_a phi_b) sigma^2``; integer
    values tend to the population values of :func:`_censored_population`."""
    p0 = ndtr(((0.5 if integer else 0.0) - mean) / std)
    pa, pb = max(0.5, p0 + 0.25 * (1 - p0)), max(0.9, p0 + 0.75 * (1 - p0))
    za, zb = ndtri(pa), ndtri(pb)
    fa, fb = np.exp(-0.5 * za * za) / math.sqrt(2 * math.pi), np.exp(-0.5 * zb * zb) / math.sqrt(2 * math.pi)
    var_a, var_b, cov = pa * (1 - pa) / fa**2 / n, pb * (1 - pb) / fb**2 / n, pa * (1 - pb) / (fa * fb) / n
    std_se = std * math.sqrt(var_a + var_b - 2 * cov) / (zb - za)
    mean_se = std * math.sqrt(var_a) + abs(za) * std_se
    if not integer:
        return mean, std, mean_se, std_se
    xa, xb = _censored_population(mean, std, pa), _censored_population(mean, std, pb)
    expected_std = (xb - xa) / (zb - za)
    return xa - za * expected_std, expected_std, mean_se, std_se


@pytest.mark.parametrize("integer", [False, True])
def test_censored_mean_std_recovers_the_gaussian_behind_a_cut_at_zero(integer):
    """Gaussian values (mean 1 DN, sigma 3 DN: 37 % of them below 0) read 0 below 0, as a floored background.  The
    estimate is two quantiles above the pile at 0, within 5 standard errors (:func:`_censored_expectation`) of the
    truth.  Integer values (rounded): the interpolation within a bin is exact at the bins' edges only, so the
    estimate tends to the population value computed from the Gaussian's CDF (:func:`_censored_population`), which
    lies within 2 % of the true sigma for these values."""
    mean, std, n = 1.0, 3.0, 200_000
    rng = np.random.default_rng(11)
    values = rng.normal(mean, std, (4, n))
    values = np.maximum(np.round(values) if integer else values, 0.0).astype(np.float32)
    got_mean, got_std, kept = censored_mean_std(values)
    expected_mean, expected_std, mean_se, std_se = _censored_expectation(mean, std, n, integer)
    assert abs(expected_std / std - 1.0) < 0.02
    assert np.all(np.abs(got_std - expected_std) < 5 * std_se)
    assert np.all(np.abs(got_mean - expected_mean) < 5 * mean_se)
    if not integer:  # kept: the values at most 3 sigma above the mean (the pile at 0 among them): Phi(3), to the
        # sampling error of a fraction and that of the limit mean + 3 std (density phi(3) / sigma there)
        limit_se = (mean_se + 3 * std_se) / std
        phi3 = math.exp(-4.5) / math.sqrt(2 * math.pi)
        assert np.all(np.abs(kept - ndtr(3.0)) < 5 * (math.sqrt(ndtr(3.0) * ndtr(-3.0) / n) + phi3 * limit_se))


def test_a_background_cut_at_zero_gives_its_gaussian_and_an_uncut_one_is_unchanged(monkeypatch):
    """A frame whose background (1 DN, noise 3 DN) is cut at 0: ``frame_background`` gives the Gaussian behind the cut
    (its expected values, as above, within 5 standard errors for the whole frame's sample), where the
    sigma-clipped statistics read the pile at 0 as part of a narrower distribution.  Frames with no pile at 0 DN (or
    one below ``CLIPPED_FRACTION``, or a dropped frame of zeros, too many to place the quantiles) give exactly what
    they gave before the censored path existed (the gate off)."""
    rng = np.random.default_rng(12)
    cut = np.maximum(np.round(rng.normal(1.0, 3.0, (SIZE, SIZE))), 0).astype(np.uint16)
    level, noise = frame_background(cut)
    expected_level, expected_noise, level_se, noise_se = _censored_expectation(1.0, 3.0, cut.size, True)
    assert abs(noise - expected_noise) < 5 * noise_se and abs(level - expected_level) < 5 * level_se
    uncut = [noisy_frame(7, 0.01), np.round(noisy_frame(8)).astype(np.uint16),
             np.maximum(np.round(rng.normal(9.0, 3.0, (SIZE, SIZE))), 0).astype(np.uint16), np.zeros((64, 64))]
    # The last: 0.13 % of its values at 0; a tile's 256-value sample reaches 2 % (6 of them) with a chance of 1e-5.
    results = [(frame_background(f), background_maps(np.asarray(f, np.float32), 32)) for f in uncut]
    gated_level, gated_noise = frame_background(cut)
    monkeypatch.setattr(background, "CLIPPED_FRACTION", 2.0)  # never: the sigma-clipped statistics alone
    old_level, old_noise = frame_background(cut)
    assert old_noise < 0.75 * gated_noise and (gated_level, gated_noise) == (level, noise)
    for frame, (scalar, maps) in zip(uncut, results, strict=True):
        assert frame_background(frame) == scalar
        for new, old in zip(maps, background_maps(np.asarray(frame, np.float32), 32), strict=True):
            assert np.array_equal(new, old)


# --- candidates ------------------------------------------------------------------------------------------------------


def test_components_above_are_scipys_8_connected_labels_in_raster_order():
    rng = np.random.default_rng(7)
    signal = ndimage.gaussian_filter(rng.normal(size=(200, 300)), 1.5)
    limit = np.full(signal.shape, 0.1)
    found = components_above(signal, limit, min_area_px=3, max_area_px=40)
    labels, count = ndimage.label(signal > limit, structure=np.ones((3, 3)))
    # ndimage numbers components by their first pixel in raster order too: the labels agree one for one.
    np.testing.assert_array_equal(found.labels, labels)
    assert found.count == count + 1
    area = np.bincount(labels.ravel(), minlength=count + 1)
    np.testing.assert_array_equal(found.area[1:], area[1:])
    within = np.flatnonzero((area >= 3) & (area <= 40))
    np.testing.assert_array_equal(found.kept, within[within > 0])
    np.testing.assert_array_equal(found.pixel, np.flatnonzero(signal > limit))


@settings(max_examples=200, deadline=None)
@given(height=st.integers(1, 9), width=st.integers(1, 9), fill=st.floats(0.05, 0.7), seed=st.integers(0, 2**32 - 1))
def test_components_of_any_pixel_set_are_scipys_8_connected_labels(height, width, fill, seed):
    # Narrow frames and dense sets put pixels on both borders, where the flat index of the next row's first pixel
    # follows the last pixel of a row: a neighbour search in flat indices must not join them.
    mask = np.random.default_rng(seed).random((height, width)) < fill
    found = components(np.flatnonzero(mask), mask.shape)
    labels, count = ndimage.label(mask, structure=np.ones((3, 3)))
    np.testing.assert_array_equal(found.labels, labels)
    assert found.count == count + 1
    assert found.label.dtype == np.int32


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), level=st.floats(1.0, 20.0), factor=st.floats(0.5, 8.0), low=st.booleans())
def test_pixels_above_a_noise_map_are_those_of_the_map_of_products(seed, level, factor, low):
    # The products in float32, as a limit map holds them.  A noise within 20 % of ``level``, or with a patch at the
    # quantisation floor (a saturated bright body's): the least noise's limit lets few pixels through (tested one by
    # one) or more than MAX_CANDIDATE_SHARE of them (compared pixel by pixel); many it lets through the map turns away.
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0.8 * level, level, (40, 60)).astype(np.float32)
    if low:
        noise[:10, :10] = background.QUANTISATION_NOISE_DN
    signal = (rng.normal(0.0, 1.0, noise.shape) * noise).astype(np.float32)
    scale = np.float32(factor)
    limit = np.multiply(noise, scale)
    # signal values placed on the limits themselves and just above them
    signal.ravel()[:50] = limit.ravel()[:50]
    signal.ravel()[50:100] = np.nextafter(limit.ravel()[50:100], np.float32(np.inf))
    np.testing.assert_array_equal(pixels_above(signal, noise, scale), np.flatnonzero(signal > limit))


def test_component_peaks_are_scipys_maxima_the_last_in_raster_order_on_a_tie():
    values = np.array([[1.0, 5.0, 0.0, 2.0], [5.0, 3.0, 0.0, 2.0], [0.0, 0.0, 0.0, 0.0]])
    found = components_above(values, 0.5)
    peak, at = component_peaks(found.label, values.ravel()[found.pixel], found.pixel, found.count)
    np.testing.assert_array_equal(peak[1:], ndimage.maximum(values, found.labels, [1, 2]))
    assert at[1:].tolist() == [4, 7]  # the 5 at (1, 0) after the one at (0, 1); the 2 at (1, 3) after (0, 3)


def gaussian_trail(shape, centre, length_px: float, angle_rad: float, flux: float, sigma_px: float = 1.0):
    """A straight trail (flux DN) of Gaussian spots spaced 0.1 px, centred on ``centre`` (x, y px)."""
    steps = max(1, int(length_px / 0.1))
    t = (np.arange(steps) + 0.5) / steps - 0.5
    xs = centre[0] + t * length_px * math.cos(angle_rad)
    ys = centre[1] + t * length_px * math.sin(angle_rad)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    image = np.zeros(shape)
    for x, y in zip(xs, ys, strict=True):
        image += np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2 * sigma_px**2))
    return image * flux / image.sum()


def test_streak_candidates_find_planted_trails_at_their_centres():
    # A trail matching the filter gives a response symmetric about its centre, so the centroid of the pixels above
    # the threshold is the centre up to the noise's asymmetry: at 40 sigmas and more, well under half a pixel.
    rng = np.random.default_rng(8)
    kernel = gaussian_trail((21, 21), (10.0, 10.0), 12.0, 0.4, 1.0)
    centres = np.array([[60.3, 50.7], [200.6, 140.2], [120.0, 220.5]])
    frame = 100.0 + rng.normal(0.0, 3.0, (300, 280))
    for xy in centres:
        frame += gaussian_trail(frame.shape, xy, 12.0, 0.4, 3000.0)
    found, _, responses = streak_candidates(frame, 100.0, 3.0, kernel, 5.0, 4)
    assert len(found) == 3
    order = np.argsort(found[:, 1])
    assert np.abs(found[order] - centres[np.argsort(centres[:, 1])]).max() < 0.5
    assert np.all(responses > 40.0)


def test_streak_candidates_on_pure_noise_stay_within_the_false_alarm_rate():
    # The response is Gaussian with unit variance at every pixel when the noise is white and its sigma known, so a
    # pixel exceeds 5 sigmas with probability Q(5) = 2.9e-7: on four 512 x 512 frames 0.3 pixels are expected above,
    # and components of 4 pixels or more are rarer still.  Two or more would happen with probability < 4 %
    # (Markov) even if every such pixel made its own component.
    kernel = gaussian_trail((21, 21), (10.0, 10.0), 12.0, 0.4, 1.0)
    expected = 4 * SIZE * SIZE * (1.0 - ndtr(5.0))
    assert expected < 0.31
    total = 0
    for seed in range(4):
        frame = 100.0 + np.random.default_rng(10 + seed).normal(0.0, 3.0, (SIZE, SIZE))
        centroids, _, _ = streak_candidates(frame, 100.0, 3.0, kernel, 5.0, 4)
        total += len(centroids)
    assert total <= 1
    # Below the threshold's implied rate the test could not fail; at 2 sigmas the same frames give thousands.
    frame = 100.0 + np.random.default_rng(10).normal(0.0, 3.0, (SIZE, SIZE))
    assert len(streak_candidates(frame, 100.0, 3.0, kernel, 2.0, 4)[0]) > 100


def test_streak_candidates_drop_a_lone_bright_pixel_only_when_given_the_spot():
    # A single 400 DN pixel is what a hot pixel or a cosmic-ray hit leaves: the 30 px trail filter still responds
    # (the pixel is inside every trail position), the spot filter responds far more (its peak ratio 1 / kappa).
    kernel = gaussian_trail((41, 41), (20.0, 20.0), 30.0, 0.0, 1.0)
    spot = gaussian_trail((7, 7), (3.0, 3.0), 0.0, 0.0, 1.0)
    frame = 100.0 + np.random.default_rng(12).normal(0.0, 3.0, (120, 120))
    frame[60, 60] += 400.0
    assert len(streak_candidates(frame, 100.0, 3.0, kernel, 5.0, 4)[0]) == 1
    assert len(streak_candidates(frame, 100.0, 3.0, kernel, 5.0, 4, spot)[0]) == 0


# --- exposure window of a row ----------------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(t_start=st.floats(0.0, 1e5), exposure=st.floats(1e-6, 10.0), line_time=st.floats(0.0, 1e-3),
       row=st.floats(0.0, 8191.0), height=st.integers(1, 8192))
def test_row_window_is_its_formula_to_rounding(t_start, exposure, line_time, row, height):
    # Exact rational arithmetic as the reference: opens = t + r l and closes = opens + T, each float operation
    # rounded once (half an ulp of its result), so the float results lie within an ulp of the exact values.
    opens, closes = row_window(t_start, exposure, line_time, row)
    exact_opens = Fraction(t_start) + Fraction(row) * Fraction(line_time)
    assert abs(Fraction(opens) - exact_opens) <= Fraction(math.ulp(opens)) + Fraction(math.ulp(row * line_time))
    assert abs(Fraction(closes) - (Fraction(opens) + Fraction(exposure))) <= Fraction(math.ulp(closes)) / 2
    assert closes >= opens
    # The frame's span: the last row's window closes exposure + l (height - 1) after the first row opens.
    span = frame_span_s(exposure, line_time, height)
    assert span == exposure + line_time * (height - 1)
    assert span == row_window(0.0, exposure, line_time, height - 1)[1]


def test_row_windows_of_a_global_shutter_coincide_and_of_a_rolling_one_step_by_the_line_time():
    rows = np.arange(512.0)
    opens, closes = row_window(2.0, 0.004, 0.0, rows)
    assert np.all(opens == 2.0) and np.all(closes == 2.0 + 0.004)
    opens, closes = row_window(2.0, 0.004, 1e-5, rows)
    np.testing.assert_allclose(np.diff(opens), 1e-5, rtol=1e-9)
    np.testing.assert_allclose(closes - opens, 0.004, rtol=1e-12)


@given(st.lists(st.integers(-3, 3), max_size=40))
@settings(max_examples=200, deadline=None)
def test_run_starts_marks_the_first_entry_of_each_run_of_equal_values(values):
    """Against an entry-by-entry walk: an entry starts a run when it is the first or differs from the one before
    (an empty array has no starts)."""
    array = np.array(values, dtype=np.int64)
    expected = [k == 0 or values[k] != values[k - 1] for k in range(len(values))]
    starts = blocks.run_starts(array)
    assert starts.dtype == bool
    assert starts.tolist() == expected
