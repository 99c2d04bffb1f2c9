"""CentroidDetector on simulator frames: sub-pixel accuracy, smeared trails and arcs, real-sky frames, stray light,
hot pixels and cosmic rays, saturation, the image edge, deblending and argument checks."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import cdist

from starenv import scenario
from starenv.agents.base import StarDetector
from starenv.agents.detect import centroid
from starenv.agents.detect.centroid import CentroidDetector
from starenv.sim.conventions import pointing
from starenv.sim.imager import Detector, DetectorSpec
from starenv.sim.motion import ConstantRate, Trajectory
from starenv.sim.optics import Camera
from starenv.sim.photometry import Photometry
from starenv.sim.render import StarRenderer, StarSignal
from starenv.sim.sensor import StarSensor
from starenv.sim.sky import StarCatalog

# Paper 000's camera: f = 49 mm, 20 um pixels, here 512 x 512; 10 ms exposure, PSF sigma 0.8 px.
CAM = Camera.from_focal_length(49e-3, 20e-6, 512, 512)
EXPOSURE = 0.01
SIGMA = 0.8
SKY_E_PER_PX_S = 50.0
QUIET = DetectorSpec(hot_pixel_fraction=0.0, cosmic_ray_rate_per_cm2_s=0.0)
METHODS = ("cog", "iwcog", "gaussian")
GATE_PX = 3.0


def render(xy, magnitude, rate=(0.0, 0.0, 0.0)):
    """Noise-free frame of stars of the given magnitudes imaged at pixel positions ``xy`` (n, 2) at t = 0, the body
    turning at ``rate`` (rad/s) during the exposure."""
    a0 = pointing(1.0, 0.3, 0.0)
    xy = np.atleast_2d(np.asarray(xy, dtype=float))
    n = len(xy)
    catalog = StarCatalog(
        hip=np.arange(1, n + 1),
        magnitude=np.broadcast_to(np.asarray(magnitude, dtype=float), (n,)).copy(),
        unit=a0.inv().apply(CAM.unproject(xy)),
        epoch=2026.0,
    )
    renderer = StarRenderer(catalog, CAM, Photometry(aperture_m=0.035), SIGMA)
    return renderer.render(Trajectory(ConstantRate(np.asarray(rate, dtype=float)), a0), 0.0, EXPOSURE)


def read_out(signal, seed, spec=QUIET):
    """A uint16 frame with the sensor's noise (seeded) for a star signal."""
    detector = Detector(spec, CAM.width, CAM.height, CAM.pixel_pitch_m, SKY_E_PER_PX_S, np.random.default_rng(seed))
    return detector.read_out(signal, EXPOSURE, np.random.default_rng(seed + 1000))


def expected_dn(signal, spec=QUIET):
    """The noise-free frame: expected DN, truncated like the sensor's ADC."""
    return np.floor(signal.image() / spec.gain_e_per_dn + spec.bias_dn).astype(np.uint16)


def nearest_px(stars, xy):
    """Distance (px) from each position in ``xy`` (n, 2) to the nearest detection (inf when there is none)."""
    if len(stars) == 0:
        return np.full(len(np.atleast_2d(xy)), np.inf)
    return cdist(np.atleast_2d(xy), stars.xy).min(axis=1)


def test_it_is_a_star_detector():
    assert isinstance(CentroidDetector(), StarDetector)


@settings(max_examples=25, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_static_star_lands_on_the_truth_at_any_sub_pixel_phase(phase_x, phase_y):
    frame = render([200.0 + phase_x, 300.0 + phase_y], 3.0)
    image = expected_dn(frame.signal)
    for method in METHODS:
        stars = CentroidDetector(method=method, psf_sigma_px=SIGMA).detect(image, CAM)
        assert len(stars) == 1, method
        assert np.hypot(*(stars.xy[0] - frame.truth.xy_centroid[0])) <= 0.05, method


def test_bright_star_with_noise_is_centroided_to_a_few_hundredths_of_a_pixel():
    rng = np.random.default_rng(7)
    errors = {m: [] for m in METHODS}
    for seed in range(12):
        frame = render(rng.uniform([100.0, 100.0], [400.0, 400.0]), 2.5)
        image = read_out(frame.signal, seed)
        for method in METHODS:
            stars = CentroidDetector(method=method, psf_sigma_px=SIGMA).detect(image, CAM)
            assert len(stars) == 1, method
            errors[method].append(np.hypot(*(stars.xy[0] - frame.truth.xy_centroid[0])))
    for method, e in errors.items():
        assert np.sqrt(np.mean(np.square(e))) < 0.04, method
        assert max(e) < 0.1, method


def test_gaussian_fit_and_weighted_centroid_beat_plain_centre_of_gravity_on_a_faint_star():
    rng = np.random.default_rng(11)
    squared = {m: [] for m in METHODS}
    for seed in range(30):
        frame = render(rng.uniform([100.0, 100.0], [400.0, 400.0]), 6.0)  # peak pixel SNR about 5.5
        image = read_out(frame.signal, seed)
        for method in METHODS:
            miss = nearest_px(CentroidDetector(method=method, psf_sigma_px=SIGMA).detect(image, CAM),
                              frame.truth.xy_centroid)
            assert miss[0] < 1.0, method
            squared[method].append(miss[0] ** 2)
    rms = {m: math.sqrt(np.mean(v)) for m, v in squared.items()}
    assert rms["gaussian"] <= rms["cog"]
    assert rms["iwcog"] <= rms["cog"]
    assert rms["gaussian"] < 0.25


TRAILS = {
    # 20 px down the rows in 10 ms (rotation about camera X), and 20 px along the diagonal.
    "rows": ([256.3, 200.7], 0.5, (20.0 / CAM.fx / EXPOSURE, 0.0, 0.0)),
    "diagonal": ([180.6, 300.2], 0.5, (14.14 / CAM.fx / EXPOSURE, 14.14 / CAM.fx / EXPOSURE, 0.0)),
    # 0.5 rad about the boresight at 200 px from the principal point: a 100 px arc.
    "arc": ([CAM.cx + 200.0, CAM.cy + 0.4], -2.0, (0.0, 0.0, 0.5 / EXPOSURE)),
}


@pytest.mark.parametrize("trail", TRAILS)
def test_smeared_trail_centroid_is_the_trail_centroid(trail):
    xy, magnitude, rate = TRAILS[trail]
    frame = render(xy, magnitude, rate)
    truth = frame.truth.xy_centroid[0]
    assert np.hypot(*(frame.truth.xy_end[0] - frame.truth.xy_start[0])) > 19.0
    for method in METHODS:
        detector = CentroidDetector(method=method, psf_sigma_px=SIGMA)
        stars = detector.detect(expected_dn(frame.signal), CAM)
        assert len(stars) == 1, method
        assert np.hypot(*(stars.xy[0] - truth)) <= 0.1, method
        for seed in range(3):
            stars = detector.detect(read_out(frame.signal, seed), CAM)
            assert len(stars) == 1, method
            assert np.hypot(*(stars.xy[0] - truth)) <= 0.1, method


def broken_trails(cuts_px, offset_px=40.0):
    """A noise-free frame with a bright 40 px trail along x and, ``offset_px`` below it, a faint parallel one from
    which the columns within 2.5 px of each of ``cuts_px`` (px along the faint trail from its centroid) are cut (set
    to the bias), as noise breaks a faint trail; returns the frame and the faint trail's truth centroid."""
    rate = (0.0, 40.0 * CAM.pixel_pitch_m / CAM.focal_length_m / EXPOSURE, 0.0)
    centre = np.array([CAM.cx, CAM.cy])
    frame = render([centre, centre + [0.0, offset_px]], [1.0, 3.0], rate)
    faint = frame.truth.xy_centroid[1]
    image = expected_dn(frame.signal)
    assert abs(frame.truth.xy_end[1, 1] - frame.truth.xy_start[1, 1]) < 0.5  # the trail runs along x
    rows = slice(round(faint[1]) - 5, round(faint[1]) + 6)
    for cut in cuts_px:
        columns = np.abs(np.arange(CAM.width) - (faint[0] + cut)) <= 2.5
        image[rows, columns] = QUIET.bias_dn
    return image, faint


def test_streak_linking_joins_the_pieces_of_a_broken_trail_at_its_centroid():
    # Cuts symmetric about the centroid leave pieces whose flux-weighted mean centroid is the trail's.
    image, faint = broken_trails([-8.0, 8.0])
    pieces = CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)
    assert np.sum(np.abs(pieces.xy[:, 1] - faint[1]) < 3.0) == 3
    joined = CentroidDetector(psf_sigma_px=SIGMA, link_streaks=True).detect(image, CAM)
    on_faint = np.abs(joined.xy[:, 1] - faint[1]) < 3.0
    assert on_faint.sum() == 1
    assert np.hypot(*(joined.xy[on_faint][0] - faint)) <= 0.3
    # The bright trail, the guide, is left as it was.
    assert np.allclose(joined.xy[~on_faint], pieces.xy[np.abs(pieces.xy[:, 1] - faint[1]) >= 3.0])


def test_streak_linking_leaves_breaks_longer_than_its_gap_and_parallel_trails_apart():
    # A 20 px break is beyond LINK_GAP_SIGMAS (6 PSF sigmas, ~5 px): two pieces stay two detections.
    image, faint = broken_trails([-10.0, -5.0, 0.0, 5.0])
    stars = CentroidDetector(psf_sigma_px=SIGMA, link_streaks=True).detect(image, CAM)
    assert np.sum(np.abs(stars.xy[:, 1] - faint[1]) < 3.0) == 2
    # Parallel trails 6 px apart are not one trail.
    image, faint = broken_trails([], offset_px=6.0)
    assert len(CentroidDetector(psf_sigma_px=SIGMA, link_streaks=True).detect(image, CAM)) == 2


def test_streak_linking_changes_nothing_on_a_still_frame():
    truth_frame = render([[100.0, 100.0], [105.0, 100.0], [300.0, 200.0]], [4.0, 5.0, 3.0])
    image = read_out(truth_frame.signal, 0)
    plain = CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)
    linked = CentroidDetector(psf_sigma_px=SIGMA, link_streaks=True).detect(image, CAM)
    assert len(plain) == 3 and np.array_equal(plain.xy, linked.xy)


def score(stars, truth, camera, inner_px=8.0):
    """Recall of the detectable stars that stand alone (no other star within 4 px: closer pairs blend at this PSF)
    and clear of the border, precision of the detections (any rendered star within the gate) and the centroid errors
    of the matched detectable stars."""
    separation = cdist(truth.xy_centroid, truth.xy_centroid)
    np.fill_diagonal(separation, np.inf)
    wanted = truth.detectable & (separation.min(axis=1) > 4.0) & camera.in_frame(truth.xy_centroid, -inner_px)
    miss = nearest_px(stars, truth.xy_centroid)
    matched = cdist(stars.xy, truth.xy_centroid).min(axis=1) <= GATE_PX
    return miss[wanted] <= GATE_PX, matched, miss[wanted & (miss <= GATE_PX)]


def test_real_sky_frames_with_hot_pixels_and_cosmic_rays():
    """Paper 000's sensor over Orion (Hipparcos stars to mag 6), with ten times its hot pixels and a hundred times its
    cosmic-ray flux (about five hits per frame)."""
    sc = scenario.load(
        "paper_000",
        {"heads.0.detector.hot_pixel_fraction": 5e-4, "heads.0.detector.cosmic_ray_rate_per_cm2_s": 500.0},
    )
    sensor = StarSensor(sc)
    head = sc.heads[0]
    detector = CentroidDetector(psf_sigma_px=head.psf_sigma_px)
    found, matched, errors = [], [], []
    for _ in range(4):
        frame = sensor.next_frame().heads[0]
        f, m, e = score(detector.detect(frame.image, head.calibrated), frame.truth, head.camera)
        found.append(f)
        matched.append(m)
        errors.append(e)
    found, matched, errors = np.concatenate(found), np.concatenate(matched), np.concatenate(errors)
    assert len(found) > 80
    assert found.mean() >= 0.95
    assert matched.mean() >= 0.95
    assert np.median(errors) < 0.1


def test_stray_light_does_not_flood_the_bright_side_with_false_stars():
    sc = scenario.load("stress_stray_light")
    sensor = StarSensor(sc)
    head = sc.heads[0]
    cam = head.camera
    towards_glow = np.array([math.cos(math.radians(30.0)), math.sin(math.radians(30.0))])
    assert head.stray_light.position_angle_deg == 30.0
    frame = sensor.next_frame().heads[0]
    stars = CentroidDetector(psf_sigma_px=head.psf_sigma_px).detect(frame.image, head.calibrated)
    found, matched, _ = score(stars, frame.truth, cam)
    bright_side = (stars.xy - [cam.cx, cam.cy]) @ towards_glow > 0
    assert bright_side.sum() >= 10
    assert matched[bright_side].mean() >= 0.9
    assert found.mean() >= 0.9


def test_hot_pixels_and_cosmic_rays_alone_are_not_stars():
    spec = DetectorSpec(hot_pixel_fraction=1e-3, cosmic_ray_rate_per_cm2_s=3000.0)  # 260 hot pixels, ~30 hits
    nothing = StarSignal(np.zeros(0, np.int64), np.zeros(0, np.float32), (CAM.height, CAM.width))
    for seed in range(3):
        image = read_out(nothing, seed, spec)
        assert np.count_nonzero(image > spec.bias_dn + 40) > 50  # the defects are there, and bright
        assert len(CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)) == 0
        assert len(CentroidDetector(psf_sigma_px=SIGMA, reject_sharp=False).detect(image, CAM)) > 10


def test_a_long_tracks_remnant_is_dropped_even_where_its_peak_touches_nothing_cleaned(monkeypatch):
    """Seed 9 of long tracks (6 px mean, a hundred times the rate, no star) leaves a remnant whose peak touches no
    pixel the cleaning took off: with the track clause off it is detected, with it (TRACK_PIECES) it is not."""
    spec = DetectorSpec(hot_pixel_fraction=0.0, cosmic_ray_rate_per_cm2_s=3000.0, cosmic_ray_track_px=6.0)
    nothing = StarSignal(np.zeros(0, np.int64), np.zeros(0, np.float32), (CAM.height, CAM.width))
    image = read_out(nothing, 9, spec)
    assert len(CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)) == 0
    monkeypatch.setattr(centroid, "TRACK_PIECES", 10**9)
    assert len(CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)) == 1


def test_a_star_hit_by_a_cosmic_ray_is_still_found_where_it_is():
    frame = render([250.3, 260.6], 4.0)
    image = read_out(frame.signal, 3)
    image[262, 251] += 400  # a hit on the star's wing, brighter than its peak
    stars = CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)
    assert len(stars) == 1
    assert np.hypot(*(stars.xy[0] - frame.truth.xy_centroid[0])) < 0.2


@pytest.mark.parametrize("dx, dy", [(-3, 0), (0, 3), (2, -2), (3, 1)])
def test_a_star_beside_a_hot_pixel_brighter_than_itself_is_still_found(dx, dy):
    """A hot pixel (or a single-pixel hit) a few px from a faint star's centre is cleaned off, and the star, whose
    own peak the spike does not touch, is no track's remnant however much brighter the spike was."""
    frame = render([250.3, 260.6], 6.0)
    image = read_out(frame.signal, 3).astype(np.int64)
    star_dn = int((expected_dn(frame.signal) - QUIET.bias_dn).sum())
    image[261 + dy, 250 + dx] += 3 * star_dn
    stars = CentroidDetector(psf_sigma_px=SIGMA).detect(image.astype(np.uint16), CAM)
    assert len(stars) == 1
    assert np.hypot(*(stars.xy[0] - frame.truth.xy_centroid[0])) < 0.3


def test_saturated_star_is_found_and_centroided():
    frame = render([300.4, 250.7], -1.0)
    image = read_out(frame.signal, 5)
    top = QUIET.max_dn
    assert np.count_nonzero(image == top) >= 3
    for method in METHODS:
        for detector in (CentroidDetector(method=method, psf_sigma_px=SIGMA),
                         CentroidDetector(method=method, psf_sigma_px=SIGMA, saturation_dn=top)):
            stars = detector.detect(image, CAM)
            assert len(stars) == 1, method
            assert np.hypot(*(stars.xy[0] - frame.truth.xy_centroid[0])) < 0.3, method


def test_star_cut_by_the_edge_is_left_out_unless_asked_for():
    frame = render([[1.5, 250.5], [100.3, 250.5]], 4.0)
    image = read_out(frame.signal, 2)
    edge, inner = frame.truth.xy_centroid
    default = CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)
    assert len(default) == 1 and np.hypot(*(default.xy[0] - inner)) < 0.2
    kept = CentroidDetector(psf_sigma_px=SIGMA, keep_edge=True).detect(image, CAM)
    assert len(kept) == 2
    assert nearest_px(kept, edge)[0] < 1.0


def test_a_bright_star_whose_wings_reach_the_border_is_kept_unbiased_and_a_trail_running_off_it_is_not():
    """The border rule bounds what a blob loses beyond the border: a bright spot 3.3 px (4.5 PSF sigmas) inside,
    whose wings stand far above the noise within the growth margin (2 px) of the border, loses next to nothing
    and is kept, centroided as well as a free spot (the 0.05 px of the bright-star test); a faint spot 1.2 px
    inside, and a trail that runs off the top of the frame, are left out (kept with ``keep_edge``)."""
    frame = render([[3.3, 250.5]], 2.5)
    assert int(expected_dn(frame.signal)[250, 2]) - QUIET.bias_dn > 100
    for seed in range(5):
        stars = CentroidDetector(psf_sigma_px=SIGMA).detect(read_out(frame.signal, seed), CAM)
        assert len(stars) == 1 and nearest_px(stars, frame.truth.xy_centroid)[0] < 0.05
    faint = render([[1.2, 250.5]], 6.0)
    assert len(CentroidDetector(psf_sigma_px=SIGMA).detect(read_out(faint.signal, 0), CAM)) == 0
    trail = render([[256.3, 8.0]], 0.5, (-20.0 / CAM.fx / EXPOSURE, 0.0, 0.0))
    assert trail.truth.xy_end[0, 1] < -10.0
    for seed in range(3):
        image = read_out(trail.signal, seed)
        assert len(CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)) == 0
        assert len(CentroidDetector(psf_sigma_px=SIGMA, keep_edge=True).detect(image, CAM)) == 1


def test_stars_come_brightest_first_and_max_stars_keeps_the_brightest():
    xy = [[100.2, 100.7], [300.5, 200.1], [400.8, 420.3]]
    frame = render(xy, [5.0, 3.0, 4.0])
    image = read_out(frame.signal, 4)
    stars = CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)
    assert len(stars) == 3
    assert np.all(np.diff(stars.flux) < 0)
    np.testing.assert_allclose(stars.xy, frame.truth.xy_centroid[[1, 2, 0]], atol=0.2)
    # Flux in DN above background: the star's electrons over the gain, less what falls outside the window.
    np.testing.assert_allclose(stars.flux, frame.truth.electrons[[1, 2, 0]] / QUIET.gain_e_per_dn, rtol=0.1)
    top2 = CentroidDetector(psf_sigma_px=SIGMA, max_stars=2).detect(image, CAM)
    np.testing.assert_array_equal(top2.xy, stars.xy[:2])


def test_close_pair_is_split_into_two_stars():
    xy = np.array([[200.3, 300.6], [204.3, 303.6]])  # 5 px apart
    frame = render(xy, [4.0, 5.0])
    image = read_out(frame.signal, 3)
    stars = CentroidDetector(psf_sigma_px=SIGMA).detect(image, CAM)
    assert len(stars) == 2
    assert np.all(nearest_px(stars, frame.truth.xy_centroid) < 0.15)
    assert len(CentroidDetector(psf_sigma_px=SIGMA, deblend_contrast=1.0).detect(image, CAM)) == 1


def test_background_follows_a_gradient_and_measures_the_noise():
    rows, cols = np.mgrid[0:CAM.height, 0:CAM.width]
    level = 300.0 + 0.2 * cols - 0.1 * rows + 2e-4 * (cols - 100.0) ** 2
    image = np.random.default_rng(0).normal(level, 3.0).astype(np.float32)
    estimate, noise = CentroidDetector().background(image)
    assert np.max(np.abs(estimate - level)) < 1.0
    assert np.median(noise) == pytest.approx(3.0, rel=0.05)


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("method", "moments"),
        ("threshold_sigma", 0.0),
        ("threshold_sigma", float("nan")),
        ("psf_sigma_px", 0.0),
        ("matched_filter", 1),
        ("tile_px", 4),
        ("tile_px", 31.5),
        ("clip_sigma", 1.0),
        ("min_area_px", 0),
        ("max_area_px", 1),
        ("deblend_contrast", 0.0),
        ("deblend_contrast", 1.5),
        ("window_margin_px", -1),
        ("reject_sharp", "yes"),
        ("keep_edge", None),
        ("saturation_dn", 70000),
        ("max_stars", 0),
        ("link_streaks", 1),
    ],
)
def test_bad_options_are_refused_by_name(option, value):
    kwargs = {"min_area_px": 2} if option == "max_area_px" else {}
    with pytest.raises(ValueError, match=option):
        CentroidDetector(**{option: value}, **kwargs)


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((CAM.height, CAM.width, 3), np.uint16),
        np.full((CAM.height, CAM.width), np.nan, np.float32),  # float images (restored frames) must be finite
        np.zeros((CAM.height, CAM.width), bool),
        np.zeros((CAM.height - 1, CAM.width), np.uint16),
        [[0] * CAM.width] * CAM.height,
    ],
)
def test_bad_images_are_refused(image):
    with pytest.raises(ValueError, match="image"):
        CentroidDetector().detect(image, CAM)
