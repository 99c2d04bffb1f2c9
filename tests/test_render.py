"""Renderer against closed forms: paper 000's smear lengths (Eqs. 11, 18), arc geometry, signal conservation."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import erf

from starenv.sim import render
from starenv.sim.conventions import DEG, pointing, radec_to_unit
from starenv.sim.motion import ConstantRate, Trajectory
from starenv.sim.optics import Camera
from starenv.sim.photometry import Photometry
from starenv.sim.render import PSF_RADIUS_SIGMA, StarRenderer
from starenv.sim.sky import StarCatalog

# Paper 000's camera: f = 49 mm, 20 um pixels (2450 px focal length), here a 512 x 512 sensor; 10 ms exposure.
CAM = Camera.from_focal_length(49e-3, 20e-6, 512, 512)
EXPOSURE = 0.01
SIGMA = 0.8
BORESIGHT_RA, BORESIGHT_DEC = 1.0, 0.3  # rad


def one_star_renderer(xy_ideal, line_time_s=0.0, sigma=SIGMA):
    """A renderer whose catalog holds one magnitude-5 star imaged at ``xy_ideal`` (px) at t = 0."""
    a0 = pointing(BORESIGHT_RA, BORESIGHT_DEC, 0.0)
    ray = CAM.unproject(np.array([xy_ideal], dtype=float))
    star = a0.inv().apply(ray)
    catalog = StarCatalog(hip=np.array([1]), magnitude=np.array([5.0]), unit=star, epoch=2026.0)
    return StarRenderer(catalog, CAM, Photometry(aperture_m=0.035), sigma, line_time_s), a0


def moments(img):
    """Centroid (x, y) and 2x2 covariance of an image's intensity."""
    ys, xs = np.indices(img.shape)
    total = img.sum(dtype=np.float64)
    c = np.array([(xs * img).sum(dtype=np.float64), (ys * img).sum(dtype=np.float64)]) / total
    dx, dy = xs - c[0], ys - c[1]
    cov = np.array([[(dx * dx * img).sum(), (dx * dy * img).sum()], [(dx * dy * img).sum(), (dy * dy * img).sum()]])
    return c, cov / total


def test_static_star_on_the_boresight_lands_on_the_principal_point():
    renderer, a0 = one_star_renderer((CAM.cx, CAM.cy))
    frame = renderer.render(Trajectory(ConstantRate([0, 0, 0]), a0), 0.0, EXPOSURE)
    assert frame.n_instants == 1
    np.testing.assert_allclose(frame.truth.xy_mid[0], [CAM.cx, CAM.cy], atol=1e-9)
    c, cov = moments(frame.signal.image())
    np.testing.assert_allclose(c, [CAM.cx, CAM.cy], atol=0.01)
    # A Gaussian integrated over pixels has variance sigma^2 + 1/12 px^2 at the pixel centres.
    np.testing.assert_allclose(np.diag(cov), SIGMA**2 + 1 / 12, rtol=1e-3)


@pytest.mark.parametrize(
    ("axis", "alpha_deg"),
    [(0, 0.0), (0, 4.0), (1, 0.0), (1, -4.0), (0, 5.0)],
)
def test_cross_boresight_smear_matches_paper_000_eq_11(axis, alpha_deg):
    """Rotation about camera X moves stars along rows (v); about Y along columns (u); L = f (tan^2 a + 1) da / d."""
    rate_dps = 70.0  # 0.7 deg over 10 ms: about 30 px on the boresight
    f_over_d = CAM.fx
    offset = f_over_d * math.tan(math.radians(alpha_deg))
    start = (CAM.cx, CAM.cy + offset) if axis == 0 else (CAM.cx + offset, CAM.cy)
    renderer, a0 = one_star_renderer(start)
    w = np.zeros(3)
    w[axis] = rate_dps * DEG
    frame = renderer.render(Trajectory(ConstantRate(w), a0), 0.0, EXPOSURE)
    d_alpha = rate_dps * DEG * EXPOSURE
    alpha = math.radians(alpha_deg)
    eq11 = f_over_d * (math.tan(alpha) ** 2 + 1) * d_alpha
    trail = frame.truth.xy_end[0] - frame.truth.xy_start[0]
    assert np.linalg.norm(trail) == pytest.approx(eq11, rel=0.01)
    # Direction: d v_cam / dt = -w x v_cam, so +w_x drives stars down the rows (+v), +w_y left (-u).
    expected_dir = np.array([0.0, 1.0]) if axis == 0 else np.array([-1.0, 0.0])
    np.testing.assert_allclose(trail / np.linalg.norm(trail), expected_dir, atol=1e-9)
    # The rendered image itself: a uniform line of length L blurred by the pixel-integrated PSF has variance
    # L^2/12 + sigma^2 + 1/12 along the trail.
    img = frame.signal.image()
    _, cov = moments(img)
    along = cov[1, 1] if axis == 0 else cov[0, 0]
    across = cov[0, 0] if axis == 0 else cov[1, 1]
    length_from_image = math.sqrt(12 * (along - SIGMA**2 - 1 / 12))
    assert length_from_image == pytest.approx(np.linalg.norm(trail), rel=0.01)
    assert across == pytest.approx(SIGMA**2 + 1 / 12, rel=0.01)


def test_boresight_roll_draws_an_arc_matching_paper_000_eq_18():
    """About Z a star at radius r sweeps an arc; Eq. 18's chord is |w_z| dt r (to first order)."""
    r = 200.0
    renderer, a0 = one_star_renderer((CAM.cx + r, CAM.cy))
    wz = 0.5 / EXPOSURE  # sweep 0.5 rad: a 100 px arc
    frame = renderer.render(Trajectory(ConstantRate([0, 0, wz]), a0), 0.0, EXPOSURE)
    t = frame.truth
    chord = np.linalg.norm(t.xy_end[0] - t.xy_start[0])
    assert chord == pytest.approx(2 * r * math.sin(0.25), rel=1e-9)  # exact chord of the arc
    assert chord == pytest.approx(abs(wz) * EXPOSURE * r, rel=0.011)  # Eq. 18: the chord ~ arc, 1 % at 0.5 rad
    # Every point of the trail stays on the circle (no straight-kernel approximation) ...
    for xy in (t.xy_start[0], t.xy_mid[0], t.xy_end[0]):
        assert math.hypot(xy[0] - CAM.cx, xy[1] - CAM.cy) == pytest.approx(r, abs=1e-6)
    # ... and the image's centroid is the arc's: r sin(theta/2)/(theta/2) from the centre, 2.08 px inside the chord's
    # distance from a straight segment's midpoint would be r cos(theta/2).
    c, _ = moments(frame.signal.image())
    arc_centroid_radius = r * math.sin(0.25) / 0.25
    assert math.hypot(c[0] - CAM.cx, c[1] - CAM.cy) == pytest.approx(arc_centroid_radius, abs=0.01)
    assert math.hypot(*(t.xy_centroid[0] - [CAM.cx, CAM.cy])) == pytest.approx(arc_centroid_radius, abs=1e-4)
    # +w_z turns the image by -w_z t about the principal point: the star at +X moves towards -Y (up).
    assert t.xy_end[0][1] < CAM.cy


@pytest.mark.parametrize("rate_dps", [0.0, 5.0, 40.0, 150.0])
def test_smearing_conserves_the_signal(rate_dps):
    renderer, a0 = one_star_renderer((CAM.cx - 20, CAM.cy + 10))
    w = np.array([1.0, -0.6, 0.8]) * rate_dps * DEG
    frame = renderer.render(Trajectory(ConstantRate(w), a0), 0.0, EXPOSURE)
    expected = renderer.electrons_per_s[0] * EXPOSURE
    total = frame.signal.image().sum(dtype=np.float64)
    assert total == pytest.approx(expected, rel=1e-5)
    assert frame.truth.electrons[0] == pytest.approx(expected, rel=1e-5)


@pytest.mark.parametrize("edge_xy", [(0.2, 300.0), (511.4, 40.0), (200.0, -0.3), (511.7, 511.2)])
def test_light_beyond_the_sensor_edge_is_lost_and_the_rest_kept(edge_xy):
    """Two still stars rendered together (the same window size, so one batch): one straddling an edge or a corner,
    one inside.  The inside one keeps all its light; the edge one keeps the pixel-integrated Gaussian's share over
    the sensor's pixels, ``prod(Phi((size - 1/2 - c) / sigma) - Phi((-1/2 - c) / sigma))``, and no pixel of either
    lies outside its own neighbourhood (light wrapped to the far side of the frame would)."""
    a0 = pointing(BORESIGHT_RA, BORESIGHT_DEC, 0.0)
    xy = np.array([edge_xy, (CAM.cx + 40.3, CAM.cy - 25.6)])
    catalog = StarCatalog(hip=np.array([1, 2]), magnitude=np.array([5.0, 5.0]),
                          unit=a0.inv().apply(CAM.unproject(xy)), epoch=2026.0)
    renderer = StarRenderer(catalog, CAM, Photometry(aperture_m=0.035), SIGMA)
    frame = renderer.render(Trajectory(ConstantRate([0, 0, 0]), a0), 0.0, EXPOSURE)
    total = renderer.electrons_per_s[0] * EXPOSURE
    order = np.argsort(frame.truth.catalog_id)
    np.testing.assert_allclose(frame.truth.xy_mid[order], xy, atol=1e-6)

    def phi(z):
        return 0.5 * (1.0 + erf(z / (SIGMA * math.sqrt(2.0))))

    sizes = (CAM.width, CAM.height)
    share = np.prod([phi(size - 0.5 - c) - phi(-0.5 - c) for c, size in zip(edge_xy, sizes, strict=True)])
    assert share < 0.9  # the case does cut light
    np.testing.assert_allclose(frame.truth.electrons[order], [total * share, total], rtol=1e-4)
    image = frame.signal.image()
    rows, cols = np.divmod(frame.signal.index, CAM.width)
    near = [np.hypot(cols - x, rows - y) <= PSF_RADIUS_SIGMA * SIGMA * math.sqrt(2.0) + 1.0 for x, y in xy]
    assert np.all(near[0] | near[1])
    np.testing.assert_allclose(image.sum(dtype=np.float64), total * (share + 1.0), rtol=1e-4)
    peak = frame.truth.peak_electrons[order][0]
    assert peak == pytest.approx(image.ravel()[frame.signal.index[near[0]]].max(), rel=1e-6)  # (float32 signal)


def test_sub_steps_follow_the_rate():
    renderer, a0 = one_star_renderer((CAM.cx, CAM.cy))
    counts = [renderer.render(Trajectory(ConstantRate([r * DEG, 0, 0]), a0), 0.0, EXPOSURE).n_instants
              for r in (1.0, 10.0, 100.0)]
    assert counts[0] < counts[1] < counts[2]
    corner = CAM.half_diagonal
    smear_bound = 100 * DEG * EXPOSURE * CAM.fx * (1 + math.tan(corner) ** 2)
    assert counts[2] >= smear_bound / renderer.max_step_px  # instants at most max_step_px apart everywhere
    assert renderer.max_step_px == min(SIGMA, 0.5)


def test_rolling_shutter_delays_each_row():
    """With a rolling shutter a star on row v is exposed v * line_time later, so it is seen further along."""
    line_time = 20e-6
    v0 = 400.0
    global_r, a0 = one_star_renderer((CAM.cx, v0))
    rolling_r, _ = one_star_renderer((CAM.cx, v0), line_time_s=line_time)
    w = np.array([0.0, 30 * DEG, 0.0])  # moves stars along -u, not across rows
    traj = Trajectory(ConstantRate(w), a0)
    g = global_r.render(traj, 0.0, EXPOSURE).truth
    r = rolling_r.render(traj, 0.0, EXPOSURE).truth
    du_dt = (g.xy_end[0, 0] - g.xy_start[0, 0]) / EXPOSURE
    delay = (r.xy_mid[0, 1]) * line_time
    assert r.xy_mid[0, 0] - g.xy_mid[0, 0] == pytest.approx(du_dt * delay, rel=1e-3)


def test_real_sky_frame_has_hipparcos_stars_where_the_catalog_says():
    from starenv.sim.sky import load_catalog

    cat = load_catalog(6.0)
    ra, dec = math.radians(83.8), math.radians(-5.4)  # Orion
    renderer = StarRenderer(cat, CAM, Photometry(0.035), SIGMA)
    a0 = pointing(ra, dec, 0.0)
    frame = renderer.render(Trajectory(ConstantRate([0, 0, 0]), a0), 0.0, EXPOSURE)
    assert len(frame.truth) > 10
    # Independent projection of the truth stars with the pinhole formula.
    idx = np.searchsorted(cat.hip, frame.truth.catalog_id)
    v = a0.apply(cat.unit[idx])
    xy = np.stack([CAM.fx * v[:, 0] / v[:, 2] + CAM.cx, CAM.fy * v[:, 1] / v[:, 2] + CAM.cy], 1)
    np.testing.assert_allclose(frame.truth.xy_mid, xy, atol=1e-9)
    # Mintaka (HIP 25930, delta Ori, at RA 83.00 deg, Dec -0.30 deg) is 5.2 deg north of the boresight: out of the
    # 5.95 deg half-field? It is inside, up in the image (north up).
    assert 25930 in frame.truth.catalog_id
    mintaka = frame.truth.xy_mid[list(frame.truth.catalog_id).index(25930)]
    assert mintaka[1] < CAM.cy - 200
    np.testing.assert_allclose(
        a0.apply(radec_to_unit(math.radians(83.8), math.radians(-5.4))), [0, 0, 1], atol=1e-12
    )


def test_bad_exposure_is_refused():
    renderer, a0 = one_star_renderer((CAM.cx, CAM.cy))
    traj = Trajectory(ConstantRate([0, 0, 0]), a0)
    for bad in (-0.01, 0.0, float("nan")):
        with pytest.raises(ValueError, match="exposure_s"):
            renderer.render(traj, 0.0, bad)


def test_mounting_rotates_what_a_head_sees():
    """A head mounted looking along body -X sees the star on body -X on its boresight."""
    mount = Rotation.from_matrix(np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]]))
    head = Camera.from_focal_length(39.078e-3, 8e-6, 512, 512, mounting=mount)
    body = Rotation.identity()
    star = np.array([[-1.0, 0.0, 0.0]])
    catalog = StarCatalog(hip=np.array([7]), magnitude=np.array([4.0]), unit=star, epoch=2026.0)
    frame = StarRenderer(catalog, head, Photometry(0.03), 1.0).render(
        Trajectory(ConstantRate([0, 0, 0]), body), 0.0, 0.05
    )
    np.testing.assert_allclose(frame.truth.xy_mid[0], [head.cx, head.cy], atol=1e-9)


def direct_trail_image(renderer, traj, exposure):
    """Independent expected image of a one-star global-shutter frame: a loop over the renderer's midpoint instants,
    each adding the star's electrons / n times the Gaussian integrated over every pixel of its n_band x n_band band,
    from erf at the pixel edges (no tabulation, no matrix products, no scatter)."""
    n = renderer._instants(traj, 0.0, exposure)
    times = exposure * (np.arange(n) + 0.5) / n
    v = CAM.inertial_to_camera(traj.attitude(times)).apply(renderer.catalog.unit[0].copy())
    xy = np.stack([CAM.fx * v[:, 0] / v[:, 2] + CAM.cx, CAM.fy * v[:, 1] / v[:, 2] + CAM.cy], 1)  # pinhole
    sigma = renderer.psf_sigma_px
    radius = PSF_RADIUS_SIGMA * sigma
    n_band = math.ceil(2 * radius) + 2
    weight = renderer.electrons_per_s[0] * exposure / n
    image = np.zeros((CAM.height, CAM.width))
    for x, y in xy:
        c0, r0 = math.floor(x - radius), math.floor(y - radius)
        cx = np.arange(c0, c0 + n_band + 1) - 0.5  # pixel edges
        ry = np.arange(r0, r0 + n_band + 1) - 0.5
        fx = 0.5 * np.diff(erf((cx - x) / (math.sqrt(2) * sigma)))
        fy = 0.5 * np.diff(erf((ry - y) / (math.sqrt(2) * sigma)))
        image[r0 : r0 + n_band, c0 : c0 + n_band] += weight * np.outer(fy, fx)  # the test keeps the band on-sensor
    return image, xy


@pytest.mark.parametrize(
    ("rate_dps", "path"),
    [(3.0, "_patches_matmul"), (25.0, "_patches_matmul"), (300.0, "_patches_scatter"), (600.0, "_patches_scatter")],
)
def test_trail_image_matches_a_direct_per_instant_sum(monkeypatch, rate_dps, path):
    """Short trails (~1 and ~12 px: window matrix products) and long ones (~150 and ~300 px: per-instant scatter)
    against :func:`direct_trail_image`.  The renderer tabulates the pixel fractions (linear interpolation error < 1e-8
    of the light per pixel and instant), so each pixel may differ by up to ~2e-8 of the star's electrons, on top of
    the float32 rounding of the image (6e-8 relative)."""
    renderer, a0 = one_star_renderer((CAM.cx - 120, CAM.cy - 90))
    traj = Trajectory(ConstantRate(np.array([1.0, -0.6, 0.4]) * rate_dps * DEG), a0)
    used = []
    for name in ("_patches_matmul", "_patches_scatter"):
        fn = getattr(render, name)
        monkeypatch.setattr(render, name, lambda *a, _fn=fn, _name=name: used.append(_name) or _fn(*a))
    frame = renderer.render(traj, 0.0, EXPOSURE)
    assert used == [path]
    expected, xy = direct_trail_image(renderer, traj, EXPOSURE)
    assert frame.n_instants == len(xy)
    total = renderer.electrons_per_s[0] * EXPOSURE
    trail = np.linalg.norm(xy[-1] - xy[0])
    assert trail < 15 if path == "_patches_matmul" else trail > 140  # the lengths the docstring gives
    image = frame.signal.image()
    np.testing.assert_allclose(image, expected, rtol=1e-6, atol=2e-8 * total)
    # Per star the tabulated fractions' sum is 1 less the light beyond the band (7e-6), so its curvature in the phase
    # is of that order and its linear interpolation error (step^2 / 8 times the curvature, step 1 / BAND_TABLE_STEPS)
    # is ~1e-13, far inside 1e-10; the peak pixel is float64, so only the ~1e-8 tabulation error is left.
    assert frame.truth.electrons[0] == pytest.approx(expected.sum(), rel=1e-10)
    assert frame.truth.peak_electrons[0] == pytest.approx(expected.max(), rel=1e-7)
    # Only pixels above MIN_ELECTRONS are listed, and those are all of the direct sum's pixels above it.
    np.testing.assert_array_equal(np.sort(frame.signal.index), np.flatnonzero(expected.ravel() > render.MIN_ELECTRONS))


@pytest.mark.parametrize("chunk", [render.SCATTER_CHUNK, 5000])
def test_scatter_and_matmul_patches_agree(monkeypatch, chunk):
    """The two ways of summing a batch's instants give the same patches to float64 rounding, however many stars one
    np.bincount call takes (a 5000-term chunk takes one star of 30 instants x 121 band pixels per call)."""
    monkeypatch.setattr(render, "SCATTER_CHUNK", chunk)
    rng = np.random.default_rng(3)
    m, k, n_band, h, w = 4, 30, 11, 40, 48
    offset = np.stack([rng.integers(0, w - n_band + 1, (m, k)), rng.integers(0, h - n_band + 1, (m, k))], -1)
    frac = rng.uniform(0.0, 1.0, (m, k, 2, n_band)) * rng.uniform(1.0, 1e4, (m, 1, 1, 1))
    a = render._patches_matmul(offset, frac, h, w)
    b = render._patches_scatter(offset, frac, h, w)
    np.testing.assert_allclose(b, a, rtol=1e-13, atol=0)
    np.testing.assert_allclose(b.sum(axis=(1, 2)), (frac[:, :, 0].sum(-1) * frac[:, :, 1].sum(-1)).sum(1), rtol=1e-13)
