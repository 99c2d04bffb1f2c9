"""The Gymnasium contract: spaces, determinism, vector envs, actions, scores, reward and episode ends."""

import pickle
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import starenv
from starenv.env import MAX_STARS, StarSensorEnv
from starenv.registration import register_envs
from starenv.scenario import SCENARIO_DIR
from starenv.sim.conventions import ARCSEC

SMALL = {"heads.0.width": 128, "heads.0.height": 128}  # paper_000 on a 128 px crop: fast


def small_env(**overrides):
    return StarSensorEnv("paper_000", {**SMALL, **overrides})


def same(a, b):
    """Bit-for-bit equality of nested observations / infos."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    return a == b


def truth_action(info, **extra):
    return {"attitude": info["truth"]["attitude"], "attitude_valid": 1, **extra}


def test_every_bundled_scenario_is_registered_once():
    ids = register_envs()  # a second registration must be harmless
    assert register_envs() == ids
    registered = [k for k in gym.registry if k.startswith("StarEnv/")]
    assert sorted(registered) == sorted(ids)
    assert "StarEnv/Paper002-v0" in ids and "StarEnv/Scenario-v0" in ids
    assert len(ids) == len(starenv.scenario.bundled_names()) + 1


@pytest.mark.parametrize("env_id", ["StarEnv/Paper000-v0", "StarEnv/Paper004-v0"])
def test_check_env_passes_without_warnings(env_id):
    env = gym.make(env_id)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    assert [str(w.message) for w in caught] == []


def test_design_contract_snippet():
    env = gym.make(
        "StarEnv/Scenario-v0",
        scenario=str(SCENARIO_DIR / "paper_002.toml"),
        overrides={"motion.kind": "constant_rate", "motion.rate_dps": [0, 0, 10], "motion.initial_ra_deg": 83.8,
                   "motion.initial_dec_deg": -5.4, "motion.initial_roll_deg": 0.0},
    )
    obs, info = env.reset(seed=0)
    assert obs["frames"].dtype == np.uint16 and obs["frames"].shape == (1, 1024, 1024)
    assert obs["frame_valid"].dtype == np.int8 and obs["frame_valid"].shape == (1,)
    q = info["truth"]["attitude"]
    assert q.shape == (4,) and abs(np.linalg.norm(q) - 1) < 1e-12
    stars = info["truth"]["stars"][0]
    for key in ("catalog_id", "magnitude", "xy_mid", "xy_centroid", "electrons"):
        assert len(stars[key]) == len(stars["catalog_id"]) > 5
    cam = env.unwrapped.cameras[0]
    assert (cam.width, cam.height) == (1024, 1024) and cam.fov[0] == pytest.approx(np.radians(11.99), abs=1e-3)
    # Head 0's boresight at frame 0's mid-exposure looks at the requested RA/Dec (rate 10 deg/s about the boresight
    # does not move it).
    boresight = (cam.mounting * Rotation.from_quat(q)).inv().apply([0, 0, 1])
    ra, dec = np.radians(83.8), np.radians(-5.4)
    expected = [np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)]
    np.testing.assert_allclose(boresight, expected, atol=1e-12)


def rollout(env, seed, steps):
    obs, info = env.reset(seed=seed)
    out = [(obs, info["truth"])]
    for _ in range(steps):
        obs, reward, term, trunc, info = env.step(truth_action(info))
        out.append((obs, info["truth"], reward, info["scores"]))
    return out


def test_seeded_rollout_is_bit_identical_across_instances_and_differs_across_seeds():
    a = rollout(small_env(), 7, 50)
    b = rollout(small_env(), 7, 50)
    assert same(a, b)
    c = rollout(small_env(), 8, 3)
    assert not np.array_equal(a[1][0]["frames"], c[1][0]["frames"])


def test_vector_envs_sync_and_async_agree_bit_for_bit():
    kwargs = {"scenario": "paper_000", "overrides": SMALL}
    template = small_env().null_action()
    results = {}
    for mode in ("sync", "async"):
        envs = gym.make_vec("StarEnv/Scenario-v0", num_envs=2, vectorization_mode=mode, **kwargs)
        obs, info = envs.reset(seed=[3, 4])
        frames = [obs["frames"].copy()]
        action = {k: np.stack([v, v]) for k, v in template.items()}  # vector envs batch every action key
        for _ in range(50):
            action["attitude"], action["attitude_valid"] = info["truth"]["attitude"], np.ones(2, np.int8)
            obs, reward, term, trunc, info = envs.step(action)
            frames.append(obs["frames"].copy())
            frames.append(obs["gyro"]["rate"].copy())
        envs.close()
        results[mode] = frames
    assert all(np.array_equal(x, y) for x, y in zip(results["sync"], results["async"], strict=True))
    # and each vector slot equals a single env with the same seed
    single = rollout(small_env(), 4, 50)
    assert np.array_equal(results["sync"][-2][1], single[-1][0]["frames"])


def test_prefetch_gives_the_same_episode_bit_for_bit():
    # The next frame is simulated on a thread while the caller works: nothing may change, across resets too.
    plain, ahead = small_env(), StarSensorEnv("paper_000", SMALL, prefetch=True)
    for seed in (7, 9):
        a, b = rollout(plain, seed, 30), rollout(ahead, seed, 30)
        assert same(a, b)
    # Pickled mid-episode (a frame being prefetched), the clone continues as the original does.
    obs, info = ahead.reset(seed=5)
    ahead.step(truth_action(info))
    clone = pickle.loads(pickle.dumps(ahead))
    x, y = ahead.step(None), clone.step(None)
    assert same(x[0], y[0]) and same(x[4]["truth"], y[4]["truth"])
    assert same(clone.step(None)[0], ahead.step(None)[0])
    ahead.close()
    clone.close()


def test_prefetch_error_reaches_the_step_that_needs_the_frame():
    env = StarSensorEnv("paper_000", SMALL, prefetch=True)
    real = env.sensor.next_frame
    calls = []

    def failing():
        calls.append(1)
        if len(calls) == 2:  # the frame prefetched after reset
            raise RuntimeError("sensor failure in frame 1")
        return real()

    env.sensor.next_frame = failing
    env.reset(seed=0)
    with pytest.raises(RuntimeError, match="sensor failure in frame 1"):
        env.step(None)
    env.close()
    with pytest.raises(ValueError, match="prefetch"):
        StarSensorEnv("paper_000", SMALL, prefetch="yes")


def test_pickled_env_continues_identically():
    env = small_env()
    obs, info = env.reset(seed=5)
    env.step(truth_action(info))
    clone = pickle.loads(pickle.dumps(env))
    a = env.step(None)
    b = clone.step(None)
    assert same(a[0], b[0]) and same(a[4]["truth"], b[4]["truth"])


def test_observation_holds_no_truth_and_a_documented_gyro_layout():
    env = small_env()
    obs, info = env.reset(seed=0)
    assert set(obs) == {"frames", "frame_valid", "gyro", "time_s", "exposure_s", "observer_velocity_m_s", "blinded"}
    assert obs in env.observation_space
    sc = env.scenario
    last = -np.inf
    for k in range(1, 6):
        obs, *_ = env.step(None)
        n = int(obs["gyro"]["count"])
        t = obs["gyro"]["t"]
        assert n == sc.gyro.rate_hz / sc.frame_rate_hz  # 500 Hz gyro, 100 Hz frames
        assert np.all(t[n:] == 0) and np.all(obs["gyro"]["rate"][n:] == 0)
        assert t[0] > last and np.all(np.diff(t[:n]) > 0)
        assert t[n - 1] <= k / sc.frame_rate_hz + sc.exposure_s + 1e-12
        last = t[n - 1]
        assert float(obs["time_s"]) == pytest.approx(k / sc.frame_rate_hz + sc.exposure_s / 2)


def test_a_smaller_head_is_padded_with_zeros_below_and_right_of_its_image():
    # paper_004's three 512 px heads, the second cut to 96 x 64: its image fills the top-left corner of its slot and
    # nothing else does, step after step (the slot's memory is reused, so stale pixels would show).
    env = StarSensorEnv("paper_004", {"heads.1.width": 96, "heads.1.height": 64})
    obs, _ = env.reset(seed=5)
    for _ in range(4):
        image = env._frame.heads[1].image
        assert image.shape == (64, 96) and image.any()
        slot = obs["frames"][1]
        assert np.array_equal(slot[:64, :96], image)
        assert not slot[64:].any() and not slot[:64, 96:].any()
        assert np.array_equal(obs["frames"][0], env._frame.heads[0].image)
        obs, *_ = env.step(None)


def test_dropped_frames_are_zeros_and_flagged():
    env = small_env(**{"drops.probability": 1.0})
    obs, info = env.reset(seed=0)
    assert obs["frame_valid"].tolist() == [0] and not obs["frames"].any()
    assert info["truth"]["dropped"] == [True] and len(info["truth"]["stars"][0]["catalog_id"]) > 0


def test_calibrated_camera_is_what_the_sensor_believes():
    env = StarSensorEnv("paper_003", {"heads.0.width": 256, "heads.0.height": 256})
    true_cam = env.scenario.heads[0].camera
    assert type(env.cameras[0].distortion).__name__ == "NoDistortion"
    assert type(true_cam.distortion).__name__ == "LegendreField"


def test_reward_scores_and_availability():
    env = small_env()
    obs, info = env.reset(seed=1)
    threshold = env.scenario.availability_threshold_arcsec.total_arcsec
    _, reward, *_, info2 = env.step(truth_action(info))
    assert reward == 1.0 and info2["scores"]["attitude"]["total_arcsec"] < 1e-6
    assert info2["scores"]["frame"] == info["truth"]["frame"] == 0
    assert info2["scores"]["time_s"] == info["truth"]["time_s"]
    # Rotate the estimate by half the threshold about head 0's boresight: all of it is roll.
    mount = env.scenario.heads[0].camera.mounting
    axis = mount.inv().apply([0, 0, 1])
    off = Rotation.from_rotvec(axis * 0.5 * threshold * ARCSEC) * Rotation.from_quat(info2["truth"]["attitude"])
    _, reward, *_, info3 = env.step({"attitude": off.as_quat(), "attitude_valid": 1})
    head = info3["scores"]["attitude"]["heads"][0]
    assert reward == pytest.approx(0.5, abs=1e-6)
    assert head["roll_arcsec"] == pytest.approx(0.5 * threshold, rel=1e-6) and head["cross_boresight_arcsec"] < 1e-6
    _, reward, *_, info4 = env.step({"attitude": np.array([0, 0, 0, 1.0]), "attitude_valid": 0})
    assert reward == 0.0 and not info4["scores"]["available"]


def test_a_per_axis_threshold_bounds_cross_boresight_and_roll_apart():
    """With ``{cross_boresight, roll}`` a turn about head 0's boresight is scored against the roll bound: 0.4 of it
    is within (reward 0.6), 1.5 of it is not, and neither is 1.5 of the cross-boresight bound about camera +X; the
    lost rule counts the steps outside."""
    env = small_env(**{"availability_threshold_arcsec": {"cross_boresight": 20.0, "roll": 200.0},
                       "lost_after_steps": 2})
    _, info = env.reset(seed=1)
    mount = env.scenario.heads[0].camera.mounting
    ends = []
    for camera_axis, size_arcsec, reward_expected, within in (
            ([0, 0, 1], 80.0, 0.6, True), ([0, 0, 1], 300.0, 0.0, False), ([1, 0, 0], 30.0, 0.0, False)):
        axis = mount.inv().apply(camera_axis)
        off = Rotation.from_rotvec(axis * size_arcsec * ARCSEC) * Rotation.from_quat(info["truth"]["attitude"])
        _, reward, terminated, _, info = env.step({"attitude": off.as_quat(), "attitude_valid": 1})
        assert reward == pytest.approx(reward_expected, abs=1e-6) and info["scores"]["within_threshold"] is within
        ends.append(terminated)
    assert ends == [False, False, True]


def test_lost_rule_terminates_and_duration_truncates():
    env = small_env(**{"lost_after_steps": 3, "duration_s": 0.1})
    obs, info = env.reset(seed=0)
    ends = []
    for _ in range(3):
        obs, r, term, trunc, info = env.step(None)
        ends.append((term, trunc))
    assert ends == [(False, False), (False, False), (True, False)]
    env.reset(seed=0)
    truncs = []
    for _ in range(env.scenario.n_steps - 1):
        obs, r, term, trunc, info = env.step(truth_action(info))
        truncs.append(trunc)
    assert truncs[-1] and not any(truncs[:-1]) and env.scenario.n_steps == 10


def test_star_stage_scores_against_truth():
    env = small_env()
    obs, info = env.reset(seed=2)
    stars = info["truth"]["stars"][0]
    n = len(stars["catalog_id"])
    assert n >= 4
    xy = np.zeros((1, MAX_STARS, 2))
    xy[0, :n] = stars["xy_centroid"] + [0.3, -0.4]  # every detection 0.5 px off
    ids = np.full((1, MAX_STARS), -1)
    ids[0, :n] = stars["catalog_id"]
    far = int(np.argmax(np.linalg.norm(stars["xy_centroid"] - stars["xy_centroid"][0], axis=1)))
    ids[0, 0] = stars["catalog_id"][far]  # one wrong id: a star far from detection 0
    mask = np.zeros((1, MAX_STARS), np.int8)
    mask[0, :n] = 1
    pred = np.zeros((1, MAX_STARS, 2))
    pred[0, :n] = stars["xy_mid"] + [1.0, 0.0]
    action = truth_action(info, detections_xy=xy, catalog_ids=ids, detection_mask=mask, predicted_xy=pred,
                          predicted_ids=np.where(mask == 1, ids, -1), prediction_mask=mask)
    *_, info2 = env.step(action)
    s = info2["scores"]["heads"][0]
    assert s["centroid_error_px_mean"] == pytest.approx(0.5) and s["centroid_error_px_max"] == pytest.approx(0.5)
    assert s["detection_precision"] == 1.0 and s["detection_recall"] == 1.0
    assert s["ids_correct"] == n - 1 and s["ids_wrong"] == 1 and s["false_id_rate"] == pytest.approx(1 / n)
    assert not s["solved"]  # a wrong id spoils the frame
    assert s["predictions_scored"] == n
    # the wrongly labelled prediction (row 0 carries the far star's id) is scored against that star's position
    assert s["prediction_error_px_max"] > 1.0 and s["prediction_error_px_mean"] > 1.0


@pytest.mark.parametrize(
    ("action", "message"),
    [
        ({"attitude": [np.nan, 0, 0, 1], "attitude_valid": 1}, "attitude"),
        ({"attitude": [0, 0, np.inf, 1], "attitude_valid": 1}, "attitude"),
        ({"attitude": [0, 0, 1], "attitude_valid": 1}, "shape"),
        ({"attitude": ["a", "b", "c", "d"], "attitude_valid": 1}, "dtype"),
        ({"attitude": [0, 0, 0, 0.0], "attitude_valid": 1}, "non-zero"),
        ({"attitude": [0, 0, 0, 1.0], "attitude_valid": 2}, "attitude_valid"),
        ({"attitude": [0, 0, 0, 1.0], "bogus": 1}, "unknown"),
        ({"detections_xy": np.zeros((1, MAX_STARS, 2))}, "detection_mask"),
        ([0, 0, 0, 1], "dict"),
    ],
)
def test_malformed_actions_are_refused_with_a_message(action, message):
    env = small_env()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=message):
        env.step(action)


def test_render_returns_a_viewable_frame():
    env = StarSensorEnv("paper_000", SMALL, render_mode="rgb_array")
    env.reset(seed=0)
    img = env.render()
    assert img.dtype == np.uint8 and img.shape == (128, 128, 3)
    assert (img[..., 1] > img[..., 0]).any()  # green truth overlay


junk = st.one_of(
    st.none(), st.booleans(), st.integers(-5, 5), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=3),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(action=st.one_of(junk, st.dictionaries(st.sampled_from(
    ["attitude", "attitude_valid", "detections_xy", "detection_mask", "catalog_ids", "predicted_xy", "predicted_ids",
     "prediction_mask", "extra"]), junk, max_size=4)))
def test_fuzzed_actions_give_an_error_message_or_an_unavailable_step(action):
    env = FUZZ_ENV
    try:
        _, reward, *_, info = env.step(action)
    except ValueError as exc:
        assert str(exc)
    else:
        assert 0.0 <= reward <= 1.0 and isinstance(info["scores"]["available"], bool)


FUZZ_ENV = small_env(**{"duration_s": 1000.0})
FUZZ_ENV.reset(seed=0)
