"""Regenerate the EBPNN's weights from simulated frames (deterministic given ``--seed``)::

    python -m starenv.agents.restore.iteration.train --out starenv/agents/restore/iteration/iteration_net.npz \
        [--samples 100] [--seed 0]

Each sample is frame 0 of scenario ``paper_000`` pointed at a random sky position, turning at a constant rate:
about camera X, Y, X and Y together, or all three axes (the centre kernel sees no roll, so pure roll is left out),
0.5 to 60 deg/s per turning axis.  The kernel comes from the frame's own gyro samples, as the deblurrer builds it;
the label is the optimal iteration count (:func:`~starenv.agents.restore.iteration.features.optimal_iterations`) on the
central ``CROP`` x ``CROP`` pixels against the sharp noise-free rendering of the same instant, the MSE taken over
the pixels within 3 px of the sharp stars.  (Over the whole crop the MSE is ruled by the slow decay of the flat
starting estimate on empty sky, which labelled most frames at the cap whatever their blur.)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from starenv import scenario as scenario_mod
from starenv.agents.base import StepInput
from starenv.agents.restore.iteration.deblurrer import KERNEL_SIGMA_PX, WEIGHTS
from starenv.agents.restore.iteration.ebpnn import EnsembleNet
from starenv.agents.restore.iteration.features import optimal_iterations, sumfc
from starenv.agents.restore.kernels import centre_kernel
from starenv.datasets.smear import smeared_frame

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "xy": (1.0, 1.0, 0.0), "xyz": (1.0, 1.0, 1.0)}
RATE_DPS = (0.5, 60.0)
CROP = 256
MAX_ITERATIONS = 250
STAR_DN = 1.0  # the MSE is taken within 3 px of where the sharp scene has at least this much signal


def sample(seed: int, axis: str, rate_dps: float, ra_deg: float, dec_deg: float) -> tuple[float, int]:
    """(SUMFC, optimal iteration count) of one simulated frame."""
    rate = [float(a * rate_dps) for a in AXES[axis]]
    scenario = scenario_mod.load("paper_000", {"motion.rate_dps": rate, "motion.initial_ra_deg": ra_deg,
                                               "motion.initial_dec_deg": dec_deg})
    frame = smeared_frame(scenario, seed)
    step = StepInput([frame.image], np.ones(1, bool), frame.time_s, frame.exposure_s, frame.gyro, frame.cameras)
    kernel, _ = centre_kernel(step, 0, KERNEL_SIGMA_PX)
    reference = frame.sharp
    h, w = reference.shape
    crop = (slice((h - CROP) // 2, (h + CROP) // 2), slice((w - CROP) // 2, (w + CROP) // 2))
    image = frame.image[crop].astype(np.float64)
    reference = reference[crop]
    near_stars = cv2.dilate((reference > STAR_DN).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    if not near_stars.any():  # an empty patch of sky: every pixel
        near_stars[:] = True
    n_opt, _ = optimal_iterations(image, kernel, reference, float(np.median(image)), MAX_ITERATIONS, near_stars)
    return sumfc(kernel), n_opt


def dataset(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` samples (SUMFC, optimal iterations) drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    axes = list(AXES)
    features, labels = np.zeros(n), np.zeros(n, dtype=np.int64)
    for i in range(n):
        axis = axes[int(rng.integers(len(axes)))]
        rate = float(np.exp(rng.uniform(*np.log(RATE_DPS))))  # log-uniform: small blurs as often as large ones
        ra, dec = float(rng.uniform(0.0, 360.0)), float(np.degrees(np.arcsin(rng.uniform(-1.0, 1.0))))
        features[i], labels[i] = sample(int(rng.integers(2**31)), axis, rate, ra, dec)
    return features, labels


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Train the EBPNN that predicts Richardson-Lucy iteration counts.")
    parser.add_argument("--out", type=Path, default=WEIGHTS, help="the .npz to write")
    parser.add_argument("--samples", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.samples < 4:
        parser.error("--samples must be at least 4")
    t0 = time.perf_counter()
    features, labels = dataset(args.samples, args.seed)
    t1 = time.perf_counter()
    net = EnsembleNet.train(features, labels, args.seed)
    net.save(args.out)
    fitted = np.array([net.predict(f) for f in features])
    print(f"{args.samples} samples in {t1 - t0:.0f} s, trained in {time.perf_counter() - t1:.1f} s -> {args.out}")
    print(f"optimal iterations {labels.min()}..{labels.max()}; ensemble (JIT) on its training set: mean |error| "
          f"{np.mean(np.abs(fitted - labels)):.1f}, max {np.max(np.abs(fitted - labels)):.1f} iterations")


if __name__ == "__main__":
    main()
