"""Render time of a 1024 x 1024 frame with a spot that varies across the field, against the same frame with the
camera's one Gaussian, in the same run (only the ratio means anything on shared machines); and what the detector's
zoned matched filter buys where the spot widens.

Paper 002's optics (1024^2, f = 58.5 mm, 12 um, 12 deg field), Orion's belt, stars to magnitude 6, 50 ms exposure;
a still frame and one smeared ~30 px.  The varying spot: defocus 0.3 px, field curvature 0.8 px, astigmatism 1.0 px
and coma 0.8 px at the field corner on a 1.0 px spot (``FieldSpot``).  Times are medians of ``--repeats`` renders,
the two cameras in turn, render alone and render + read-out.  Goal: ratio <= 2.

Detection (``--detect-frames``): ``paper_000`` still, stars to magnitude 8, field curvature 2 px at the corner on its
0.8 px spot (3.6 times wider there); the default detector (matched filter by zones of the field) against the same
detector told the on-axis sigma (one filter); stars found within 2 px beyond 200 px from the centre, detections
within 2 px of a star of all detections, and the median detect time after the first frame.

    python benchmarks/varying_spot_speed.py [--repeats N] [--detect-frames N]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np

from starenv.sim.conventions import DEG, pointing
from starenv.sim.imager import Detector, DetectorSpec
from starenv.sim.motion import ConstantRate, Trajectory
from starenv.sim.optics import Camera, FieldSpot
from starenv.sim.photometry import Photometry
from starenv.sim.render import StarRenderer
from starenv.sim.sky import load_catalog

SPOT = FieldSpot(defocus_sigma_px=0.3, field_curvature_sigma_px=0.8, astigmatism_sigma_px=1.0, coma_px=0.8)


def interleaved_medians(fns, repeats: int) -> list[float]:
    """Median time (s) of each callable, run in turn ``repeats`` times (A B A B ...), so load changes hit all alike."""
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, out in zip(fns, times, strict=True):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
    return [float(np.median(t)) for t in times]


def frame_maker(renderer: StarRenderer, traj: Trajectory, exposure: float, detector: Detector | None = None,
                rng: np.random.Generator | None = None):
    """A callable rendering one frame (and reading it out when ``detector`` is given)."""
    if detector is None:
        return lambda: renderer.render(traj, 0.0, exposure)
    return lambda: detector.read_out(renderer.render(traj, 0.0, exposure).signal, exposure, rng)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--detect-frames", type=int, default=6)
    args = parser.parse_args()
    cam = Camera.from_focal_length(58.5e-3, 12e-6, 1024, 1024, f_number=1.4)
    catalog = load_catalog(mag_limit=6.0)
    exposure = 0.05
    start = pointing(83.8 * DEG, -5.4 * DEG, 0.0)
    rate = 30.0 / (cam.fx * exposure) / math.sqrt(2)  # rad/s per axis: 30 px trails on the boresight
    detector = Detector(DetectorSpec(), cam.width, cam.height, cam.pixel_pitch_m, 5.0, np.random.default_rng(0))
    print("| frame | stars | one Gaussian (ms) | varying spot (ms) | ratio | with read-out: one / varying (ms) "
          "| ratio |")
    print("|---|---|---|---|---|---|---|")
    for label, r in (("still", 0.0), ("30 px trails", rate)):
        traj = Trajectory(ConstantRate([r, r, 0.0]), start)
        renderers = [StarRenderer(catalog, camera, Photometry(camera.aperture_m), psf_sigma_px=1.0)
                     for camera in (cam, dataclasses.replace(cam, spot=SPOT))]
        n = len(renderers[0].render(traj, 0.0, exposure).truth)  # and warm the caches
        renderers[1].render(traj, 0.0, exposure)
        rng = np.random.default_rng(1)
        a0, a1 = interleaved_medians([frame_maker(r, traj, exposure) for r in renderers], args.repeats)
        f0, f1 = interleaved_medians([frame_maker(r, traj, exposure, detector, rng) for r in renderers], args.repeats)
        print(f"| {label} | {n} | {a0 * 1e3:.2f} | {a1 * 1e3:.2f} | {a1 / a0:.2f} | {f0 * 1e3:.2f} / {f1 * 1e3:.2f} | "
              f"{f1 / f0:.2f} |")
    if args.detect_frames:
        detection(args.detect_frames)


def detection(frames: int) -> None:
    import gymnasium as gym
    from scipy.spatial import cKDTree

    import starenv  # noqa: F401  (registers the environments)
    from starenv.agents.detect.centroid import CentroidDetector

    env = gym.make("StarEnv/Paper000-v0", overrides={"motion.rate_dps": [0.0, 0.0, 0.0], "mag_limit": 8.0,
                                                     "heads.0.spot": {"field_curvature_sigma_px": 2.0}})
    cam = env.unwrapped.cameras[0]
    detectors = {"zoned (default)": CentroidDetector(),
                 "on-axis sigma": CentroidDetector(psf_sigma_px=cam.psf_sigma_px)}
    counts = {name: [0, 0, 0, []] for name in detectors}
    for seed in range(frames):
        obs, info = env.reset(seed=seed)
        image = obs["frames"][0][: cam.height, : cam.width]
        truth = np.asarray(info["truth"]["stars"][0]["xy_centroid"])
        edge = np.hypot(*(truth - [cam.cx, cam.cy]).T) > 200
        for name, det in detectors.items():
            t0 = time.perf_counter()
            xy = det.detect(image, cam).xy
            spent = time.perf_counter() - t0
            c = counts[name]
            c[0] += int(np.sum(edge & (cKDTree(xy).query(truth)[0] < 2.0)))
            c[1] += int(np.sum(cKDTree(truth).query(xy)[0] < 2.0))
            c[2] += len(xy)
            c[3].append(spent)
    print(f"\n| detector ({frames} frames) | edge stars found | true detections / detections | detect (ms) |")
    print("|---|---|---|---|")
    for name, (edge_found, true, total, spent) in counts.items():
        print(f"| {name} | {edge_found} | {true} / {total} | {np.median(spent[1:]) * 1e3:.1f} |")


if __name__ == "__main__":
    main()
