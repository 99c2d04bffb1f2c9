"""Instructions per call of the hot paths (valgrind's callgrind): lost in space and tracking on centroid sets, the
star render of the ``env.step`` benchmark's frames, the detector on paper 002's frames.

A count repeats exactly from run to run on one machine (same code, inputs and libraries), whatever else the machine
is doing, where a timing on a shared machine drifts by tens of percent within seconds: it is how two versions of the
code are compared here, one checkout after the other.  It counts work, not time: a pass over memory weighs less than
it costs, a cache miss nothing.  OpenBLAS runs on one thread (its idle threads would otherwise spin into the count).

Workloads (inputs drawn from ``--seed``, default 8800: no test draws from it):

- ``lis``: :class:`~starenv.agents.identify.LostInSpaceIdentifier` on ``--count`` centroid sets of
  ``benchmarks/identify_peers.py`` (paper 002's head, ``--fov`` 12 or 20 deg, ``--noise`` px per axis);
- ``heads``: :class:`~starenv.agents.identify.LostInSpaceIdentifier` on ``--count`` frames of paper 004's three
  heads (``benchmarks/multi_head_false_ids.py``'s: stars to Hp 6.5, the identifier on the catalogue to Hp 7.5,
  ``--noise`` px per axis);
- ``render``: :meth:`~starenv.sim.render.StarRenderer.render` of ``--count`` consecutive frames of
  ``benchmarks/env_speed.py``'s 1024 x 1024 env (30 px trails);
- ``detect``: :class:`~starenv.agents.detect.CentroidDetector` on ``--count`` frames of ``benchmarks/detect_speed.py``
  at 5 deg/s (a pointing each).

Each workload is built and run once untimed, then counted over its ``--count`` calls.

    python benchmarks/instruction_counts.py [--workloads lis,track,heads,render,detect] [--count N] [--seed S] [--fov F]
                                            [--noise PX]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

WORKLOADS = ("lis", "track", "heads", "render", "detect")
TRACK_PRIOR_DEG = 0.5  # track: the prior's error, within the tracking gate's reach at 12 and 20 deg


def _workload(name: str, count: int, seed: int, fov: int, noise: float):
    """The calls of workload ``name``: a function of no argument per call."""
    import numpy as np

    if name in ("lis", "track"):
        from identify_peers import EPOCH, MAG_LIMIT, TRACK_STARS, make_camera, make_sets, split  # from benchmarks/
        from scipy.spatial.transform import Rotation

        from starenv.agents.base import StarMeasurements
        from starenv.agents.identify import LostInSpaceIdentifier, TrackingIdentifier
        from starenv.sim.conventions import DEG
        from starenv.sim.sky import load_catalog

        camera = make_camera(fov)
        rng = np.random.default_rng(seed)
        sets = make_sets(camera, MAG_LIMIT[fov], count, rng, noise)
        identifier = LostInSpaceIdentifier() if name == "lis" else TrackingIdentifier()
        identifier.reset([camera], load_catalog(MAG_LIMIT[fov], EPOCH))
        stars = [StarMeasurements(xy, f) for xy, f in zip(split(sets, "xy"), split(sets, "flux"), strict=True)]
        if name == "lis":
            return [lambda s=s: identifier.identify([s], [camera]) for s in stars]
        axes = rng.normal(size=(count, 3))
        priors = Rotation.from_rotvec(axes / np.linalg.norm(axes, axis=1, keepdims=True) * (TRACK_PRIOR_DEG * DEG))
        priors = priors * Rotation.from_matrix(sets["attitude"])
        cut = [(StarMeasurements(stars[k].xy[:TRACK_STARS], stars[k].flux[:TRACK_STARS]), priors[k])
               for k in sets["track"]]
        return [lambda s=s, p=p: identifier.identify([s], [camera], p) for s, p in cut]
    if name == "heads":
        from multi_head_false_ids import draw_frames, heads_and_catalogues  # from benchmarks/

        from starenv.agents.base import StarMeasurements
        from starenv.agents.identify import LostInSpaceIdentifier

        cameras, visible, onboard = heads_and_catalogues()
        identifier = LostInSpaceIdentifier()
        identifier.reset(cameras, onboard)
        frames = [[StarMeasurements(x, f) for x, f in zip(cs.xy, cs.flux, strict=True)]
                  for cs, _ in draw_frames(visible, cameras, seed, count, noise, 2.0)]
        return [lambda stars=stars: identifier.identify(stars, cameras) for stars in frames]
    if name == "render":
        from env_speed import frame_env

        env = frame_env(seed, count)
        env.reset(seed=seed)
        sensor = env.unwrapped.sensor
        renderer, scenario = sensor.renderers[0], sensor.scenario
        return [lambda k=k: renderer.render(scenario.trajectory, k / scenario.frame_rate_hz, scenario.exposure_s)
                for k in range(count)]
    from detect_speed import frames

    from starenv.agents.detect.centroid import CentroidDetector

    images, head = frames(5.0, range(seed, seed + count))
    detector = CentroidDetector()
    return [lambda image=image: detector.detect(image, head.calibrated) for image, _ in images]


def child(args: argparse.Namespace) -> None:
    """Inside valgrind: build the workload, run it once, then count its calls (instrumentation on only for them)."""
    import cv2

    cv2.setNumThreads(1)
    calls = _workload(args.child, args.count, args.seed, args.fov, args.noise)
    for call in calls:
        call()
    control = ["callgrind_control", "-i"]
    subprocess.run([*control, "on", str(os.getpid())], check=True, capture_output=True)
    for call in calls:
        call()
    subprocess.run([*control, "off", str(os.getpid())], check=True, capture_output=True)
    print(f"calls {len(calls)}")


def count(name: str, args: argparse.Namespace) -> int:
    """Instructions of workload ``name``'s calls and their number, from a run of this script under callgrind."""
    with tempfile.TemporaryDirectory() as folder:
        command = ["valgrind", "--tool=callgrind", "--instr-atstart=no",
                   f"--callgrind-out-file={Path(folder) / 'callgrind.out'}", sys.executable, __file__, "--child", name,
                   "--count", str(args.count), "--seed", str(args.seed), "--fov", str(args.fov),
                   "--noise", str(args.noise)]
        env = os.environ | {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        run = subprocess.run(command, capture_output=True, text=True, env=env)
    found = re.search(r"Collected\s*:\s*(\d+)", run.stderr)
    calls = re.search(r"^calls (\d+)$", run.stdout, re.MULTILINE)
    if run.returncode != 0 or found is None or calls is None:
        raise RuntimeError(f"callgrind run of {name} failed (exit {run.returncode}):\n{run.stderr[-2000:]}")
    return int(found.group(1)), int(calls.group(1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workloads", default=",".join(WORKLOADS), help=f"comma-separated, of {', '.join(WORKLOADS)}")
    parser.add_argument("--count", type=int, default=40, help="calls counted per workload")
    parser.add_argument("--seed", type=int, default=8800)
    parser.add_argument("--fov", type=int, choices=(12, 20), default=12, help="lis, track: the field (deg)")
    parser.add_argument("--noise", type=float, default=1.0, help="lis, track: centroid noise per axis (px)")
    parser.add_argument("--child", choices=WORKLOADS, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args)
        return
    names = args.workloads.split(",")
    if not set(names) <= set(WORKLOADS) or args.count < 1:
        parser.error(f"--workloads must name some of {', '.join(WORKLOADS)}; --count must be >= 1")
    missing = [tool for tool in ("valgrind", "callgrind_control") if shutil.which(tool) is None]
    if missing:
        sys.exit(f"{' and '.join(missing)} not found: install valgrind (Debian: apt install valgrind)")
    print(f"seed {args.seed}, {args.count} calls a workload (lis, track: {args.fov} deg, {args.noise} px; track: the "
          f"sets of {args.count} with >= 30 stars)")
    for name in names:
        total, calls = count(name, args)
        print(f"{name:8} {total:>15,} instructions = {total / calls:>13,.0f} a call ({calls} calls)")


if __name__ == "__main__":
    main()
