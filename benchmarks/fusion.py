"""The MEKF (``starenv.agents.fusion.MekfPredictor``) against the classical pipeline on the same frames: each scenario's
own pipeline (gyro propagation from the last solution, frame-by-frame solutions) and the same pipeline with the filter
as its predictor (gyro noise values from the scenario's datasheet, as a user would configure it).  Prints per
scenario the median and p95 attitude error, the roll (about head 0's boresight) and cross-boresight RMS (arcsec) and
the availability, over ``--steps`` steps from ``--seeds`` seeds::

    python benchmarks/fusion.py [--steps 100] [--seeds 0 1]
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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    args = parser.parse_args(argv)
    print("| case | pipeline | median error (\") | p95 (\") | roll RMS (\") | cross-boresight RMS (\") | available |")
    print("|---|---|---|---|---|---|---|")
    for label, (name, overrides) in CASES.items():
        env = StarSensorEnv(name, overrides=overrides)
        gyro = env.scenario.gyro
        options = {"predictor": {"arw_deg_rthr": gyro.arw_deg_rthr, "rrw_deg_hr_rthr": gyro.rrw_deg_hr_rthr,
                                 "bias_instability_deg_hr": gyro.bias_instability_deg_hr}}
        for pipeline_name, agents, opts in (("scenario's own", {}, {}),
                                            ("MEKF", {"predictor": "starenv.agents.fusion:MekfPredictor"}, options)):
            records = []
            for seed in args.seeds:
                pipe = Pipeline.for_scenario(env.scenario, agents, opts)
                records += run_episode(env, pipe, seed=seed, steps=args.steps).records[5:]  # after the first fix
            err, roll = values(records, "attitude_error_arcsec"), values(records, "roll_error_arcsec")
            cross = values(records, "cross_boresight_error_arcsec")
            available = np.mean([r["available"] for r in records])
            print(f"| {label} | {pipeline_name} | {np.median(err):.1f} | {np.percentile(err, 95):.1f} | "
                  f"{np.sqrt(np.mean(roll**2)):.1f} | {np.sqrt(np.mean(cross**2)):.1f} | {available:.2f} |")


if __name__ == "__main__":
    main()
