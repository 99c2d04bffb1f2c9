"""The region-of-interest deblurrer: Richardson-Lucy on patches around candidate streaks, each restored with its own
space-variant gyro kernel, the patches batched by size (:class:`RoiDeblurrer`)."""

from __future__ import annotations

import cv2
import numpy as np

from starenv import checks
from starenv.agents.base import StepInput
from starenv.agents.restore.algorithms import (
    convolve_batch,
    richardson_lucy_batch,
)
from starenv.agents.restore.kernels import (
    frame_streaks,
    path_kernel,
    spot_sigma,
    star_paths,
    window,
)

PATCH_STEP_PX = 8  # patch sizes are rounded up to multiples of this, one Richardson-Lucy batch per size


class RoiDeblurrer:
    """Richardson-Lucy on patches around candidate streaks, each with its own space-variant kernel.

    Candidates: :func:`~starenv.agents.restore.algorithms.streak_candidates` with the frame centre's streak (the
    kernel of a star at the frame centre with the sensor's ``psf_sigma_px``), ``threshold_sigma`` and
    ``min_area_px``, at their centroids.  A candidate's kernel
    is the path of a star at that centre (:func:`starenv.agents.restore.kernels.star_paths`); its box is the
    kernel's extent about the centre and its patch that box grown by ``margin_px`` on each side, rounded up to a
    multiple of ``PATCH_STEP_PX`` per axis.  Patches of one size are restored together by
    :func:`richardson_lucy_batch` (boxes larger than ``max_patch_px`` are left as they are and counted in
    ``last_info["skipped"]``); each box is pasted back (the background level added again), the margins (which carry
    the patch-edge artefacts) are not.  Where boxes overlap, the later candidate's restoration wins.
    """

    def __init__(self, iterations: int = 20, psf_sigma_px: float | None = None, threshold_sigma: float = 5.0,
                 min_area_px: int = 4, margin_px: int = 3, max_patch_px: int = 256):
        self.iterations = checks.integer("iterations", iterations, 0, 10000)
        self.psf_sigma_px = spot_sigma(psf_sigma_px)
        self.threshold_sigma = checks.in_range("threshold_sigma", threshold_sigma, 0.0, 100.0, low_open=True)
        self.min_area_px = checks.integer("min_area_px", min_area_px, 1, 10**6)
        self.margin_px = checks.integer("margin_px", margin_px, 0, 100)
        self.max_patch_px = checks.integer("max_patch_px", max_patch_px, 8, 4096)
        self.last_info: dict = {}

    def deblur(self, image: np.ndarray, head: int, step: StepInput) -> np.ndarray:
        cam = step.cameras[head]
        found = frame_streaks(image, head, step, self.psf_sigma_px, self.threshold_sigma, self.min_area_px)
        data, sigma, level, centres = found.data, found.sigma, found.level, found.centroids
        out = data.copy()
        self.last_info = {"iterations": self.iterations, "candidates": int(len(centres)), "skipped": 0,
                          "batches": 0, "patch_px": 0}
        if len(centres) == 0:
            return out
        t0, t1 = window(step)
        kernels = [path_kernel(p, sigma)[0] for p in star_paths(cam, step.gyro, t0, t1, centres)]
        half = np.array([[k.shape[1] // 2, k.shape[0] // 2] for k in kernels])  # (k, 2) x, y
        mid = np.rint(centres).astype(np.int64)
        lo = np.maximum(mid - half, 0)
        hi = np.minimum(mid + half, [cam.width - 1, cam.height - 1])
        size = 2 * half + 1 + 2 * self.margin_px  # patch width, height: the kernel and its margins
        size = np.minimum(-(-size // PATCH_STEP_PX) * PATCH_STEP_PX, [cam.width, cam.height])
        fits = np.all(size <= self.max_patch_px, axis=1)
        idx = np.flatnonzero(fits)
        keys = size[idx, 0] * 65536 + size[idx, 1]
        for key in np.unique(keys):
            group = idx[keys == key]
            self._restore(out, data, level, group, [kernels[g] for g in group], lo, hi, size[group[0]], sigma)
        self.last_info.update(skipped=int((~fits).sum()), batches=int(len(np.unique(keys))),
                              patch_px=int(size[idx].max(initial=0)))
        return out

    def _restore(self, out, data, level, idx, kernels, lo, hi, patch, sigma) -> None:
        """Restore candidates ``idx`` on patches of ``patch`` = (width, height) px in one batch; paste their boxes
        ``lo``..``hi`` (inclusive x, y) into ``out``."""
        pw, ph = int(patch[0]), int(patch[1])
        height, width = data.shape
        kh = max(k.shape[0] for k in kernels)
        kw = max(k.shape[1] for k in kernels)
        psfs = np.zeros((len(idx), kh, kw))
        for i, k in enumerate(kernels):  # centre each odd kernel in the common odd frame
            r, c = (kh - k.shape[0]) // 2, (kw - k.shape[1]) // 2
            psfs[i, r : r + k.shape[0], c : c + k.shape[1]] = k
        # Patch origins: the box centred in the patch, the patch kept inside the frame.
        box = hi[idx] - lo[idx] + 1
        px0 = np.clip(lo[idx, 0] - (pw - box[:, 0]) // 2, 0, width - pw)
        py0 = np.clip(lo[idx, 1] - (ph - box[:, 1]) // 2, 0, height - ph)
        rows = py0[:, None] + np.arange(ph)[None, :]
        cols = px0[:, None] + np.arange(pw)[None, :]
        patches = data[rows[:, :, None], cols[:, None, :]]
        psfs = psfs.astype(np.float32)
        estimate = richardson_lucy_batch(np.maximum(patches, 0.0).astype(np.float32), psfs, self.iterations,
                                         background=level, circular=True)
        # resharpen() on the batch, with the same periodic convolutions (the margins that wrap are not pasted).
        model = convolve_batch(estimate, psfs / psfs.sum(axis=(1, 2), keepdims=True), circular=True)
        radius = int(np.ceil(4.0 * sigma))
        g = cv2.getGaussianKernel(2 * radius + 1, sigma, cv2.CV_64F)  # the kernel cv2.GaussianBlur applies
        still = convolve_batch(estimate, (g @ g.T).astype(np.float32)[None], circular=True)
        restored = patches - model + still
        for i, j in enumerate(idx):
            (x0, y0), (x1, y1) = lo[j], hi[j]
            out[y0 : y1 + 1, x0 : x1 + 1] = restored[i, y0 - py0[i] : y1 + 1 - py0[i], x0 - px0[i] : x1 + 1 - px0[i]]
