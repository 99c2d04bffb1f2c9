"""Tracking identification (:class:`TrackingIdentifier`): gated nearest-star pairing around a prior attitude, with
a lost-in-space fallback."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from starenv import checks
from starenv.agents.base import Identifier, StarMeasurements
from starenv.agents.identify.geometry import MERGE_PX, body_vectors, chord, resolvable, with_ids
from starenv.agents.identify.lost_in_space import LostInSpaceIdentifier
from starenv.agents.solve import wahba_svd
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog


class TrackingIdentifier:
    """Identification from a prior attitude by gated nearest-star pairing; lost in space when that fails.

    ``gate_px`` is the first pairing radius, ``refine_gate_px`` the radius after refining the attitude on the first
    pairs (both converted to angles with each head's plate scale); fewer than ``min_matches`` pairs (or no prior)
    hands the frame to ``fallback`` (default :class:`LostInSpaceIdentifier` with its defaults).  The stars are all
    those of the catalogue given to :meth:`reset` but the fainter of pairs closer than ``MERGE_PX`` pixels.
    """

    def __init__(
        self,
        fallback: Identifier | None = None,
        gate_px: float = 5.0,
        refine_gate_px: float = 2.0,
        min_matches: int = 3,
    ):
        if fallback is not None and not isinstance(fallback, Identifier):
            raise ValueError(f"fallback must implement the Identifier protocol, got {type(fallback).__name__}")
        self.fallback = LostInSpaceIdentifier() if fallback is None else fallback
        self.gate_px = checks.in_range("gate_px", gate_px, 0.0, 1000.0, low_open=True, unit="px")
        self.refine_gate_px = checks.in_range(
            "refine_gate_px", refine_gate_px, 0.0, self.gate_px, low_open=True, unit="px"
        )
        self.min_matches = checks.integer("min_matches", min_matches, 3, 1000)
        self.catalog: StarCatalog | None = None

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        """Index the catalogue's resolvable stars for these heads and reset the fallback."""
        if not cameras:
            raise ValueError("cameras must hold at least one Camera")
        merge_rad = MERGE_PX * max(1.0 / min(cam.fx, cam.fy) for cam in cameras)
        self._rows = np.flatnonzero(resolvable(catalog.unit, catalog.magnitude, merge_rad))
        self._tree = cKDTree(catalog.unit[self._rows])
        self.catalog = catalog
        self.fallback.reset(cameras, catalog)

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """Label all heads' detections with HIP numbers (-1: unidentified), tracking from ``prior`` if it is given;
        ``images`` goes to the fallback."""
        if self.catalog is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        body, heads = body_vectors(stars, cameras)
        if prior is not None and len(body) >= self.min_matches:
            pixel_rad = np.array([1.0 / min(cam.fx, cam.fy) for cam in cameras])[heads]
            attitude = prior.as_matrix()
            rows = self._in_view(cameras, attitude)
            detections, matched_rows = self._pairs(body, rows, attitude, self.gate_px * pixel_rad)
            if len(detections) >= self.min_matches:
                attitude = wahba_svd(body[detections], self.catalog.unit[matched_rows])
                detections, matched_rows = self._pairs(body, rows, attitude, self.refine_gate_px * pixel_rad)
                if len(detections) >= self.min_matches:
                    ids = np.full(len(body), -1, dtype=np.int64)
                    ids[detections] = self.catalog.hip[matched_rows]
                    return with_ids(stars, ids)
        return self.fallback.identify(stars, cameras, prior, images)

    def _in_view(self, cameras: list[Camera], attitude: np.ndarray) -> np.ndarray:
        """Catalogue rows of the resolvable stars within each head's half diagonal plus the gate of its boresight
        under ``attitude`` (3, 3), inertial -> body (a cone query per head)."""
        boresights = np.stack([cam.mounting.as_matrix()[2] @ attitude for cam in cameras])
        reach = [chord(cam.half_diagonal + 2.0 * self.gate_px / min(cam.fx, cam.fy)) for cam in cameras]
        found = self._tree.query_ball_point(boresights, reach)
        return self._rows[np.unique(np.concatenate([np.asarray(f, dtype=np.intp) for f in found]))]

    def _pairs(
        self, body: np.ndarray, rows: np.ndarray, attitude: np.ndarray, gate_rad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Detections (rows of ``body``) and catalogue rows (from ``rows``) paired under ``attitude`` (3, 3): each
        detection within its ``gate_rad`` of a star, one to one, least total squared distance."""
        predicted = self.catalog.unit[rows] @ attitude.T  # body frame
        squared = np.maximum(2.0 - 2.0 * (body @ predicted.T), 0.0)  # squared chord, = squared angle here
        gated = squared <= gate_rad[:, None] ** 2
        near_detections, near_stars = np.flatnonzero(gated.any(axis=1)), np.flatnonzero(gated.any(axis=0))
        near = np.ix_(near_detections, near_stars)
        gated, squared = gated[near], squared[near]
        # Pairs outside the gate cost more than any set of gated pairs: the most pairs win, then the closest.
        outside = (min(gated.shape) + 1) * float(np.max(gate_rad)) ** 2
        detection, star = linear_sum_assignment(np.where(gated, squared, outside))
        inside = gated[detection, star]
        return near_detections[detection[inside]], rows[near_stars[star[inside]]]
