"""Verifying an attitude hypothesis against the catalogue, for identifiers that first guess and then check.

For a hypothesis (inertial -> body), every head's catalogue stars in its field are projected, each detection is
paired with the nearest projected star within ``radius_px`` (one detection a star, closest pairs first), the
attitude is refined from the pairs (SVD solution of Wahba's problem) and the pairing repeated.  With ``n``
detections in all heads, ``m`` paired, and ``p`` the chance that a random detection lands within ``radius_px`` of
some catalogue star (stars in the field times the disc area over the image area), the probability that a wrong
attitude pairs as many is ``P(X >= m - g)`` for ``X ~ Binomial(n - g, p)``, where ``g`` detections were used to
form the hypothesis and pair by construction (as tetra3 / cedar-solve verify).  Callers compare it, multiplied by
the number of hypotheses they tried, against their threshold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import binom

from starenv.agents.solve import wahba_svd
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog


def wahba(body: np.ndarray, inertial: np.ndarray) -> Rotation:
    """The rotation A (inertial -> body) minimising sum |b - A r|^2 over unit-vector pairs (n, 3), n >= 2 (SVD)."""
    return Rotation.from_matrix(wahba_svd(body, inertial))


@dataclass
class Verdict:
    """A verified (or refuted) hypothesis: pooled ids (-1 none), pairs ``m`` of ``n`` detections, the false-match
    probability and the refined attitude."""

    ids: np.ndarray
    matched: int
    detections: int
    p_false: float
    attitude: Rotation


def verify(attitude: Rotation, body: np.ndarray, heads: np.ndarray, cameras: list[Camera], catalog: StarCatalog,
           radius_px: float = 3.0, given: int = 0, refine: int = 2) -> Verdict:
    """Pair detections (pooled body vectors ``body`` of heads ``heads``) with the catalogue under ``attitude``;
    ``given``: detections the hypothesis was built from."""
    n = len(body)
    ids = np.full(n, -1, dtype=np.int64)
    for _ in range(refine + 1):
        ids = np.full(n, -1, dtype=np.int64)
        pairs_b, pairs_r = [], []
        expected = 0.0
        for h, cam in enumerate(cameras):
            rows_det = np.flatnonzero(heads == h)
            cam_rot = cam.mounting * attitude
            axis = cam_rot.inv().apply([0.0, 0.0, 1.0])
            rows = catalog.cone(axis, min(math.pi, cam.half_diagonal + 0.01))
            xy, front = cam.project(cam_rot.apply(catalog.unit[rows]))
            inside = front & cam.in_frame(xy)
            rows, xy = rows[inside], xy[inside]
            area = cam.width * cam.height
            expected += len(rows_det) * min(1.0, len(rows) * math.pi * radius_px**2 / area)
            if not len(rows_det) or not len(rows):
                continue
            det_xy, _ = cam.project(cam.mounting.apply(body[rows_det]))
            d = np.linalg.norm(det_xy[:, None, :] - xy[None, :, :], axis=2)
            order = np.argsort(d, axis=None)
            used_d, used_s = set(), set()
            for flat in order:
                i, j = divmod(int(flat), len(rows))
                if d[i, j] > radius_px:
                    break
                if i in used_d or j in used_s:
                    continue
                used_d.add(i)
                used_s.add(j)
                ids[rows_det[i]] = catalog.hip[rows[j]]
                pairs_b.append(body[rows_det[i]])
                pairs_r.append(catalog.unit[rows[j]])
        if len(pairs_b) < 2:
            break
        attitude = wahba(np.array(pairs_b), np.array(pairs_r))
    m = int((ids >= 0).sum())
    p = expected / n if n else 0.0
    p_false = float(binom.sf(m - given - 1, n - given, p)) if m > given else 1.0
    return Verdict(ids, m, n, p_false, attitude)
