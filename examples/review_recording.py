"""Record a run to MCAP and build its Rerun review.

The MCAP file is the record to keep and share (Foxglove opens it too); the ``.rrd`` review is rebuilt from it at
any time.  Open the review with ``rerun FILE.rrd`` (or ``starenv view FILE.mcap``, which builds and opens it).

    python examples/review_recording.py --steps 12 --out recordings/example
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.record.mcap import McapRecorder, read_steps
from starenv.record.rerun import analytics_off, mcap_to_rrd


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="stress_drops")
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="recordings/example")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    analytics_off()
    env = StarSensorEnv(args.scenario)
    mcap = out / f"{args.scenario}.mcap"
    run_episode(env, Pipeline.for_scenario(env.scenario), seed=args.seed, steps=args.steps,
                observers=[McapRecorder(mcap)])
    rrd = mcap_to_rrd(mcap, out / f"{args.scenario}.rrd")
    steps = list(read_steps(mcap))
    logs = [text for s in steps for _, text in s.logs]
    result = {"mcap": str(mcap), "rrd": str(rrd), "steps": len(steps), "log_lines": len(logs),
              "dropped": sum("frame dropped" in t for t in logs)}
    print(json.dumps(result))
    print(f"review: rerun {rrd}")
    return result


if __name__ == "__main__":
    main()
