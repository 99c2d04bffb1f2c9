"""Detector speed and accuracy beside SEP (Source Extractor as a C library) on the same 1024 x 1024 frames.

Frames: seed 002's scenario (1024^2, 12 deg field, 92 ms exposure, stars to magnitude 6.5, hot pixels and cosmic
rays) turning at 0, 5 and 10 deg/s about [1, 1, 1].  Both detectors run on one core (OpenCV held to one thread; SEP
is single-threaded), interleaved frame by frame; the time of each is the median over the repeats, and the ratio
``CentroidDetector / SEP`` is taken in the same run (the machines are shared and noisy).

SEP is set up as an astronomer would for this sensor: ``sep.Background`` (64 px boxes, 3 x 3 median filter of the
grid) subtracted, then ``sep.extract`` with the PSF-matched Gaussian kernel (``filter_type="matched"``), a 5 sigma
threshold on the per-pixel background noise map and at least 2 pixels, as CentroidDetector's defaults; its positions
are the isophotal barycentres (``x``, ``y``).  Both are scored like the env scores a step (one-to-one matching within
3 px of the true intensity-weighted trail centroids): recall of the detectable stars, precision of the detections,
mean centroid error of the matched stars.

``--profile`` prints where CentroidDetector's time goes (cProfile, internal time).

    python -m pip install sep        # benchmark-only dependency (the ``bench`` extra)
    python benchmarks/detect_speed.py [--frames N] [--repeats N] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import cv2
import numpy as np

from starenv import scenario
from starenv.agents.detect import CentroidDetector
from starenv.scoring import match
from starenv.sim.sensor import StarSensor

RATES_DPS = (0.0, 5.0, 10.0)
THRESHOLD_SIGMA = 5.0


def frames(rate_dps: float, count: int) -> tuple[list, object]:
    """``count`` consecutive frames (image, truth) of seed 002's head at ``rate_dps`` about [1, 1, 1], and the head."""
    per_axis = rate_dps / np.sqrt(3.0)
    sc = scenario.load("paper_002", {"motion.rate_dps": [per_axis] * 3})
    sensor = StarSensor(sc)
    out = []
    for _ in range(count):
        head = sensor.next_frame().heads[0]
        out.append((head.image, head.truth))
    return out, sc.heads[0]


def sep_detector(sigma_px: float):
    """SEP background + extraction with a PSF-matched Gaussian kernel: image -> xy (n, 2) px."""
    import sep

    radius = int(np.ceil(3.0 * sigma_px))
    kernel = cv2.getGaussianKernel(2 * radius + 1, sigma_px, cv2.CV_64F)
    kernel = kernel @ kernel.T

    def detect(image: np.ndarray) -> np.ndarray:
        data = image.astype(np.float32)
        background = sep.Background(data)
        background.subfrom(data)
        objects = sep.extract(data, THRESHOLD_SIGMA, err=background.rms(), minarea=2, filter_kernel=kernel,
                              filter_type="matched")
        return np.column_stack([objects["x"], objects["y"]])

    return detect


def accuracy(xys: list[np.ndarray], truths: list) -> tuple[float, float, float]:
    """Pooled recall of detectable stars, precision and mean centroid error (px) over frames."""
    found = detectable = matched = detections = 0
    errors = []
    for xy, truth in zip(xys, truths, strict=True):
        det, tru, dist = match(xy, truth.xy_centroid)
        found += int(truth.detectable[tru].sum())
        detectable += int(truth.detectable.sum())
        matched += len(det)
        detections += len(xy)
        errors.append(dist)
    return found / detectable, matched / max(detections, 1), float(np.concatenate(errors).mean())


def median_times(fns: list, images: list[np.ndarray], repeats: int) -> list[float]:
    """Median time (s) per image of each fn, the fns interleaved image by image."""
    times = [[] for _ in fns]
    for _ in range(repeats):
        for image in images:
            for k, fn in enumerate(fns):
                t0 = time.perf_counter()
                fn(image)
                times[k].append(time.perf_counter() - t0)
    return [float(np.median(t)) for t in times]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4, help="frames per rate")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()
    cv2.setNumThreads(1)

    print(f"{'rate':>8} {'detector':>17} {'ms/frame':>9} {'recall':>7} {'precision':>9} {'centroid px':>11}")
    for rate in RATES_DPS:
        data, head = frames(rate, args.frames)
        images, truths = [d[0] for d in data], [d[1] for d in data]
        ours = CentroidDetector()
        sep_detect = sep_detector(head.psf_sigma_px)

        def our_detect(image, ours=ours, camera=head.calibrated):
            return ours.detect(image, camera).xy

        fns = {"CentroidDetector": our_detect, "SEP": sep_detect}
        times = median_times(list(fns.values()), images, args.repeats)
        for (name, fn), t in zip(fns.items(), times, strict=True):
            recall, precision, error = accuracy([fn(im) for im in images], truths)
            print(f"{rate:6.1f}/s {name:>17} {t * 1e3:9.2f} {recall:7.3f} {precision:9.3f} {error:11.3f}")
        print(f"{'':8} {'ratio to SEP':>17} {times[0] / times[1]:9.2f}")
        if args.profile:
            profile = cProfile.Profile()
            profile.enable()
            for image in images * args.repeats:
                our_detect(image)
            profile.disable()
            pstats.Stats(profile).sort_stats("tottime").print_stats(12)


if __name__ == "__main__":
    main()
