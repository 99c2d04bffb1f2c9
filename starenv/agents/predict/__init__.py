"""Prediction: where the stars and the attitude will be at the next frame, from the gyro
(:class:`~starenv.agents.base.Predictor`).

``reset(cameras, catalog)``; ``predict(step) -> Prediction`` (the attitude at the frame's mid-exposure and each head's
stars where they will be measured); ``update(attitude, stars, time_s)`` with the pipeline's estimate.

* :class:`QuaternionPredictor`: gyro delta-angles integrated as quaternions with a two-sample coning correction;
* :class:`FirstOrderPredictor`: paper 000's first-order star-position prediction (its Eqs. 5-7).

A predictor that also fuses the solved attitudes (a filter) lives in :mod:`starenv.agents.fuse`.  To add a
predictor, write a class with those three methods in a module here and name it in ``__all__``.
"""

from starenv.agents.predict.gyro import FirstOrderPredictor, QuaternionPredictor

__all__ = ["FirstOrderPredictor", "QuaternionPredictor"]
