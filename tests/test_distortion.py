"""Paper 003's distortion types against their closed forms, and the 2-D Legendre model (basis, least squares, torch)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from starenv import scenario as scenario_mod
from starenv.sim.optics import (
    DISTORTION_PRESETS,
    Composite,
    Intrinsics,
    Perspective,
    Radial,
    Shear,
    Tangential,
    ThinPrism,
    legendre_basis,
)

K = Intrinsics(5798.7, 5798.7, 1023.5, 1023.5, 2048, 2048)  # paper 003's head: s = 1024 px
S = 1024.0
coord = st.floats(-1.0, 1.0)


def _at(x, y):
    return np.array([[K.cx + S * x, K.cy + S * y]])


@settings(max_examples=40, deadline=None)
@given(coord, coord)
def test_each_type_matches_its_closed_form(x, y):
    r2 = x * x + y * y
    q1, q2, p1, p2, s1, s2 = -1.6e-3, -3.5e-4, 4e-4, 8e-4, 1.2e-3, 1.55e-3
    expected = {
        Radial(q1, q2): (x * (q1 * r2 + q2 * r2 * r2), y * (q1 * r2 + q2 * r2 * r2)),
        Tangential(p1, p2): (p1 * (3 * x * x + y * y) + 2 * p2 * x * y, 2 * p1 * x * y + p2 * (x * x + 3 * y * y)),
        ThinPrism(s1, s2): (s1 * r2, s2 * r2),
        Shear(0.003, -0.001): (math.tan(0.003) * y, math.tan(-0.001) * x),
    }
    h = (0.999, 0.000625, 0.0005, 0.0, 0.999248, 0.001, 0.0, 0.00125)
    w = h[6] * x + h[7] * y + 1
    expected[Perspective(h)] = ((h[0] * x + h[1] * y + h[2]) / w - x, (h[3] * x + h[4] * y + h[5]) / w - y)
    for model, (dx, dy) in expected.items():
        got = model.distort(_at(x, y), K) - _at(x, y)
        np.testing.assert_allclose(got[0], [S * dx, S * dy], atol=1e-9, err_msg=type(model).__name__)
        back = model.undistort(model.distort(_at(x, y), K), K)
        np.testing.assert_allclose(back, _at(x, y), atol=1e-7)


def test_composite_applies_models_in_turn():
    a, b = Radial(q1=1e-3), Shear(phi_x=0.002)
    p = np.array([[100.0, 1800.0], [2000.0, 30.0]])
    np.testing.assert_allclose(Composite((a, b)).distort(p, K), b.distort(a.distort(p, K), K))
    # first order: the offsets add up, to within the product of the two fields' gradients (~1e-3 * 2 px)
    sum_offsets = p + (a.distort(p, K) - p) + (b.distort(p, K) - p)
    assert np.max(np.abs(Composite((a, b)).distort(p, K) - sum_offsets)) < 0.02


def test_presets_reach_the_papers_magnitudes_at_the_edge():
    edges = np.array([[2047.5, 1023.5], [1023.5, 2047.5], [-0.5, 1023.5], [1023.5, -0.5]])
    grid = np.stack(np.meshgrid(np.linspace(-0.5, 2047.5, 41), np.linspace(-0.5, 2047.5, 41)), -1).reshape(-1, 2)
    for name in ("barrel", "pincushion", "tangential", "thin_prism"):
        m = DISTORTION_PRESETS[name]
        edge = np.linalg.norm(m.distort(edges, K) - edges, axis=1).max()
        assert 1.9 < edge < 2.6, (name, edge)  # "about 2 pixels" at the edge
    for name in ("shear", "perspective"):
        m = DISTORTION_PRESETS[name]
        worst = np.linalg.norm(m.distort(grid, K) - grid, axis=1).max()
        assert 2.8 < worst < 3.7, (name, worst)  # "about 3 pixels" at most
    bar, pin = DISTORTION_PRESETS["barrel"], DISTORTION_PRESETS["pincushion"]
    assert bar.distort(edges[:1], K)[0, 0] < edges[0, 0] < pin.distort(edges[:1], K)[0, 0]  # barrel pulls inwards


def test_scenario_kinds_build_the_models():
    def head0(dist):
        return scenario_mod.load("paper_003", {"heads.0.distortion": dist}).heads[0].camera.distortion

    assert head0({"kind": "radial", "q1": -1e-3}) == Radial(q1=-1e-3)
    assert head0({"kind": "preset", "preset": "thin_prism"}) == DISTORTION_PRESETS["thin_prism"]
    assert head0({"kind": "shear", "phi_x_deg": 0.1}) == Shear(phi_x=math.radians(0.1))
    comp = head0({"kind": "composite", "models": [{"kind": "tangential", "p1": 1e-4}, {"kind": "preset",
                                                                                        "preset": "perspective"}]})
    assert comp == Composite((Tangential(p1=1e-4), DISTORTION_PRESETS["perspective"]))
    with pytest.raises(scenario_mod.ScenarioError, match="heads.0.distortion.preset"):
        head0({"kind": "preset", "preset": "fisheye"})
    with pytest.raises(scenario_mod.ScenarioError,  # the paper-named former kind names the kind to write now
                       match=r"paper_003.toml: heads.0.distortion.kind: expected kind = 'preset' .*got 'seed003'"):
        head0({"kind": "seed003", "preset": "barrel"})
    with pytest.raises(scenario_mod.ScenarioError, match="heads.0.distortion.*h31, h32"):
        head0({"kind": "perspective", "h": [1, 0, 0, 0, 1, 0, 0, 0.9]})
    with pytest.raises(scenario_mod.ScenarioError, match="heads.0.distortion.h"):
        head0({"kind": "perspective", "h": [1, 0, 0]})


def test_legendre_modes_are_orthonormal_by_quadrature():
    """Gauss-Legendre quadrature of order 8 integrates products of degree <= 10 per axis exactly."""
    nodes, weights = np.polynomial.legendre.leggauss(8)
    x, y = (a.ravel() for a in np.meshgrid(nodes, nodes, indexing="ij"))
    w = np.outer(weights, weights).ravel()
    b = legendre_basis(x, y, 5)
    assert b.shape == (64, 21)
    np.testing.assert_allclose(b.T @ (w[:, None] * b), np.eye(21), atol=1e-12)


def _planted(order=5, seed=7):
    """Weights (n_modes, 2), normalised, of a ~2 px field; pairs (measured, reference) on a 2048^2 camera."""
    from starenv.sim.optics import Camera

    rng = np.random.default_rng(seed)
    cam = Camera.from_fov(20.0, 2048, 2048, 7.45e-6)
    w = rng.normal(0.0, 1.0 / 1024, (21, 2))
    measured = rng.uniform(-0.5, 2047.5, (3000, 2))
    return cam, w, measured


def test_least_squares_recovers_planted_coefficients():
    from starenv.agents.correct.legendre import LegendreModel, fit_least_squares

    cam, w, measured = _planted()
    reference = measured - LegendreModel(w).offset(measured, cam)
    np.testing.assert_allclose(fit_least_squares(measured, reference, cam), w, atol=1e-13)
    # the model's inverse: uncorrect(correct(p)) = p to far below a micro-pixel
    model = LegendreModel(w)
    np.testing.assert_allclose(model.uncorrect(model.correct(measured, cam), cam), measured, atol=1e-9)


def test_torch_ground_training_matches_least_squares():
    """Adam (lr 1e-4, batch 128, 8:2 split) on noise-free planted pairs: without the forgetting factor it reaches the
    least-squares weights; with the paper's tau = 0.999 it stays within the jitter of its lr-sized steps."""
    from starenv.agents.correct.ground import train_ground
    from starenv.agents.correct.legendre import LegendreModel, fit_least_squares

    cam, w, measured = _planted()
    reference = measured - LegendreModel(w).offset(measured, cam)
    ls = fit_least_squares(measured, reference, cam)
    plain = train_ground(measured, reference, cam, epochs=40, tau=1.0, seed=0)
    assert len(plain.test) == 600 and plain.loss[-1] < plain.loss[0] / 100
    px = 1024.0
    assert np.max(np.abs(plain.model.weights - ls)) * px < 0.05  # each weight within 0.05 px of the LS optimum
    test_xy = measured[plain.test]
    err = np.abs(plain.model.offset(test_xy, cam) - LegendreModel(ls).offset(test_xy, cam))
    assert err.mean() < 0.02
    again = train_ground(measured, reference, cam, epochs=40, tau=1.0, seed=0)
    np.testing.assert_array_equal(again.model.weights, plain.model.weights)  # same seed, same bits
    paper = train_ground(measured, reference, cam, epochs=40, tau=0.999, seed=0)
    assert np.abs(paper.model.offset(test_xy, cam) - LegendreModel(ls).offset(test_xy, cam)).mean() < 0.1


def test_pairs_are_reproducible_alone_and_follow_the_distortion():
    from starenv.datasets.pairs import frame_pairs, orbit_pairs

    sc = scenario_mod.load("leo_distortion")
    a, b = frame_pairs(sc, 5, 3), frame_pairs(sc, 5, 3)
    np.testing.assert_array_equal(a.measured, b.measured)
    assert len(a) > 10 and not np.array_equal(a.catalog_id, frame_pairs(sc, 5, 4).catalog_id)
    cam = sc.heads[0].camera
    np.testing.assert_allclose(cam.distortion.distort(a.reference, cam.intrinsics), a.distorted, atol=1e-9)
    assert 0.02 < np.std(a.measured - a.distorted) < 0.08  # 0.05 px centroid noise
    o = orbit_pairs(sc, 0, 10)
    assert (o.attitude * sc.trajectory.attitude(10.0).inv()).magnitude() < 1e-12


def test_coverage_of_discs():
    from starenv.datasets.pairs import coverage

    # one disc of 96 px in the middle of a 2048^2 sensor: pi 96^2 / 2048^2 = 0.69 %, to a cell's rounding
    assert abs(coverage(np.array([[1024.0, 1024.0]]), 2048, 2048) - np.pi * 96**2 / 2048**2) < 5e-4
    assert coverage(np.zeros((0, 2)), 2048, 2048) == 0.0
    grid = np.stack(np.meshgrid(np.arange(0, 2048, 64.0), np.arange(0, 2048, 64.0)), -1).reshape(-1, 2)
    assert coverage(grid, 2048, 2048) == 1.0
