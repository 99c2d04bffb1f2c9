"""``IterationNetDeblurrer``: paper 000's improved Richardson-Lucy, the iteration count from the EBPNN."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from starenv import checks
from starenv.agents.restore.algorithms import resharpen, richardson_lucy, richardson_lucy_batch
from starenv.agents.restore.iteration.ebpnn import EnsembleNet
from starenv.agents.restore.iteration.features import INITIAL_FLOOR_DN, initial_estimate, sumfc
from starenv.agents.restore.kernels import centre_kernel, frame_streaks, sigma_for, spot_sigma
from starenv.agents.restore.patches import restore_streaks

WEIGHTS = Path(__file__).with_name("iteration_net.npz")
KERNEL_SIGMA_PX = 0.5  # the Gaussian each kernel sample is drawn with, in training and here
REGIONS = ("frame", "streaks")


class IterationNetDeblurrer:
    """Full-frame Richardson-Lucy with the frame centre's gyro kernel (paper 000's single kernel per image) and the
    iteration count the EBPNN predicts from the kernel's SUMFC (rounded, clipped to [1, ``max_iterations``]).

    ``weights``: an ``.npz`` from ``python -m starenv.agents.restore.iteration.train`` (default: the shipped
    ``iteration_net.npz`` beside this module).  The frame's median is the background term; RL starts from the frame
    less that level, as in training.  Returns the frame with each trail replaced by its still star
    (:func:`starenv.agents.restore.algorithms.resharpen` of the RL estimate: the frame keeps its own noise, which the
    detector models, instead of RL's amplified noise), the still star drawn with the sensor's spot ``psf_sigma_px`` (px;
    None: the calibrated camera's); float64 DN.  Sets ``last_info`` (``iterations``, ``sumfc``, timings in s).

    ``region="streaks"`` (real time): the same RL, started the same way, on a patch around each candidate streak
    (:func:`~starenv.agents.restore.patches.restore_streaks`; candidates at ``threshold_sigma`` as the
    region-of-interest deblurrer finds them), each with its own space-variant kernel; the patches of one size share one
    iteration count, the EBPNN's for the SUMFC of their middle member's kernel.  The rest of the frame is left as
    observed.
    """

    def __init__(self, weights: str | Path | None = None, max_iterations: int = 300, psf_sigma_px: float | None = None,
                 region: str = "frame", threshold_sigma: float = 5.0):
        path = WEIGHTS if weights is None else Path(weights)
        if not path.is_file():
            raise ValueError(f"weights: no file {path}; make one with "
                             "python -m starenv.agents.restore.iteration.train --out PATH")
        self.net = EnsembleNet.load(path)
        self.max_iterations = checks.integer("max_iterations", max_iterations, 1, 100000)
        self.psf_sigma_px = spot_sigma(psf_sigma_px)
        self.region = checks.choice("region", region, REGIONS)
        self.threshold_sigma = checks.in_range("threshold_sigma", threshold_sigma, 0.0, 100.0, low_open=True)
        self.last_info: dict = {}

    def iterations_for(self, kernel: np.ndarray) -> tuple[int, float]:
        """The predicted iteration count for a kernel, and the kernel's SUMFC."""
        feature = sumfc(kernel)
        n = int(np.clip(round(self.net.predict(feature)), 1, self.max_iterations))
        return n, feature

    def deblur(self, image: np.ndarray, head: int, step) -> np.ndarray:
        if self.region == "streaks":
            return self._deblur_streaks(image, head, step)
        t0 = time.perf_counter()
        data = checks.finite("image", image).astype(np.float64)
        kernel, _ = centre_kernel(step, head, KERNEL_SIGMA_PX)
        n, feature = self.iterations_for(kernel)
        t_predict = time.perf_counter() - t0
        level = float(np.median(data))
        restored = richardson_lucy(np.maximum(data, 0.0), kernel, n, background=level,
                                   initial=initial_estimate(data, level))
        self.last_info = {"iterations": n, "sumfc": feature, "predict_s": t_predict,
                          "total_s": time.perf_counter() - t0}
        sigma = sigma_for(self.psf_sigma_px, step.cameras[head])
        return resharpen(data, restored, kernel, sigma)

    def _deblur_streaks(self, image: np.ndarray, head: int, step) -> np.ndarray:
        t0 = time.perf_counter()
        found = frame_streaks(image, head, step, self.psf_sigma_px, self.threshold_sigma, 4)
        counts = []

        def deconvolve(patches, psfs, level, members):
            n, _ = self.iterations_for(psfs[len(psfs) // 2])
            counts.append(n)
            start = np.maximum(patches - np.float32(level), np.float32(INITIAL_FLOOR_DN))
            return richardson_lucy_batch(np.maximum(patches, 0.0), psfs, n, background=level, initial=start,
                                         circular=True)

        out, info = restore_streaks(found, step, head, deconvolve, kernel_sigma_px=KERNEL_SIGMA_PX)
        self.last_info = {"iterations": max(counts, default=0), **info, "total_s": time.perf_counter() - t0}
        return out
