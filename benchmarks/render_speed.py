"""Render speed against the RNG floor: one 1024 x 1024 frame, ~40 stars smeared ~30 px, full noise chain; and a
long-trail frame (paper 002's scenario at 30 deg/s, ~100 stars smeared ~150 px, ~480 instants per star).

The floor is drawing one float32 standard normal per pixel with numpy's Generator, measured in the same run (the
machines are shared and noisy, so only the ratio means anything).  Goal: render + read-out <= 1.5x the floor on the
short-trail frame.  Both frames are also rendered with each patch path forced (``SCATTER_AREA_RATIO`` = inf: window
matrix products only, the renderer before per-instant scattering existed; = 0: scatter only), so the speed-up and
the choice between the paths are measured in the same run.

    python benchmarks/render_speed.py [--repeats N] [--slow-repeats N]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from starenv.sim import render as render_module
from starenv.sim.conventions import DEG, pointing
from starenv.sim.imager import Detector, DetectorSpec
from starenv.sim.motion import ConstantRate, Trajectory
from starenv.sim.optics import Camera
from starenv.sim.photometry import Photometry
from starenv.sim.render import StarRenderer
from starenv.sim.sky import load_catalog


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
    parser.add_argument("--slow-repeats", type=int, default=3, help="repeats of the matrix-product-only long trails")
    args = parser.parse_args()

    # Paper 002's optics: 1024^2, f = 58.5 mm, 12 um (12 deg field); 50 ms exposure at 7 deg/s about X and Y.
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

    def frame_time(rend, trajectory, exp) -> float:
        """Median time (s) of one frame: render, then the full read-out noise chain."""
        return median_time(lambda: detector.read_out(rend.render(trajectory, 0.0, exp).signal, exp, rng), args.repeats)

    total = frame_time(renderer, traj, exposure)
    print(f"frame: {cam.width}x{cam.height}, {len(frame.truth)} stars, median trail {np.median(trail):.1f} px, "
          f"{frame.n_instants} instants per star")
    print(f"RNG floor (float32 normal per pixel): {floor * 1e3:8.2f} ms")
    print(f"render (stars, noise-free):           {render * 1e3:8.2f} ms")
    print(f"read-out (full noise chain):          {readout * 1e3:8.2f} ms")
    print(f"render + read-out:                    {total * 1e3:8.2f} ms  = {total / floor:.2f} x floor (goal <= 1.5)")


    # Paper 002's scenario at 30 deg/s (17.32 deg/s about each body axis), 92 ms exposure, stars to magnitude 6.5.
    long_renderer = StarRenderer(load_catalog(mag_limit=6.5), cam, Photometry(cam.aperture_m), psf_sigma_px=1.0)
    long_traj = Trajectory(ConstantRate(np.full(3, 17.32 * DEG)), pointing(83.8 * DEG, -5.4 * DEG, 0.0))
    long_exposure = 0.092
    long_frame = long_renderer.render(long_traj, 0.0, long_exposure)
    long_trail = np.linalg.norm(long_frame.truth.xy_end - long_frame.truth.xy_start, axis=1)

    long_total = frame_time(long_renderer, long_traj, long_exposure)
    print(f"long trails: {len(long_frame.truth)} stars, median trail {np.median(long_trail):.1f} px, "
          f"{long_frame.n_instants} instants per star")
    print(f"render + read-out:                    {long_total * 1e3:8.2f} ms  = {long_total / floor:.2f} x floor")

    default_ratio = render_module.SCATTER_AREA_RATIO
    print("render only, by patch path (ms):      chosen    matmul only   scatter only")
    for name, rend, tr, exp, repeats in (
        ("short trails", renderer, traj, exposure, args.repeats),
        ("long trails", long_renderer, long_traj, long_exposure, args.slow_repeats),
    ):
        times = []
        for ratio, n in ((default_ratio, args.repeats), (math.inf, repeats), (0, args.repeats)):
            render_module.SCATTER_AREA_RATIO = ratio
            times.append(median_time(lambda r=rend, t=tr, e=exp: r.render(t, 0.0, e), n))
        render_module.SCATTER_AREA_RATIO = default_ratio
        print(f"  {name:35s}{times[0] * 1e3:8.2f}   {times[1] * 1e3:10.2f}   {times[2] * 1e3:10.2f}"
              f"   (matmul only / chosen = {times[1] / times[0]:.1f})")

if __name__ == "__main__":
    main()
