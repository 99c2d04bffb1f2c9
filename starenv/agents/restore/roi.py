"""The region-of-interest deblurrer: Richardson-Lucy on patches around candidate streaks, each restored with its own
space-variant gyro kernel, the patches batched by size (:class:`RoiDeblurrer`)."""

from __future__ import annotations

import numpy as np

from starenv import checks
from starenv.agents.base import StepInput
from starenv.agents.restore.algorithms import richardson_lucy_batch
from starenv.agents.restore.kernels import frame_streaks, spot_sigma
from starenv.agents.restore.patches import restore_streaks


class RoiDeblurrer:
    """Richardson-Lucy on patches around candidate streaks, each with its own space-variant kernel.

    Candidates: :func:`~starenv.agents.blocks.streak_candidates` with the frame centre's streak (the
    kernel of a star at the frame centre with the sensor's ``psf_sigma_px``), ``threshold_sigma`` and
    ``min_area_px``, at their centroids.  Each is restored on its own patch by
    :func:`~starenv.agents.restore.patches.restore_streaks` (its kernel drawn with the sensor's spot, ``margin_px``
    around the kernel's extent; boxes larger than ``max_patch_px`` are left as they are and counted in
    ``last_info["skipped"]``), ``iterations`` Richardson-Lucy steps from each patch's flat mean, the patches of one
    size in one :func:`~starenv.agents.restore.algorithms.richardson_lucy_batch`.
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
        found = frame_streaks(image, head, step, self.psf_sigma_px, self.threshold_sigma, self.min_area_px,
                              drop_points=True)

        def deconvolve(patches, psfs, level, members):
            return richardson_lucy_batch(np.maximum(patches, 0.0), psfs, self.iterations, background=level,
                                         circular=True)

        out, info = restore_streaks(found, step, head, deconvolve, kernel_sigma_px=found.sigma,
                                    margin_px=self.margin_px, max_patch_px=self.max_patch_px,
                                    spot=self.psf_sigma_px is None)
        self.last_info = {"iterations": self.iterations, **info}
        return out
