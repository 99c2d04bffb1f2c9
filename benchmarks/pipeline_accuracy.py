"""Classical pipeline accuracy on the paper scenarios.

1. Paper 002's sensor (12 deg, 1024^2, 92 ms) at 0, 2, 5 and 10 deg/s three-axis (the rate split equally over the body
   axes): solved frames and ID rate with the lost-in-space identifier alone vs tracking (gyro-propagated prior,
   lost-in-space fallback).
2. Paper 000's sensor (512^2 crop, 10 ms, 100 Hz) at 1 deg/s three-axis: attitude error per camera axis (x, y across
   the boresight; roll about it), signed, arcsec: its bias (mean), RMS and the p95 of its size.

    python benchmarks/pipeline_accuracy.py [--frames N]
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.scoring import flatten, summarize


def run(scenario: str, overrides: dict, pipeline: Pipeline, frames: int, seed: int = 0):
    env = StarSensorEnv(scenario, overrides)
    obs, info = env.reset(seed=seed)
    pipeline.reset(env.unwrapped.sensor_info)
    records, heads = [], []
    for _ in range(frames):
        obs, _, _, truncated, info = env.step(pipeline(obs))
        records.append(flatten(info["scores"], pipeline.report.latency_s))
        if info["scores"]["attitude"]:  # empty when the step had no estimate
            heads.append(info["scores"]["attitude"]["heads"][0])
        if truncated:
            break
    return summarize(records), heads


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    args = parser.parse_args()

    print(f"Paper 002 sensor, {args.frames} frames per cell")
    print(f"{'rate deg/s':>10} | {'identifier':>14} | {'solved':>6} | {'ID rate':>7} | {'att. err median':>15} | "
          f"{'identify ms':>11}")
    for rate in (0.0, 2.0, 5.0, 10.0):
        per_axis = rate / math.sqrt(3.0)
        overrides = {"motion.rate_dps": [per_axis] * 3, "lost_after_steps": 10**6}
        for name, identifier in (("lost-in-space", "starenv.agents.identify:LostInSpaceIdentifier"),
                                 ("tracking", "starenv.agents.identify:TrackingIdentifier")):
            s, _ = run("paper_002", overrides, Pipeline(identifier=identifier), args.frames)
            err = s.get("attitude_error_arcsec", {}).get("median", float("nan"))
            id_rate = s.get("id_rate", {}).get("mean", 0.0)
            print(f"{rate:10.1f} | {name:>14} | {s['solved']['mean']:6.2f} | {id_rate:7.3f} "
                  f"| {err:12.2f} as | {s['latency_identifier_ms']['median']:11.3f}")

    _, heads = run("paper_000", {"lost_after_steps": 10**6}, Pipeline(), max(args.frames, 200))
    print("\nPaper 000 sensor at 1 deg/s three-axis, attitude error per axis (arcsec)")
    for axis in ("x_arcsec", "y_arcsec", "roll_arcsec"):
        v = np.array([h[axis] for h in heads])
        print(f"  {axis[:-7]:5s}  bias {np.mean(v):7.2f}  rms {np.sqrt(np.mean(v**2)):7.2f}  "
              f"p95 of size {np.percentile(np.abs(v), 95):7.2f}   ({len(v)} frames)")


if __name__ == "__main__":
    main()
