"""Viewable images: a display stretch of the raw uint16 frames, with the truth drawn over them (OpenCV)."""

from __future__ import annotations

import cv2
import numpy as np

from starenv.sim.render import StarTruth

TRUTH_COLOUR = (80, 220, 80)  # RGB


def stretch(frame: np.ndarray, black_sigma: float = 0.0) -> np.ndarray:
    """8-bit asinh stretch of a raw frame around its background.

    With the background level ``m`` (median) and noise ``s`` (1.4826 x median absolute deviation), black at
    ``b = m + black_sigma s``, a pixel maps to ``asinh((x - b) / 3s) / asinh((top - b) / 3s)``: noise stays dim grey
    (black up to ``black_sigma`` s, for frames shown small), faint stars show, bright ones do not clip until ``top``
    (the 99.99th percentile, at least 20 s above the background).
    """
    sample = frame[::4, ::4].astype(np.float32) if frame.size > 65536 else frame.astype(np.float32)
    m = float(np.median(sample))
    s = max(1.4826 * float(np.median(np.abs(sample - m))), 0.5)
    top = max(float(np.percentile(frame, 99.99)) - m, 20.0 * s) - black_sigma * s
    x = (frame.astype(np.float32) - np.float32(m + black_sigma * s)) / np.float32(3.0 * s)
    y = np.arcsinh(np.clip(x, 0.0, None)) / np.float32(np.arcsinh(top / (3.0 * s)))
    return (np.clip(y, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def overlay(frame: np.ndarray, truth: StarTruth | None = None, dropped: bool = False) -> np.ndarray:
    """RGB uint8 image of one head's frame with the true trails (start -> end) and mid-exposure circles drawn."""
    rgb = cv2.cvtColor(stretch(frame), cv2.COLOR_GRAY2RGB)
    if dropped:
        cv2.putText(rgb, "DROPPED", (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 80, 80), 2, cv2.LINE_AA)
        return rgb
    if truth is not None:
        shift = 4  # sub-pixel drawing: coordinates in 1/16 px
        s = 1 << shift
        for xy0, xy1, xym in zip(truth.xy_start, truth.xy_end, truth.xy_mid, strict=True):
            p0 = tuple(int(round(v * s)) for v in xy0)
            p1 = tuple(int(round(v * s)) for v in xy1)
            pm = tuple(int(round(v * s)) for v in xym)
            cv2.line(rgb, p0, p1, TRUTH_COLOUR, 1, cv2.LINE_AA, shift)
            cv2.circle(rgb, pm, 6 * s, TRUTH_COLOUR, 1, cv2.LINE_AA, shift)
    return rgb


def mosaic(images: list[np.ndarray], gap: int = 4) -> np.ndarray:
    """Heads side by side (RGB), padded to the tallest."""
    height = max(im.shape[0] for im in images)
    tiles = []
    for i, im in enumerate(images):
        pad = np.zeros((height, im.shape[1] + (gap if i < len(images) - 1 else 0), 3), np.uint8)
        pad[: im.shape[0], : im.shape[1]] = im
        tiles.append(pad)
    return np.concatenate(tiles, axis=1)
