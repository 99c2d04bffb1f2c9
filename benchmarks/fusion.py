"""The MEKF (``starenv.agents.fuse.mekf.MekfPredictor``) against the classical pipelines on the same frames: each
scenario's own pipeline (the gyro propagates the last solution open loop, every frame is solved on its own), the same
pipeline with the filter as its predictor (gyro noise values from the scenario's datasheet, as a user would configure
them) and, where it matters, frame-by-frame solutions (no predictor: lost-in-space identification on every frame)::

    python benchmarks/fusion.py [--tables main bursts bias edge] [--steps 100] [--seeds 0 1]
                                [--bias-seconds 60] [--bias-seeds 0 1 2 3] [--edge-steps 30]

Tables (all errors in arcsec against the truth at mid-exposure):

The filter is told the gyro's bias 1-sigma: the bias instability's for the scenarios' calibrated gyros, 10 deg/h for
the MEMS-grade one, 10 deg/h in the bias table.

* ``main``: per scenario the median and p95 attitude error, the roll (about head 0's boresight) and cross-boresight
  RMS and the availability, over ``--steps`` steps of ``--seeds``;
* ``bursts``: ``stress_drops`` at 10 frames/s with drop bursts of 0.5-5 s (Gilbert-Elliott bad spells of 2 s on
  average, ``BURSTS``), the error on dropped steps binned by the time since the last delivered frame, with the
  scenario's gyro and with a MEMS-grade one (``MEMS``);
* ``bias``: ``paper_000`` at 1 deg/s about X, 10 frames/s, the filter started with a 10 deg/h bias 1-sigma: its gyro
  bias error per body axis against its own 1-sigma and the angle-random-walk bound over ``--bias-seeds``, and the
  bounds that decide the 10 %-of-bias-instability goal (Farrenkopf's steady state);
* ``edge``: ``paper_002`` at 5-25 deg/s (three-axis), where frame-by-frame solutions start failing.
"""

from __future__ import annotations

import argparse
import math
from itertools import pairwise

import numpy as np

from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.sim.conventions import DEG
from starenv.sim.gyro import GM_PEAK_ADEV_PER_SIGMA, IEEE_FLICKER_FLOOR

CASES = {
    "paper_000 at 1 deg/s about X": ("paper_000", {"motion.rate_dps": [1.0, 0.0, 0.0]}),
    "stress_drops (bursty drops)": ("stress_drops", {}),
    "paper_004 (three heads)": ("paper_004", {}),
}
FILTER = {"predictor": "starenv.agents.fuse:MekfPredictor"}
FRAME_BY_FRAME = {"predictor": None}
# stress_drops at 10 frames/s for 30 s, every frame lost in a bad spell: bad spells of 1 / 0.05 = 20 frames (2 s) on
# average (geometric: 1 in 12 lasts 5 s or more), good spells of 25 frames; 44 % of frames lost
BURSTS = {"frame_rate_hz": 10.0, "duration_s": 30.0, "drops.probability": 0.0, "drops.p_good_to_bad": 0.04,
          "drops.p_bad_to_good": 0.05, "drops.drop_bad": 1.0}
# a MEMS-grade gyro with its turn-on bias left in (the filter is told a 10 deg/h 1-sigma, its repeatability)
MEMS = {"gyro.arw_deg_rthr": 0.15, "gyro.bias_instability_deg_hr": 5.0, "gyro.bias_deg_hr": [10.0, -8.0, 6.0]}
MEMS_BIAS_PRIOR_DEG_HR = 10.0
BURST_BINS = (0.0, 0.5, 1.0, 2.0, 3.0, 5.0, math.inf)  # s since the last delivered frame
BIAS_TABLE_PRIOR_DEG_HR = 10.0  # the bias table starts the filter knowing nothing of the bias: it must learn it
DEG_HR = np.degrees(1.0) * 3600.0  # rad/s -> deg/h (and rad -> arcsec)


def values(records, key):
    return np.array([r[key] for r in records if r[key] is not None])


class Steps:
    """An observer that keeps, per step: the time (s), whether every head's frame was dropped, where the attitude
    came from, and a filter's bias error (3,) and 1-sigma (3,) in deg/h (None without a filter)."""

    def start(self, env, seed, pipeline):
        self.time, self.dropped, self.source, self.bias = [], [], [], []

    def step(self, log):
        self.time.append(float(log.truth["time_s"]))
        self.dropped.append(all(log.truth["dropped"]))
        self.source.append(log.source)
        bias = None
        if log.covariance is not None:
            error = (np.asarray(log.gyro_bias) - np.asarray(log.truth["gyro_bias"])) * DEG_HR
            bias = (error, np.sqrt(np.diag(log.covariance)[3:]) * DEG_HR)
        self.bias.append(bias)

    def close(self, error=None):
        pass


def filter_options(env, bias_prior_deg_hr: float | None = None) -> dict:
    """The filter's options from the scenario's gyro datasheet; its initial bias 1-sigma ``bias_prior_deg_hr`` (deg/h)
    defaults to the bias instability's Gauss-Markov sigma (0.664 B / 0.618): a gyro whose constant bias has been
    calibrated out, as every bundled scenario's is."""
    gyro = env.scenario.gyro
    if bias_prior_deg_hr is None:
        bias_prior_deg_hr = IEEE_FLICKER_FLOOR * gyro.bias_instability_deg_hr / GM_PEAK_ADEV_PER_SIGMA
    return {"predictor": {"arw_deg_rthr": gyro.arw_deg_rthr, "rrw_deg_hr_rthr": gyro.rrw_deg_hr_rthr,
                          "bias_instability_deg_hr": gyro.bias_instability_deg_hr,
                          "bias_correlation_s": gyro.bias_correlation_s,
                          "initial_bias_sigma_deg_hr": bias_prior_deg_hr}}


def pipelines(env, frame_by_frame: bool = False, bias_prior_deg_hr: float | None = None):
    """(name, agents, options) of the pipelines compared on ``env``'s scenario."""
    out = [("open loop (scenario's own)", {}, {}), ("MEKF", FILTER, filter_options(env, bias_prior_deg_hr))]
    return out + [("frame by frame", FRAME_BY_FRAME, {})] if frame_by_frame else out


def episode(env, agents, options, seed, steps=None):
    seen = Steps()
    pipe = Pipeline.for_scenario(env.scenario, agents, options)
    records = run_episode(env, pipe, seed=seed, steps=steps, observers=[seen]).records
    return records, seen


def main_table(steps: int, seeds) -> None:
    print("| case | pipeline | median error (\") | p95 (\") | roll RMS (\") | cross-boresight RMS (\") | available |")
    print("|---|---|---|---|---|---|---|")
    for label, (name, overrides) in CASES.items():
        env = StarSensorEnv(name, overrides=overrides)
        for pipeline_name, agents, opts in pipelines(env):
            records = []
            for seed in seeds:
                records += episode(env, agents, opts, seed, steps)[0][5:]  # after the first fix
            err, roll = values(records, "attitude_error_arcsec"), values(records, "head0_error_roll_arcsec")
            cross = values(records, "head0_cross_boresight_error_arcsec")
            available = np.mean([r["available"] for r in records])
            print(f"| {label} | {pipeline_name} | {np.median(err):.1f} | {np.percentile(err, 95):.1f} | "
                  f"{np.sqrt(np.mean(roll**2)):.1f} | {np.sqrt(np.mean(cross**2)):.1f} | {available:.2f} |")


def burst_table(seeds) -> None:
    """Dropped steps binned by the time since the last delivered frame; the steps with a frame beside them."""
    print("\n| gyro | pipeline | " + " | ".join(f"{lo:g}-{hi:g} s" for lo, hi in pairwise(BURST_BINS))
          + " | steps with a frame |")
    print("|---" * (len(BURST_BINS) + 2) + "|")
    for gyro_name, gyro, prior in (("scenario's FOG", {}, None), ("MEMS-grade", MEMS, MEMS_BIAS_PRIOR_DEG_HR)):
        env = StarSensorEnv("stress_drops", overrides={**BURSTS, **gyro})
        for name, agents, opts in pipelines(env, frame_by_frame=True, bias_prior_deg_hr=prior):
            gaps, errors, framed = [], [], []
            for seed in seeds:
                records, seen = episode(env, agents, opts, seed)
                last = None
                for t, dropped, r in zip(seen.time, seen.dropped, records, strict=True):
                    if not dropped:
                        last = t
                        if r["available"]:
                            framed.append(r["attitude_error_arcsec"])
                    elif last is not None:
                        gaps.append(t - last)
                        errors.append(r["attitude_error_arcsec"] if r["available"] else None)
            cells = []
            gaps = np.array(gaps)
            for lo, hi in pairwise(BURST_BINS):
                inside = [e for g, e in zip(gaps, errors, strict=True) if lo <= g < hi]
                scored = [e for e in inside if e is not None]
                cells.append("no estimate" if inside and not scored else
                             f"{np.median(scored):.1f} / {np.percentile(scored, 95):.1f} ({len(inside)})"
                             if scored else "-")
            print(f"| {gyro_name} | {name} | " + " | ".join(cells) +
                  f" | {np.median(framed):.1f} / {np.percentile(framed, 95):.1f} ({len(framed)}) |")
    print("\ncells: median / p95 attitude error (\") on the dropped steps of each bin (number of steps)")


def bias_bounds(arw_deg_rthr: float, rrw: float, instability: float, tau: float, prior_deg_hr: float, t: float):
    """Per-axis bias 1-sigma bounds (deg/h) with a perfectly known attitude: after ``t`` s of a constant bias seen
    through angle random walk sigma_v, ``1 / sqrt(1 / s0^2 + t / sigma_v^2)``; and Farrenkopf's steady state of a bias
    walking at sigma_u, ``sqrt(sigma_u sigma_v)``, with the walk of the simulated Gauss-Markov bias instability."""
    sigma_v = arw_deg_rthr * DEG / 60.0
    gm = IEEE_FLICKER_FLOOR * instability / GM_PEAK_ADEV_PER_SIGMA * DEG / 3600.0
    sigma_u = math.sqrt((rrw * DEG / 3600.0 / 60.0) ** 2 + 2.0 * gm**2 / tau)
    constant = 1.0 / math.sqrt(1.0 / (prior_deg_hr / DEG_HR) ** 2 + t / sigma_v**2)
    return constant * DEG_HR, math.sqrt(sigma_u * sigma_v) * DEG_HR, gm * DEG_HR


def bias_table(seconds: float, seeds) -> None:
    env = StarSensorEnv("paper_000", overrides={"motion.rate_dps": [1.0, 0.0, 0.0], "frame_rate_hz": 10.0,
                                                "duration_s": seconds + 0.2})
    gyro = env.scenario.gyro
    runs = [episode(env, FILTER, filter_options(env, BIAS_TABLE_PRIOR_DEG_HR), seed)[1].bias for seed in seeds]
    print(f"\n| time (s) | RMS bias error x, y, z (deg/h, {len(seeds)} seeds) | filter 1-sigma x, y, z | "
          "ARW bound (perfect attitude) |\n|---|---|---|---|")
    for t in (1, 5, 10, 20, 30, 45, 60, 90, 120, 180, 300):
        k = int(round(10 * t))
        if k >= len(runs[0]):
            break
        err = np.sqrt(np.mean([run[k][0] ** 2 for run in runs], axis=0))
        sigma = np.mean([run[k][1] for run in runs], axis=0)
        bound = bias_bounds(gyro.arw_deg_rthr, gyro.rrw_deg_hr_rthr, gyro.bias_instability_deg_hr,
                            gyro.bias_correlation_s, BIAS_TABLE_PRIOR_DEG_HR, t)[0]
        print(f"| {t} | {err[0]:.3f}, {err[1]:.3f}, {err[2]:.3f} | {sigma[0]:.3f}, {sigma[1]:.3f}, {sigma[2]:.3f} "
              f"| {bound:.3f} |")
    z2 = np.mean([np.mean((run[-1][0] / run[-1][1]) ** 2) for run in runs])
    goal = 0.1 * gyro.bias_instability_deg_hr
    sigma_v = gyro.arw_deg_rthr * DEG / 60.0
    _, steady, gm = bias_bounds(gyro.arw_deg_rthr, gyro.rrw_deg_hr_rthr, gyro.bias_instability_deg_hr,
                                gyro.bias_correlation_s, 10.0, 0.0)
    print(f"\nmean normalised squared bias error at the end, per axis: {z2:.2f} (1 when consistent)")
    print(f"goal: {goal:.3f} deg/h per axis (10 % of B = {gyro.bias_instability_deg_hr} deg/h); a constant bias "
          f"reaches it after (sigma_v / goal)^2 = {(sigma_v / (goal / DEG_HR)) ** 2 / 3600.0:.1f} h with a perfect "
          f"attitude; the simulated bias wanders (Gauss-Markov sigma {gm:.3f} deg/h, tau {gyro.bias_correlation_s:g} "
          f"s): Farrenkopf's steady-state floor sqrt(sigma_u sigma_v) = {steady:.3f} deg/h")


def edge_table(steps: int, seeds, rates=(5.0, 10.0, 15.0, 20.0, 25.0)) -> None:
    """paper_002 three-axis at ``rates`` deg/s: availability (error under the scenario's 60" threshold), median and
    p95 error over the steps with an estimate, and the share of steps whose frame was solved."""
    print("\n| rate (deg/s) | pipeline | within 60\" | median error (\") | p95 (\") | frames solved |")
    print("|---|---|---|---|---|---|")
    for rate in rates:
        env = StarSensorEnv("paper_002", overrides={"motion.rate_dps": [rate / math.sqrt(3.0)] * 3})
        for name, agents, opts in pipelines(env, frame_by_frame=True):
            records, solved = [], []
            for seed in seeds:
                recs, seen = episode(env, agents, opts, seed, steps)
                records += recs
                solved += [s == "solved" for s in seen.source]
            err = values(records, "attitude_error_arcsec")
            within = np.mean([bool(r["within_threshold"]) for r in records])
            cells = f"{np.median(err):.1f} | {np.percentile(err, 95):.1f}" if len(err) else "- | -"
            print(f"| {rate:g} | {name} | {within:.2f} | {cells} | {np.mean(solved):.2f} |")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tables", nargs="+", default=["main", "bursts", "bias", "edge"],
                        choices=["main", "bursts", "bias", "edge"])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--bias-seconds", type=float, default=60.0)
    parser.add_argument("--bias-seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--edge-steps", type=int, default=30)
    args = parser.parse_args(argv)
    if "main" in args.tables:
        main_table(args.steps, args.seeds)
    if "bursts" in args.tables:
        burst_table(args.seeds)
    if "bias" in args.tables:
        bias_table(args.bias_seconds, args.bias_seeds)
    if "edge" in args.tables:
        edge_table(args.edge_steps, args.seeds)


if __name__ == "__main__":
    main()
