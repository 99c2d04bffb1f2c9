"""Replay a mission's attitude history (a CCSDS AEM) over your own star list, then hand the estimated attitude back
as an AEM for flight-dynamics tools.

The scenario is paper_000's sensor with ``[motion] kind = "attitude_file"`` (``examples/data/orion_pass.aem``) and
``[catalog]`` a CSV of stars (``examples/data/orion_stars.csv``); the run is recorded to MCAP and exported with
``starenv export --format aem`` (the estimate in ``OUT.aem``, the truth in ``OUT.truth.aem``).  Needs the ``aem``
extra (``pip install "starenv[aem]"``: the ccsds-ndm library).

    python examples/replay_attitude.py --steps 50 --out recordings/replay
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from starenv.agents.pipeline import Pipeline
from starenv.cli import main as starenv_cli
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.record.mcap import McapRecorder, read_steps
from starenv.sim.attitude_files import read_aem

DATA = Path(__file__).parent / "data"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="recordings/replay")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    overrides = {"motion": {"kind": "attitude_file", "file": str(DATA / "orion_pass.aem")},
                 "catalog": {"file": str(DATA / "orion_stars.csv"), "epoch": 1991.25}}
    env = StarSensorEnv("paper_000", overrides)
    mcap = out / "replay.mcap"
    run = run_episode(env, Pipeline.for_scenario(env.scenario), seed=args.seed, steps=args.steps,
                      observers=[McapRecorder(mcap)])
    starenv_cli(["export", str(mcap), "--format", "aem", "--out", str(out / "replay.aem")])
    given = read_aem(DATA / "orion_pass.aem")  # the mission's history: ICRS -> body at simulation times (s)
    slerp = Slerp(given.t, given.attitude)  # an independent SLERP of the file, to check the run's truth against
    steps = list(read_steps(mcap))
    t = np.array([s.time_ns for s in steps]) * 1e-9
    truth = Rotation.from_quat([s.attitude_true for s in steps])
    truth_vs_file = (truth * slerp(t).inv()).magnitude()
    estimate = read_aem(out / "replay.aem")  # the exported estimate, read back by the AEM reader
    errors = [r["attitude_error_arcsec"] for r in run.records if r["attitude_error_arcsec"] is not None]
    result = {"steps": len(run.records), "solved": len(errors), "median_error_arcsec": float(np.median(errors)),
              "max_truth_vs_file_rad": float(truth_vs_file.max()), "estimate_samples": len(estimate.t),
              "estimate_aem": str(out / "replay.aem")}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
