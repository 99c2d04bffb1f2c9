"""Grid star identification (Padgett & Kreutz-Delgado 1997), the pattern comparator of paper 002.

*Pattern of a star*: its neighbours within ``pattern_radius`` (default: half the narrowest head's shorter field
side, so a star at the image centre sees its whole pattern) in the gnomonic plane tangent at the star, turned so
that the nearest neighbour farther than ``buffer_px`` lies along +x, then binned on a ``grid`` x ``grid`` grid over
the pattern's square: the set of occupied cells.

*Database* (:meth:`GridIdentifier.reset`): the pattern of every resolvable catalogue star down to ``mag_limit``
(neighbours from the same stars), as a sparse star x cell matrix, and each star's orientation neighbour.

*Matching*: per head, the detection nearest the principal point (paper 002's "main star") is the pattern star; its
pattern from the other detections is scored against every catalogue pattern by shared cells; catalogue stars with
at least ``min_score`` shared cells, best first (at most ``max_candidates``), give an attitude from the two pairs
(pattern star, orientation star), verified against the whole catalogue (:mod:`starenv.agents.identify.verify`).
The first verified hypothesis labels all heads' detections.  A missed or false nearest neighbour turns the whole
pattern, the weakness paper 002 shows at high rates.  Ids are HIP numbers; -1 unidentified.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from starenv.agents.base import StarMeasurements
from starenv.agents.blocks import wahba_svd
from starenv.agents.identify.geometry import body_vectors, with_ids
from starenv.agents.identify.triangle import _MERGE_PX, usable_stars
from starenv.agents.identify.verify import verify
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog


def _tangent_basis(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ref = np.array([0.0, 0.0, 1.0]) if abs(c[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(ref, c)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(c, e1)


def pattern_cells(centre: np.ndarray, neighbours: np.ndarray, radius: float, buffer: float,
                  grid: int) -> tuple[np.ndarray, int]:
    """Occupied cells (sorted, unique) of the pattern of unit vector ``centre`` from ``neighbours`` (n, 3), and the
    row in ``neighbours`` of the orientation star (-1: none beyond ``buffer``, no pattern)."""
    e1, e2 = _tangent_basis(centre)
    z = neighbours @ centre
    front = z > 0
    xy = np.where(front[:, None], np.column_stack([neighbours @ e1, neighbours @ e2]) / np.where(front, z, 1)[:, None],
                  np.inf)
    r = np.hypot(xy[:, 0], xy[:, 1])
    inside = (r > buffer) & (r <= math.tan(radius))
    if not inside.any():
        return np.zeros(0, dtype=np.int64), -1
    k = int(np.flatnonzero(inside)[np.argmin(r[inside])])
    angle = math.atan2(xy[k, 1], xy[k, 0])
    c, s = math.cos(-angle), math.sin(-angle)
    turned = xy[inside] @ np.array([[c, s], [-s, c]])
    half = math.tan(radius)
    cells = np.clip(((turned + half) / (2 * half) * grid).astype(np.int64), 0, grid - 1)
    return np.unique(cells[:, 1] * grid + cells[:, 0]), k


class GridIdentifier:
    """Lost-in-space identification by the grid algorithm (see the module docstring).

    ``mag_limit``: database stars (Hp); ``grid``: cells per side; ``pattern_radius_deg`` (None: half the narrowest
    head's shorter side); ``buffer_px``: nearest-neighbour exclusion radius; ``min_score``: shared cells needed;
    ``max_candidates``: hypotheses verified; ``radius_px``, ``min_matches``, ``max_false``: verification.
    """

    def __init__(self, mag_limit: float = 6.5, grid: int = 20, pattern_radius_deg: float | None = None,
                 buffer_px: float = 4.0, min_score: int = 3, max_candidates: int = 10, radius_px: float = 2.0,
                 min_matches: int = 5, max_false: float = 1e-3):
        if grid < 2 or buffer_px < 0 or min_score < 1 or max_candidates < 1 or min_matches < 3:
            raise ValueError("grid >= 2, buffer_px >= 0, min_score >= 1, max_candidates >= 1, min_matches >= 3 "
                             "expected")
        self.mag_limit, self.grid, self.pattern_radius_deg = mag_limit, grid, pattern_radius_deg
        self.buffer_px, self.min_score, self.max_candidates = buffer_px, min_score, max_candidates
        self.radius_px, self.min_matches, self.max_false = radius_px, min_matches, max_false
        self.catalog: StarCatalog | None = None

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        pixel = max(1.0 / min(c.fx, c.fy) for c in cameras)
        self.radius = (math.radians(self.pattern_radius_deg) if self.pattern_radius_deg is not None
                       else min(min(c.fov) for c in cameras) / 2)
        self.buffer = self.buffer_px * pixel
        rows = usable_stars(catalog, self.mag_limit, _MERGE_PX * pixel)
        unit = catalog.unit[rows]
        tree = cKDTree(unit)
        cells, owners, orient = [], [], np.full(len(rows), -1, dtype=np.int64)
        for i, near in enumerate(tree.query_ball_point(unit, 2 * math.sin(self.radius / 2))):
            near = [j for j in near if j != i]
            occupied, k = pattern_cells(unit[i], unit[near], self.radius, self.buffer, self.grid)
            if k >= 0:
                cells.append(occupied)
                owners.append(np.full(len(occupied), i))
                orient[i] = rows[near[k]]
        data_rows = np.concatenate(owners) if owners else np.zeros(0, dtype=np.int64)
        data_cols = np.concatenate(cells) if cells else np.zeros(0, dtype=np.int64)
        self.patterns = sparse.csr_matrix((np.ones(len(data_rows), dtype=np.int32), (data_rows, data_cols)),
                                          shape=(len(rows), self.grid**2))
        self.rows, self.orient = rows, orient
        self.catalog = catalog

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None = None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """Label all heads' detections (HIP; -1 unidentified); ``prior`` and ``images`` are not used."""
        if self.catalog is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        body, heads = body_vectors(stars, cameras)
        offsets = np.concatenate([[0], np.cumsum([len(s) for s in stars])])
        for h, (s, cam) in enumerate(zip(stars, cameras, strict=True)):
            if len(s) < 3:
                continue
            centre = int(np.argmin(np.hypot(s.xy[:, 0] - cam.cx, s.xy[:, 1] - cam.cy)))
            mine = body[offsets[h]:offsets[h + 1]]
            others = np.delete(np.arange(len(s)), centre)
            occupied, k = pattern_cells(mine[centre], mine[others], self.radius, self.buffer, self.grid)
            if k < 0:
                continue
            query = np.zeros(self.grid**2, dtype=np.int32)
            query[occupied] = 1
            score = self.patterns @ query
            best = np.argsort(-score, kind="stable")[: self.max_candidates]
            best = best[score[best] >= self.min_score]
            for tried, b in enumerate(best, start=1):
                if self.orient[b] < 0:
                    continue
                inertial = self.catalog.unit[[self.rows[b], self.orient[b]]]
                attitude = Rotation.from_matrix(wahba_svd(mine[[centre, others[k]]], inertial))
                v = verify(attitude, body, heads, cameras, self.catalog, self.radius_px, given=2)
                if v.matched >= self.min_matches and v.p_false * tried <= self.max_false:
                    return with_ids(stars, v.ids)
        return with_ids(stars, np.full(len(body), -1, dtype=np.int64))
