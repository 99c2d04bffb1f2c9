"""Distortion correctors (:class:`~starenv.agents.base.DistortionCorrector`): map measured centroids to the
calibrated camera's positions, learning from identified stars on the way."""
