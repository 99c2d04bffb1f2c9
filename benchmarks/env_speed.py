"""Environment speed: steps/s of the 512 x 512 seed-000 scenario with a do-nothing action on one core, and the
speed-up of an async vector env with 2 workers over that single env (measured in the same run), observations through
shared memory (Gymnasium's default) and pickled; then a cProfile of single-env steps.

Goals: >= 300 steps/s; >= 1.8x with 2 workers.  The machines are shared: each figure is the median of ``--repeats``
rounds, every round timing all variants back to back, and the floor of a step (one float32 standard normal per pixel
of the frame with numpy's Generator, the read-out's noise draw) is timed in the same rounds, alone and in two processes
at once: the second gives the ceiling any 2-worker speed-up has on this machine (two cores that share a physical core
or memory bandwidth give less than 2x); the 1-minute load average is printed before and after.

    python benchmarks/env_speed.py [--steps N] [--repeats N] [--profile-steps N]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import multiprocessing
import os
import pstats
import time

import gymnasium as gym
import numpy as np

import starenv  # noqa: F401  (registers the ids)

ENV_ID = "StarEnv/Paper000-v0"


def single(steps: int) -> float:
    """Steps/s of one env."""
    env = gym.make(ENV_ID)
    action = env.unwrapped.null_action()  # the same (empty) action the vector env sends
    env.reset(seed=0)
    env.step(action)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate


def vector(steps: int, workers: int, shared_memory: bool) -> float:
    """Steps/s (all workers) of an async vector env."""
    envs = gym.make_vec(ENV_ID, num_envs=workers, vectorization_mode="async",
                        vector_kwargs={"shared_memory": shared_memory})
    template = envs.env_fns[0]().unwrapped.null_action()
    action = {k: np.stack([v] * workers) for k, v in template.items()}
    envs.reset(seed=0)
    envs.step(action)
    t0 = time.perf_counter()
    for _ in range(steps):
        envs.step(action)  # autoreset handles episode ends
    rate = steps * workers / (time.perf_counter() - t0)
    envs.close()
    return rate


def floor_rate(shape: tuple[int, int], steps: int) -> float:
    """Frames/s of the noise floor: one float32 standard normal per pixel."""
    rng = np.random.default_rng(0)
    out = np.empty(shape, np.float32)
    t0 = time.perf_counter()
    for _ in range(steps):
        rng.standard_normal(dtype=np.float32, out=out)
    return steps / (time.perf_counter() - t0)


def parallel_floor(shape: tuple[int, int], steps: int) -> float:
    """Frames/s of the noise floor summed over two processes drawing at once."""
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        pool.starmap(floor_rate, [(shape, 5)] * 2)  # both workers started and warm
        return float(sum(pool.starmap(floor_rate, [(shape, steps)] * 2)))


def profile(steps: int) -> str:
    """The top of a cProfile of ``steps`` single-env steps, by cumulative and by own time."""
    env = gym.make(ENV_ID)
    action = env.unwrapped.null_action()
    env.reset(seed=0)
    env.step(action)
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(steps):
        env.step(action)
    profiler.disable()
    text = io.StringIO()
    stats = pstats.Stats(profiler, stream=text)
    stats.sort_stats("cumulative").print_stats(r"starenv", 18)
    stats.sort_stats("tottime").print_stats(12)
    return "\n".join(line for line in text.getvalue().splitlines() if line.strip() and "Ordered by" not in line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile-steps", type=int, default=300)
    args = parser.parse_args()
    shape = gym.make(ENV_ID).observation_space["frames"].shape[1:]
    load_before = os.getloadavg()[0]
    rounds = []
    for _ in range(args.repeats):
        rounds.append({
            "floor": floor_rate(shape, args.steps), "floor x2": parallel_floor(shape, args.steps),
            "single": single(args.steps),
            "shared": vector(args.steps, 2, True), "pickled": vector(args.steps, 2, False),
        })
    median = {k: float(np.median([r[k] for r in rounds])) for k in rounds[0]}
    ratio = {k: float(np.median([r[k] / r["single"] for r in rounds])) for k in rounds[0]}
    ceiling = float(np.median([r["floor x2"] / r["floor"] for r in rounds]))
    print(f"load average (1 min): {load_before:.2f} before, {os.getloadavg()[0]:.2f} after, on {os.cpu_count()} cores; "
          f"medians of {args.repeats} rounds of {args.steps} steps")
    print(f"noise floor ({shape[0]}x{shape[1]} float32 normals): {median['floor']:8.1f} frames/s")
    print(f"single env, do-nothing action:    {median['single']:8.1f} steps/s   (goal >= 300) = "
          f"{ratio['floor']:.2f} x the floor's time")
    print(f"noise floor in 2 processes at once: {ceiling:.2f} x one process (the ceiling of a 2-worker speed-up here)")
    for key, label in (("shared", "shared memory"), ("pickled", "pickled     ")):
        print(f"async vector env, 2 workers, {label}: {median[key]:8.1f} steps/s = {ratio[key]:.2f} x single "
              f"(goal >= 1.8; {ratio[key] / ceiling:.2f} of the ceiling)")
    print(f"\nprofile of {args.profile_steps} single-env steps:\n{profile(args.profile_steps)}")


if __name__ == "__main__":
    main()
