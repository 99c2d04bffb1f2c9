"""Restorers in real time, on one core: each streak restorer against the same algorithm on the whole frame.

Three goals, each timed against its own baseline in the same run (median of ``--repeats`` rounds that run every
restorer once in turn, so load from other processes falls on all alike):

* ``paper_002`` (1024 x 1024, 92 ms exposure, 10 Hz) at 10 deg/s three-axis (trails of ~60 px): the
  region-of-interest Richardson-Lucy (``RoiDeblurrer``, 20 iterations) and the trail fit (``TrailFitDeblurrer``)
  against full-frame Richardson-Lucy with the frame centre's kernel (``RichardsonLucyDeblurrer``, 20 iterations).
  Goal: <= 100 ms per frame.
* ``paper_000`` (512 x 512, 10 ms, 100 Hz) at ``--paper000-rate`` deg/s about X: paper 000's EBPNN-count RL on the
  candidate streaks' patches (``IterationNetDeblurrer(region="streaks")``) against the paper's full-frame form
  (``region="frame"``).  Goal: <= 200 ms per frame.
* ``paper_001`` (800 x 600, 60 ms, 10 Hz) at ``--paper001-rate`` deg/s about X and Y: paper 001's curvature filter,
  RL and Eq. 25 stop on the patches (``CurvatureRLDeblurrer(region="streaks")``) against the full frame.  Goal:
  <= 300 ms per frame.

One core: OpenMP, MKL and OpenBLAS held to one thread (set before numpy is imported; a value already in the
environment wins), OpenCV to one thread, scipy's FFTs run with one worker on frames of this size.  Printed per line:
median ms per frame, the speed-up over the baseline (baseline time / restorer time), the goal and the RL iterations
run.  ``--profile NAME`` ends with a cProfile of that restorer (``roi``, ``trail_fit``, ``paper000``, ``paper001``).

    python benchmarks/restore_realtime.py [--repeats 5] [--paper000-rate 40] [--paper001-rate 4] [--profile NAME]
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import math  # noqa: E402
import pstats  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402

from starenv.agents.base import step_input  # noqa: E402
from starenv.agents.restore.curvature import CurvatureRLDeblurrer  # noqa: E402
from starenv.agents.restore.frame import RichardsonLucyDeblurrer  # noqa: E402
from starenv.agents.restore.iteration.deblurrer import IterationNetDeblurrer  # noqa: E402
from starenv.agents.restore.roi import RoiDeblurrer  # noqa: E402
from starenv.agents.restore.trail_fit import TrailFitDeblurrer  # noqa: E402
from starenv.env import StarSensorEnv  # noqa: E402


def first_step(scenario: str, rate_dps: list[float], seed: int = 0):
    """The StepInput of frame 1 of ``scenario`` turning at ``rate_dps`` (deg/s, body axes)."""
    env = StarSensorEnv(scenario, {"motion.rate_dps": rate_dps})
    env.reset(seed=seed)
    obs, *_ = env.step(env.null_action())
    return step_input(obs, env.sensor_info)


def timed(agents: dict, step, repeats: int) -> dict[str, float]:
    """Median wall time (s) of ``agent.deblur`` on head 0 of ``step``, every agent once per round."""
    image = step.images[0]
    for agent in agents.values():
        agent.deblur(image, 0, step)  # warm-up: caches, lazy imports
    times = {name: [] for name in agents}
    for _ in range(repeats):
        for name, agent in agents.items():
            t0 = time.perf_counter()
            agent.deblur(image, 0, step)
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--paper000-rate", type=float, default=40.0, help="deg/s about X on paper_000")
    parser.add_argument("--paper001-rate", type=float, default=4.0, help="deg/s about X and Y on paper_001")
    parser.add_argument("--profile", choices=("roi", "trail_fit", "paper000", "paper001"))
    args = parser.parse_args()
    cv2.setNumThreads(1)
    per_axis = 10.0 / math.sqrt(3.0)
    cases = [
        ("paper_002 1024^2, 10 deg/s three-axis", first_step("paper_002", [per_axis] * 3), 100.0,
         "full-frame RL, 20 iterations", RichardsonLucyDeblurrer(20),
         {"ROI RL, 20 iterations": RoiDeblurrer(20), "trail fit": TrailFitDeblurrer()}),
        (f"paper_000 512^2, {args.paper000_rate:g} deg/s about X", first_step("paper_000", [args.paper000_rate, 0, 0]),
         200.0, "paper 000 full frame", IterationNetDeblurrer(),
         {"paper 000 streak patches": IterationNetDeblurrer(region="streaks")}),
        (f"paper_001 800 x 600, {args.paper001_rate:g} deg/s about X and Y",
         first_step("paper_001", [args.paper001_rate, args.paper001_rate, 0]), 300.0, "paper 001 full frame",
         CurvatureRLDeblurrer(), {"paper 001 streak patches": CurvatureRLDeblurrer(region="streaks")}),
    ]
    print(f"one core, median of {args.repeats}; speed-up = baseline time / restorer time")
    for title, step, goal_ms, base_name, baseline, agents in cases:
        runs = timed({base_name: baseline, **agents}, step, args.repeats)
        base = runs[base_name]
        print(f"{title}: baseline {base_name} {base * 1e3:.0f} ms "
              f"({baseline.last_info.get('iterations', 0)} iterations)")
        for name, agent in agents.items():
            ms = runs[name] * 1e3
            verdict = "meets" if ms <= goal_ms else "misses"
            print(f"  {name:28s} {ms:7.1f} ms  x{base / runs[name]:6.1f}  goal <= {goal_ms:g} ms: {verdict}  "
                  f"iterations {agent.last_info.get('iterations', 0)}, candidates "
                  f"{agent.last_info.get('candidates', 0)}")
    if args.profile:
        which = {"roi": (0, "ROI RL, 20 iterations"), "trail_fit": (0, "trail fit"),
                 "paper000": (1, "paper 000 streak patches"), "paper001": (2, "paper 001 streak patches")}
        case, name = which[args.profile]
        step, agent = cases[case][1], cases[case][5][name]
        profiler = cProfile.Profile()
        profiler.enable()
        for _ in range(args.repeats):
            agent.deblur(step.images[0], 0, step)
        profiler.disable()
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(20)


if __name__ == "__main__":
    main()
