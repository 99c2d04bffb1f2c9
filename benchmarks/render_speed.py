"""Render speed against the RNG floor: 1024 x 1024 frames, stars to magnitude 7 (the count printed) smeared ~30 px, full
noise chain; and a long-trail frame (paper 002's scenario at 30 deg/s, stars to magnitude 6.5 smeared ~150 px, ~480
instants per star).

The floor is drawing one float32 standard normal per pixel with numpy's Generator, measured in the same round (the
machines are shared and noisy, so only the ratio means anything).  Goal: render + read-out <= 1.5x the floor on the
short-trail frame.  Each of ``--rounds`` rounds points the camera somewhere else (uniform on the sky, random roll,
drawn from ``--seed``, which also seeds the detector's fixed pattern and noise) and prints its ratio; the median and
the spread (lowest and highest round) follow.  The first round's frames are also rendered with each patch path
forced (``SCATTER_AREA_RATIO`` = inf: window matrix products only, the renderer before per-instant scattering
existed; = 0: scatter only), so the speed-up and the choice between the paths are measured in the same run.  This
times the renderer and the detector alone; ``benchmarks/env_speed.py`` times the whole ``env.step``.

    python benchmarks/render_speed.py [--seed N] [--rounds N] [--repeats N] [--slow-repeats N]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from env_speed import random_pointing_deg  # run from benchmarks/, whose folder is on the path

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


def interleaved_times(fns, repeats: int) -> list[float]:
    """Median time (s) of each of ``fns``, timed one after the other ``repeats`` times (so that the machine's load
    falls on all alike)."""
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, spent in zip(fns, times, strict=True):
            t0 = time.perf_counter()
            fn()
            spent.append(time.perf_counter() - t0)
    return [float(np.median(spent)) for spent in times]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=6121, help="draws the pointings, the fixed pattern and the noise")
    parser.add_argument("--rounds", type=int, default=3, help="pointings, each timed against the floor")
    parser.add_argument("--repeats", type=int, default=30, help="timings (median) of each figure in a round")
    parser.add_argument("--slow-repeats", type=int, default=3, help="repeats of the matrix-product-only long trails")
    args = parser.parse_args()
    if args.rounds < 1 or args.repeats < 1:
        parser.error("--rounds and --repeats must be >= 1")

    # Paper 002's optics: 1024^2, f = 58.5 mm, 12 um (12 deg field); 50 ms exposure, 30 px trails on the boresight.
    cam = Camera.from_focal_length(58.5e-3, 12e-6, 1024, 1024, f_number=1.4)
    catalog = load_catalog(mag_limit=7.0)
    exposure = 0.05
    rate = 30.0 / (cam.fx * exposure) / math.sqrt(2)  # rad/s about X and Y
    renderer = StarRenderer(catalog, cam, Photometry(cam.aperture_m), psf_sigma_px=1.0)
    pointings = np.random.default_rng(args.seed)
    detector = Detector(DetectorSpec(), cam.width, cam.height, cam.pixel_pitch_m, 5.0,
                        np.random.default_rng([args.seed, 1]))
    rng = np.random.default_rng([args.seed, 2])
    noise = np.empty((cam.height, cam.width), np.float32)

    rounds = []
    for k in range(args.rounds):
        traj = Trajectory(ConstantRate([rate, rate, 0.0]), pointing(*np.radians(random_pointing_deg(pointings))))
        frame = renderer.render(traj, 0.0, exposure)
        trail = np.linalg.norm(frame.truth.xy_end - frame.truth.xy_start, axis=1)
        detector.read_out(frame.signal, exposure, rng)
        floor, render, readout, total = interleaved_times((
            lambda: rng.standard_normal(dtype=np.float32, out=noise),
            lambda t=traj: renderer.render(t, 0.0, exposure),
            lambda f=frame: detector.read_out(f.signal, exposure, rng),
            lambda t=traj: detector.read_out(renderer.render(t, 0.0, exposure).signal, exposure, rng),
        ), args.repeats)
        rounds.append((floor, render, readout, total))
        print(f"round {k}: {len(frame.truth)} stars, median trail {np.median(trail):.1f} px, {frame.n_instants} "
              f"instants per star; floor {floor * 1e3:.2f} ms, render {render * 1e3:.2f} ms, read-out "
              f"{readout * 1e3:.2f} ms, together {total * 1e3:.2f} ms = {total / floor:.2f} x floor")
        if k == 0:
            first = traj
    floor, render, readout, total = (np.array(x) for x in zip(*rounds, strict=True))

    def spread(values: np.ndarray) -> str:
        return f"{np.median(values):.2f} [{values.min():.2f}-{values.max():.2f}]"

    print(f"{cam.width}x{cam.height}, seed {args.seed}, medians of {args.rounds} rounds [lowest-highest round]:")
    print(f"RNG floor (float32 normal per pixel): {spread(floor * 1e3)} ms")
    print(f"render (stars, noise-free):           {spread(render / floor)} x floor")
    print(f"read-out (full noise chain):          {spread(readout / floor)} x floor")
    print(f"render + read-out:                    {spread(total / floor)} x floor (goal <= 1.5)")

    # Paper 002's scenario at 30 deg/s (17.32 deg/s about each body axis), 92 ms exposure, stars to magnitude 6.5,
    # at the first round's pointing.
    long_renderer = StarRenderer(load_catalog(mag_limit=6.5), cam, Photometry(cam.aperture_m), psf_sigma_px=1.0)
    long_traj = Trajectory(ConstantRate(np.full(3, 17.32 * DEG)), first.attitude(0.0))
    long_exposure = 0.092
    long_frame = long_renderer.render(long_traj, 0.0, long_exposure)
    long_trail = np.linalg.norm(long_frame.truth.xy_end - long_frame.truth.xy_start, axis=1)

    long_floor, long_total = interleaved_times((
        lambda: rng.standard_normal(dtype=np.float32, out=noise),
        lambda: detector.read_out(long_renderer.render(long_traj, 0.0, long_exposure).signal, long_exposure, rng),
    ), args.slow_repeats)
    print(f"long trails: {len(long_frame.truth)} stars, median trail {np.median(long_trail):.1f} px, "
          f"{long_frame.n_instants} instants per star")
    print(f"render + read-out:                    {long_total * 1e3:8.2f} ms  = {long_total / long_floor:.2f} x floor")

    default_ratio = render_module.SCATTER_AREA_RATIO
    print("render only, by patch path (ms):      chosen    matmul only   scatter only")
    for name, rend, tr, exp, repeats in (
        ("short trails", renderer, first, exposure, args.repeats),
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
