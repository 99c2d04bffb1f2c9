"""SharedMemoryVectorEnv against Gymnasium's SyncVectorEnv, which steps the same envs one after the other in this
process: every observation, reward, flag and info must be the same bit for bit, episode ends included."""

import os
from unittest import mock

import gymnasium as gym
import numpy as np
import pytest

from starenv.env import StarSensorEnv
from starenv.vector import SharedMemoryVectorEnv

SMALL = {"heads.0.width": 128, "heads.0.height": 128}  # paper_000 on a 128 px crop: fast
KWARGS = {"scenario": "paper_000", "overrides": SMALL, "max_episode_steps": 3}


def truth_actions(envs, infos) -> dict:
    """Every sub-env's true attitude as its estimate (scored, so the rewards are not all zero)."""
    action = {k: np.stack([v] * envs.num_envs) for k, v in StarSensorEnv("paper_000", SMALL).null_action().items()}
    action["attitude"], action["attitude_valid"] = infos["truth"]["attitude"].copy(), np.ones(envs.num_envs, np.int8)
    return action


def rollout(envs, steps: int) -> list:
    observations, infos = envs.reset(seed=11)
    out = [observations, infos]
    for _ in range(steps):
        observations, rewards, terminations, truncations, infos = envs.step(truth_actions(envs, infos))
        out += [observations, rewards, terminations, truncations, infos]
    envs.close()
    return out


def same(a, b) -> bool:
    """Bit-for-bit equality of nested observations and merged infos (object arrays of per-env lists included)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray) and a.dtype == object:
        return b.dtype == object and a.shape == b.shape and same(a.tolist(), b.tolist())
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    return type(a) is type(b) and a == b


def test_three_envs_in_two_workers_step_as_gymnasiums_sync_vector_env_across_episode_ends():
    # max_episode_steps=3: the 3rd and 7th steps truncate, the 4th and 8th reset (Gymnasium's "next step" mode).
    ours = rollout(SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", 3, workers=2, **KWARGS), 8)
    theirs = rollout(gym.make_vec("StarEnv/Scenario-v0", num_envs=3, vectorization_mode="sync", **KWARGS), 8)
    assert len(ours) == len(theirs)
    assert all(same(a, b) for a, b in zip(ours, theirs, strict=True))
    truncations = [ours[2 + 5 * k + 3] for k in range(8)]
    assert [bool(t.all()) for t in truncations] == [False, False, True, False, False, False, True, False]
    rewards = [ours[2 + 5 * k + 1] for k in range(8)]
    assert (rewards[3] == 0).all() and (rewards[0] > 0).all()  # the reset step pays nothing, a scored one does
    # each env i is the single env seeded 11 + i; the returned observations are copies, not the shared memory
    single = StarSensorEnv("paper_000", SMALL)
    first, _ = single.reset(seed=12)
    assert np.array_equal(ours[0]["frames"][1], first["frames"])
    assert not np.array_equal(ours[0]["frames"][1], ours[2]["frames"][1])


def test_gym_make_vec_without_a_mode_builds_it_and_it_steps_as_gymnasiums_async_default_bit_for_bit():
    # Gymnasium's async vector env in its default mode (observations through shared memory); the same episode ends
    # as above.  The vector env's own options (workers) go to it, the rest to each env.
    envs = gym.make_vec("StarEnv/Scenario-v0", num_envs=3, workers=2, **KWARGS)
    assert isinstance(envs.unwrapped, SharedMemoryVectorEnv) and len(envs.unwrapped._processes) == 2
    ours = rollout(envs, 8)
    theirs = rollout(gym.make_vec("StarEnv/Scenario-v0", num_envs=3, vectorization_mode="async", **KWARGS), 8)
    assert len(ours) == len(theirs) == 2 + 5 * 8
    assert all(same(a, b) for a, b in zip(ours, theirs, strict=True))
    assert [bool(ours[2 + 5 * k + 3].all()) for k in range(8)] == [False, False, True, False] * 2
    # a bundled id builds its own scenario
    bundled = gym.make_vec("StarEnv/Paper000-v0", num_envs=2, overrides=SMALL)
    assert isinstance(bundled.unwrapped, SharedMemoryVectorEnv)
    reference = gym.make_vec("StarEnv/Paper000-v0", num_envs=2, vectorization_mode="sync", overrides=SMALL)
    assert same(bundled.reset(seed=5), reference.reset(seed=5))
    bundled.close()
    reference.close()


def test_infos_can_be_turned_off_and_observations_returned_as_views():
    envs = SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", 2, workers=2, infos=False, copy=False, **KWARGS)
    observations, infos = envs.reset(seed=3)
    assert "truth" in infos  # a reset always returns its infos
    frames = observations["frames"]
    stepped, _, _, _, infos = envs.step(truth_actions(envs, envs.reset(seed=3)[1]))
    assert infos == {} and stepped["frames"] is frames  # the same shared memory, overwritten in place
    reference = StarSensorEnv("paper_000", SMALL)
    reference.reset(seed=4)
    assert np.array_equal(frames[1], reference.step(reference.null_action())[0]["frames"])
    envs.close()


def test_a_nan_action_is_refused_with_the_envs_index_and_the_pipes_stay_in_step():
    envs = SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", 2, workers=2, **KWARGS)
    _, infos = envs.reset(seed=0)
    action = truth_actions(envs, infos)
    action["attitude"][1, 0] = np.nan
    with pytest.raises(ValueError, match=r"env 1: .*finite"):
        envs.step(action)
    action["attitude"][1] = infos["truth"]["attitude"][1]
    _, rewards, *_ = envs.step(action)  # the next step's answers are this step's, not the failed one's
    assert rewards.shape == (2,) and np.isfinite(rewards).all()
    envs.close()


@pytest.mark.parametrize(("actions", "message"), [
    ({"attitude": np.zeros(4)}, "actions must be a dict with keys"),
    ("shape", r"actions\['attitude'\] must have shape \(2, 4\)"),
])
def test_malformed_actions_are_refused_before_any_worker_steps(actions, message):
    envs = SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", 2, workers=1, **KWARGS)
    _, infos = envs.reset(seed=0)
    if actions == "shape":
        actions = truth_actions(envs, infos)
        actions["attitude"] = actions["attitude"][:1]
    with pytest.raises(ValueError, match=message):
        envs.step(actions)
    envs.close()


class _DiesOnStep(gym.Wrapper):
    def step(self, action):
        os._exit(3)


def test_a_worker_that_dies_is_named_and_the_vector_env_still_closes():
    envs = SharedMemoryVectorEnv([lambda: StarSensorEnv("paper_000", SMALL),
                                  lambda: _DiesOnStep(StarSensorEnv("paper_000", SMALL))], workers=2,
                                 context="fork")
    _, infos = envs.reset(seed=0)
    with pytest.raises(RuntimeError, match=r"the worker of envs 1-1 died \(exit code 3\)"):
        envs.step(truth_actions(envs, infos))
    envs.close()
    assert envs.closed


@pytest.mark.parametrize("workers", [0, 3, 1.5, True])
def test_a_worker_count_outside_one_to_num_envs_is_refused(workers):
    with pytest.raises(ValueError, match=r"workers must be an integer from 1 to num_envs \(2\)"):
        SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", 2, workers=workers, **KWARGS)


@pytest.mark.parametrize(("cpus", "num_envs", "workers", "thread"),
                         [(4, 2, 2, True), (3, 2, 2, False), (16, 4, None, True), (6, 4, None, False),
                          (2, 4, 1, True), (1, 2, 1, False)])
def test_workers_draw_noise_on_a_second_thread_only_with_two_cores_each(cpus, num_envs, workers, thread):
    # from_id gives each env a noise thread exactly when the process may use two cores for every worker (one worker
    # per env up to the CPU count by default); an explicit setting is kept.
    given = []

    def init(self, env_fns, **options):  # (no workers started)
        given.append(env_fns[0].kwargs["noise_thread"])
        self.closed = True

    with mock.patch("multiprocessing.cpu_count", return_value=cpus), \
            mock.patch("os.sched_getaffinity", return_value=set(range(cpus))), \
            mock.patch.object(SharedMemoryVectorEnv, "__init__", init):
        SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", num_envs, workers=workers)
        SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", num_envs, workers=workers, noise_thread=not thread)
    assert given == [thread, not thread]


def test_a_spawned_worker_builds_its_envs_from_the_id_and_gives_the_same_frames():
    # Under "spawn" nothing is inherited: the env makers and the shared blocks travel pickled to the workers.
    envs = SharedMemoryVectorEnv.from_id("StarEnv/Scenario-v0", 2, workers=2, context="spawn", **KWARGS)
    envs.reset(seed=5)
    stepped, *_ = envs.step(truth_actions(envs, envs.reset(seed=5)[1]))
    envs.close()
    reference = StarSensorEnv("paper_000", SMALL)
    reference.reset(seed=6)
    assert np.array_equal(stepped["frames"][1], reference.step(reference.null_action())[0]["frames"])


SCRIPT = """
import os, sys
import gymnasium as gym
from starenv.env import StarSensorEnv
from starenv.vector import SharedMemoryVectorEnv

class MarksClose(gym.Wrapper):
    def close(self):
        with open(os.path.join(sys.argv[1], str(os.getpid())), "w") as f:
            f.write("closed")
        super().close()

small = {"heads.0.width": 128, "heads.0.height": 128}
envs = SharedMemoryVectorEnv([lambda: MarksClose(StarSensorEnv("paper_000", small))] * 2, workers=2, context="fork")
envs.reset(seed=0)
print(os.getpid(), flush=True)
os._exit(0)  # gone without closing anything
"""


def test_workers_close_their_envs_when_the_main_process_dies(tmp_path):
    import subprocess
    import sys
    import time

    main = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path)], capture_output=True, text=True, check=True)
    main_pid = main.stdout.split()[-1]
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline and len([p for p in tmp_path.iterdir() if p.name != main_pid]) < 2:
        time.sleep(0.1)
    closed = [p for p in tmp_path.iterdir() if p.name != main_pid]  # the main process closed only its probe env
    assert len(closed) == 2 and all(p.read_text() == "closed" for p in closed)
