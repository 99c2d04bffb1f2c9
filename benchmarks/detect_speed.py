"""Detector speed and accuracy beside SEP (Source Extractor as a C library) on the same 1024 x 1024 frames.

Frames: paper 002's scenario (1024^2, 12 deg field, 92 ms exposure, stars to magnitude 6.5, hot pixels and cosmic
rays) at 0, 5 and 10 deg/s, drawn fresh for each run: frame ``k`` of a rate comes from seed ``--seed + k`` (the
sensor's noise and a pointing, roll and rotation axis drawn uniformly on the sphere from it), so ``--frames`` frames
are that many independent pointings.  Both detectors run on one core (OpenCV held to one thread; SEP is
single-threaded), interleaved frame by frame; each repeat times every detector on every frame, and the ratio
``CentroidDetector / SEP`` is taken per repeat in the same run (the machines are shared and noisy): its median and
range over the repeats are printed.

SEP runs ``sep.Background`` (64 px boxes, 3 x 3 median filter of the grid), subtracted, then ``sep.extract`` with
at least 2 pixels, in two set-ups: "matched", the PSF-matched Gaussian kernel (``filter_type="matched"``) with a
5 sigma threshold on the background noise map, as CentroidDetector's defaults; "default", SEP's own 3 x 3 kernel
against the global noise at 5 sigma of the filtered noise (faster).  Its positions are the isophotal barycentres
(``x``, ``y``).  Both are scored like the env scores a step (one-to-one matching within
3 px of the true intensity-weighted trail centroids): recall of the detectable stars whose trail lies 4 px inside the
frame (CentroidDetector leaves out stars cut by the border by design) and of all detectable stars, precision of the
detections, mean centroid error of each detector's matched stars and of the stars every detector matched ("common"),
and, for CentroidDetector against each SEP set-up, the mean error of each on the stars the two both matched.

"linked streaks" is CentroidDetector with ``link_streaks=True`` (the pieces of faint trails that noise broke joined
into one star).

``--profile`` prints where CentroidDetector's time goes (cProfile, internal time).

    python -m pip install -e ".[bench]"   # SEP, a benchmark-only dependency
    python benchmarks/detect_speed.py [--frames N] [--seed S] [--repeats N] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import cv2
import numpy as np
from env_speed import random_pointing_deg  # run from benchmarks/, whose folder is on the path

from starenv import scenario
from starenv.agents.detect.centroid import CentroidDetector
from starenv.scoring import match
from starenv.sim.sensor import StarSensor

RATES_DPS = (0.0, 5.0, 10.0)
THRESHOLD_SIGMA = 5.0
EDGE_PX = 4.0  # CentroidDetector leaves out stars cut by the border (their centroids are biased); SEP keeps them
WIDTH = 1024


def frames(rate_dps: float, seeds: range) -> tuple[list, object]:
    """One frame (image, truth) of paper 002's head at ``rate_dps`` per seed, each from its own pointing, roll and
    rotation axis drawn from the seed (uniform on the sphere); and the head."""
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        ra, dec, roll = random_pointing_deg(rng)
        axis = rng.normal(size=3)
        rate = (rate_dps * axis / np.linalg.norm(axis)).tolist()
        sc = scenario.load("paper_002", {"seed": int(seed), "motion.rate_dps": rate, "motion.initial_ra_deg": ra,
                                         "motion.initial_dec_deg": dec, "motion.initial_roll_deg": roll})
        head = StarSensor(sc).next_frame().heads[0]
        out.append((head.image, head.truth))
    return out, sc.heads[0]


def sep_detector(sigma_px: float, matched: bool):
    """SEP background + extraction, image -> xy (n, 2) px.  ``matched``: the PSF-matched Gaussian kernel against the
    background noise map, 5 sigma; else SEP's default 3 x 3 kernel against the global noise, at the threshold that is
    5 sigma of the filtered noise (the kernel's noise gain is 0.375)."""
    import sep

    radius = int(np.ceil(3.0 * sigma_px))
    kernel = cv2.getGaussianKernel(2 * radius + 1, sigma_px, cv2.CV_64F)
    kernel = kernel @ kernel.T

    def detect(image: np.ndarray) -> np.ndarray:
        data = image.astype(np.float32)
        background = sep.Background(data)
        background.subfrom(data)
        if matched:
            objects = sep.extract(data, THRESHOLD_SIGMA, err=background.rms(), minarea=2, filter_kernel=kernel,
                                  filter_type="matched")
        else:
            objects = sep.extract(data, THRESHOLD_SIGMA * 0.375, err=background.globalrms, minarea=2)
        return np.column_stack([objects["x"], objects["y"]])

    return detect


def scores(xys: dict[str, list[np.ndarray]], truths: list) -> tuple[dict[str, tuple[float, ...]], dict]:
    """Per detector, pooled over frames: recall of the detectable stars whose trail (both ends and centroid) lies
    at least EDGE_PX inside the frame, recall of all detectable stars, precision, mean centroid error (px) of its
    matched stars and of the stars every detector matched.  Second, per pair of detectors (first name, second
    name): the number of stars both matched and the mean centroid error of each on them."""
    counts = {name: np.zeros(4, int) for name in xys}  # inner found, all found, matched detections, detections
    errors = {name: [] for name in xys}
    common_errors = {name: [] for name in xys}
    pairs = {(a, b): ([], []) for a in xys for b in xys if a < b}
    n_inner = n_all = 0
    for k, truth in enumerate(truths):
        ends = np.stack([truth.xy_start, truth.xy_end, truth.xy_centroid])
        inner = truth.detectable & np.all((ends >= EDGE_PX) & (ends <= WIDTH - 1 - EDGE_PX), axis=(0, 2))
        n_inner, n_all = n_inner + int(inner.sum()), n_all + int(truth.detectable.sum())
        error = {}
        for name, per_frame in xys.items():
            det, tru, dist = match(per_frame[k], truth.xy_centroid)
            counts[name] += [inner[tru].sum(), truth.detectable[tru].sum(), len(det), len(per_frame[k])]
            errors[name].append(dist)
            error[name] = dict(zip(tru.tolist(), dist, strict=True))
        common = set.intersection(*(set(e) for e in error.values()))
        for name in xys:
            common_errors[name].extend(error[name][i] for i in common)
        for (a, b), (on_a, on_b) in pairs.items():
            both = set(error[a]) & set(error[b])
            on_a.extend(error[a][i] for i in both)
            on_b.extend(error[b][i] for i in both)
    per_detector = {
        name: (c[0] / n_inner, c[1] / n_all, c[2] / max(c[3], 1), float(np.concatenate(errors[name]).mean()),
               float(np.mean(common_errors[name])))
        for name, c in counts.items()
    }
    return per_detector, {key: (len(on_a), float(np.mean(on_a)), float(np.mean(on_b)))
                          for key, (on_a, on_b) in pairs.items()}


def repeat_times(fns: list, images: list[np.ndarray], repeats: int) -> np.ndarray:
    """Time (s) per image of each fn in each repeat (repeats, fns): the fns interleaved image by image, each
    repeat's time the median over the images."""
    times = np.empty((repeats, len(fns)))
    for r in range(repeats):
        per_image = [[] for _ in fns]
        for image in images:
            for k, fn in enumerate(fns):
                t0 = time.perf_counter()
                fn(image)
                per_image[k].append(time.perf_counter() - t0)
        times[r] = [np.median(t) for t in per_image]
    return times


def spread(ratios: np.ndarray) -> str:
    """``median [min-max]`` of per-repeat ratios."""
    return f"{np.median(ratios):.2f} [{ratios.min():.2f}-{ratios.max():.2f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=16, help="frames per rate, each its own pointing")
    parser.add_argument("--seed", type=int, default=4100, help="frame k of a rate is drawn from seed + k")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()
    cv2.setNumThreads(1)

    print(f"{'rate':>8} {'detector':>17} {'ms/frame':>9} {'recall':>7} {'(all)':>6} {'precision':>9} "
          f"{'centroid px':>11} {'(common)':>8}")
    for rate in RATES_DPS:
        data, head = frames(rate, range(args.seed, args.seed + args.frames))
        images, truths = [d[0] for d in data], [d[1] for d in data]
        ours, linked = CentroidDetector(), CentroidDetector(link_streaks=True)

        def our_detect(image, ours=ours, camera=head.calibrated):
            return ours.detect(image, camera).xy

        def linked_detect(image, linked=linked, camera=head.calibrated):
            return linked.detect(image, camera).xy

        fns = {"CentroidDetector": our_detect, "SEP matched": sep_detector(head.psf_sigma_px, True),
               "SEP default": sep_detector(head.psf_sigma_px, False), "linked streaks": linked_detect}
        per_repeat = repeat_times(list(fns.values()), images, args.repeats)
        times = np.median(per_repeat, axis=0)
        found, pairwise = scores({name: [fn(im) for im in images] for name, fn in fns.items()}, truths)
        for name, t in zip(fns, times, strict=True):
            recall, recall_all, precision, error, common = found[name]
            print(f"{rate:6.1f}/s {name:>17} {t * 1e3:9.2f} {recall:7.3f} {recall_all:6.3f} {precision:9.3f} "
                  f"{error:11.3f} {common:8.3f}")
        for k, name in ((0, "ratio to SEP"), (3, "linked / SEP")):
            print(f"{'':8} {name:>17} {spread(per_repeat[:, k] / per_repeat[:, 1])} (matched) "
                  f"{spread(per_repeat[:, k] / per_repeat[:, 2])} (default)")
        for sep in ("SEP matched", "SEP default"):
            n, ours_px, sep_px = pairwise[("CentroidDetector", sep)]
            print(f"{'':8} {'on stars both find':>17}: CentroidDetector {ours_px:.3f} px, {sep} {sep_px:.3f} px "
                  f"({n} stars)")
        if args.profile:
            profile = cProfile.Profile()
            profile.enable()
            for image in images * args.repeats:
                our_detect(image)
            profile.disable()
            pstats.Stats(profile).sort_stats("tottime").print_stats(12)


if __name__ == "__main__":
    main()
