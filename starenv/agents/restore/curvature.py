"""Paper 001's restorer: gated Gaussian-curvature denoising, then Richardson-Lucy stopped when the centroids settle.

Denoising (paper 001 Eqs. 17-23, :func:`curvature_filter`).  Per pass, every pixel has eight signed distances
``d_n`` (Eq. 17, x = column, y = row, each a three-point mean minus the centre) to the tangent planes through its
3 x 3 neighbours, and the projection ``f + d_m`` onto the nearest one (Eq. 18).  The energy
``E = |d_m| + sum of the 4 smallest |f - f_neighbour|^alpha`` (Eqs. 19-23) gates the update: a pixel is filtered
only where ``E >= threshold``.  Decisions the paper leaves open:

* updates run on nine interleaved pixel subsets (stride 3), each on the current image, so that a subset's pixels
  share no neighbourhood; a gated projection is kept only if it does not raise the curvature energy
  ``sum |d_m|`` over the pixel's 3 x 3 window.  The windows of one subset are disjoint, so the image's curvature
  energy never increases from pass to pass (Gong's filters reduce it; this makes it a guarantee);
* borders replicate the edge pixels; the energy is evaluated on the current iterate at each subset pass;
* ``threshold=None`` sets T from the image's own noise sigma (the sigma-clipped spread of horizontal pixel
  differences / sqrt 2, :func:`~starenv.agents.blocks.frame_background`): ``T = threshold_sigma * sigma``,
  default 3.  The paper's T = 50 grey levels at noise variance 50 is ``7.07 sigma``; on Gaussian noise the median
  pixel has E = 2.3 sigma, so 7.07 sigma gates almost only outliers and leaves the noise of a star field nearly as it
  was, while 3 sigma reaches a large share of the noise pixels.
  Star slopes have a high E and are always filtered: the gate as written does not protect stars.
  The paper's alpha = 1 and 3 passes are the defaults.

Deblurring (:class:`CurvatureRLDeblurrer`).  Richardson-Lucy (Eq. 24) with one motion kernel per frame: the path
across the exposure of a star at the image centre, from the gyro samples (``starenv.agents.restore.kernels``); the
frame's median is the background term and the first estimate is RL's flat default (the paper gives no ``f^(0)``):
started from the frame less its background instead, the watched centroids move at a steady pace in the first iterations,
so the second difference of Eq. 25 vanishes and the rule fires at iteration 3 or 4, before the trails are restored
(the centroids are still moving then, and settle only many iterations later).
Stopping (Eq. 25): after iteration ``k + 1`` the tracked stars' centroids ``c_{k-1}, c_k, c_{k+1}`` (centre of
mass of the estimate in a window around each star found on the denoised frame) must satisfy, per axis and for
every tracked star, ``| |c_{k+1} - c_k| - |c_k - c_{k-1}| | <= eps(blur)``.  The paper gives no form for
``eps``; we take ``eps(L) = max(eps_min_px, eps_per_px * L)`` with ``L`` the kernel's extent along that axis (px),
and cap the iterations at ``max_iterations``.  The earliest possible stop is after iteration 3 (three iterates
are needed).

Output.  The RL estimate is the paper's restored image (:meth:`CurvatureRLDeblurrer.restore`); the deblurrer hands
the detector the raw frame with each trail replaced by its still star (:func:`starenv.agents.restore.frame.resharpen`),
since the bare estimate's amplified noise and one-pixel stars are not what a detector tuned to the sensor expects.
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np
from scipy import ndimage

from starenv import checks
from starenv.agents.blocks import components_above, frame_background
from starenv.agents.restore.algorithms import (
    curvature_filter,
    resharpen,
    richardson_lucy,
    richardson_lucy_batch,
)
from starenv.agents.restore.kernels import centre_kernel, frame_streaks, sigma_for, spot_sigma
from starenv.agents.restore.patches import restore_streaks

CENTROID_FLOOR = 0.2  # watched centroids weigh each pixel above 20 % of its window's peak (RL noise stays out)
REGIONS = ("frame", "streaks")


def window_centroids(image: np.ndarray, boxes: np.ndarray, floor_fraction: float = 0.0) -> np.ndarray:
    """Centre of mass (n, 2) px (x = column, y = row) of ``image`` in each box ``(x0, y0, x1, y1)`` (end-exclusive),
    each pixel weighted by its value less ``floor_fraction`` times the box's maximum (negative weights count as 0);
    NaN where a box holds no positive weight.  Boxes are clipped to the image."""
    out = np.full((len(boxes), 2), np.nan)
    h, w = image.shape
    for i, (x0, y0, x1, y1) in enumerate(np.asarray(boxes, dtype=np.int64).reshape(-1, 4)):
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        patch = image[y0:y1, x0:x1]
        if patch.size == 0:
            continue
        patch = np.maximum(patch - floor_fraction * patch.max(), 0.0)
        total = patch.sum()
        if total > 0:
            out[i, 0] = x0 + (patch.sum(axis=0) @ np.arange(x1 - x0)) / total
            out[i, 1] = y0 + (patch.sum(axis=1) @ np.arange(y1 - y0)) / total
    return out


def patch_centroids(stack: np.ndarray, floor_fraction: float = 0.0) -> np.ndarray:
    """:func:`window_centroids` with each image of a stack (b, h, w) as one window: (b, 2) px in patch pixels."""
    p = np.asarray(stack, dtype=np.float64)
    p = np.maximum(p - floor_fraction * p.max(axis=(1, 2), keepdims=True), 0.0)
    total = p.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        x = p.sum(axis=1) @ np.arange(p.shape[2]) / total
        y = p.sum(axis=2) @ np.arange(p.shape[1]) / total
    return np.where((total > 0)[:, None], np.stack([x, y], axis=1), np.nan)


class CentroidStop:
    """Paper 001's Eq. 25 as a Richardson-Lucy callback: ``stop(iteration, estimate)`` is True once, for every
    tracked star and both axes, ``| |c_{k+1} - c_k| - |c_k - c_{k-1}| | <= eps`` (``eps`` (2,) px, x then y), or
    when ``max_iterations`` is reached.  Centroids: :func:`window_centroids` in ``boxes`` with ``floor_fraction``;
    ``boxes=None``: the estimate is a stack of patches, each one window (:func:`patch_centroids`).
    ``history`` keeps each iterate's centroids, ``iterations`` the last iteration seen, ``converged`` whether the
    rule (not the cap) stopped it."""

    def __init__(self, boxes: np.ndarray | None, eps_px, max_iterations: int, floor_fraction: float = 0.0):
        self.boxes = None if boxes is None else np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
        self.eps = checks.finite("eps_px", eps_px, shape=(2,))
        if np.any(self.eps < 0):
            raise ValueError(f"eps_px must be non-negative, got {self.eps}")
        self.max_iterations = checks.integer("max_iterations", max_iterations, 1, 100000)
        self.floor_fraction = checks.in_range("floor_fraction", floor_fraction, 0.0, 1.0, high_open=True)
        self.history: list[np.ndarray] = []
        self.iterations = 0
        self.converged = False

    def __call__(self, iteration: int, estimate: np.ndarray) -> bool:
        self.iterations = iteration
        if self.boxes is None:
            self.history.append(patch_centroids(estimate, self.floor_fraction))
        else:
            self.history.append(window_centroids(estimate, self.boxes, self.floor_fraction))
        if len(self.history) >= 3 and self.history[-1].size:
            c0, c1, c2 = self.history[-3:]
            change = np.abs(np.abs(c2 - c1) - np.abs(c1 - c0))
            self.converged = bool(np.all(change <= self.eps))  # NaN (an emptied window) never converges
        return self.converged or iteration >= self.max_iterations


class CurvatureRLDeblurrer:
    """Paper 001's restorer as a :class:`~starenv.agents.base.Deblurrer` (module docstring): gated curvature
    denoising, then Richardson-Lucy with the gyro kernel of the image centre, stopped by Eq. 25.

    Options: ``threshold`` (energy gate T, DN; None: ``threshold_sigma`` times the frame's noise),
    ``denoise_iterations`` (3, the
    paper's), ``alpha`` (1, the paper's), ``max_iterations`` (cap), ``eps_min_px`` and ``eps_per_px`` (the stop
    tolerance ``max(eps_min_px, eps_per_px * blur length)`` per axis), ``kernel_sigma_px`` (Gaussian each kernel
    sample is drawn with: the restored stars keep the optics' own spot), ``detect_sigma`` (threshold, in noise
    sigmas of the kernel-matched image, of the stars whose centroids are watched), ``max_stars`` (the brightest
    watched), ``psf_sigma_px`` (the sensor's spot, px, that the still stars are drawn with; None: the calibrated
    camera's).  :meth:`restore` gives the paper's restored image (the RL estimate, from the denoised frame);
    :meth:`deblur` returns the raw frame with each trail replaced by its still star
    (:func:`starenv.agents.restore.frame.resharpen` of that estimate): the output keeps the raw frame's noise, which the
    detector models, instead of RL's amplified noise, so the detector's
    precision holds (float64 DN).  Both set ``last_info``.

    ``region="streaks"`` (real time; :meth:`deblur` only): the same denoising, RL and stopping rule on a patch around
    each candidate streak (:func:`~starenv.agents.restore.patches.restore_streaks`, candidates at ``detect_sigma``),
    each with its own space-variant kernel, all patches in one batch; the ``max_stars`` strongest candidates are
    watched, each patch one centroid window.  The rest of the frame is left as observed.
    """

    def __init__(self, threshold: float | None = None, threshold_sigma: float = 3.0, denoise_iterations: int = 3,
                 alpha: float = 1.0,
                 max_iterations: int = 50, eps_min_px: float = 0.002, eps_per_px: float = 0.0005,
                 kernel_sigma_px: float = 0.5, detect_sigma: float = 5.0, max_stars: int = 20,
                 psf_sigma_px: float | None = None, region: str = "frame"):
        self.threshold = None if threshold is None else checks.non_negative("threshold", threshold)
        self.threshold_sigma = checks.non_negative("threshold_sigma", threshold_sigma)
        self.denoise_iterations = checks.integer("denoise_iterations", denoise_iterations, 0, 100)
        self.alpha = checks.in_range("alpha", alpha, 1.0, 2.0)
        self.max_iterations = checks.integer("max_iterations", max_iterations, 3, 10000)
        self.eps_min_px = checks.non_negative("eps_min_px", eps_min_px, "px")
        self.eps_per_px = checks.non_negative("eps_per_px", eps_per_px)
        self.kernel_sigma_px = checks.in_range("kernel_sigma_px", kernel_sigma_px, 0.1, 20.0, unit="px")
        self.detect_sigma = checks.positive("detect_sigma", detect_sigma)
        self.max_stars = checks.integer("max_stars", max_stars, 1, 10000)
        self.psf_sigma_px = spot_sigma(psf_sigma_px)
        self.region = checks.choice("region", region, REGIONS)
        self.last_info: dict = {}

    def watched_stars(self, image: np.ndarray, level: float, sigma: float, kernel: np.ndarray) -> np.ndarray:
        """Boxes ``(x0, y0, x1, y1)`` around the brightest stars of a denoised frame: the frame matched-filtered with
        the motion kernel, thresholded at ``detect_sigma`` times its noise, each blob grown by the kernel size."""
        matched = cv2.filter2D(image - level, cv2.CV_64F, kernel[::-1, ::-1], borderType=cv2.BORDER_REFLECT)
        found = components_above(matched, self.detect_sigma * sigma * math.sqrt(float(np.sum(kernel**2))))
        if found.count <= 1:
            return np.zeros((0, 4), np.int64)
        boxes = ndimage.find_objects(found.labels)  # (rows, columns) slices of labels 1 .. count - 1
        flux = np.array([matched[box].sum() for box in boxes])
        order = np.argsort(-flux, kind="stable")[: self.max_stars]
        y0, x0, y1, x1 = np.array([[rows.start, cols.start, rows.stop, cols.stop] for rows, cols in boxes])[order].T
        grow_y, grow_x = (np.array(kernel.shape) + 1) // 2
        h, w = image.shape
        return np.stack([np.maximum(x0 - grow_x, 0), np.maximum(y0 - grow_y, 0),
                         np.minimum(x1 + grow_x, w), np.minimum(y1 + grow_y, h)], axis=1)

    def restore(self, image: np.ndarray, head: int, step) -> tuple[np.ndarray, np.ndarray]:
        """The paper's restoration: the Richardson-Lucy estimate (H, W) of the scene, DN above the denoised frame's
        median (the paper's restored image), and the kernel it was restored with.  Sets ``last_info``."""
        t_start = time.perf_counter()
        raw = checks.finite("image", image).astype(np.float64)
        _, sigma = frame_background(raw)
        t = self.threshold_sigma * sigma if self.threshold is None else self.threshold
        denoised = curvature_filter(raw, t, self.denoise_iterations, self.alpha)
        t_denoise = time.perf_counter() - t_start
        level = float(np.median(denoised))
        kernel, extent = centre_kernel(step, head, self.kernel_sigma_px)
        boxes = self.watched_stars(denoised, level, sigma, kernel)
        eps = np.maximum(self.eps_min_px, self.eps_per_px * extent)
        stop = CentroidStop(boxes, eps, self.max_iterations, CENTROID_FLOOR)
        restored = richardson_lucy(np.maximum(denoised, 0.0), kernel, self.max_iterations, background=level,
                                   callback=stop)
        self.last_info = {"iterations": stop.iterations, "converged": stop.converged, "stars_watched": len(boxes),
                          "denoise_threshold": t, "denoise_s": t_denoise, "total_s": time.perf_counter() - t_start}
        return restored, kernel

    def deblur(self, image: np.ndarray, head: int, step) -> np.ndarray:
        """The raw frame with each trail replaced by its still star (class docstring), float64 DN."""
        if self.region == "streaks":
            return self._deblur_streaks(image, head, step)
        restored, kernel = self.restore(image, head, step)
        sigma = sigma_for(self.psf_sigma_px, step.cameras[head])
        return resharpen(np.asarray(image, dtype=np.float64), restored, kernel, sigma)

    def _deblur_streaks(self, image: np.ndarray, head: int, step) -> np.ndarray:
        t_start = time.perf_counter()
        found = frame_streaks(image, head, step, self.psf_sigma_px, self.detect_sigma, 4)
        t = self.threshold_sigma * found.noise if self.threshold is None else self.threshold
        _, extent = centre_kernel(step, head, self.kernel_sigma_px)
        stop = CentroidStop(None, np.maximum(self.eps_min_px, self.eps_per_px * extent), self.max_iterations,
                            CENTROID_FLOOR)

        def deconvolve(patches, psfs, level, members):
            denoised = curvature_filter(patches, t, self.denoise_iterations, self.alpha).astype(np.float32)
            watch = np.argsort(-found.responses[members], kind="stable")[: self.max_stars]
            return richardson_lucy_batch(np.maximum(denoised, 0.0), psfs, self.max_iterations, background=level,
                                         circular=True, callback=lambda k, f: stop(k, f[watch]))

        out, info = restore_streaks(found, step, head, deconvolve, kernel_sigma_px=self.kernel_sigma_px,
                                    one_batch=True)
        self.last_info = {"iterations": stop.iterations, "converged": stop.converged,
                          "stars_watched": min(info["candidates"] - info["skipped"], self.max_stars),
                          "denoise_threshold": t, **info, "total_s": time.perf_counter() - t_start}
        return out
