"""Command line: ``starenv scenarios``, ``starenv render SCENARIO``, ``starenv run SCENARIO``."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from starenv import scenario as scenario_mod


def _overrides(pairs: list[str]) -> dict:
    """``key.path=VALUE`` pairs; VALUE is parsed as JSON when it can be (numbers, lists), else kept as a string."""
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise scenario_mod.ScenarioError(f"--set {pair!r}: expected KEY.PATH=VALUE, e.g. motion.rate_dps=[0,0,5]")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def cmd_scenarios(args) -> int:
    for name in scenario_mod.bundled_names():
        sc = scenario_mod.load(name)
        print(f"{name:24s} {sc.description}")
    return 0


def cmd_render(args) -> int:
    import cv2

    from starenv.sensor import StarSensor
    from starenv.view import mosaic, overlay

    sc = scenario_mod.load(args.scenario, _overrides(args.set))
    sensor = StarSensor(sc)
    sensor.reset(sc.seed if args.seed is None else args.seed)
    for _ in range(args.frame + 1):
        frame = sensor.next_frame()
    images = [overlay(h.image, h.truth if args.truth else None, h.dropped) for h in frame.heads]
    out = Path(args.out or f"recordings/{sc.name}_frame{args.frame}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), cv2.cvtColor(mosaic(images), cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {out}")
    stars = ", ".join(f"{hf.truth.catalog_id.size} stars" + (" (dropped)" if hf.dropped else "") for hf in frame.heads)
    rate_dps = math.degrees(float(np.linalg.norm(sc.trajectory.body_rate(frame.t_mid))))
    print(f"{sc.name}: frame {frame.index} at t = {frame.t_mid:.4f} s, |w| = {rate_dps:.3g} deg/s, {stars}")
    print(f"wrote {out}")
    return 0


def _agents(pairs: list[str]) -> dict[str, str]:
    out = {}
    for pair in pairs:
        role, sep, spec = pair.partition("=")
        if not sep:
            raise ValueError(f"--agent {pair!r}: expected ROLE=module:Class (or ROLE=none)")
        out[role] = None if spec.lower() == "none" else spec
    return out


def cmd_run(args) -> int:
    from starenv.env import StarSensorEnv
    from starenv.episode import run_episode
    from starenv.scoring import summarize

    env = StarSensorEnv(args.scenario, _overrides(args.set))
    pipeline = None
    if args.pipeline != "none":
        from starenv.agents.pipeline import Pipeline

        pipeline = Pipeline.for_scenario(env.scenario, _agents(args.agent))
    sc = env.scenario
    result = run_episode(env, pipeline, seed=args.seed, steps=args.steps)
    records, wall, dropped, lost_at = result.records, result.wall_s, result.dropped, result.lost_at
    summary = summarize(records)
    print(f"{sc.name}: {sc.description}")
    print(f"  {len(records)} steps ({len(records) / sc.frame_rate_hz:.2f} s simulated) in {wall:.2f} s wall; "
          f"frames dropped per head: {dropped.tolist()}; lost rule fired at step: {lost_at}")
    if pipeline is None:
        print("  pipeline: none (every step unavailable)")
        return 0
    print("  pipeline: " + ", ".join(f"{r}={a}" for r, a in pipeline.describe().items() if a))
    avail = summary.get("within_threshold", {}).get("mean", 0.0)
    print(f"  availability (error < {sc.availability_threshold_arcsec:g} arcsec): {avail:.3f}")
    for key, unit in (("attitude_error_arcsec", "arcsec"), ("cross_boresight_error_arcsec", "arcsec"),
                      ("roll_error_arcsec", "arcsec"), ("centroid_error_px_mean", "px"), ("id_rate", ""),
                      ("false_id_rate", ""), ("solved", ""), ("prediction_error_px_mean", "px"),
                      ("restoration_centroid_error_blurred_px", "px"), ("restoration_centroid_error_px", "px"),
                      ("restoration_stars_before", ""), ("restoration_stars_after", ""),
                      ("restoration_psnr_gain_db", "dB"), ("restoration_iterations", "")):
        if key in summary:
            v = summary[key]
            print(f"  {key:38s} median {v['median']:10.4g}  p95 {v['p95']:10.4g}  mean {v['mean']:10.4g} {unit}")
    for key in sorted(k for k in summary if k.startswith("latency_")):
        v = summary[key]
        print(f"  {key:38s} median {v['median']:10.3f}  p95 {v['p95']:10.3f} ms")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="starenv", description="Star sensor simulator under dynamic conditions")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("scenarios", help="list the bundled scenarios").set_defaults(fn=cmd_scenarios)
    p = sub.add_parser("render", help="render one frame of a scenario to a PNG, truth overlaid")
    p.add_argument("scenario", help="bundled scenario name or path to a .toml file")
    p.add_argument("--frame", type=int, default=0, help="frame index (default 0)")
    p.add_argument("--seed", type=int, default=None, help="seed (default: the scenario's)")
    p.add_argument("--out", default=None, help="PNG path (default recordings/NAME_frameN.png)")
    p.add_argument("--no-truth", dest="truth", action="store_false", help="do not draw the true star trails")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", help="override a scenario key")
    p.set_defaults(fn=cmd_render)
    p = sub.add_parser("run", help="run an episode of a scenario and print a summary")
    p.add_argument("scenario", help="bundled scenario name or path to a .toml file")
    p.add_argument("--steps", type=int, default=None, help="steps to run (default: the whole scenario)")
    p.add_argument("--seed", type=int, default=None, help="seed (default: the scenario's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", help="override a scenario key")
    p.add_argument("--pipeline", choices=("default", "none"), default="default",
                   help="the built-in classical pipeline (default) or none")
    p.add_argument("--agent", action="append", default=[], metavar="ROLE=module:Class",
                   help="replace one agent of the pipeline (roles: predictor, deblurrer, detector, corrector, "
                        "identifier, solver; ROLE=none empties an optional role)")
    p.set_defaults(fn=cmd_run)
    args = parser.parse_args(argv)
    try:
        return args.fn(args)
    except (scenario_mod.ScenarioError, ValueError, OSError) as exc:
        print(f"starenv: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
