"""Deblurrers (:class:`~starenv.agents.base.Deblurrer`): restore a smeared frame from the gyro's rates.

The blur kernel comes from :mod:`starenv.agents.restore.kernels`: the gyro samples of the step are integrated over the
exposure ``[time_s - exposure_s / 2, time_s + exposure_s / 2]`` (global shutter; the rolling-shutter row delay is not in
``StepInput``) and a star's path through the calibrated camera is rasterised with the sensor's Gaussian PSF
(``psf_sigma_px``), so the restoration estimates the point-like scene ``f``.  The output is the observed frame with
each trail replaced by its still image (:func:`resharpen`): ``g - f (x) h + f (x) G``, the frame a still sensor
would have taken, with the frame's own noise: stars of the shape a detector tuned to the sensor expects (a bare
Richardson-Lucy estimate has one-pixel stars, which a detector's hot-pixel tests reject, and amplified noise).

* :class:`RichardsonLucyDeblurrer`: one kernel for the whole frame, the path of a star at the frame centre
  (paper 000's single-kernel model), Richardson-Lucy over the full frame.
* :class:`WienerDeblurrer`: the same kernel, frequency-domain Wiener filter of the background-subtracted frame.
* :class:`RoiDeblurrer`: candidate streaks (connected components of a matched-filter response above the robust
  background noise), one patch per candidate restored with that candidate's own space-variant kernel, the patches
  in Richardson-Lucy batches (one per patch size) and pasted back; the rest of the frame is left as it was.

Each returns a float64 image in the input's DN (background kept) and sets ``last_info`` (``iterations`` and more).
"""

from __future__ import annotations

import numpy as np

from starenv import checks
from starenv.agents.base import StepInput
from starenv.agents.blocks import frame_background
from starenv.agents.restore.algorithms import checked_image, resharpen, richardson_lucy, wiener
from starenv.agents.restore.kernels import frame_kernel, sigma_for, spot_sigma


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
        data = checked_image(image, step.cameras[head])
        sigma = sigma_for(self.psf_sigma_px, step.cameras[head])
        level, _ = frame_background(data)
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


