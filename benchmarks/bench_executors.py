"""Benchmark runner executors: wall time of one small bench in this process (the baseline), on 2 local worker
processes and on a local 2-CPU Ray instance, all measured in the same run (each including its start-up: spawning
workers, starting Ray, per-process catalog loads); prints the speed-ups and checks that every executor gave the same
per-step scores (latencies excluded).

    PYTHONPATH=. python benchmarks/bench_executors.py [--steps 20] [--no-ray]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from starenv.bench.runner import comparable, read_run, run_bench
from starenv.bench.spec import parse_bench

BENCH = """
name = "executors"
seeds = [0, 1]
steps = {steps}
[[runs]]
scenario = "paper_000"
pipelines = ["tracking", "lost_in_space"]
sweep = {{ key = "motion.rate_dps", axis = [1, 1, 1], values = [1, 3] }}
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--no-ray", action="store_true")
    args = parser.parse_args()
    bench = parse_bench(BENCH.format(steps=args.steps))
    with tempfile.TemporaryDirectory() as tmp:
        # fill the disk caches (catalog, pattern database) in worker processes, so that no executor, the in-process
        # baseline included, starts with them already in memory
        run_bench(bench, Path(tmp) / "warm", jobs=2, progress=False, log=lambda *a: None)
        timings, scores, episodes = {}, {}, {}
        cases = [("in-process", {"jobs": 1}), ("2 processes", {"jobs": 2})]
        if not args.no_ray:
            cases.append(("ray, 2 CPUs", {"use_ray": True, "ray_options": {"num_cpus": 2}}))
        for name, kwargs in cases:
            out = Path(tmp) / name.replace(" ", "_").replace(",", "")
            t0 = time.perf_counter()
            files = run_bench(bench, out, progress=False, log=lambda *a: None, **kwargs)
            timings[name] = time.perf_counter() - t0
            scores[name] = [comparable(read_run(f)[1]) for f in files]
            episodes[name] = sum(read_run(f)[2]["wall_s"] for f in files)
        if not args.no_ray:
            import ray

            ray.shutdown()
    base = timings["in-process"]
    print(f"{len(bench.runs)} runs x {args.steps} steps of paper_000")
    for name, t in timings.items():
        same = "identical scores" if scores[name] == scores["in-process"] else "SCORES DIFFER"
        print(f"  {name:12s} {t:7.2f} s wall ({episodes[name]:7.2f} s inside episodes, summed over runs)   "
              f"speed-up vs in-process {base / t:5.2f}x   {same}")


if __name__ == "__main__":
    main()
