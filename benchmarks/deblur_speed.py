"""Restoring one smeared 1024 x 1024 frame: scikit-image's Richardson-Lucy on the full frame against ours.

Run with ``python benchmarks/deblur_speed.py [--rate-dps 5] [--iterations 20] [--repeats 3]``.  The frame is frame 1 of
the bundled ``paper_002`` scenario (1024 x 1024, f = 4875 px, 92 ms exposure) turning at ``--rate-dps`` (resultant,
equal on the three body axes; 5 deg/s smears stars over 30-35 px).  Timed side by side in one run (median of
``--repeats`` rounds, each running every method once in turn):

* ``skimage.restoration.richardson_lucy`` on the full frame with the kernel of a star at the frame centre (float64,
  ``clip=False``), the baseline of the speed ratios;
* :class:`~starenv.agents.restore.frame.RichardsonLucyDeblurrer` (the same full-frame algorithm, our FFT loop);
* :class:`~starenv.agents.restore.frame.RoiDeblurrer` (patches around candidate streaks, each with its own kernel);
* :class:`~starenv.agents.restore.frame.WienerDeblurrer` (full frame, one kernel);
* :class:`~starenv.agents.restore.trail_fit.TrailFitDeblurrer` (each streak fitted with its own trail, no
  deconvolution).

Every restored frame goes through the same :func:`~starenv.agents.restore.frame.resharpen` step (each trail replaced by
its still image) and the same ``CentroidDetector``; centroid errors are against the true mid-exposure positions
``xy_mid`` (matched one-to-one within 3 px), and "stars" counts detections matched to a true star.  The speed goal
is RoiDeblurrer >= 10x faster than scikit-image at the same iteration count.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import gymnasium as gym
import numpy as np

import starenv  # noqa: F401  (registers the environments)
from starenv.agents.base import step_input
from starenv.agents.detect.centroid import CentroidDetector
from starenv.agents.restore.algorithms import resharpen
from starenv.agents.restore.frame import RichardsonLucyDeblurrer, WienerDeblurrer
from starenv.agents.restore.kernels import frame_kernel
from starenv.agents.restore.roi import RoiDeblurrer
from starenv.agents.restore.trail_fit import TrailFitDeblurrer
from starenv.scoring import match


def smeared_frame(rate_dps: float, seed: int):
    """Frame 1 of paper_002 at ``rate_dps`` (resultant, three-axis): its StepInput and the truth of its stars."""
    per_axis = rate_dps / math.sqrt(3.0)
    env = gym.make("StarEnv/Paper002-v0", overrides={"motion.rate_dps": [per_axis] * 3})
    env.reset(seed=seed)
    obs, _, _, _, info = env.step(None)
    base = env.unwrapped
    step = step_input(obs, base.sensor_info)
    return step, info["truth"]["stars"][0], base.scenario.heads[0].psf_sigma_px


def interleaved(calls: dict, repeats: int) -> tuple[dict, dict]:
    """Each call's last result and median wall time (s) over ``repeats`` rounds that run every call once, in turn,
    so that load from other processes on a shared machine falls on all of them alike."""
    results, times = {}, {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            t0 = time.perf_counter()
            results[name] = call()
            times[name].append(time.perf_counter() - t0)
    return results, {name: statistics.median(t) for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate-dps", type=float, default=5.0)
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from skimage.restoration import richardson_lucy as skimage_rl

    step, truth, sigma = smeared_frame(args.rate_dps, args.seed)
    image = step.images[0]
    cam = step.cameras[0]
    detector = CentroidDetector(psf_sigma_px=sigma)
    kernel, _ = frame_kernel(step, 0, sigma)
    trail = np.linalg.norm(np.asarray(truth["xy_end"]) - np.asarray(truth["xy_start"]), axis=1)
    print(f"paper_002 frame 1 at {args.rate_dps:g} deg/s: {image.shape[1]} x {image.shape[0]} px, "
          f"{len(trail)} stars, trails {np.percentile(trail, 5):.1f}-{np.percentile(trail, 95):.1f} px "
          f"(5-95 %), kernel {kernel.shape[1]} x {kernel.shape[0]} px, {args.iterations} iterations, "
          f"median of {args.repeats}")

    data = image.astype(np.float64)
    skimage_name = "skimage richardson_lucy (full frame)"
    agents = {
        "starenv RichardsonLucyDeblurrer (full frame)": RichardsonLucyDeblurrer(args.iterations, psf_sigma_px=sigma),
        "starenv RoiDeblurrer": RoiDeblurrer(args.iterations, psf_sigma_px=sigma),
        "starenv WienerDeblurrer (full frame)": WienerDeblurrer(psf_sigma_px=sigma),
        "starenv TrailFitDeblurrer": TrailFitDeblurrer(psf_sigma_px=sigma),
    }
    calls = {skimage_name: lambda: skimage_rl(data, kernel, args.iterations, clip=False)}
    calls.update({name: (lambda agent=agent: agent.deblur(image, 0, step)) for name, agent in agents.items()})
    restored, runs = interleaved(calls, args.repeats)
    restored[skimage_name] = resharpen(data, restored[skimage_name], kernel, sigma)
    infos = {name: agent.last_info for name, agent in agents.items()}

    base = runs["skimage richardson_lucy (full frame)"]
    xy_mid = np.asarray(truth["xy_mid"])

    def centroid_line(img) -> str:
        stars = detector.detect(img, cam)
        _, _, dist = match(stars.xy, xy_mid)
        mean = f"{dist.mean():.3f}" if len(dist) else "  n/a"
        return f"stars {len(dist):3d} of {len(stars):3d} detections, centroid error vs xy_mid {mean} px"

    print(f"  {'blurred frame (no restoration)':46s} {'':>10s}  {'':>9s}   {centroid_line(image)}")
    for name, seconds in runs.items():
        print(f"  {name:46s} {seconds * 1e3:8.1f} ms  x{base / seconds:7.1f}   {centroid_line(restored[name])}")
    print(f"  RoiDeblurrer: {infos['starenv RoiDeblurrer']}")
    print(f"  TrailFitDeblurrer: {infos['starenv TrailFitDeblurrer']}")
    ratio = base / runs["starenv RoiDeblurrer"]
    print(f"speed ratio skimage / RoiDeblurrer = {ratio:.1f} (goal >= 10)")
    for name in ("starenv RoiDeblurrer", "starenv TrailFitDeblurrer"):
        print(f"{name}: {runs[name] * 1e3:.0f} ms per frame (goal <= 100 ms at 10 deg/s)")


if __name__ == "__main__":
    main()
