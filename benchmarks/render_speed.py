"""Render speed against the RNG floor: one 1024 x 1024 frame, ~40 stars smeared ~30 px, full noise chain.

The floor is drawing one float32 standard normal per pixel with numpy's Generator, measured in the same run (the
machines are shared and noisy, so only the ratio means anything).  Goal: render + read-out <= 1.5x the floor.

    python benchmarks/render_speed.py [--repeats N]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from starenv.detector import Detector, DetectorSpec
from starenv.frames import DEG, pointing
from starenv.motion import ConstantRate, Trajectory
from starenv.optics import Camera
from starenv.photometry import Photometry
from starenv.render import StarRenderer
from starenv.sky import load_catalog


def median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()

    # Seed 002's optics: 1024^2, f = 58.5 mm, 12 um (12 deg field); 50 ms exposure at 7 deg/s about X and Y.
    cam = Camera.from_focal_length(58.5e-3, 12e-6, 1024, 1024, f_number=1.4)
    catalog = load_catalog(mag_limit=6.0)
    exposure = 0.05
    rate = 30.0 / (cam.fx * exposure) / math.sqrt(2)  # rad/s per axis: 30 px trails on the boresight
    traj = Trajectory(ConstantRate([rate, rate, 0.0]), pointing(83.8 * DEG, -5.4 * DEG, 0.0))
    renderer = StarRenderer(catalog, cam, Photometry(cam.aperture_m), psf_sigma_px=1.0)
    detector = Detector(DetectorSpec(), cam.width, cam.height, cam.pixel_pitch_m, 5.0, np.random.default_rng(0))
    rng = np.random.default_rng(1)

    frame = renderer.render(traj, 0.0, exposure)
    trail = np.linalg.norm(frame.truth.xy_end - frame.truth.xy_start, axis=1)
    detector.read_out(frame.signal, exposure, rng)

    floor = median_time(lambda: rng.standard_normal((cam.height, cam.width), dtype=np.float32), args.repeats)
    render = median_time(lambda: renderer.render(traj, 0.0, exposure), args.repeats)
    readout = median_time(lambda: detector.read_out(frame.signal, exposure, rng), args.repeats)

    def full():
        f = renderer.render(traj, 0.0, exposure)
        detector.read_out(f.signal, exposure, rng)

    total = median_time(full, args.repeats)
    print(f"frame: {cam.width}x{cam.height}, {len(frame.truth)} stars, median trail {np.median(trail):.1f} px, "
          f"{frame.n_instants} instants per star")
    print(f"RNG floor (float32 normal per pixel): {floor * 1e3:8.2f} ms")
    print(f"render (stars, noise-free):           {render * 1e3:8.2f} ms")
    print(f"read-out (full noise chain):          {readout * 1e3:8.2f} ms")
    print(f"render + read-out:                    {total * 1e3:8.2f} ms  = {total / floor:.2f} x floor (goal <= 1.5)")


if __name__ == "__main__":
    main()
