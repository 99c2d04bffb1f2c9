"""Fusion: a predictor whose state is a filter over the gyro and the solved attitudes
(:class:`~starenv.agents.base.AttitudeFilter`, a ``Predictor`` with ``posterior()``).

When the predictor is an ``AttitudeFilter``, the pipeline reports its posterior attitude as the action.

* :class:`MekfPredictor`: a multiplicative extended Kalman filter on attitude and gyro bias, tuned from the gyro's
  datasheet noise, updated star by star with chi-square gating.

To add a filter, write a predictor with a ``posterior() -> (attitude, gyro bias, covariance) | None`` method in a module
here and name it in ``__all__``.
"""

from starenv.agents.fuse.mekf import MekfPredictor

__all__ = ["MekfPredictor"]
