"""Star identification: detections in, catalogue ids out (:class:`~starenv.agents.base.Identifier`).

``reset(cameras, catalog)``; ``identify(stars, cameras, prior, images=None)`` returns each head's stars with
``catalog_id`` set (-1 where unidentified); ``prior`` is the predicted attitude or None (lost in space), ``images``
each head's frame for identifiers that read pixels.  An identifier must prefer no answer to a wrong one: each verifies
its labels against the catalogue before returning them.

* :class:`LostInSpaceIdentifier`: Tetra 4-star pattern hashing (pattern database and its cache: :mod:`.database`);
* :class:`TrackingIdentifier`: pairwise-angle voting within a gate about the prior, lost in space as fallback;
* :class:`GrnnIdentifier`: paper 004's generalised regression network on each star's triangle;
* :class:`TriangleIdentifier`, :class:`GridIdentifier`: paper 002's comparators (angular-distance triangles,
  Padgett's grid patterns), verified by :mod:`.verify`;
* :class:`NetworkIdentifier`: paper 002's CNN + Transformer on the raw frame (torch, imported on first use; model
  :mod:`.network_model`, shard reader :mod:`.network_data`, training :mod:`.network_train`, shipped weights in
  ``weights/``).

To add an identifier, write a class with ``reset`` and ``identify`` in a module here and name it in ``__all__``
(lazily, with :func:`starenv.agents.lazy_exports`, if it imports torch).
"""

from starenv.agents import lazy_exports
from starenv.agents.identify.grid import GridIdentifier
from starenv.agents.identify.grnn import GrnnIdentifier
from starenv.agents.identify.lost_in_space import LostInSpaceIdentifier
from starenv.agents.identify.tracking import TrackingIdentifier
from starenv.agents.identify.triangle import TriangleIdentifier

__all__ = ["GridIdentifier", "GrnnIdentifier", "LostInSpaceIdentifier", "NetworkIdentifier", "TrackingIdentifier",
           "TriangleIdentifier"]
__getattr__ = lazy_exports(__name__, {"NetworkIdentifier": "network"})
