"""The MEKF (``starenv.agents.fusion.MekfPredictor``) against the classical pipeline on the same frames: each scenario's
own pipeline (gyro propagation from the last solution, frame-by-frame solutions) and the same pipeline with the filter
as its predictor (gyro noise values from the scenario's datasheet, as a user would configure it).  Prints per
scenario the median and p95 attitude error, the roll (about head 0's boresight) and cross-boresight RMS (arcsec) and
the availability, over ``--steps`` steps from ``--seeds`` seeds::

    python benchmarks/fusion.py [--steps 100] [--seeds 0 1] [--bias-seconds 70]

Then, on ``stress_drops``, the attitude error on the steps whose frame was dropped against those that were not; and
the filter's gyro bias error against time on ``paper_000`` at 1 deg/s, run at 10 frames/s for ``--bias-seconds``
(the scenario's gyro: bias instability 0.05 deg/h, a constant bias of 0).
"""

from __future__ import annotations

import argparse

import numpy as np

from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.episode import run_episode

CASES = {
    "paper_000 at 1 deg/s about X": ("paper_000", {"motion.rate_dps": [1.0, 0.0, 0.0]}),
    "stress_drops (bursty drops)": ("stress_drops", {}),
    "paper_004 (three heads)": ("paper_004", {}),
}


def values(records, key):
    return np.array([r[key] for r in records if r[key] is not None])


class Dropped:
    """An observer that keeps, per step, whether any head's frame was dropped."""

    def __init__(self):
        self.flags = []

    def start(self, env, seed, pipeline):
        pass

    def step(self, log):
        self.flags.append(any(log.truth["dropped"]))

    def close(self, error=None):
        pass


def filter_options(env) -> dict:
    gyro = env.scenario.gyro
    return {"predictor": {"arw_deg_rthr": gyro.arw_deg_rthr, "rrw_deg_hr_rthr": gyro.rrw_deg_hr_rthr,
                          "bias_instability_deg_hr": gyro.bias_instability_deg_hr}}


FILTER = {"predictor": "starenv.agents.fusion:MekfPredictor"}


def drop_table(steps: int, seeds) -> None:
    env = StarSensorEnv("stress_drops")
    print("\n| stress_drops | pipeline | median error, dropped steps (\") | p95 | median error, other steps (\") |"
          " p95 |\n|---|---|---|---|---|---|")
    for name, agents, options in (("scenario's own", {}, {}), ("MEKF", FILTER, filter_options(env))):
        dropped, other = [], []
        for seed in seeds:
            flags = Dropped()
            records = run_episode(env, Pipeline.for_scenario(env.scenario, agents, options), seed=seed, steps=steps,
                                  observers=[flags]).records
            for flag, r in zip(flags.flags[5:], records[5:], strict=True):
                if r["attitude_error_arcsec"] is not None:
                    (dropped if flag else other).append(r["attitude_error_arcsec"])
        print(f"| | {name} | {np.median(dropped):.1f} | {np.percentile(dropped, 95):.1f} | {np.median(other):.1f} | "
              f"{np.percentile(other, 95):.1f} |")
    print(f"\n({len(dropped)} dropped and {len(other)} other steps)")


def bias_table(seconds: float) -> None:
    env = StarSensorEnv("paper_000", overrides={"motion.rate_dps": [1.0, 0.0, 0.0], "frame_rate_hz": 10.0,
                                                "duration_s": seconds + 0.2})
    records = run_episode(env, Pipeline.for_scenario(env.scenario, FILTER, filter_options(env)), seed=0).records
    print("\n| time (s) | gyro bias error (deg/h) | attitude NEES (3 dof) |\n|---|---|---|")
    for t in (1, 5, 10, 20, 30, 45, 60):
        if 10 * t < len(records):
            r = records[10 * t]
            print(f"| {t} | {r['gyro_bias_error_deg_hr']:.3f} | {r['attitude_nees']:.1f} |")
    nees = [r["attitude_nees"] for r in records[10:]]
    print(f"\nmean attitude NEES over steps 10-{len(records) - 1}: {np.mean(nees):.2f} (3 when consistent)")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--bias-seconds", type=float, default=70.0)
    args = parser.parse_args(argv)
    print("| case | pipeline | median error (\") | p95 (\") | roll RMS (\") | cross-boresight RMS (\") | available |")
    print("|---|---|---|---|---|---|---|")
    for label, (name, overrides) in CASES.items():
        env = StarSensorEnv(name, overrides=overrides)
        for pipeline_name, agents, opts in (("scenario's own", {}, {}), ("MEKF", FILTER, filter_options(env))):
            records = []
            for seed in args.seeds:
                pipe = Pipeline.for_scenario(env.scenario, agents, opts)
                records += run_episode(env, pipe, seed=seed, steps=args.steps).records[5:]  # after the first fix
            err, roll = values(records, "attitude_error_arcsec"), values(records, "roll_error_arcsec")
            cross = values(records, "cross_boresight_error_arcsec")
            available = np.mean([r["available"] for r in records])
            print(f"| {label} | {pipeline_name} | {np.median(err):.1f} | {np.percentile(err, 95):.1f} | "
                  f"{np.sqrt(np.mean(roll**2)):.1f} | {np.sqrt(np.mean(cross**2)):.1f} | {available:.2f} |")

    drop_table(args.steps, args.seeds)
    bias_table(args.bias_seconds)


if __name__ == "__main__":
    main()
