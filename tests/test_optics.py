import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from starenv.sim.conventions import pointing, radec_to_unit
from starenv.sim.optics import (
    BrownConrady,
    Camera,
    LegendreField,
    NoDistortion,
    RadialXY,
    legendre_basis,
    legendre_mode_count,
)

PAPER_003_FIELD = LegendreField(
    coeffs_x=(0.1, 0.8, -0.3, 0.2, 0.15, -0.1, 0.05, 0.0, 0.02, -0.04),
    coeffs_y=(-0.2, 0.1, 0.7, -0.1, 0.1, 0.2, 0.0, 0.03, -0.02, 0.01),
)
MODELS = [
    NoDistortion(),
    BrownConrady(k1=-0.12, k2=0.05, k3=-0.01, p1=1e-3, p2=-5e-4),
    RadialXY(kx=2e-7, ky=-1.5e-7),
    PAPER_003_FIELD,
]


def paper_000_camera(distortion=None):
    distortion = NoDistortion() if distortion is None else distortion
    return Camera.from_focal_length(49e-3, 20e-6, 512, 512, distortion=distortion)


def test_fov_of_the_paper_cameras():
    # Paper 000: 865 px of 20 um behind f = 49 mm span 2 atan(8.65 mm / 49 mm) = 20.02 deg.
    full = Camera.from_focal_length(49e-3, 20e-6, 865, 865)
    assert math.degrees(full.fov[0]) == pytest.approx(2 * math.degrees(math.atan(8.65 / 49)), abs=1e-9)
    # Paper 004: 512 px of 8 um behind f = 39.078 mm is a 6.0000 deg field.
    head = Camera.from_focal_length(39.078e-3, 8e-6, 512, 512)
    assert math.degrees(head.fov[0]) == pytest.approx(6.0, abs=1e-4)
    # from_fov inverts it.
    assert math.degrees(Camera.from_fov(20.0, 2048, 2048, 7.45e-6).fov[0]) == pytest.approx(20.0, abs=1e-9)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: type(m).__name__)
@settings(max_examples=60, deadline=None)
@given(u=st.floats(0, 511), v=st.floats(0, 511))
def test_unproject_then_project_round_trips(model, u, v):
    cam = paper_000_camera(model)
    ray = cam.unproject(np.array([[u, v]]))
    assert np.linalg.norm(ray) == pytest.approx(1.0, abs=1e-12)
    xy, front = cam.project(ray)
    assert front.all()
    np.testing.assert_allclose(xy, [[u, v]], atol=1e-7)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: type(m).__name__)
@settings(max_examples=60, deadline=None)
@given(x=st.floats(-0.1, 0.1), y=st.floats(-0.1, 0.1))
def test_project_then_unproject_round_trips(model, x, y):
    cam = paper_000_camera(model)
    ray = np.array([[x, y, 1.0]]) / math.sqrt(x * x + y * y + 1)
    xy, _ = cam.project(ray)
    np.testing.assert_allclose(cam.unproject(xy), ray, atol=1e-11)


def test_brown_conrady_matches_opencv():
    cam = paper_000_camera(BrownConrady(k1=-0.2, k2=0.08, k3=-0.02, p1=2e-3, p2=-1e-3))
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-0.1, 0.1, (50, 2)), np.ones(50)])
    ours, _ = cam.project(pts)
    kmat = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    d = cam.distortion
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), kmat, np.array([d.k1, d.k2, d.p1, d.p2, d.k3]))
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-9)


def test_radial_xy_correction_is_paper_000_eq_1():
    model = RadialXY(kx=3e-7, ky=-2e-7)
    cam = paper_000_camera(model)
    measured = np.array([[10.0, 480.0], [300.0, 20.0]])
    dx, dy = measured[:, 0] - cam.cx, measured[:, 1] - cam.cy
    r2 = dx**2 + dy**2
    expected = np.column_stack([cam.cx + dx * (1 + 3e-7 * r2), cam.cy + dy * (1 - 2e-7 * r2)])
    np.testing.assert_allclose(model.undistort(measured, cam.intrinsics), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(model.distort(expected, cam.intrinsics), measured, atol=1e-8)


def test_legendre_basis_is_orthonormal_and_matches_paper_003_eq_12():
    order = 5
    assert legendre_mode_count(order) == 21
    nodes, weights = np.polynomial.legendre.leggauss(12)
    gx, gy = np.meshgrid(nodes, nodes)
    gw = np.outer(weights, weights).ravel()
    b = legendre_basis(gx.ravel(), gy.ravel(), order)
    gram = (b * gw[:, None]).T @ b
    np.testing.assert_allclose(gram, np.eye(21), atol=1e-12)
    x, y = 0.3, -0.7
    b = legendre_basis(np.array([x]), np.array([y]), 2)[0]
    # Eq. 12's first modes, with L2 = (sqrt 5 / 2)(3x^2 - 1)/2 ... times L0 = 1/sqrt 2.
    expected = {
        0: 0.5,
        1: math.sqrt(3) / 2 * x,
        2: math.sqrt(3) / 2 * y,
        3: math.sqrt(5) / 4 * (3 * x * x - 1),
        4: 1.5 * x * y,
        5: math.sqrt(5) / 4 * (3 * y * y - 1),
    }
    for m, val in expected.items():
        assert b[m] == pytest.approx(val, abs=1e-14)


def test_legendre_field_shifts_by_the_constant_mode():
    # Mode 0 is the constant 1/2: weight w shifts every point by w/2 pixels.
    cam = paper_000_camera(LegendreField(coeffs_x=(2.0, 0, 0), coeffs_y=(-4.0, 0, 0)))
    xy = np.array([[3.0, 4.0], [500.0, 12.0]])
    np.testing.assert_allclose(cam.distortion.distort(xy, cam.intrinsics), xy + [1.0, -2.0], atol=1e-12)


def test_pointing_puts_the_target_on_the_boresight_north_up_east_left():
    ra, dec = math.radians(83.8), math.radians(-5.4)
    cam_att = pointing(ra, dec, 0.0)
    np.testing.assert_allclose(cam_att.apply(radec_to_unit(ra, dec)), [0, 0, 1], atol=1e-15)
    cam = paper_000_camera()
    north, _ = cam.project(cam_att.apply(radec_to_unit(ra, dec + 0.01)))
    east, _ = cam.project(cam_att.apply(radec_to_unit(ra + 0.01, dec)))
    assert north[0, 1] < cam.cy and abs(north[0, 0] - cam.cx) < 1e-9
    assert east[0, 0] < cam.cx
    # Positive roll turns the camera about +Z by roll: the sky turns by -roll in the image.
    rolled = pointing(ra, dec, math.radians(90.0))
    north_rolled, _ = cam.project(rolled.apply(radec_to_unit(ra, dec + 0.01)))
    assert north_rolled[0, 0] < cam.cx and abs(north_rolled[0, 1] - cam.cy) < 1e-6


def test_paper_004_orthogonal_heads_are_expressible():
    mounts = [
        np.eye(3),
        np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]]),
        np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0.0]]),
    ]
    heads = [
        Camera.from_focal_length(39.078e-3, 8e-6, 512, 512, mounting=Rotation.from_matrix(m)) for m in mounts
    ]
    boresights = np.array([h.mounting.inv().apply([0, 0, 1]) for h in heads])
    np.testing.assert_allclose(boresights, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-15)
    np.testing.assert_allclose(boresights @ boresights.T, np.eye(3), atol=1e-15)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"fov_deg": 180.0}, "fov_deg"),
        ({"fov_deg": 200.0}, "fov_deg"),
        ({"fov_deg": float("nan")}, "fov_deg"),
        ({"fov_deg": 20.0, "pixel_pitch_m": -1e-6}, "pixel_pitch_m"),
    ],
)
def test_bad_camera_input_names_the_parameter(kwargs, name):
    args = {"width": 512, "height": 512, "pixel_pitch_m": 20e-6} | kwargs
    with pytest.raises(ValueError, match=name):
        Camera.from_fov(**args)


def test_behind_the_camera_is_masked():
    xy, front = paper_000_camera().project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert front.tolist() == [False, True]
    assert np.isnan(xy[0]).all()


def test_radial_xy_closed_form_jacobian_matches_central_differences():
    from starenv.sim.optics import _central_jacobian

    model = RadialXY(kx=3e-7, ky=-2e-7, center=(250.0, 260.0))
    k = paper_000_camera(model).intrinsics
    pts = np.random.default_rng(3).uniform(0, 511, (20, 2))
    exact = model._undistort_jacobian(pts, k)
    numeric = _central_jacobian(lambda p: model.undistort(p, k), pts)
    for a, b in zip(exact, numeric, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8)
