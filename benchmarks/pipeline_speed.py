"""Whole classical pipeline speed on one core: predict, detect, identify and solve per frame, each stage timed.

Frames: paper 002's scenario (``paper_002``: 1024 x 1024, 12 deg field, 10 Hz) turning at 0, 2 and 5 deg/s about an
axis, from a pointing and roll, drawn uniformly from ``--seed``, and each scenario of ``--others`` (default the other
papers) at its own motion, every env reset with ``--seed``, are rendered first (rendering is not timed); each
scenario's own ``[pipeline]`` then runs over them ``--repeats`` times, reset before each pass (so the first frame
of a pass is identified lost in space, the rest tracked).  Times come from the pipeline's own per-role clocks
(``Pipeline.report.latency_s``): predictor, detector, identifier, solver, and "other" (the rest of a call: input
checks, the action); median and 95th percentile over all timed frames.

One core: OpenMP, MKL and OpenBLAS are held to one thread (set below before numpy is imported; a value already in
the environment wins) and OpenCV to one thread.

Baseline: one ``cv2.GaussianBlur`` (sigma 1 px) of the same frame, timed just before each pipeline call.  It is a
fixed amount of memory-bound work of the frame's size, the same kind of work the detector's filtering does, so the
ratio pipeline / blur follows the machine's speed (shared and noisy machines, turbo, load) and is the figure to
compare between runs.  Each scenario's line gives its frame rate's period beside the pipeline's median and p95 per
frame ("fits": p95 within the period).

``--profile`` ends with a cProfile of passes of paper 002 at the fastest rate (cumulative time, top ``--top``).
Most of a run's time is rendering.

    python benchmarks/pipeline_speed.py [--frames N] [--repeats N] [--seed S] [--others paper_000,...] [--profile]
                                        [--top N]
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import copy  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from env_speed import random_pointing_deg  # noqa: E402  (run from benchmarks/, whose folder is on the path)

from starenv.agents.pipeline import Pipeline  # noqa: E402
from starenv.env import StarSensorEnv  # noqa: E402

RATES_DPS = (0.0, 2.0, 5.0)
STAGES = ("predictor", "detector", "identifier", "solver", "other")
OTHERS = ("paper_000", "paper_001", "paper_003", "paper_004")


def render(scenario: str, overrides: dict, frames: int, seed: int = 0) -> tuple[StarSensorEnv, list[dict]]:
    """The env and ``frames`` observations (copies) of ``scenario``, stepped with the null action."""
    env = StarSensorEnv(scenario, {"lost_after_steps": 10**6, **overrides})
    obs, _ = env.reset(seed=seed)
    out = [copy.deepcopy(obs)]
    action = env.null_action()
    while len(out) < frames:
        obs, _, terminated, truncated, _ = env.step(action)
        out.append(copy.deepcopy(obs))
        if terminated or truncated:
            break
    return env, out


def blur(obs: dict) -> None:
    """The baseline: one Gaussian blur (sigma 1 px) of every head's frame."""
    for image in obs["frames"]:
        cv2.GaussianBlur(image, (0, 0), 1.0)


def timed_passes(env: StarSensorEnv, observations: list[dict], repeats: int) -> dict[str, np.ndarray]:
    """Per stage (and "pipeline", "baseline") the times (s) of every frame of ``repeats`` passes, baseline and
    pipeline interleaved frame by frame."""
    pipeline = Pipeline.for_scenario(env.scenario)
    times = {name: [] for name in (*STAGES, "pipeline", "baseline")}
    for _ in range(repeats):
        pipeline.reset(env.sensor_info)
        for obs in observations:
            t0 = time.perf_counter()
            blur(obs)
            times["baseline"].append(time.perf_counter() - t0)
            pipeline(obs)
            latency = pipeline.report.latency_s
            staged = 0.0
            for stage in STAGES[:-1]:
                times[stage].append(latency.get(stage, 0.0))
                staged += latency.get(stage, 0.0)
            times["pipeline"].append(latency["pipeline"])
            times["other"].append(latency["pipeline"] - staged)
    return {name: np.array(t) for name, t in times.items()}


def print_row(label: str, times: dict[str, np.ndarray], period_s: float) -> None:
    """One scenario's line: per stage median (p95) ms, the pipeline's, its ratio to the baseline, the frame period."""
    baseline = float(np.median(times["baseline"]))
    cells = " ".join(f"{1e3 * np.median(times[s]):6.2f} ({1e3 * np.percentile(times[s], 95):6.2f})" for s in STAGES)
    total, p95 = float(np.median(times["pipeline"])), float(np.percentile(times["pipeline"], 95))
    fits = "yes" if p95 <= period_s else "NO"
    print(f"{label:24} {cells} | {1e3 * total:7.2f} ({1e3 * p95:7.2f}) | {1e3 * baseline:6.2f} "
          f"{total / baseline:7.1f}x | {1e3 * period_s:7.1f} {fits:>4}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=12, help="frames rendered per case")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes over them")
    parser.add_argument("--seed", type=int, default=5150, help="the envs' seed; paper 002's pointing and axis")
    parser.add_argument("--others", default=",".join(OTHERS), help="other scenarios at their own motion ('' none)")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--top", type=int, default=25, help="functions in the profile")
    args = parser.parse_args()
    cv2.setNumThreads(1)

    rng = np.random.default_rng(args.seed)
    ra, dec, roll = random_pointing_deg(rng)
    axis = rng.normal(size=3)
    pointing = {"motion.initial_ra_deg": ra, "motion.initial_dec_deg": dec, "motion.initial_roll_deg": roll}
    cases = [(f"paper_002 {rate:.0f} deg/s", "paper_002",
              {"motion.rate_dps": (rate * axis / np.linalg.norm(axis)).tolist(), **pointing}) for rate in RATES_DPS]
    cases += [(name, name, {}) for name in args.others.split(",") if name]
    print(f"{args.frames} frames x {args.repeats} passes a case, seed {args.seed}; ms median (p95); baseline: "
          f"GaussianBlur of the frame")
    print(f"{'case':24} " + " ".join(f"{s:>15}" for s in STAGES) + f" | {'pipeline ms':>17} | {'blur ms':>6} "
          f"{'ratio':>8} | {'frame ms':>7} fits")
    last = None
    for label, scenario, overrides in cases:
        env, observations = render(scenario, overrides, args.frames, args.seed)
        times = timed_passes(env, observations, args.repeats)
        print_row(label, times, env.scenario.frame_period_s)
        if scenario == "paper_002":
            last = (env, observations)
    if args.profile and last is not None:
        env, observations = last
        pipeline = Pipeline.for_scenario(env.scenario)
        profile = cProfile.Profile()
        for _ in range(args.repeats):
            pipeline.reset(env.sensor_info)
            profile.enable()
            for obs in observations:
                pipeline(obs)
            profile.disable()
        print(f"\nprofile: paper_002 at {RATES_DPS[-1]:.0f} deg/s, {args.repeats} passes (cumulative time)")
        pstats.Stats(profile).sort_stats("cumulative").print_stats(args.top)


if __name__ == "__main__":
    main()
