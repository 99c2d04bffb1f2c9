"""Environment speed: steps/s of the 512 x 512 paper_000 scenario with a do-nothing action on one core, and the
speed-up of an async vector env with 2 workers over that single env (measured in the same run), observations through
shared memory (Gymnasium's default), pickled, and through shared memory with each worker prefetching its next frame
(``prefetch=True``: simulated while the main process handles the last step); starenv's ``SharedMemoryVectorEnv``
(actions, observations, rewards and flags in shared memory) with its defaults (infos sent, observations copied) and
lean (no infos, observations as views of the shared memory); "bare workers", the floor of any process-based vector
env's overhead (a byte to step, the frames written straight into shared memory, a byte back and nothing else); one
env driven by the scenario's own pipeline, with and without prefetch (the next frame simulated on a thread while the
pipeline works); then a cProfile of single-env steps.

Goals: >= 300 steps/s; >= 1.8x with 2 workers.  The machines are shared: each figure is the median of ``--repeats``
rounds, every round timing all variants back to back, and the floor of a step (one float32 standard normal per pixel
of the frame with numpy's Generator, the read-out's noise draw) is timed in the same rounds, alone and in two processes
at once: the second gives the ceiling any 2-worker speed-up has on this machine (two cores that share a physical core
or memory bandwidth give less than 2x).  The CPU time per env step of the vector env's workers and main process is
printed beside the single env's: two cores cannot run more than 2 / (their sum) env steps a second, whatever the
schedule.  The 1-minute load average is printed before and after.

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


def single(steps: int) -> tuple[float, float]:
    """Steps/s of one env, and its CPU time (s) per step."""
    env = gym.make(ENV_ID)
    action = env.unwrapped.null_action()  # the same (empty) action the vector env sends
    env.reset(seed=0)
    env.step(action)
    cpu, t0 = time.process_time(), time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - t0)
    cpu = (time.process_time() - cpu) / steps
    env.close()
    return rate, cpu


def vector(steps: int, workers: int, shared_memory: bool, prefetch: bool = False) -> tuple[float, float, float]:
    """Steps/s (all workers) of an async vector env, and the CPU time (s) per env step of the main process and of
    the workers (their env step, the pipes, the shared memory; with their set-up and ``steps = 0``'s share of it
    taken off by the caller); ``prefetch``: each worker's env simulates its next frame while the main process
    handles the last one."""
    before = os.times()
    envs = gym.make_vec(ENV_ID, num_envs=workers, vectorization_mode="async",
                        vector_kwargs={"shared_memory": shared_memory}, prefetch=prefetch)
    template = envs.env_fns[0]().unwrapped.null_action()
    action = {k: np.stack([v] * workers) for k, v in template.items()}
    envs.reset(seed=0)
    envs.step(action)
    main_cpu, t0 = time.process_time(), time.perf_counter()
    for _ in range(steps):
        envs.step(action)  # autoreset handles episode ends
    rate = steps * workers / max(time.perf_counter() - t0, 1e-9)
    main_cpu = time.process_time() - main_cpu
    envs.close()  # a worker's CPU time is counted once it has exited
    after = os.times()
    worker_cpu = (after.children_user + after.children_system) - (before.children_user + before.children_system)
    return rate, main_cpu / max(steps * workers, 1), worker_cpu / max(steps * workers, 1)


def lean_vector(steps: int, workers: int, infos: bool, copy: bool) -> float:
    """Steps/s (all workers) of starenv's ``SharedMemoryVectorEnv`` (actions, observations, rewards and flags in
    shared memory)."""
    from starenv.vector import SharedMemoryVectorEnv

    envs = SharedMemoryVectorEnv.from_id(ENV_ID, workers, workers=workers, infos=infos, copy=copy)
    template = gym.make(ENV_ID).unwrapped.null_action()
    action = {k: np.stack([v] * workers) for k, v in template.items()}
    envs.reset(seed=0)
    envs.step(action)
    t0 = time.perf_counter()
    for _ in range(steps):
        envs.step(action)
    rate = steps * workers / (time.perf_counter() - t0)
    envs.close()
    return rate


def _bare_worker(index: int, envs: int, shm_name: str, pipe) -> None:
    """Step env ``index`` whenever the main process says so, write its frames into the shared block, answer a byte."""
    from multiprocessing.shared_memory import SharedMemory

    env = gym.make(ENV_ID)
    action = env.unwrapped.null_action()
    block = SharedMemory(name=shm_name)
    frames = np.ndarray((envs, *env.observation_space["frames"].shape), np.uint16, buffer=block.buf)
    env.reset(seed=index)
    while pipe.recv():
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
        frames[index] = obs["frames"]
        pipe.send(True)
    del frames
    block.close()


def bare_workers(steps: int, workers: int) -> float:
    """Steps/s (all workers) of the least a process-based vector env can do per step: each worker steps its env on a
    one-byte message, writes the frames into one shared-memory block and answers a byte (no action, no observation
    or info sent, no autoreset bookkeeping in the main process)."""
    from multiprocessing.shared_memory import SharedMemory

    shape = gym.make(ENV_ID).observation_space["frames"].shape
    block = SharedMemory(create=True, size=workers * int(np.prod(shape)) * 2)
    context = multiprocessing.get_context("fork")
    pipes, processes = [], []
    for index in range(workers):
        ours, theirs = context.Pipe()
        process = context.Process(target=_bare_worker, args=(index, workers, block.name, theirs), daemon=True)
        process.start()
        pipes.append(ours)
        processes.append(process)

    def step_all() -> None:
        for pipe in pipes:
            pipe.send(True)
        for pipe in pipes:
            pipe.recv()

    step_all()
    t0 = time.perf_counter()
    for _ in range(steps):
        step_all()
    rate = steps * workers / (time.perf_counter() - t0)
    for pipe, process in zip(pipes, processes, strict=True):
        pipe.send(False)
        process.join()
    block.close()
    block.unlink()
    return rate


def with_pipeline(steps: int, prefetch: bool) -> float:
    """Steps/s of one env driven by the scenario's own classical pipeline (OpenCV held to one thread)."""
    import cv2

    from starenv.agents.pipeline import Pipeline

    cv2.setNumThreads(1)
    env = gym.make(ENV_ID, prefetch=prefetch)
    pipeline = Pipeline.for_scenario(env.unwrapped.scenario)
    obs, _ = env.reset(seed=0)
    pipeline.reset(env.unwrapped.sensor_info)
    obs, *_ = env.step(pipeline(obs))
    t0 = time.perf_counter()
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(pipeline(obs))
        if terminated or truncated:
            obs, _ = env.reset()
            pipeline.reset(env.unwrapped.sensor_info)
    rate = steps / (time.perf_counter() - t0)
    env.close()
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
    set_up = vector(0, 2, True)[2]  # the workers' CPU time to start, reset and take one step, per env
    rounds = []
    for _ in range(args.repeats):
        one, one_cpu = single(args.steps)
        shared, main_cpu, worker_cpu = vector(args.steps, 2, True)
        rounds.append({
            "floor": floor_rate(shape, args.steps), "floor x2": parallel_floor(shape, args.steps),
            "single": one, "single cpu": one_cpu, "shared": shared, "main cpu": main_cpu,
            "worker cpu": worker_cpu - set_up / (2 * args.steps),
            "pickled": vector(args.steps, 2, False)[0], "prefetch": vector(args.steps, 2, True, prefetch=True)[0],
            "bare": bare_workers(args.steps, 2),
            "lean": lean_vector(args.steps, 2, infos=True, copy=True),
            "lean views": lean_vector(args.steps, 2, infos=False, copy=False),
            "pipeline": with_pipeline(args.steps // 3, False),
            "pipeline prefetch": with_pipeline(args.steps // 3, True),
        })
    median = {k: float(np.median([r[k] for r in rounds])) for k in rounds[0]}
    ratio = {k: float(np.median([r[k] / r["single"] for r in rounds])) for k in rounds[0]}
    ceiling = float(np.median([r["floor x2"] / r["floor"] for r in rounds]))
    # Two cores run the workers' and the main process's CPU time per env step: no schedule beats 2 / their sum.
    cpu_bound = float(np.median([2.0 / (r["main cpu"] + r["worker cpu"]) / r["single"] for r in rounds]))
    print(f"load average (1 min): {load_before:.2f} before, {os.getloadavg()[0]:.2f} after, on {os.cpu_count()} cores; "
          f"medians of {args.repeats} rounds of {args.steps} steps")
    print(f"noise floor ({shape[0]}x{shape[1]} float32 normals): {median['floor']:8.1f} frames/s")
    print(f"single env, do-nothing action:    {median['single']:8.1f} steps/s   (goal >= 300) = "
          f"{ratio['floor']:.2f} x the floor's time")
    print(f"noise floor in 2 processes at once: {ceiling:.2f} x one process (the ceiling of a 2-worker speed-up here)")
    for key, label in (("shared", "Gymnasium async, shared memory"), ("pickled", "Gymnasium async, pickled"),
                       ("prefetch", "Gymnasium async, + prefetch"), ("bare", "bare workers (the floor)"),
                       ("lean", "SharedMemoryVectorEnv"), ("lean views", "SharedMemoryVectorEnv, no infos, views")):
        print(f"vector env, 2 workers, {label:<38} {median[key]:6.1f} steps/s = {ratio[key]:.2f} x single "
              f"(goal >= 1.8; {ratio[key] / ceiling:.2f} of the ceiling)")
    print(f"CPU time per env step: single env {median['single cpu'] * 1e3:.2f} ms; in Gymnasium's async vector env "
          f"worker {median['worker cpu'] * 1e3:.2f} ms + main process {median['main cpu'] * 1e3:.2f} ms: on 2 cores "
          f"at most {cpu_bound:.2f} x single")
    print(f"single env + the scenario's pipeline: {median['pipeline']:8.1f} steps/s; with prefetch "
          f"{median['pipeline prefetch']:.1f} steps/s = {ratio['pipeline prefetch'] / ratio['pipeline']:.2f} x")
    print(f"\nprofile of {args.profile_steps} single-env steps:\n{profile(args.profile_steps)}")


if __name__ == "__main__":
    main()
