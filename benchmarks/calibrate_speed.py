"""``starenv calibrate``'s speed on one core: 10 frames read, solved and fitted into a twin (goal: under a minute).

Frames: paper 003's camera (``paper_003``: 2048 x 2048 px, 20 deg field, its Legendre distortion, 0.1 s exposures)
rendered at ``--frames`` instants 100 s apart along its orbit (each sees another part of the sky), written as 16-bit
PNG files (rendering is not timed); or the image files of ``--files`` with their ``--fov``.  Then
:func:`starenv.real.calibrate.calibrate_files` runs on them as the command does (read, solve lost in space with the
spot measured, the three distortion models, spot, noise, zero point), timed in process CPU time and wall time.  The
catalogue and the pattern database are loaded once before (a first run on a machine builds the database and caches
it on disk).

Baseline, in the same run: the solver alone on the same frames (the sum of the solutions' ``time_ms``, detection,
spot measurement, identification and solution), so the line shows what the fit adds to solving.

One core: OpenMP, MKL and OpenBLAS are held to one thread (set below before numpy is imported; a value already in
the environment wins), OpenCV to one thread, and the process to one CPU where the system allows it.

    python benchmarks/calibrate_speed.py [--frames N] [--files FILE ... --fov DEG] [--epoch YEAR]
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402

from starenv import scenario as scenario_mod  # noqa: E402
from starenv.real import camera_from_fov, read_frame, solve_frame  # noqa: E402
from starenv.real.calibrate import calibrate_files, residual_table  # noqa: E402
from starenv.sim.sensor import StarSensor  # noqa: E402

GOAL_S = 60.0


def render(n: int, folder: Path) -> list[Path]:
    """``n`` frames of paper 003's head, 100 s apart along its orbit, as 16-bit PNG files."""
    sc = scenario_mod.load("paper_003", {"frame_rate_hz": 0.01, "duration_s": 100.0 * (n + 1)})
    sensor = StarSensor(sc)
    paths = []
    for k in range(n):
        frame = sensor.next_frame()
        paths.append(folder / f"paper003_{k:02d}.png")
        cv2.imwrite(str(paths[-1]), frame.heads[0].image)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10, help="frames of paper 003 to render (default 10)")
    parser.add_argument("--files", nargs="*", default=None, help="image files to calibrate on instead")
    parser.add_argument("--fov", type=float, default=None, help="their field across the columns (deg)")
    parser.add_argument("--epoch", type=float, default=2026.0, help="catalogue epoch (Julian year)")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    with tempfile.TemporaryDirectory() as tmp:
        if args.files:
            if args.fov is None:
                parser.error("--files needs --fov")
            paths, fov = [Path(p) for p in args.files], args.fov
        else:
            print(f"rendering {args.frames} frames of paper_003 (not timed) ...")
            paths, fov = render(args.frames, Path(tmp)), 20.0
        first = read_frame(paths[0])
        solve_frame(first, camera_from_fov(fov, first.shape), spot_calibrated=False, epoch=args.epoch)  # warm
        cpu, wall = time.process_time(), time.perf_counter()
        cal, solutions = calibrate_files(paths, fov, epoch=args.epoch, exposure_s=0.1 if not args.files else 1.0)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    solve_s = sum(s.time_ms for s in solutions) / 1e3
    print(residual_table(cal))
    print(f"{len(paths)} frames ({sum(s.solved for s in solutions)} solved), "
          f"{first.shape[1]} x {first.shape[0]} px, one core")
    print(f"calibrate: {cpu:.1f} s CPU, {wall:.1f} s wall (goal: under {GOAL_S:.0f} s); the solver alone on the same "
          f"frames (baseline): {solve_s:.1f} s wall; calibrate / solver: {wall / max(solve_s, 1e-9):.1f}")


if __name__ == "__main__":
    main()
