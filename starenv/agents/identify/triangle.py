"""Triangle (angular-distance) star identification, the classical comparator of paper 002 (Liebe 1995 in its
common form; paper 002 gives no implementation details).

*Database* (:meth:`TriangleIdentifier.reset`): the catalogue's resolvable stars down to ``mag_limit``, and every
pair of them closer than the largest head's field diagonal, sorted by angular distance.

*Matching*: per head, the ``max_stars`` brightest detections plus the one nearest the principal point (paper 002's
"main star") form triangles, brightest first.  A triangle's three angular distances select, within
``tolerance_px`` (through the plate scale), the catalogue pairs of each edge; catalogue triangles whose three pairs
close (A-B, A-C, B-C) and whose handedness matches the detections' (a mirror image is not a rotation) are
candidate matches, the ``max_candidates`` with the smallest edge residuals first.  Each gives an attitude (Wahba's
problem on the three stars), verified against the whole catalogue (:mod:`starenv.agents.identify.verify`): the first one
whose false-match probability, times the candidates tried, is below ``max_false`` with at least ``min_matches``
pairs labels all heads' detections; at most ``max_hypotheses`` are verified per frame.
Ids are HIP numbers; -1 unidentified.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.agents.base import StarMeasurements
from starenv.agents.blocks import wahba_svd
from starenv.agents.identify.geometry import body_vectors, with_ids
from starenv.agents.identify.verify import verify
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog

_MERGE_PX = 3.0  # stars closer than this (px) blend on the sensor: neither is used in the database


def usable_stars(catalog: StarCatalog, mag_limit: float, merge_rad: float) -> np.ndarray:
    """Rows of catalogue stars with Hp <= ``mag_limit`` and no other such star within ``merge_rad``."""
    rows = np.flatnonzero(catalog.magnitude <= mag_limit)
    unit = catalog.unit[rows]
    from scipy.spatial import cKDTree

    pairs = cKDTree(unit).query_pairs(2 * math.sin(merge_rad / 2), output_type="ndarray")
    blended = np.zeros(len(rows), dtype=bool)
    blended[pairs.ravel()] = True
    return rows[~blended]


class TriangleIdentifier:
    """Lost-in-space identification by angular-distance triangles (see the module docstring).

    ``mag_limit``: database stars (Hp); ``tolerance_px``: edge tolerance; ``max_stars``: brightest detections per
    head used in triangles; ``max_candidates``: catalogue triangles verified per detection triangle,
    ``max_hypotheses``: in all; ``radius_px``, ``min_matches``, ``max_false``: verification.
    """

    def __init__(self, mag_limit: float = 6.5, tolerance_px: float = 1.0, max_stars: int = 8,
                 max_candidates: int = 10, max_hypotheses: int = 100, radius_px: float = 2.0, min_matches: int = 5,
                 max_false: float = 1e-3):
        if not tolerance_px > 0 or max_stars < 3 or max_candidates < 1 or min_matches < 3:
            raise ValueError("tolerance_px > 0, max_stars >= 3, max_candidates >= 1 and min_matches >= 3 expected")
        self.mag_limit, self.tolerance_px, self.max_stars = mag_limit, tolerance_px, max_stars
        self.max_candidates, self.max_hypotheses, self.radius_px = max_candidates, max_hypotheses, radius_px
        self.min_matches, self.max_false = min_matches, max_false
        self.catalog: StarCatalog | None = None

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        pixel = max(1.0 / min(c.fx, c.fy) for c in cameras)
        rows = usable_stars(catalog, self.mag_limit, _MERGE_PX * pixel)
        diagonal = max(2 * c.half_diagonal for c in cameras)
        from scipy.spatial import cKDTree

        unit = catalog.unit[rows]
        pairs = cKDTree(unit).query_pairs(2 * math.sin(diagonal / 2), output_type="ndarray")
        angle = 2 * np.arcsin(np.minimum(np.linalg.norm(unit[pairs[:, 0]] - unit[pairs[:, 1]], axis=1) / 2, 1.0))
        order = np.argsort(angle, kind="stable")
        self.angle, self.pairs = angle[order], rows[pairs[order]]
        self.catalog = catalog

    def _edge(self, angle: float, tol: float) -> dict[int, set[int]]:
        lo, hi = np.searchsorted(self.angle, [angle - tol, angle + tol])
        out: dict[int, set[int]] = {}
        for a, b in self.pairs[lo:hi].tolist():
            out.setdefault(a, set()).add(b)
            out.setdefault(b, set()).add(a)
        return out

    def _candidates(self, v: np.ndarray, tol: float) -> list[tuple[int, int, int]]:
        """Catalogue rows (A, B, C) matching detection directions v (3, 3) with the same handedness, the
        ``max_candidates`` with the smallest summed edge residual first."""
        edges = [2 * math.asin(min(np.linalg.norm(v[p] - v[q]) / 2, 1.0)) for p, q in ((0, 1), (0, 2), (1, 2))]
        e01, e02, e12 = (self._edge(e, tol) for e in edges)
        found = [(a, b, c) for a in e01.keys() & e02.keys() for b in e01[a] for c in e02[a] & e12.get(b, set())
                 if c != b]
        if not found:
            return []
        tri = np.array(found)
        u = self.catalog.unit[tri]  # (m, 3, 3)
        same = np.sign(np.linalg.det(u)) == np.sign(np.linalg.det(v))
        tri, u = tri[same], u[same]
        ang = lambda p, q: 2 * np.arcsin(np.minimum(np.linalg.norm(u[:, p] - u[:, q], axis=1) / 2, 1.0))  # noqa: E731
        residual = np.abs(ang(0, 1) - edges[0]) + np.abs(ang(0, 2) - edges[1]) + np.abs(ang(1, 2) - edges[2])
        order = np.argsort(residual, kind="stable")[: self.max_candidates]
        return [tuple(int(x) for x in tri[k]) for k in order]

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None = None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """Label all heads' detections (HIP; -1 unidentified); ``prior`` and ``images`` are not used."""
        if self.catalog is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        body, heads = body_vectors(stars, cameras)
        offsets = np.concatenate([[0], np.cumsum([len(s) for s in stars])])
        tried = 0
        for h, (s, cam) in enumerate(zip(stars, cameras, strict=True)):
            if len(s) < 3:
                continue
            centre = int(np.argmin(np.hypot(s.xy[:, 0] - cam.cx, s.xy[:, 1] - cam.cy)))
            bright = [int(i) for i in np.argsort(-s.flux, kind="stable")[: self.max_stars] if i != centre]
            tol = self.tolerance_px / min(cam.fx, cam.fy)
            triangles = list(itertools.combinations([*bright, centre], 3))  # brightest first, the main star last
            for tri in triangles:
                rows = offsets[h] + np.array(tri)
                for cand in self._candidates(body[rows], tol):
                    tried += 1
                    attitude = Rotation.from_matrix(wahba_svd(body[rows], self.catalog.unit[list(cand)]))
                    v = verify(attitude, body, heads, cameras, self.catalog, self.radius_px, given=3)
                    if v.matched >= self.min_matches and v.p_false * tried <= self.max_false:
                        return with_ids(stars, v.ids)
                    if tried >= self.max_hypotheses:
                        return with_ids(stars, np.full(len(body), -1, dtype=np.int64))
        return with_ids(stars, np.full(len(body), -1, dtype=np.int64))
