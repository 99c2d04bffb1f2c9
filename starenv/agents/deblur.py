"""Deblurrers (:class:`~starenv.agents.base.Deblurrer`): restore a smeared frame from the gyro's rates.

The blur kernel comes from :mod:`starenv.psf`: the gyro samples of the step are integrated over the exposure
``[time_s - exposure_s / 2, time_s + exposure_s / 2]`` (global shutter; the rolling-shutter row delay is not in
``StepInput``) and a star's path through the calibrated camera is rasterised with the sensor's Gaussian PSF
(``psf_sigma_px``), so the restoration estimates the point-like scene ``f``.  The output is the observed frame with
each trail replaced by its still image (:func:`resharpen`): ``g - f (x) h + f (x) G``, the frame a still sensor
would have taken, with the frame's own noise: stars of the shape a detector tuned to the sensor expects (a bare
Richardson-Lucy estimate has one-pixel stars, which a detector's hot-pixel tests reject, and amplified noise).

* :class:`RichardsonLucyDeblurrer`: one kernel for the whole frame, the path of a star at the frame centre
  (seed 000's single-kernel model), Richardson-Lucy over the full frame.
* :class:`WienerDeblurrer`: the same kernel, frequency-domain Wiener filter of the background-subtracted frame.
* :class:`RoiDeblurrer`: candidate streaks (connected components of a matched-filter response above the robust
  background noise), one patch per candidate restored with that candidate's own space-variant kernel, the patches
  in Richardson-Lucy batches (one per patch size) and pasted back; the rest of the frame is left as it was.

Each returns a float64 image in the input's DN (background kept) and sets ``last_info`` (``iterations`` and more).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.signal import fftconvolve

from starenv import checks
from starenv.agents.base import StepInput
from starenv.optics import Camera
from starenv.psf import path_kernel, star_paths
from starenv.restoration import convolve_batch, richardson_lucy, richardson_lucy_batch, wiener

MAD_TO_SIGMA = 1.4826  # standard deviation per median absolute deviation of a Gaussian
BACKGROUND_STRIDE = 4  # every n-th pixel (each axis) enters the robust background estimate
PATCH_STEP_PX = 8  # patch sizes are rounded up to multiples of this, one Richardson-Lucy batch per size


def robust_background(image: np.ndarray) -> tuple[float, float]:
    """Median level and noise (``1.4826 MAD``) of an image (DN), from every ``BACKGROUND_STRIDE``-th pixel."""
    sample = np.asarray(image[::BACKGROUND_STRIDE, ::BACKGROUND_STRIDE], dtype=np.float64)
    level = float(np.median(sample))
    noise = MAD_TO_SIGMA * float(np.median(np.abs(sample - level)))
    return level, max(noise, 0.5)


def _checked_image(image, camera: Camera) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.ndim != 2:
        raise ValueError(f"image must be a 2-D array (DN), got {type(image).__name__}")
    if image.shape != (camera.height, camera.width):
        raise ValueError(f"image shape {image.shape} does not match the camera's {(camera.height, camera.width)}")
    return checks.finite("image", image)


def spot_sigma(option: float | None) -> float | None:
    """A deblurrer's ``psf_sigma_px`` option checked: None (the calibrated camera's ``psf_sigma_px``) or px."""
    return None if option is None else checks.in_range("psf_sigma_px", option, 0.1, 20.0, unit="px")


def sigma_for(option: float | None, camera: Camera) -> float:
    """The spot sigma (px) a deblurrer draws still stars with: its option, else the calibrated camera's."""
    return camera.psf_sigma_px if option is None else option


def _window(step: StepInput) -> tuple[float, float]:
    half = 0.5 * float(step.exposure_s)
    return step.time_s - half, step.time_s + half


def resharpen(data: np.ndarray, estimate: np.ndarray, kernel: np.ndarray, psf_sigma_px: float) -> np.ndarray:
    """The frame with each blurred star replaced by its still image: ``g - f (x) h + f (x) G``.

    ``data`` g (..., H, W) the observed frame(s), ``estimate`` f the restored scene (background removed),
    ``kernel`` h (..., kh, kw) the blur it was restored with, G the Gaussian PSF of ``psf_sigma_px`` (px).  The
    residual ``g - f (x) h - b`` (pixel noise, what the model does not explain) is kept as observed, so the output has
    the frame's own noise and background, with no seam where only part of the frame was restored.
    """
    axes = (-2, -1)
    model = fftconvolve(estimate, kernel, mode="same", axes=axes)
    flat = estimate.reshape(-1, *estimate.shape[-2:])
    still = np.stack([cv2.GaussianBlur(x, (0, 0), psf_sigma_px, borderType=cv2.BORDER_REFLECT) for x in flat])
    return data - model + still.reshape(estimate.shape)


def exposure_path(step: StepInput, head: int, xy_mid=None) -> np.ndarray:
    """The path (m, 2) px over the exposure of a star at ``xy_mid`` (px) at mid-exposure on head ``head``, from the
    step's gyro samples; None: the centre of the frame."""
    cam = step.cameras[head]
    t0, t1 = _window(step)
    xy = [(cam.width - 1) / 2.0, (cam.height - 1) / 2.0] if xy_mid is None else xy_mid
    return star_paths(cam, step.gyro, t0, t1, np.reshape(xy, (1, 2)))[0]


def frame_kernel(step: StepInput, head: int, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The kernel of a star at the centre of head ``head``'s frame (:func:`starenv.psf.path_kernel` result)."""
    return path_kernel(exposure_path(step, head), sigma_px)


class _FrameKernelDeblurrer:
    """Full-frame restoration with one kernel (the frame centre's): subclasses give :meth:`estimate` of the scene
    from the frame, its robust background level and the kernel; :meth:`deblur` resharpens it."""

    iterations = 0

    def __init__(self, psf_sigma_px: float | None):
        self.psf_sigma_px = spot_sigma(psf_sigma_px)
        self.last_info: dict = {}

    def estimate(self, data: np.ndarray, level: float, kernel: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def deblur(self, image: np.ndarray, head: int, step: StepInput) -> np.ndarray:
        data = _checked_image(image, step.cameras[head])
        sigma = sigma_for(self.psf_sigma_px, step.cameras[head])
        level, _ = robust_background(data)
        kernel, _ = frame_kernel(step, head, sigma)
        restored = self.estimate(data, level, kernel)
        self.last_info = {"iterations": self.iterations, "kernel_px": int(max(kernel.shape))}
        return resharpen(data, restored, kernel, sigma)


class RichardsonLucyDeblurrer(_FrameKernelDeblurrer):
    """Full-frame Richardson-Lucy with one kernel (the frame centre's), ``iterations`` fixed; the robust background
    level is the model's background term."""

    def __init__(self, iterations: int = 20, psf_sigma_px: float | None = None):
        super().__init__(psf_sigma_px)
        self.iterations = checks.integer("iterations", iterations, 0, 10000)

    def estimate(self, data: np.ndarray, level: float, kernel: np.ndarray) -> np.ndarray:
        return richardson_lucy(np.maximum(data, 0.0), kernel, self.iterations, background=level)


class WienerDeblurrer(_FrameKernelDeblurrer):
    """Full-frame Wiener filter with one kernel (the frame centre's) and a constant noise-to-signal ratio ``nsr``."""

    def __init__(self, nsr: float = 0.1, psf_sigma_px: float | None = None):
        super().__init__(psf_sigma_px)
        self.nsr = checks.in_range("nsr", nsr, 0.0, 1e6, low_open=True)

    def estimate(self, data: np.ndarray, level: float, kernel: np.ndarray) -> np.ndarray:
        return wiener(data - level, kernel, self.nsr)


class RoiDeblurrer:
    """Richardson-Lucy on patches around candidate streaks, each with its own space-variant kernel.

    Candidates: the background-subtracted frame is correlated with the frame centre's streak (the kernel of a star
    at the frame centre with the sensor's ``psf_sigma_px``: the matched filter of a trail); 8-connected components
    of at least ``min_area_px`` pixels where it exceeds ``threshold_sigma`` times its noise are candidates, at their
    centroids (the trail's centre, as the filtered response of a trail is symmetric about it).  A candidate's kernel
    is the path of a star at that centre (:func:`starenv.psf.star_paths`); its box is the
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

    def candidates(self, data: np.ndarray, level: float, noise: float, streak: np.ndarray) -> np.ndarray:
        """Centres (k, 2) px of the candidate streaks: components of the matched-filter response to ``streak``."""
        template = streak.astype(np.float32)
        response = cv2.filter2D((data - level).astype(np.float32), cv2.CV_32F, template,
                                borderType=cv2.BORDER_REFLECT)  # correlation with the expected trail
        response_noise = noise * float(np.sqrt(np.sum(streak**2)))  # white pixel noise through the filter
        above = (response > self.threshold_sigma * response_noise).astype(np.uint8)
        _, _, stats, centroids = cv2.connectedComponentsWithStats(above, connectivity=8, ltype=cv2.CV_32S)
        keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= self.min_area_px) + 1
        return centroids[keep].reshape(-1, 2)

    def deblur(self, image: np.ndarray, head: int, step: StepInput) -> np.ndarray:
        cam = step.cameras[head]
        data = _checked_image(image, cam)
        sigma = sigma_for(self.psf_sigma_px, cam)
        level, noise = robust_background(data)
        streak, _ = frame_kernel(step, head, sigma)
        centres = self.candidates(data, level, noise, streak)
        out = data.copy()
        self.last_info = {"iterations": self.iterations, "candidates": int(len(centres)), "skipped": 0,
                          "batches": 0, "patch_px": 0}
        if len(centres) == 0:
            return out
        t0, t1 = _window(step)
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
