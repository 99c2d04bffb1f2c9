"""Paper 000's restoration result: the highest angular rate at which attitude is still solved, per rotation axis,
from blurred frames and from frames restored by Richardson-Lucy with the EBPNN's iteration count.

Scenario ``paper_000`` turning at a constant rate about one body axis (``motion.rate_dps``), the scenario's own
pipeline (``Pipeline.for_scenario``) without and with ``IterationNetDeblurrer``, ``--steps`` scored steps per rate.
A step counts as solved when the pipeline's attitude came from that frame's stars (not from the gyro prediction)
and is within the scenario's availability threshold (100 arcsec); a rate works when at least half its steps are
solved.  Like the paper's tables, the report gives the last working and the first failing grid rate; an axis's scan
stops after two failing rates in a row.  ``--restored-threshold-sigma S`` adds a scan of the restored frames with
the detector's threshold at S sigma (the scenario's detector uses 5; default 0: no such scan).

    python benchmarks/paper000_restoration.py [--axes x y z] [--steps 4] [--seed 0] [--restored-threshold-sigma S]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from starenv.agents.pipeline import Pipeline
from starenv.agents.restore.iteration.deblurrer import IterationNetDeblurrer
from starenv.env import StarSensorEnv
from starenv.episode import run_episode

GRIDS = {  # deg/s
    "x": (5, 10, 20, 30, 45, 60, 80),
    "y": (5, 10, 20, 30, 45, 60, 80),
    "z": (10, 30, 60, 100, 170),
}
AXIS = {"x": 0, "y": 1, "z": 2}


class Sources:
    """Observer keeping, per step, where the attitude came from and whether it was within the threshold."""

    def __init__(self):
        self.solved: list[bool] = []
        self.iterations: list[int] = []
        self.recall: list[float] = []
        self.precision: list[float] = []

    def start(self, env, seed, pipeline) -> None:
        self.solved, self.iterations, self.recall, self.precision = [], [], [], []

    def step(self, log) -> None:
        self.solved.append(log.source == "solved" and bool(log.record["within_threshold"]))
        for key, values in (("detection_recall", self.recall), ("detection_precision", self.precision)):
            if log.record.get(key) is not None:
                values.append(log.record[key])
        deblurrer = log.pipeline.agents["deblurrer"] if log.pipeline is not None else None
        if deblurrer is not None:
            self.iterations.append(deblurrer.last_info.get("iterations", 0))

    def close(self, error=None) -> None:
        pass


def solved_fraction(axis: str, rate: float, restored: bool, steps: int, seed: int,
                    threshold_sigma: float | None = None) -> tuple:
    """(share of steps solved, median RL iterations, median deblur ms per step, mean detection recall and
    precision) at one rate."""
    vector = [0.0, 0.0, 0.0]
    vector[AXIS[axis]] = float(rate)
    env = StarSensorEnv("paper_000", overrides={"motion.rate_dps": vector})
    sigma = env.scenario.heads[0].psf_sigma_px  # the sensor's spot: the still stars are drawn with it
    agents = {"deblurrer": IterationNetDeblurrer(psf_sigma_px=sigma)} if restored else None
    options = {"detector": {"threshold_sigma": threshold_sigma}} if threshold_sigma is not None else None
    pipeline = Pipeline.for_scenario(env.scenario, agents=agents, options=options)
    watch = Sources()
    result = run_episode(env, pipeline, seed=seed, steps=steps, observers=[watch])
    ms = [r.get("latency_deblurrer_ms") for r in result.records if r.get("latency_deblurrer_ms") is not None]
    mean = lambda v: float(np.mean(v)) if v else float("nan")  # noqa: E731
    return (float(np.mean(watch.solved)), float(np.median(watch.iterations)) if watch.iterations else 0.0,
            float(np.median(ms)) if ms else 0.0, mean(watch.recall), mean(watch.precision))


def scan(axis: str, restored: bool, steps: int, seed: int,
         threshold_sigma: float | None = None) -> tuple[list[tuple], float | None, float | None]:
    """Per-rate results and (last working rate, first failing rate) along the axis's grid."""
    rows, last_ok, first_fail, fails_in_row = [], None, None, 0
    for rate in GRIDS[axis]:
        share, iters, ms, recall, precision = solved_fraction(axis, rate, restored, steps, seed, threshold_sigma)
        rows.append((rate, share, iters, ms, recall, precision))
        if share >= 0.5:
            fails_in_row = 0
            if first_fail is None:
                last_ok = rate
        else:
            fails_in_row += 1
            first_fail = rate if first_fail is None else first_fail
            if fails_in_row == 2:
                break
    return rows, last_ok, first_fail


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--axes", nargs="+", choices=list(GRIDS), default=list(GRIDS))
    parser.add_argument("--steps", type=int, default=4, help="scored steps per rate")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--restored-threshold-sigma", type=float, default=0.0,
                        help="also scan restored frames with the detector at this threshold (0: skip)")
    args = parser.parse_args()
    variants = [("blurred", False, None), ("restored (EBPNN RL)", True, None)]
    if args.restored_threshold_sigma > 0:
        label = f"restored, detector at {args.restored_threshold_sigma:g} sigma"
        variants.append((label, True, args.restored_threshold_sigma))
    t0 = time.perf_counter()
    summary, detail = [], []
    for axis in args.axes:
        for label, restored, threshold in variants:
            rows, last_ok, first_fail = scan(axis, restored, args.steps, args.seed, threshold)
            summary.append((axis, label, last_ok, first_fail))
            detail += [(axis, label, *r) for r in rows]
    print(f"paper_000, constant rate about one body axis, {args.steps} steps per rate, seed {args.seed}")
    print("| axis | frames | last working rate (deg/s) | first failing rate (deg/s) |")
    print("|---|---|---|---|")
    for axis, label, ok, fail in summary:
        print(f"| {axis.upper()} | {label} | {ok if ok is not None else '-'} | {fail if fail is not None else '-'} |")
    print()
    print("| axis | frames | rate (deg/s) | steps solved | detection recall | detection precision | "
          "RL iterations (median) | deblur ms / step (median) |")
    print("|---|---|---|---|---|---|---|---|")
    for axis, label, rate, share, iters, ms, recall, precision in detail:
        print(f"| {axis.upper()} | {label} | {rate} | {share:.2f} | {recall:.2f} | {precision:.2f} | {iters:.0f} "
              f"| {ms:.0f} |")
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
