"""Environment speed: steps/s of the 512 x 512 paper_000 scenario with a do-nothing action on one core, and the
speed-up of an async vector env with 2 workers over that single env (measured in the same run), observations through
shared memory (Gymnasium's default), pickled, and through shared memory with each worker prefetching its next frame
(``prefetch=True``: simulated while the main process handles the last step); starenv's ``SharedMemoryVectorEnv``
(actions, observations, rewards and flags in shared memory) with its defaults (infos sent, observations copied) and
lean (no infos, observations as views of the shared memory); "bare workers", the floor of any process-based vector
env's overhead (a byte to step, the frames written straight into shared memory, a byte back and nothing else); one
env driven by the scenario's own pipeline, with and without prefetch (the next frame simulated on a thread while the
pipeline works); then a cProfile of single-env steps.  ``--parts breakdown`` times the parts of the 1024 x 1024 step
below (the read-out, the render, scoring, the gyro, the observation, the action's parsing) by wrapping each one's
function, each part's time over the floor draw's (with ``noise_thread=False``, so that the read-out holds its draw).

Then ``env.step`` on a 1024 x 1024 frame (paper 002's optics, stars to magnitude 7, ~40 on a frame; 50 ms exposure,
~30 px trails; noise on; the true attitude of the last frame sent as the action, so the step scores it): everything a
step does (scoring, the star render, the read-out, the gyro, truth and observation) against the floor of drawing the
frame's noise, one float32 standard normal per pixel, each step timed beside one floor draw.  Each round points the
camera somewhere else, drawn from ``--seed``.  The env takes its default, which in this process draws the noise on a
second thread while the stars render; the same steps with ``noise_thread=False`` (all on one thread) and the CPU time
a step (both threads) follow, each over the floor.  A vector env's workers draw on one thread (see
:func:`~starenv.sim.sensor.noise_thread_default`), so their speed-up is also given over a single env without the
noise thread, the same work a step as a worker's.

Goals: >= 300 steps/s; >= 1.8x with 2 workers; a 1024 x 1024 ``env.step`` <= 1.5x the floor.  The machines are shared:
each figure is the median of ``--repeats`` rounds with its spread (lowest and highest round) beside it, every round
timing all variants back to back, and the floor of a step (one float32 standard normal per pixel of the frame with
numpy's Generator, the read-out's noise draw) is timed in the same rounds, alone and in two processes at once: the
second gives the ceiling any 2-worker speed-up has on this machine (two cores that share a physical core or memory
bandwidth give less than 2x).  The CPU time per env step of the vector env's workers and main process is printed
beside the single env's: two cores cannot run more than 2 / (their sum) env steps a second, whatever the schedule.
The 1-minute load average is printed before and after.  Every env is seeded from ``--seed`` (env ``i`` of a vector
env with ``seed + i``); ``--parts`` picks what to time.

    python benchmarks/env_speed.py [--seed N] [--steps N] [--repeats N] [--profile-steps N] [--parts step,vector,...]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import math
import multiprocessing
import os
import pstats
import time

import gymnasium as gym
import numpy as np

import starenv  # noqa: F401  (registers the ids)

ENV_ID = "StarEnv/Paper000-v0"
FRAME_SCENARIO = "paper_002"  # the 1024 x 1024 step: paper 002's optics (12 deg field)
FRAME_MAG_LIMIT = 7.0  # a star tracker's depth on a 12 deg frame (the star count per pointing is printed)
FRAME_EXPOSURE_S = 0.05
FRAME_TRAIL_PX = 30.0  # trail length on the boresight


def single(steps: int, seed: int, noise_thread: bool | None = None) -> tuple[float, float]:
    """Steps/s of one env, and its CPU time (s) per step; ``noise_thread``: the env's (None: its default)."""
    env = gym.make(ENV_ID, noise_thread=noise_thread)
    action = env.unwrapped.null_action()  # the same (empty) action the vector env sends
    env.reset(seed=seed)
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


def vector(steps: int, workers: int, shared_memory: bool, seed: int,
           prefetch: bool = False) -> tuple[float, float, float]:
    """Steps/s (all workers) of an async vector env, and the CPU time (s) per env step of the main process and of
    the workers (their env step, the pipes, the shared memory; with their set-up and ``steps = 0``'s share of it
    taken off by the caller); ``prefetch``: each worker's env simulates its next frame while the main process
    handles the last one."""
    before = os.times()
    envs = gym.make_vec(ENV_ID, num_envs=workers, vectorization_mode="async",
                        vector_kwargs={"shared_memory": shared_memory}, prefetch=prefetch)
    template = envs.env_fns[0]().unwrapped.null_action()
    action = {k: np.stack([v] * workers) for k, v in template.items()}
    envs.reset(seed=seed)
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


def lean_vector(steps: int, workers: int, infos: bool, copy: bool, seed: int) -> float:
    """Steps/s (all workers) of starenv's ``SharedMemoryVectorEnv`` (actions, observations, rewards and flags in
    shared memory)."""
    from starenv.vector import SharedMemoryVectorEnv

    envs = SharedMemoryVectorEnv.from_id(ENV_ID, workers, workers=workers, infos=infos, copy=copy)
    template = gym.make(ENV_ID).unwrapped.null_action()
    action = {k: np.stack([v] * workers) for k, v in template.items()}
    envs.reset(seed=seed)
    envs.step(action)
    t0 = time.perf_counter()
    for _ in range(steps):
        envs.step(action)
    rate = steps * workers / (time.perf_counter() - t0)
    envs.close()
    return rate


def _bare_worker(index: int, envs: int, shm_name: str, pipe, seed: int) -> None:
    """Step env ``index`` whenever the main process says so, write its frames into the shared block, answer a byte."""
    from multiprocessing.shared_memory import SharedMemory

    env = gym.make(ENV_ID)
    action = env.unwrapped.null_action()
    block = SharedMemory(name=shm_name)
    frames = np.ndarray((envs, *env.observation_space["frames"].shape), np.uint16, buffer=block.buf)
    env.reset(seed=seed + index)
    while pipe.recv():
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
        frames[index] = obs["frames"]
        pipe.send(True)
    del frames
    block.close()


def bare_workers(steps: int, workers: int, seed: int) -> float:
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
        process = context.Process(target=_bare_worker, args=(index, workers, block.name, theirs, seed),
                                  daemon=True)
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


def with_pipeline(steps: int, prefetch: bool, seed: int) -> float:
    """Steps/s of one env driven by the scenario's own classical pipeline (OpenCV held to one thread)."""
    import cv2

    from starenv.agents.pipeline import Pipeline

    cv2.setNumThreads(1)
    env = gym.make(ENV_ID, prefetch=prefetch)
    pipeline = Pipeline.for_scenario(env.unwrapped.scenario)
    obs, _ = env.reset(seed=seed)
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


def floor_rate(shape: tuple[int, int], steps: int, seed: int = 0) -> float:
    """Frames/s of the noise floor: one float32 standard normal per pixel."""
    rng = np.random.default_rng(seed)
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


def random_pointing_deg(rng: np.random.Generator) -> tuple[float, float, float]:
    """A boresight uniform on the sky and a uniform roll about it: right ascension, declination, roll (deg)."""
    return 360.0 * rng.random(), math.degrees(math.asin(2.0 * rng.random() - 1.0)), 360.0 * rng.random()


def frame_env(seed: int, steps: int, noise_thread: bool | None = None) -> gym.Env:
    """The 1024 x 1024 env of the ``env.step`` figure, pointed at a direction drawn from ``seed``
    (:func:`random_pointing_deg`), long enough for ``steps`` steps after its reset; ``noise_thread``: the env's."""
    ra, dec, roll = random_pointing_deg(np.random.default_rng(seed))
    focal_px = 58.5e-3 / 12e-6  # paper 002: f = 58.5 mm, 12 um pixels
    rate = math.degrees(FRAME_TRAIL_PX / (focal_px * FRAME_EXPOSURE_S)) / math.sqrt(2.0)  # deg/s about X and Y
    overrides = {"mag_limit": FRAME_MAG_LIMIT, "exposure_s": FRAME_EXPOSURE_S, "motion.rate_dps": [rate, rate, 0.0],
                 "motion.initial_ra_deg": ra, "motion.initial_dec_deg": dec, "motion.initial_roll_deg": roll,
                 "duration_s": (steps + 3) / 10.0}  # paper 002 runs at 10 Hz
    return gym.make("StarEnv/Scenario-v0", scenario=FRAME_SCENARIO, overrides=overrides, noise_thread=noise_thread)


def _scored_step(env: gym.Env, action: dict, info: dict) -> dict:
    """One step sending the true attitude of the last observation (scored as a pipeline's would be); its info."""
    action["attitude"] = info["truth"]["attitude"]
    return env.step(action)[4]


def _stepped_frame_env(seed: int, steps: int, noise_thread: bool | None = None) -> tuple[gym.Env, dict, dict, int]:
    """:func:`frame_env` reset and stepped once (untimed): the env, the action it is stepped with, the last info and
    the stars on the first frame."""
    env = frame_env(seed, steps + 1, noise_thread)
    action = env.unwrapped.null_action()
    action["attitude_valid"] = np.array(1, np.int8)
    _, info = env.reset(seed=seed)
    stars = len(info["truth"]["stars"][0]["catalog_id"])
    return env, action, _scored_step(env, action, info), stars


def frame_step(steps: int, seed: int, warmed=None, noise_thread: bool | None = None) -> tuple[float, float, int, float]:
    """Median time (s) of a 1024 x 1024 ``env.step`` and of one floor draw of its frame, each step timed beside one
    draw (after one untimed step; then ``warmed()``, if given); the stars on the first frame; the process's mean CPU
    time (s, all threads) a step over the floor draw's."""
    env, action, info, stars = _stepped_frame_env(seed, steps, noise_thread)
    if warmed is not None:
        warmed()
    rng = np.random.default_rng(seed)
    noise = np.empty(env.observation_space["frames"].shape[1:], np.float32)
    step_times, floor_times, step_cpu, floor_cpu = [], [], 0.0, 0.0
    for _ in range(steps):
        c0, t0 = time.process_time(), time.perf_counter()
        rng.standard_normal(dtype=np.float32, out=noise)
        c1, t1 = time.process_time(), time.perf_counter()
        info = _scored_step(env, action, info)
        step_times.append(time.perf_counter() - t1)
        floor_times.append(t1 - t0)
        step_cpu, floor_cpu = step_cpu + time.process_time() - c1, floor_cpu + c1 - c0
    env.close()
    return float(np.median(step_times)), float(np.median(floor_times)), stars, step_cpu / floor_cpu


def profile(steps: int, seed: int) -> str:
    """The top of a cProfile of ``steps`` steps of the 1024 x 1024 env, by cumulative and by own time."""
    env, action, info, _ = _stepped_frame_env(seed, steps)
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(steps):
        info = _scored_step(env, action, info)
    profiler.disable()
    text = io.StringIO()
    stats = pstats.Stats(profiler, stream=text)
    stats.sort_stats("cumulative").print_stats(r"starenv", 18)
    stats.sort_stats("tottime").print_stats(12)
    return "\n".join(line for line in text.getvalue().splitlines() if line.strip() and "Ordered by" not in line)


# The parts of a 1024 x 1024 step that ``--parts breakdown`` times: (module, function or Class.method, label).
BREAKDOWN = (("starenv.sim.imager", "Detector.read_out", "read-out"), ("starenv.sim.render", "StarRenderer.render",
             "render"), ("starenv.env", "score_step", "scoring"), ("starenv.sim.gyro", "Gyro.sample_until", "gyro"),
             ("starenv.env", "StarSensorEnv._observation", "observation"), ("starenv.env", "parse_action",
             "action parsing"))


def breakdown(steps: int, seed: int) -> dict[str, float]:
    """Each part of :data:`BREAKDOWN` of :func:`frame_step`'s ``steps`` timed steps, its mean time a step over the
    median floor draw; every part's function wrapped by a timer (the reset and the untimed first step left out)."""
    import contextlib
    import importlib
    from unittest import mock

    spent = dict.fromkeys([label for *_, label in BREAKDOWN], 0.0)

    def timed(function, label):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                spent[label] += time.perf_counter() - start
        return wrapper

    with contextlib.ExitStack() as stack:
        for module, name, label in BREAKDOWN:
            owner = importlib.import_module(module)
            *outer, attribute = name.split(".")
            for part in outer:
                owner = getattr(owner, part)
            stack.enter_context(mock.patch.object(owner, attribute, timed(getattr(owner, attribute), label)))
        _, floor_s, *_ = frame_step(steps, seed, warmed=lambda: spent.update(dict.fromkeys(spent, 0.0)),
                                    noise_thread=False)
    return {label: total / steps / floor_s for label, total in spent.items()}


PARTS = ("step", "single", "vector", "pipeline", "profile", "breakdown")


def spread(values: list[float]) -> str:
    """Median of the rounds' values, and the lowest and highest."""
    return f"{np.median(values):.2f} [{min(values):.2f}-{max(values):.2f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=9173, help="seeds every env and draws the 1024^2 pointings")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile-steps", type=int, default=100)
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated, of {', '.join(PARTS)}")
    args = parser.parse_args()
    parts = set(args.parts.split(","))
    if not parts <= set(PARTS) or args.repeats < 1:
        parser.error(f"--parts must name some of {', '.join(PARTS)}; --repeats must be >= 1")
    seed = args.seed
    shape = gym.make(ENV_ID).observation_space["frames"].shape[1:]
    load_before = os.getloadavg()[0]
    # the workers' CPU time to start, reset and take one step, per env
    set_up = vector(0, 2, True, seed)[2] if "vector" in parts else 0.0
    rounds = []
    for k in range(args.repeats):
        found: dict[str, float] = {}
        if "step" in parts:
            step_s, floor_s, stars, cpu = frame_step(args.steps, seed + k)
            serial_s, serial_floor_s, *_ = frame_step(args.steps, seed + k, noise_thread=False)
            found |= {"frame step": step_s, "frame floor": floor_s, "frame stars": stars, "frame cpu": cpu,
                      "serial ratio": serial_s / serial_floor_s}
        if parts & {"single", "vector", "pipeline"}:
            one, one_cpu = single(args.steps, seed)
            found |= {"floor": floor_rate(shape, args.steps, seed), "single": one, "single cpu": one_cpu,
                      "single serial": single(args.steps, seed, noise_thread=False)[0]}
        if "vector" in parts:
            shared, main_cpu, worker_cpu = vector(args.steps, 2, True, seed)
            found |= {
                "floor x2": parallel_floor(shape, args.steps), "shared": shared, "main cpu": main_cpu,
                "worker cpu": worker_cpu - set_up / (2 * args.steps),
                "pickled": vector(args.steps, 2, False, seed)[0],
                "prefetch": vector(args.steps, 2, True, seed, prefetch=True)[0],
                "bare": bare_workers(args.steps, 2, seed),
                "lean": lean_vector(args.steps, 2, infos=True, copy=True, seed=seed),
                "lean views": lean_vector(args.steps, 2, infos=False, copy=False, seed=seed),
            }
        if "breakdown" in parts:
            found |= {f"part {label}": value for label, value in breakdown(args.steps, seed + k).items()}
        if "pipeline" in parts:
            found |= {"pipeline": with_pipeline(args.steps // 3, False, seed),
                      "pipeline prefetch": with_pipeline(args.steps // 3, True, seed)}
        rounds.append(found)
    print(f"load average (1 min): {load_before:.2f} before, {os.getloadavg()[0]:.2f} after, on {os.cpu_count()} cores; "
          f"seed {seed}; medians of {args.repeats} rounds of {args.steps} steps [lowest-highest round]")
    if "step" in parts:
        steps_ms = [r["frame step"] * 1e3 for r in rounds]
        stars = ", ".join(str(int(r["frame stars"])) for r in rounds)
        print(f"env.step, 1024x1024, {stars} stars (a pointing a round), noise on, scored: {spread(steps_ms)} ms = "
              f"{spread([r['frame step'] / r['frame floor'] for r in rounds])} x the floor "
              f"({spread([r['frame floor'] * 1e3 for r in rounds])} ms; goal <= 1.5)")
        print(f"  its CPU time (both threads) {spread([r['frame cpu'] for r in rounds])} x the floor's; with "
              f"noise_thread=False (the noise drawn after the render): {spread([r['serial ratio'] for r in rounds])} x "
              "the floor")
    if "breakdown" in parts:
        print("env.step, 1024x1024, each part's time in floor draws: " + "; ".join(
            f"{label} {spread([r[f'part {label}'] for r in rounds])}" for *_, label in BREAKDOWN))
    if not parts & {"single", "vector", "pipeline"}:
        rounds = []
    if rounds:
        print(f"noise floor ({shape[0]}x{shape[1]} float32 normals): {spread([r['floor'] for r in rounds])} frames/s")
        print(f"single env, do-nothing action: {spread([r['single'] for r in rounds])} steps/s (goal >= 300) = "
              f"{spread([r['floor'] / r['single'] for r in rounds])} x the floor's time; with noise_thread=False "
              f"(as in a worker) {spread([r['single serial'] for r in rounds])} steps/s")
    if rounds and "vector" in parts:
        ceiling = [r["floor x2"] / r["floor"] for r in rounds]
        print(f"noise floor in 2 processes at once: {spread(ceiling)} x one process (the ceiling of a 2-worker "
              "speed-up here)")
        for key, label in (("shared", "Gymnasium async, shared memory (its default)"),
                           ("pickled", "Gymnasium async, pickled"), ("prefetch", "Gymnasium async, + prefetch"),
                           ("bare", "bare workers (the floor)"), ("lean", "SharedMemoryVectorEnv"),
                           ("lean views", "SharedMemoryVectorEnv, no infos, views")):
            print(f"vector env, 2 workers, {label:<46} {np.median([r[key] for r in rounds]):6.1f} steps/s = "
                  f"{spread([r[key] / r['single'] for r in rounds])} x single, "
                  f"{spread([r[key] / r['single serial'] for r in rounds])} x single without its noise thread "
                  "(goal >= 1.8)")
        # Two cores run the workers' and the main process's CPU time per env step: no schedule beats 2 / their sum.
        cpu_bound = [2.0 / (r["main cpu"] + r["worker cpu"]) / r["single"] for r in rounds]
        print(f"CPU time per env step: single env {np.median([r['single cpu'] for r in rounds]) * 1e3:.2f} ms; in "
              f"Gymnasium's async vector env worker {np.median([r['worker cpu'] for r in rounds]) * 1e3:.2f} ms + "
              f"main process {np.median([r['main cpu'] for r in rounds]) * 1e3:.2f} ms: on 2 cores at most "
              f"{spread(cpu_bound)} x single")
    if rounds and "pipeline" in parts:
        print(f"single env + the scenario's pipeline: {spread([r['pipeline'] for r in rounds])} steps/s; with "
              f"prefetch {spread([r['pipeline prefetch'] / r['pipeline'] for r in rounds])} x")
    if "profile" in parts:
        print(f"\nprofile of {args.profile_steps} steps of the 1024x1024 env:\n{profile(args.profile_steps, seed)}")


if __name__ == "__main__":
    main()
