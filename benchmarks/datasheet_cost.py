"""What the datasheet and its intervals add to a bench: one small bench's runs (the baseline), then, in the same
process, the report's figures (cases, ``summary.csv``'s statistics with their 95 % intervals, ``datasheet.csv``'s
rows: ``starenv.bench.report.tabulate``) and the whole report step (tables, CSVs, every plot); prints each as a share of
the runs' wall time.  Goal: the figures add under 5 % to the bench's wall time.

    PYTHONPATH=. python benchmarks/datasheet_cost.py [--seeds 5] [--steps 30] [--jobs 2]
    PYTHONPATH=. python benchmarks/datasheet_cost.py --existing DIR   # the figures of a bench already run in DIR
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from starenv.bench.report import tabulate, write_report
from starenv.bench.runner import run_bench
from starenv.bench.spec import parse_bench

# the bundled bench's shape: plain cases of two pipelines over several seeds, and a rate sweep on one seed
BENCH = """
name = "datasheet-cost"
seeds = {seeds}
steps = {steps}
[[runs]]
scenario = "paper_002"
pipelines = ["tracking", "lost_in_space"]
[[runs]]
scenario = "paper_000"
pipelines = ["tracking", "lost_in_space"]
sweep = {{ key = "motion.rate_dps", axis = [1, 0, 0], values = [0, 20, 40] }}
seeds = [0]
steps = 5
"""


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--existing", type=Path, default=None, help="a bench output folder: time its figures only")
    args = parser.parse_args()
    if args.existing is not None:
        files = sorted((args.existing / "runs").glob("*.jsonl"))
        (cases, _, sheet), figures = timed(tabulate, files)
        print(f"{len(files)} run files, {len(cases)} cases, {len(sheet)} datasheet rows: figures {figures:.2f} s")
        return
    bench = parse_bench(BENCH.format(seeds=args.seeds, steps=args.steps))
    with tempfile.TemporaryDirectory() as tmp:
        # fill the disk caches (catalog, pattern database) first, so that the timed runs do not build them
        run_bench(parse_bench(BENCH.format(seeds=1, steps=1)), Path(tmp) / "warm", jobs=args.jobs, progress=False,
                  log=lambda *a: None)
        out = Path(tmp) / "bench"
        files, runs = timed(lambda: run_bench(bench, out, jobs=args.jobs, progress=False, log=lambda *a: None))
        (cases, _, sheet), figures = timed(tabulate, files)
        _, report = timed(write_report, bench, files, out)
    print(f"{len(bench.runs)} runs ({args.seeds} seeds x {args.steps} steps on paper_002, a 3-rate sweep of "
          f"paper_000), {len(cases)} cases, {len(sheet)} datasheet rows, {args.jobs} worker processes")
    print(f"  runs                                 {runs:7.2f} s wall")
    print(f"  figures (summary + datasheet, CIs)   {figures:7.2f} s   {100 * figures / runs:5.1f} % of the runs "
          "(goal: < 5 %)")
    print(f"  whole report (figures, tables, plots) {report:6.2f} s   {100 * report / runs:5.1f} % of the runs")


if __name__ == "__main__":
    main()
