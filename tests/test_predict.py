"""Gyro predictors (starenv.agents.predict) against the simulator's truth: attitude over 100 frames (constant rate and
coning), star positions one frame ahead, 20 dropped frames, the image-axis sign convention and Eq. 7."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from starenv.agents.base import Prediction, Predictor, StarMeasurements, StepInput, step_input
from starenv.agents.predict.gyro import FirstOrderPredictor, QuaternionPredictor
from starenv.env import StarSensorEnv
from starenv.sim.conventions import ARCSEC
from starenv.sim.gyro import GyroSamples
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog

NOISE_FREE = {"gyro.arw_deg_rthr": 0.0, "gyro.rrw_deg_hr_rthr": 0.0, "gyro.bias_instability_deg_hr": 0.0}
TINY = {"heads.0.width": 64, "heads.0.height": 64}  # attitude runs need no stars
CONING = {"kind": "coning", "half_angle_deg": 2.0, "frequency_hz": 4.0, "initial_ra_deg": 83.8, "initial_dec_deg": -5.4}


@dataclass
class Episode:
    """Truth of frames 0..n, predictions (by predictor name) of frames 1..n, and every gyro sample delivered."""

    cameras: list[Camera]
    truth: list[dict]
    predictions: list[dict[str, Prediction]]
    gyro: GyroSamples

    def sample_angles(self, t0: float, t1: float) -> np.ndarray:
        """|rate dt| (rad) of the gyro samples whose interval overlaps (t0, t1] (s)."""
        t, dt = self.gyro.t, self.gyro.dt
        return np.linalg.norm(self.gyro.rate[(t > t0) & (t - dt < t1)], axis=1) * dt

    def attitude_errors(self, name: str) -> np.ndarray:
        """Angle (rad) between predictor ``name``'s attitude and the truth on frames 1..n."""
        pairs = zip(self.predictions, self.truth[1:], strict=True)
        return np.array([attitude_error(predictions[name], truth) for predictions, truth in pairs])


def episode(overrides: dict, predictors: dict[str, Predictor], n_frames: int) -> Episode:
    """paper_000 with ``overrides``: frame 0's truth (attitude, star positions and ids) given to every predictor,
    then ``n_frames`` frames predicted without update."""
    env = StarSensorEnv("paper_000", {"lost_after_steps": 10**6, **overrides})
    obs, info = env.reset()
    step = step_input(obs, env.sensor_info)
    for predictor in predictors.values():
        predictor.reset(env.cameras, env.sensor.catalog)
        predictor.predict(step)
        predictor.update(Rotation.from_quat(info["truth"]["attitude"]), truth_stars(info), step.time_s)
    truth, predictions, records = [info["truth"]], [], [step.gyro]
    for _ in range(n_frames):
        obs, _, _, _, info = env.step(None)
        step = step_input(obs, env.sensor_info)
        predictions.append({name: p.predict(step) for name, p in predictors.items()})
        truth.append(info["truth"])
        records.append(step.gyro)
    gyro = GyroSamples(np.concatenate([r.t for r in records]), np.concatenate([r.rate for r in records]), step.gyro.dt)
    return Episode(env.cameras, truth, predictions, gyro)


def truth_stars(info: dict) -> list[StarMeasurements]:
    return [StarMeasurements(s["xy_mid"], catalog_id=s["catalog_id"]) for s in info["truth"]["stars"]]


def attitude_error(prediction: Prediction, truth: dict) -> float:
    """Angle (rad) between a predicted attitude and the true one."""
    return float((prediction.attitude * Rotation.from_quat(truth["attitude"]).inv()).magnitude())


def matched(predicted: StarMeasurements, truth: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Catalog ids, predicted and true positions (n, 2) px of the stars in both lists."""
    ids, p, t = np.intersect1d(predicted.catalog_id, truth["catalog_id"], return_indices=True)
    return ids, predicted.xy[p], truth["xy_mid"][t]


def angles_between(camera: Camera, xy_a: np.ndarray, xy_b: np.ndarray) -> np.ndarray:
    """Angles (rad) between the directions imaged at two sets of pixel positions."""
    a, b = camera.unproject(xy_a), camera.unproject(xy_b)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


@pytest.mark.parametrize("predictor_class", [FirstOrderPredictor, QuaternionPredictor])
def test_nothing_is_predicted_before_the_first_update_and_nan_gyro_is_refused(predictor_class):
    env = StarSensorEnv("paper_000", TINY)
    obs, _ = env.reset()
    predictor = predictor_class()
    predictor.reset(env.cameras, env.sensor.catalog)
    step = step_input(obs, env.sensor_info)
    prediction = predictor.predict(step)
    assert prediction.attitude is None and [len(s) for s in prediction.stars] == [0]
    step.gyro.rate[0, 1] = np.nan
    with pytest.raises(ValueError, match="gyro.rate"):
        predictor.predict(step)


def test_constant_rate_attitude_quaternion_exact_first_order_short_by_its_closed_form():
    """37 deg/s with a 200 Hz gyro whose samples end on the frame times: the quaternion predictor is exact; each
    re-orthonormalised first-order increment turns by atan|theta| instead of |theta| (theta = rate x sample
    interval), well inside the |theta|^2 / 2 bound on the increment's error."""
    overrides = {**TINY, **NOISE_FREE, "gyro.rate_hz": 200.0, "motion.rate_dps": [20.0, -30.0, 10.0]}
    run = episode(overrides, {"quaternion": QuaternionPredictor(), "first_order": FirstOrderPredictor()}, 100)
    predictions, truth = run.predictions[-1], run.truth[-1]
    theta = run.sample_angles(run.truth[0]["time_s"], truth["time_s"])
    assert len(theta) == 200
    assert run.attitude_errors("quaternion").max() < 1e-3 * ARCSEC
    first_order = attitude_error(predictions["first_order"], truth)
    assert first_order == pytest.approx(np.sum(theta - np.arctan(theta)), rel=1e-3)  # 0.48 arcsec
    assert first_order < np.sum(theta**2 / 2)


@pytest.mark.parametrize("time_offset_s", [0.0, 0.0013])
def test_coning_attitude_needs_the_coning_term(time_offset_s):
    """Coning (2 deg at 4 Hz, up to 50 deg/s) with a 200 Hz gyro.  With the offset the frame times split gyro
    samples: held at the sample's average rate instead of interpolated, each split part would err by up to
    s dt^2 / 8 (s = 2 pi 4 Hz x 50 deg/s the rate's slope, dt = 5 ms: ~14 arcsec).  Every frame is checked (frame
    100 is four coning periods on, where split-part errors cancel)."""
    overrides = {**TINY, **NOISE_FREE, "gyro.rate_hz": 200.0, "gyro.time_offset_s": time_offset_s, "motion": CONING}
    predictors = {
        "quaternion": QuaternionPredictor(),
        "no_coning_term": QuaternionPredictor(coning_correction=False),
        "first_order": FirstOrderPredictor(),
    }
    run = episode(overrides, predictors, 100)
    assert run.attitude_errors("quaternion").max() < 0.5 * ARCSEC
    truth = run.truth[-1]
    error = {name: attitude_error(p, truth) for name, p in run.predictions[-1].items()}
    assert error["quaternion"] < 0.1 * ARCSEC
    # the coning drift of a one-sample update, (W a^2 / 2)(1 - sin(W dt) / (W dt)) with W = 2 pi 4 Hz, a = 2 deg and
    # dt = 5 ms, is about 8 arcsec/s
    assert error["no_coning_term"] > 5.0 * ARCSEC
    theta = run.sample_angles(run.truth[0]["time_s"], truth["time_s"])
    assert error["quaternion"] < error["first_order"] < np.sum(theta**2 / 2)


def test_first_order_increment_is_eq7_with_plus_f():
    """One gyro sample, an undistorted camera with an off-centre principal point: positions follow Eq. 7 written for
    a +Z boresight in principal-point-relative coordinates, and the attitude turns by atan|theta|."""
    camera = Camera.from_focal_length(0.049, 20e-6, 512, 512, cx=300.0, cy=200.0)
    catalog = StarCatalog(hip=[1], magnitude=[0.0], unit=[[0.0, 0.0, 1.0]], epoch=2026.0)
    xy = np.array([[10.0, 20.0], [300.0, 200.0], [500.0, 480.0], [40.0, 400.0]])
    theta, dt = np.array([2e-3, -3e-3, 5e-3]), 0.002
    predictor = FirstOrderPredictor()
    predictor.reset([camera], catalog)
    predictor.update(Rotation.identity(), [StarMeasurements(xy, catalog_id=[5, 6, 7, 8])], 0.0)
    step = StepInput([np.zeros((512, 512), np.uint16)], np.array([True]), dt, 0.01,
                     GyroSamples(np.array([dt]), theta[None, :] / dt, dt), [camera])
    prediction = predictor.predict(step)
    f, (tx, ty, tz) = camera.fx, theta
    x, y = xy[:, 0] - camera.cx, xy[:, 1] - camera.cy
    d = 1.0 + (x * ty - y * tx) / f
    expected = np.stack([(x + y * tz - f * ty) / d + camera.cx, (y - x * tz + f * tx) / d + camera.cy], axis=1)
    assert prediction.stars[0].catalog_id.tolist() == [5, 6, 7, 8]
    np.testing.assert_allclose(prediction.stars[0].xy, expected, atol=1e-9)
    angle = np.linalg.norm(theta)
    turned = Rotation.from_rotvec(-theta / angle * np.arctan(angle))
    assert (prediction.attitude * turned.inv()).magnitude() < 1e-15


def test_star_positions_one_frame_ahead_at_paper_rate():
    """paper_000 as bundled (1 deg/s about each axis, RadialXY distortion), noise-free gyro: frame 1 from frame 0.

    First-order bound, per increment of angle theta: theta^2 / 4 (the stretch across the rotation axis) plus
    theta^3 / 3 (the angle shortfall), summed over the gyro samples the frame interval overlaps."""
    run = episode(NOISE_FREE, {"quaternion": QuaternionPredictor(), "first_order": FirstOrderPredictor()}, 1)
    predictions, truth = run.predictions[0], run.truth[1]
    _, predicted, true = matched(predictions["quaternion"].stars[0], truth["stars"][0])
    assert len(predicted) > 20
    assert np.abs(predicted - true).max() < 0.01
    theta = run.sample_angles(run.truth[0]["time_s"], truth["time_s"])
    bound = np.sum(theta**2 / 4 + theta**3 / 3)
    _, predicted, true = matched(predictions["first_order"].stars[0], truth["stars"][0])
    assert len(predicted) > 20
    error = angles_between(run.cameras[0], predicted, true)
    assert error.max() < bound
    assert error.max() > 0.3 * bound  # the model's own error shows: it is not the exact rotation


def test_dropped_frames_keep_tracking():
    """20 dropped frames at 3.7 deg/s with the scenario's (noisy) gyro and no update: both predictions stay on the
    stars, and the quaternion predictor picks up the stars that enter the field."""
    overrides = {"heads.0.width": 256, "heads.0.height": 256, "drops.probability": 1.0,
                 "motion.rate_dps": [3.0, -2.0, 1.0]}
    run = episode(overrides, {"quaternion": QuaternionPredictor(), "first_order": FirstOrderPredictor()}, 20)
    camera = run.cameras[0]
    for predictions, truth in zip(run.predictions, run.truth[1:], strict=True):
        assert truth["dropped"] == [True]
        stars = truth["stars"][0]
        in_view = set(stars["catalog_id"][camera.in_frame(stars["xy_mid"])])
        for name, prediction in predictions.items():
            assert attitude_error(prediction, truth) < 2 * ARCSEC, name
            _, predicted, true = matched(prediction.stars[0], stars)
            assert np.abs(predicted - true).max() < 0.05, name
        assert in_view <= set(predictions["quaternion"].stars[0].catalog_id)
    assert in_view - set(run.truth[0]["stars"][0]["catalog_id"])  # some entered during the drop-out
    assert len(predictions["first_order"].stars[0]) > 5


def test_rotation_about_camera_x_moves_stars_towards_plus_rows():
    """The head is mounted turned 90 deg about body z and the body turns at 3 deg/s about the camera's +X axis: the
    renderer's stars move by f * 3 deg/s * 10 ms = 1.28 px per frame towards +v (rows), and so do the predictions."""
    mounting_deg = [0.0, 0.0, 90.0]
    rate_dps = Rotation.from_euler("xyz", mounting_deg, degrees=True).inv().apply([3.0, 0.0, 0.0]).tolist()
    overrides = {"heads.0.width": 256, "heads.0.height": 256, "heads.0.mounting_euler_deg": mounting_deg,
                 "motion.rate_dps": rate_dps, **NOISE_FREE}
    run = episode(overrides, {"quaternion": QuaternionPredictor(), "first_order": FirstOrderPredictor()}, 1)
    frame_px = run.cameras[0].fx * np.radians(3.0) * 0.01
    before = run.truth[0]["stars"][0]
    start = dict(zip(before["catalog_id"], before["xy_mid"], strict=True))
    for name, prediction in run.predictions[0].items():
        ids, predicted, true = matched(prediction.stars[0], run.truth[1]["stars"][0])
        assert len(ids) > 3, name
        moved_true = true - np.array([start[i] for i in ids])
        moved_predicted = predicted - np.array([start[i] for i in ids])
        np.testing.assert_allclose(moved_true[:, 1], frame_px, rtol=0.02)
        np.testing.assert_allclose(moved_true[:, 0], 0.0, atol=0.02 * frame_px)
        np.testing.assert_allclose(moved_predicted, moved_true, atol=1e-3, err_msg=name)
