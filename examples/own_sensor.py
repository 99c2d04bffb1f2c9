"""Your own star tracker from its datasheet: ``starenv new`` writes the scenario (every derived figure in a comment),
then it runs like a bundled one.

    python examples/own_sensor.py --out mine.toml --steps 20
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from starenv import scenario as scenario_mod
from starenv.agents.pipeline import Pipeline
from starenv.cli import main as starenv_cli
from starenv.env import StarSensorEnv
from starenv.episode import run_episode

DATASHEET = {"--fov": "20", "--pixel-um": "5.5", "--resolution": ["1024", "1024"], "--aperture-mm": "25",
             "--exposure-ms": "50", "--rate-hz": "10", "--read-noise-e": "3", "--dark-current-e-s": "10",
             "--full-well-e": "10000", "--gain-e-dn": "1.5", "--qe": "0.6"}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="mine.toml")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    command = ["new"]
    for flag, value in DATASHEET.items():
        command += [flag, *(value if isinstance(value, list) else [value])]
    starenv_cli(command + ["--out", args.out, "--force"])
    scenario = scenario_mod.load(args.out)
    camera = scenario.heads[0].camera
    env = StarSensorEnv(args.out)
    run = run_episode(env, Pipeline.for_scenario(scenario), seed=args.seed, steps=args.steps)
    errors = [r["attitude_error_arcsec"] for r in run.records if r["attitude_error_arcsec"] is not None]
    result = {"scenario": args.out, "focal_length_px": camera.fx,
              "focal_length_px_datasheet": 512 / math.tan(math.radians(10.0)),
              "ifov_arcsec": math.degrees(1.0 / camera.fx) * 3600.0, "steps": len(run.records), "solved": len(errors),
              "median_error_arcsec": float(np.median(errors)) if errors else None}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
