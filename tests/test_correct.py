"""The Legendre corrector: its learners against closed forms, on-orbit convergence, and the corrector in the loop."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from starenv import scenario as scenario_mod
from starenv.agents.correct.baselines import PiecewiseLinearMap, PolynomialMap
from starenv.agents.correct.legendre import (
    AdamLearner,
    LegendreCorrector,
    LegendreModel,
    RlsLearner,
    design,
    fit_least_squares,
    labels,
    learn_frame,
    rotation_modes,
)
from starenv.datasets.pairs import orbit_pairs
from starenv.sim.optics import Camera
from starenv.sim.sky import load_catalog

CAM = Camera.from_fov(20.0, 2048, 2048, 7.45e-6)


def test_adam_first_step_is_the_papers_eq_25():
    """At t = 1, m_hat = g and v_hat = g^2, so W1 = tau W0 - lr g / (|g| + eps): a step of lr against the sign."""
    rng = np.random.default_rng(1)
    b, f = rng.normal(size=(40, 21)), rng.normal(size=(40, 2)) * 1e-3
    w0 = rng.normal(size=(21, 2)) * 1e-3
    model = LegendreModel(w0)
    AdamLearner(lr=1e-4, tau=0.999).update(model, b, f)
    e = f - b @ w0
    g = -(b.T @ e) / (40 * np.sqrt(np.mean(e * e, axis=0)))  # d RMSE / dW per axis (Eq. 28)
    np.testing.assert_allclose(model.weights, 0.999 * w0 - 1e-4 * g / (np.abs(g) + 1e-8), rtol=1e-12, atol=1e-18)


def test_rls_is_ridge_least_squares_of_every_frame():
    rng = np.random.default_rng(2)
    frames = [(rng.normal(size=(30, 21)), rng.normal(size=(30, 2))) for _ in range(4)]
    model, rls = LegendreModel.zeros(), RlsLearner(prior_px=2.0, noise_px=0.1)
    for b, f in frames:
        rls.update(model, b, f)
    b_all, f_all = np.vstack([b for b, _ in frames]), np.vstack([f for _, f in frames])
    ridge = (0.1 / 2.0) ** 2 * np.eye(21)
    np.testing.assert_allclose(model.weights, np.linalg.solve(b_all.T @ b_all + ridge, b_all.T @ f_all), rtol=1e-10)


def test_rotation_modes_span_small_camera_rotations():
    g = rotation_modes(CAM)
    np.testing.assert_allclose(g @ g.T, np.eye(3), atol=1e-12)
    # a 10 arcsec turn about the boresight, as measured/reference pairs, lies in the span of the modes
    xy = np.random.default_rng(3).uniform(0, 2047, (500, 2))
    v = CAM.unproject(xy)
    turned = CAM.project(Rotation.from_rotvec([0, 0, 10 / 206265]).apply(v))[0]
    w = fit_least_squares(turned, xy, CAM).T.ravel()
    # up to the second-order difference of fitting at the turned (measured) positions: ~ the turn angle, 5e-5
    assert np.linalg.norm(w - g.T @ (g @ w)) < 1e-4 * np.linalg.norm(w)


def _replay(scenario, corrector, frames, cam, catalog):
    for i in range(frames):
        p = orbit_pairs(scenario, 0, i)
        learn_frame(corrector, p.measured, p.catalog_id, cam, catalog)
    p = orbit_pairs(scenario, 0, frames)
    return np.abs(corrector.models[0].correct(p.distorted, cam) - p.reference).mean(axis=0)


@pytest.fixture(scope="module")
def paper_003():
    sc = scenario_mod.load("paper_003")
    return sc, sc.heads[0].calibrated, load_catalog(sc.mag_limit, sc.epoch)


def test_online_learners_converge_on_orbit(paper_003):
    """paper_003's Legendre field (0.7 px mean, no rotation-like part) from the solved attitude of each frame: RLS
    within 30 frames, the paper's Adam within 300, to the distortion-free truth."""
    sc, cam, catalog = paper_003
    p = orbit_pairs(sc, 0, 0)
    assert np.abs(p.distorted - p.reference).mean() > 0.4
    rls = LegendreCorrector(learner="rls")
    rls.reset([cam], catalog)
    assert np.all(_replay(sc, rls, 30, cam, catalog) < 0.02)
    adam = LegendreCorrector(learner="adam")
    adam.reset([cam], catalog)
    assert np.all(_replay(sc, adam, 300, cam, catalog) < 0.08)


def test_corrector_leaves_a_distortion_free_camera_alone(paper_003):
    sc = scenario_mod.load("paper_003", {"heads.0.distortion": {"kind": "none"}})
    _, cam, catalog = paper_003
    c = LegendreCorrector()
    c.reset([cam], catalog)
    residual = _replay(sc, c, 30, cam, catalog)
    assert np.all(residual < 0.01)  # 30 frames x ~80 stars with 0.05 px noise: ~0.006 px of fitted noise
    _replay(sc, c, 300, cam, catalog)  # once stars have swept the whole sensor, nowhere more than noise
    grid = np.stack(np.meshgrid(np.linspace(0, 2047, 21), np.linspace(0, 2047, 21)), -1).reshape(-1, 2)
    assert np.abs(c.models[0].offset(grid, cam)).max() < 0.05


def test_baselines_fit_what_they_can(paper_003):
    """A field of total order 3 is exact for the polynomial map; the piecewise-linear map is exact on a plane."""
    _, cam, _ = paper_003
    xy = np.random.default_rng(4).uniform(0, 2047, (400, 2))
    w = np.zeros((21, 2))
    w[[1, 4, 8], 0], w[[2, 6], 1] = 1e-3, 2e-3
    ref = xy - LegendreModel(w).offset(xy, cam)
    np.testing.assert_allclose(PolynomialMap(xy, ref, cam).offset(xy[:50], cam), xy[:50] - ref[:50], atol=1e-9)
    affine = np.array([[1.001, 2e-4], [-3e-4, 0.999]])
    plane = xy @ affine.T + [0.3, -0.2]
    inner = np.random.default_rng(5).uniform(300, 1700, (50, 2))
    np.testing.assert_allclose(PiecewiseLinearMap(xy, plane).offset(inner), inner - (inner @ affine.T + [0.3, -0.2]),
                               atol=1e-9)


def test_bad_options_name_the_field():
    with pytest.raises(ValueError, match="learner"):
        LegendreCorrector(learner="sgd")
    with pytest.raises(ValueError, match="lr"):
        LegendreCorrector(learner="adam", learner_options={"lr": -1.0})
    with pytest.raises(ValueError, match="LegendreModel.weights"):
        LegendreModel(np.zeros((20, 2)))
    with pytest.raises(ValueError, match="at least 21 stars"):
        fit_least_squares(np.zeros((5, 2)), np.zeros((5, 2)), CAM)
    assert design(np.zeros((3, 2)), CAM, 5).shape == (3, 21)
    assert labels(np.ones((2, 2)), np.zeros((2, 2)), CAM).max() == 1 / 1024


def test_corrector_in_the_loop_on_paper_003():
    """The pipeline with the corrector: after two frames the predictions land within 0.1 px of the stars (0.7 px
    without), and the correction score falls from the distortion's size."""
    from starenv.agents.pipeline import Pipeline
    from starenv.env import StarSensorEnv
    from starenv.episode import run_episode

    records = {}
    for name, agents in (("none", {}), ("rls", {"corrector": "starenv.agents.correct:LegendreCorrector"})):
        env = StarSensorEnv("paper_003")
        records[name] = run_episode(env, Pipeline.for_scenario(env.scenario, agents), seed=0, steps=4).records
    last, before = records["rls"][-1], records["none"][-1]
    assert before["prediction_error_px_mean"] > 0.5 and last["prediction_error_px_mean"] < 0.1
    assert records["rls"][0]["correction_error_px_mean"] > 0.5 and last["correction_error_px_mean"] < 0.05
    assert before["correction_error_px_mean"] == pytest.approx(before["distortion_px_mean"])


def test_correction_score_is_the_offset_error_on_correct_ids():
    """Two stars, true offsets (1, 0) and (0, -2) px; the corrector removes (0.9, 0) and (0, -2.2); a third detection
    claims a wrong id and is not scored."""
    from starenv.scoring import score_stars
    from starenv.sim.render import StarTruth

    centroid = np.array([[100.0, 100.0], [500.0, 400.0], [900.0, 900.0]])
    calibrated = centroid - [[1.0, 0.0], [0.0, -2.0], [0.0, 0.0]]
    n = 3
    truth = StarTruth(np.array([11, 22, 33]), np.zeros(n), centroid, centroid, centroid, centroid, np.ones(n),
                      np.ones(n), np.ones(n, dtype=bool))
    detected = centroid + [[0.03, 0.0], [0.0, 0.04], [0.0, 0.0]]  # centroid noise: not part of the score
    corrected = detected - [[0.9, 0.0], [0.0, -2.2], [0.0, 0.0]]
    s = score_stars(truth, detected, np.array([11, 22, 99]), corrected_xy=corrected, calibrated_xy=calibrated)
    assert s.ids_correct == 2 and s.ids_wrong == 1
    assert s.correction_error_px_mean == pytest.approx((0.1 + 0.2) / 2)
    assert (s.correction_error_x_px, s.correction_error_y_px) == pytest.approx((0.05, 0.1))
    assert s.distortion_px_mean == pytest.approx(1.5)
