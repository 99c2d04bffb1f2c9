"""Restoring a frame patch by patch: one patch per candidate streak, deconvolved with that candidate's own
space-variant gyro kernel, then pasted back resharpened (:func:`restore_streaks`).

The engine of the region-of-interest deblurrers: :class:`~starenv.agents.restore.roi.RoiDeblurrer` (plain
Richardson-Lucy) and the ``region="streaks"`` modes of paper 000's and paper 001's restorers, which differ only in how
a stack of patches is deconvolved (the ``deconvolve`` callable).  Work grows with the stars, not the frame.

A candidate's kernel is the path of a star at that candidate's centroid (:func:`~starenv.agents.restore.kernels.
sparse_paths`), drawn with ``kernel_sigma_px``; its box is the kernel's extent about the centroid, its patch that box
grown by ``margin_px`` on each side and rounded up to a multiple of ``PATCH_STEP_PX`` per axis.  Patches are
deconvolved periodically on themselves (``circular``: transforms of the patch's size; their borders hold only
background and noise, the wrap-around there is harmless), then resharpened as the whole-frame restorers do
(``g - f (x) h + f (x) G``, ``G`` the sensor's spot): only each box is pasted back, not the margins that carry the
patch-edge artefacts.  Where boxes overlap, the later candidate's restoration wins.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from starenv.agents.base import StepInput
from starenv.agents.restore.algorithms import convolve_batch
from starenv.agents.restore.kernels import FrameStreaks, path_kernels, sparse_paths, window

PATCH_STEP_PX = 8  # patch sizes are rounded up to multiples of this, one batch per size

# deconvolve(patches (b, h, w) float32 DN, psfs (b, kh, kw) float32 normalised, level DN, members (b,) candidate
# indices) -> the estimated scene (b, h, w) above the background level.
Deconvolve = Callable[[np.ndarray, np.ndarray, float, np.ndarray], np.ndarray]


def restore_streaks(found: FrameStreaks, step: StepInput, head: int, deconvolve: Deconvolve, *,
                    kernel_sigma_px: float, margin_px: int = 3, max_patch_px: int = 256,
                    one_batch: bool = False, spot: bool = False) -> tuple[np.ndarray, dict]:
    """The frame of ``found`` with each candidate streak's box restored (module docstring), float64 DN, and a dict
    ``candidates``, ``skipped`` (boxes over ``max_patch_px``, left as observed), ``batches``, ``patch_px`` (largest
    patch side).  ``one_batch``: every patch padded to the largest size and deconvolved in one call (for
    ``deconvolve`` rules that look at all the stars at once); otherwise one call per patch size.  ``spot``: where the
    camera's spot varies across the field, draw each kernel with the spot where its candidate is (and resharpen to
    it) instead of ``kernel_sigma_px``."""
    cam = step.cameras[head]
    data, centres = found.data, found.centroids
    out = data.copy()
    info = {"candidates": int(len(centres)), "skipped": 0, "batches": 0, "patch_px": 0}
    if len(centres) == 0:
        return out, info
    t0, t1 = window(step)
    local = cam.spot_shape(centres) if spot and cam.spot is not None else None
    kernels, _ = path_kernels(sparse_paths(cam, step.gyro, t0, t1, centres), kernel_sigma_px, spot=local)
    still = None if local is None else path_kernels(np.zeros((len(centres), 1, 2)), kernel_sigma_px, spot=local)[0]
    half = np.array([[k.shape[1] // 2, k.shape[0] // 2] for k in kernels])  # (k, 2) x, y
    mid = np.rint(centres).astype(np.int64)
    lo = np.maximum(mid - half, 0)
    hi = np.minimum(mid + half, [cam.width - 1, cam.height - 1])
    size = 2 * half + 1 + 2 * margin_px  # patch width, height: the kernel and its margins
    size = np.minimum(-(-size // PATCH_STEP_PX) * PATCH_STEP_PX, [cam.width, cam.height])
    fits = np.all(size <= max_patch_px, axis=1)
    idx = np.flatnonzero(fits)
    if one_batch and len(idx):
        size[idx] = size[idx].max(axis=0)
    keys = size[idx, 0] * 65536 + size[idx, 1]
    for key in np.unique(keys):
        group = idx[keys == key]
        _restore(out, data, found.level, group, [kernels[g] for g in group], lo, hi, size[group[0]], found.sigma,
                 deconvolve, None if still is None else [still[g] for g in group])
    info.update(skipped=int((~fits).sum()), batches=int(len(np.unique(keys))), patch_px=int(size[idx].max(initial=0)))
    return out, info


def _restore(out, data, level, idx, kernels, lo, hi, patch, sigma, deconvolve: Deconvolve, spots=None) -> None:
    """Restore candidates ``idx`` on patches of ``patch`` = (width, height) px in one call; paste their boxes
    ``lo``..``hi`` (inclusive x, y) into ``out``.  The still spot resharpened to is the Gaussian of ``sigma``, or
    each candidate's own kernel of ``spots`` (odd sizes, centred)."""
    pw, ph = int(patch[0]), int(patch[1])
    height, width = data.shape
    kh = max(k.shape[0] for k in kernels)
    kw = max(k.shape[1] for k in kernels)
    psfs = np.zeros((len(idx), kh, kw), dtype=np.float32)
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
    estimate = deconvolve(patches.astype(np.float32), psfs, level, idx)
    # resharpen() on the batch, with the same periodic convolutions (the margins that wrap are not pasted), in one:
    # g - f (x) h + f (x) G = g - f (x) (h - G).
    radius = int(np.ceil(4.0 * sigma))
    g = cv2.getGaussianKernel(2 * radius + 1, sigma, cv2.CV_64F)  # the kernel cv2.GaussianBlur applies
    if spots is not None:
        radius = max(max(k.shape) for k in spots) // 2
    ch, cw = max(kh, 2 * radius + 1), max(kw, 2 * radius + 1)  # odd: the kernels' and the spot's centres align
    change = np.zeros((len(idx), ch, cw), dtype=np.float32)
    r, c = (ch - kh) // 2, (cw - kw) // 2
    change[:, r : r + kh, c : c + kw] = psfs / psfs.sum(axis=(1, 2), keepdims=True)
    if spots is None:
        r, c = ch // 2 - radius, cw // 2 - radius
        change[:, r : r + 2 * radius + 1, c : c + 2 * radius + 1] -= (g @ g.T).astype(np.float32)
    else:
        for i, k in enumerate(spots):
            r, c = (ch - k.shape[0]) // 2, (cw - k.shape[1]) // 2
            change[i, r : r + k.shape[0], c : c + k.shape[1]] -= k.astype(np.float32)
    restored = patches - convolve_batch(estimate, change, circular=True)
    for i, j in enumerate(idx):
        (x0, y0), (x1, y1) = lo[j], hi[j]
        out[y0 : y1 + 1, x0 : x1 + 1] = restored[i, y0 - py0[i] : y1 + 1 - py0[i], x0 - px0[i] : x1 + 1 - px0[i]]
