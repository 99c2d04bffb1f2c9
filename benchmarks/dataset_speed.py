"""Dataset generator speed against the env: per-sample time of ``starenv dataset``'s sample function and of the env
rendering the same frame, and their ratio.

    python benchmarks/dataset_speed.py [--spec datasets/paper002_sky.toml] [--samples 8] [--repeats 3]

For each of the spec's first ``--samples`` samples the env is built beforehand with that sample's motion (the
scenario, its constant rate and the initial attitude that puts the drawn attitude at mid-exposure) and not timed;
then, ``--repeats`` times, each sample is generated (:func:`starenv.datasets.sample`: the draws, the edited sky, the
render, the preprocessing) and its frame rendered by ``env.reset(seed=...)`` (the env's sensor reset and frame 0),
one after the other so that both see the same machine load.  The generator's per-process context (scenario,
catalogues) is built before timing, as a worker builds it once.  Prints the median of each per repeat, their ratio,
and the median ratio with its spread over the repeats (one core; wall clock).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from starenv.datasets import load_spec, sample  # noqa: E402
from starenv.datasets.samples import context, draw, motion_table  # noqa: E402
from starenv.env import StarSensorEnv  # noqa: E402


def envs_for(spec, indices) -> list:
    """One env per sample, rendering that sample's geometry (its scenario with the sample's motion)."""
    sc = context(spec).scenario
    return [StarSensorEnv(spec.load_scenario().data, overrides={"motion": motion_table(sc, draw(spec, i))})
            for i in indices]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--spec", default=str(ROOT / "datasets" / "paper002_sky.toml"))
    p.add_argument("--samples", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    spec = load_spec(args.spec)
    indices = range(args.samples)
    envs = envs_for(spec, indices)
    sample(spec, 0)  # the worker's context, built once
    envs[0].reset(seed=0)
    ratios = []
    cam = context(spec).scenario.heads[0].camera
    for r in range(args.repeats):
        gen, env = [], []
        for i, e in zip(indices, envs, strict=True):
            t0 = time.perf_counter()
            sample(spec, i)
            t1 = time.perf_counter()
            e.reset(seed=i)
            t2 = time.perf_counter()
            gen.append(t1 - t0)
            env.append(t2 - t1)
        ratio = statistics.median(gen) / statistics.median(env)
        ratios.append(ratio)
        print(f"repeat {r}: generator {1e3 * statistics.median(gen):.1f} ms/sample, env render "
              f"{1e3 * statistics.median(env):.1f} ms/frame, ratio {ratio:.2f}")
    print(f"{spec.name}: generator / env render = {statistics.median(ratios):.2f} (repeats {min(ratios):.2f} - "
          f"{max(ratios):.2f}, {args.repeats} repeats of {args.samples} samples, {cam.width} x {cam.height} px "
          f"frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
