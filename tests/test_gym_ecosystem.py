"""Gymnasium ecosystem: sampled spaces step for every id, registered episode lengths, the observation wrappers in a
vector env, RecordVideo, and the info dict's keys all documented."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.wrappers import FlattenObservation, RecordVideo

import starenv
from starenv.env import StarSensorEnv
from starenv.registration import register_envs
from starenv.scenario import bundled_names, load
from starenv.wrappers import FlatStateObservation, ImageObservation

SMALL = {"heads.0.width": 128, "heads.0.height": 128}


def small(name: str) -> dict:
    """Every head cropped to 96 x 96 px (same optics otherwise): cheap frames."""
    n = len(load(name).heads)
    return {f"heads.{h}.{k}": 96 for h in range(n) for k in ("width", "height")}


@pytest.mark.filterwarnings("ignore:.*Casting input x")  # Box.sample() of a () int box returns a numpy scalar
@pytest.mark.parametrize("env_id", register_envs())
def test_sampled_observation_and_action_step(env_id):
    name = "paper_001" if env_id == "StarEnv/Scenario-v0" else gym.spec(env_id).kwargs["scenario"]
    kwargs = {"scenario": name} if env_id == "StarEnv/Scenario-v0" else {}
    env = gym.make(env_id, overrides=small(name), **kwargs)
    env.observation_space.seed(1)
    env.action_space.seed(1)
    sample = env.observation_space.sample()
    assert env.observation_space.contains(sample)
    assert all(np.all(np.isfinite(v)) for v in (sample["time_s"], sample["gyro"]["t"], sample["gyro"]["rate"]))
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    for _ in range(2):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs) and 0.0 <= reward <= 1.0


def test_registered_episode_length_is_where_the_env_truncates():
    for name in bundled_names():
        spec = gym.spec(starenv.registration.env_id(name))
        assert spec.max_episode_steps == load(name).n_steps - 1
    assert gym.spec("StarEnv/Scenario-v0").max_episode_steps is None


def test_whole_episode_stays_inside_the_time_bounds():
    """stress_stray_light (50 frames) with truth actions: truncated on the last frame by both the env and TimeLimit,
    every observation (times included) inside the finite space."""
    env = gym.make("StarEnv/StressStrayLight-v0", overrides=small("stress_stray_light"))
    obs, info = env.reset(seed=3)
    steps, truncated, terminated = 0, False, False
    while not (truncated or terminated):
        obs, _, terminated, truncated, info = env.step({"attitude": info["truth"]["attitude"], "attitude_valid": 1})
        assert env.observation_space.contains(obs)
        steps += 1
    assert truncated and not terminated and steps == load("stress_stray_light").n_steps - 1
    assert obs["time_s"] <= env.unwrapped.time_horizon_s - env.unwrapped.scenario.frame_period_s


def available(envs, seed: int) -> dict:
    """A sampled batched action with every sub-env's estimate marked available."""
    envs.action_space.seed(seed)
    action = envs.action_space.sample()
    action["attitude_valid"][:] = 1
    return action


@pytest.mark.parametrize("valid", [(1, 0), (0, 1)])
def test_a_vector_env_merges_available_and_unavailable_steps(valid):
    """One sub-env scored, the other not, in either order: the infos merge (an unavailable step's attitude scores
    are empty, not None) and each sub-env's scores are its own."""
    envs = gym.make_vec("StarEnv/Scenario-v0", num_envs=2, vectorization_mode="sync", scenario="paper_000",
                        overrides=SMALL)
    envs.reset(seed=3)
    action = available(envs, 2)
    action["attitude_valid"][:] = valid
    _, _, _, _, info = envs.step(action)
    scores = info["scores"]
    assert scores["available"].tolist() == [bool(v) for v in valid]
    scored = valid.index(1)
    assert scores["attitude"]["_total_arcsec"].tolist() == [i == scored for i in range(2)]
    assert scores["attitude"]["total_arcsec"][scored] > 0
    envs.close()


def test_image_wrapper_in_a_vector_env():
    envs = gym.make_vec("StarEnv/Scenario-v0", num_envs=2, vectorization_mode="sync", scenario="paper_000",
                        overrides=SMALL, wrappers=[lambda e: ImageObservation(e, channels_last=True)])
    obs, _ = envs.reset(seed=5)
    assert obs.shape == (2, 128, 128, 1) and obs.dtype == np.uint16
    plain = StarSensorEnv("paper_000", SMALL)
    for i in range(2):  # sub-env i is seeded with seed + i
        ref, _ = plain.reset(seed=5 + i)
        assert np.array_equal(obs[i, :, :, 0], ref["frames"][0])
    obs, reward, *_ = envs.step(available(envs, 0))
    assert envs.observation_space.contains(obs) and reward.shape == (2,)
    envs.close()


def test_flat_state_wrapper_in_a_vector_env():
    envs = gym.make_vec("StarEnv/Scenario-v0", num_envs=2, vectorization_mode="sync", scenario="paper_000",
                        overrides=SMALL, wrappers=[FlatStateObservation])
    obs, _ = envs.reset(seed=7)
    names = FlatStateObservation(StarSensorEnv("paper_000", SMALL)).state_names()
    assert set(obs) == {"frames", "state"} and obs["state"].shape == (2, len(names))
    ref, _ = StarSensorEnv("paper_000", SMALL).reset(seed=8)  # sub-env 1
    state = dict(zip(names, obs["state"][1], strict=True))
    n = int(ref["gyro"]["count"])
    assert state["time_s"] == ref["time_s"] and state["gyro.count"] == n > 0
    assert state[f"gyro.rate[{n - 1},2]"] == ref["gyro"]["rate"][n - 1, 2]
    assert state[f"gyro.t[{n - 1}]"] == ref["gyro"]["t"][n - 1]
    assert envs.observation_space.contains(obs)
    obs, *_ = envs.step(available(envs, 1))
    assert envs.observation_space.contains(obs)
    envs.close()


def test_gymnasium_flatten_observation_round_trips():
    env = FlattenObservation(StarSensorEnv("paper_000", SMALL))
    flat, _ = env.reset(seed=2)
    back = gym.spaces.unflatten(env.unwrapped.observation_space, flat)
    ref, _ = StarSensorEnv("paper_000", SMALL).reset(seed=2)
    assert np.array_equal(back["frames"], ref["frames"]) and back["time_s"] == ref["time_s"]


def test_record_video_with_the_video_extra(tmp_path):
    pytest.importorskip("moviepy", reason="the 'video' extra")
    env = gym.make("StarEnv/Scenario-v0", scenario="paper_000", overrides=SMALL, render_mode="rgb_array",
                   max_episode_steps=4)
    env = RecordVideo(env, str(tmp_path), episode_trigger=lambda _: True, disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(env.unwrapped.null_action())
        done = terminated or truncated
    env.close()
    (video,) = tmp_path.glob("*.mp4")
    assert video.stat().st_size > 1000


def _keys(value):
    if isinstance(value, dict):
        for k, v in value.items():
            yield k
            yield from _keys(v)
    elif isinstance(value, list):
        for v in value:
            yield from _keys(v)


def test_every_info_key_is_documented():
    env = StarSensorEnv("paper_000", SMALL)
    _, info = env.reset(seed=0)
    _, _, _, _, step_info = env.step({"attitude": info["truth"]["attitude"], "attitude_valid": 1,
                                     **{k: v for k, v in env.null_action().items() if k not in ("attitude",
                                                                                               "attitude_valid")}})
    keys = set(_keys(info)) | set(_keys(step_info))
    assert {"scores", "truth", "total_arcsec", "cross_boresight_arcsec", "centroid_error_px_max"} <= keys
    undocumented = sorted(k for k in keys if k not in starenv.env.__doc__)
    assert undocumented == []
