"""Restoration of smeared frames (:class:`~starenv.agents.base.Deblurrer`).

``deblur(image, head, step) -> image``: one head's frame (counts) restored, knowing the gyro samples over its
exposure (``step.gyro``) and the calibrated cameras; the result has the frame's shape and is what the detector sees.

* :class:`TrailFitDeblurrer`: each streak fitted by least squares with its gyro-predicted trail and replaced by its
  still star (:mod:`.trail_fit`);
* :class:`RoiDeblurrer`: Richardson-Lucy on patches around candidate streaks, each with its own kernel (:mod:`.roi`);
* :class:`RichardsonLucyDeblurrer`, :class:`WienerDeblurrer`: the whole frame with the frame centre's kernel
  (:mod:`.frame`);
* :class:`CurvatureRLDeblurrer`: paper 001's gated Gaussian-curvature denoising and Richardson-Lucy stopped when the
  centroids settle (:mod:`.curvature`);
* :class:`IterationNetDeblurrer`: paper 000's Richardson-Lucy with the iteration count a small numpy network ensemble
  predicts from the kernel (:mod:`.iteration`, with its training).

Shared by them: blur kernels from the gyro (:mod:`.kernels`), the algorithms (:mod:`.algorithms`: Richardson-Lucy,
Wiener, the curvature filter, resharpening) and restoration on streak patches (:mod:`.patches`).  No deblurrer imports
another.  To add a deblurrer, write a class with that ``deblur`` method in a module here and name it in ``__all__``.
"""

from starenv.agents.restore.curvature import CurvatureRLDeblurrer
from starenv.agents.restore.frame import RichardsonLucyDeblurrer, WienerDeblurrer
from starenv.agents.restore.iteration.deblurrer import IterationNetDeblurrer
from starenv.agents.restore.roi import RoiDeblurrer
from starenv.agents.restore.trail_fit import TrailFitDeblurrer

__all__ = ["CurvatureRLDeblurrer", "IterationNetDeblurrer", "RichardsonLucyDeblurrer", "RoiDeblurrer",
           "TrailFitDeblurrer", "WienerDeblurrer"]
