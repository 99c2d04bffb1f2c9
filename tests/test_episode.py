"""The shared episode loop: each step's log pairs a frame with its truth, action and scores; observers always close."""

import gymnasium as gym
import numpy as np
import pytest

from starenv.agents.base import StepReport
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.scoring import flatten


class Collect:
    def __init__(self, fail_at=None):
        self.logs, self.closed, self.fail_at = [], None, fail_at

    def start(self, env, seed, pipeline):
        self.seed = seed

    def step(self, log):
        if log.index == self.fail_at:
            raise RuntimeError("observer failure")
        self.logs.append(log)

    def close(self, error=None):
        self.closed = error if error is not None else "ok"


def test_logs_pair_each_frame_with_its_truth_action_and_scores():
    env = StarSensorEnv("paper_004")
    seen = Collect()
    result = run_episode(env, None, seed=3, steps=4, observers=[seen])
    assert seen.seed == 3 and seen.closed == "ok"
    assert [log.index for log in seen.logs] == [0, 1, 2, 3]
    for log in seen.logs:
        assert log.truth["frame"] == log.scores["frame"] == log.record["frame"] == log.index
        assert log.truth["time_s"] == log.scores["time_s"] == log.record["time_s"]
        assert log.action is None and log.record["available"] == 0.0
    assert len(result.records) == 4 and result.dropped.shape == (len(env.scenario.heads),)


def test_records_match_a_hand_written_loop_with_the_true_attitude():
    env = StarSensorEnv("paper_004")

    class Oracle:
        """Reports the true attitude, fed by the wrapper below (no real agent may see truth)."""

        report = StepReport(source="solved")

        def reset(self, sensor):
            pass

        def describe(self):
            return {}

        def __call__(self, obs):
            return {"attitude": self.truth["attitude"], "attitude_valid": np.int8(1)}

    oracle = Oracle()

    class Remember(gym.Wrapper):
        def reset(self, **kw):
            obs, info = self.env.reset(**kw)
            oracle.truth = info["truth"]
            return obs, info

        def step(self, action):
            out = self.env.step(action)
            oracle.truth = out[4]["truth"]
            return out

    result = run_episode(Remember(env), oracle, seed=5, steps=3, observers=[Collect()])
    assert all(r["attitude_error_arcsec"] == pytest.approx(0.0, abs=1e-6) for r in result.records)

    env2 = StarSensorEnv("paper_004")
    obs, info = env2.reset(seed=5)
    manual = []
    for _ in range(3):
        obs, _, _, _, info2 = env2.step({"attitude": info["truth"]["attitude"], "attitude_valid": np.int8(1)})
        manual.append(flatten(info2["scores"], {}))
        info = info2
    assert result.records == manual


def test_observers_are_closed_with_the_error_and_it_propagates():
    env = StarSensorEnv("paper_004")
    seen = Collect(fail_at=2)
    with pytest.raises(RuntimeError, match="observer failure"):
        run_episode(env, None, seed=0, steps=5, observers=[seen])
    assert isinstance(seen.closed, RuntimeError) and len(seen.logs) == 2


def test_a_policy_that_misses_the_contract_is_refused_by_name():
    class Bare:
        def __call__(self, obs):
            return None

    with pytest.raises(TypeError, match="Policy protocol"):
        run_episode(StarSensorEnv("paper_004"), Bare(), seed=0, steps=1)
