"""Star detection: a frame in, star centroids out (:class:`~starenv.agents.base.StarDetector`).

``detect(image, camera) -> StarMeasurements``: ``image`` is one head's frame (counts, rows x columns), ``camera`` the
calibrated camera; the result holds the measured (distorted) pixel positions, the flux above background and no ids.

* :class:`CentroidDetector`: tiled background, matched filter, connected components, deblending; centre of gravity,
  intensity-weighted centre of gravity or a Gaussian fit; optional linking of broken faint trails.

The spot a camera model carries can be measured on a frame instead, for cameras whose spot size is not calibrated
(``starenv solve`` does so): :func:`~starenv.agents.detect.spot.measure_spot_sigma`, the Gaussian sigma of the
frame's brightest isolated unsaturated stars.

To add a detector, write a class with a ``detect`` method of that signature in a module here and name it in
``__all__``; the pipeline checks the protocol before it constructs the class.
"""

from starenv.agents.detect.centroid import CentroidDetector

__all__ = ["CentroidDetector"]
