"""Distortion correction: measured star positions -> the calibrated camera's
(:class:`~starenv.agents.base.DistortionCorrector`).

``reset(cameras, catalog)``; ``correct(stars, head, camera)`` and its inverse ``uncorrect``; ``learn(stars, head,
camera, attitude, catalog)`` from the identified stars of a solved frame (on-orbit learning).

* :class:`LegendreCorrector`: paper 003's 2-D Legendre network, learning on orbit by the paper's Adam with a
  forgetting factor or by recursive least squares (:mod:`.legendre`);
* :class:`PiecewiseLinearMap`, :class:`PolynomialMap`: ground-calibration baselines (:mod:`.baselines`);
* :func:`train_ground`: the network's ground batch training in torch (:mod:`.ground`, imported on first use).

To add a corrector, write a class with those four methods in a module here and name it in ``__all__`` (lazily, with
:func:`starenv.agents.lazy_exports`, if it imports torch).
"""

from starenv.agents import lazy_exports
from starenv.agents.correct.baselines import PiecewiseLinearMap, PolynomialMap
from starenv.agents.correct.legendre import LegendreCorrector

__all__ = ["LegendreCorrector", "PiecewiseLinearMap", "PolynomialMap", "train_ground"]
__getattr__ = lazy_exports(__name__, {"train_ground": "ground"})
