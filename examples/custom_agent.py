"""A detector of your own in starenv's pipeline, scored beside the built-in one.

``OpenCvDetector`` thresholds the frame at its median plus ``k`` robust sigmas, labels the connected regions with
OpenCV and centroids each by its background-subtracted intensity moments: the textbook detector.  Any class with
the role's method (here ``detect(image, camera) -> StarMeasurements``, see ``starenv.agents.detect``) plugs in by
instance, by class, or as a ``"module:Class"`` string from a scenario or bench file (``--trust MODULE`` then, since
a file may only name starenv's own code unless you trust more).

    python examples/custom_agent.py --steps 20 --seed 0
"""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np

from starenv.agents.base import StarMeasurements
from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.episode import run_episode


class OpenCvDetector:
    """Stars as connected regions above median + ``k`` sigma (sigma from the median absolute deviation), at least
    ``min_pixels`` px; centroids (px, starenv's pixel convention: (0, 0) the centre of the top-left pixel) by
    first moments above the median, flux in DN above it."""

    def __init__(self, k: float = 5.0, min_pixels: int = 3):
        self.k, self.min_pixels = float(k), int(min_pixels)

    def detect(self, image: np.ndarray, camera) -> StarMeasurements:
        frame = image.astype(np.float32)
        median = float(np.median(frame))
        sigma = 1.4826 * float(np.median(np.abs(frame - median))) or 1.0
        mask = (frame > median + self.k * sigma).astype(np.uint8)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        above = np.clip(frame - median, 0.0, None)
        xy, flux = [], []
        for label in range(1, count):
            x0, y0, w, h, area = stats[label]
            if area < self.min_pixels:
                continue
            patch = above[y0:y0 + h, x0:x0 + w] * (labels[y0:y0 + h, x0:x0 + w] == label)
            total = float(patch.sum())
            ys, xs = np.mgrid[y0:y0 + h, x0:x0 + w]
            xy.append(((patch * xs).sum() / total, (patch * ys).sum() / total))
            flux.append(total)
        return StarMeasurements(np.array(xy).reshape(-1, 2), np.array(flux))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper_002")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    result = {}
    for name, detector in (("built-in", None), ("opencv", OpenCvDetector())):
        env = StarSensorEnv(args.scenario)
        agents = {"identifier": "starenv.agents.identify:LostInSpaceIdentifier"}
        if detector is not None:
            agents["detector"] = detector  # an instance; OpenCvDetector (a class) or a trusted string work too
        run = run_episode(env, Pipeline.for_scenario(env.scenario, agents), seed=args.seed, steps=args.steps)
        errors = [r["attitude_error_arcsec"] for r in run.records if r["attitude_error_arcsec"] is not None]
        result[name] = {"steps": len(run.records), "solved": len(errors),
                        "median_error_arcsec": float(np.median(errors)) if errors else None,
                        "recall": float(np.nanmean([r.get("detection_recall") or np.nan for r in run.records]))}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
