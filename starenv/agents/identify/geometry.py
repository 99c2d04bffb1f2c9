"""Geometry shared by the identifiers: pooled body-frame vectors of all heads, labelling, pattern edges, the
separation under which two stars are one on the sensor."""

from __future__ import annotations

import itertools
import math
import operator

import numpy as np
from scipy.spatial import cKDTree

from starenv.agents.base import StarMeasurements
from starenv.sim.optics import Camera

MERGE_PX = 2.0  # a star closer than this (px, coarsest head) to a brighter one is taken as part of it
# A centroid with Gaussian noise of sigma per axis lies beyond r of its star with probability exp(-r^2 / (2 sigma^2))
# (Rayleigh): beyond this many sigmas with probability 1e-4 (of a scatter measured on a few pairs, more:
# :func:`claim_scale2`).  A star with two detections within it cannot tell which is its own, nor a detection with two
# stars within it which one made it (:func:`sole_per_star`).
CLAIM_SIGMAS = math.sqrt(2.0 * math.log(1e4))
EDGE_FROM, EDGE_TO = np.triu_indices(4, 1)  # the six edges of a pattern: 01, 02, 03, 12, 13, 23
STAR_ORDERS = np.array(list(itertools.permutations(range(4))))  # (24, 4)
EDGE_OF = np.zeros((4, 4), dtype=np.intp)  # edge number of a star pair
EDGE_OF[EDGE_FROM, EDGE_TO] = EDGE_OF[EDGE_TO, EDGE_FROM] = np.arange(6)
ORDER_EDGES = EDGE_OF[STAR_ORDERS[:, EDGE_FROM], STAR_ORDERS[:, EDGE_TO]]  # (24, 6) edges of a reordered pattern
IDENTITY = np.eye(3)


def chord(angle_rad: float) -> float:
    """Straight-line distance between two unit vectors ``angle_rad`` apart."""
    return 2.0 * math.sin(min(angle_rad, math.pi) / 2.0)


def pattern_edges(vectors: np.ndarray) -> np.ndarray:
    """The six pairwise angles (rad), ordered 01, 02, 03, 12, 13, 23, of unit-vector quadruples (..., 4, 3)."""
    chord = np.linalg.norm(vectors[..., EDGE_FROM, :] - vectors[..., EDGE_TO, :], axis=-1)
    return 2.0 * np.arcsin(np.minimum(chord / 2.0, 1.0))


def body_vectors(stars: list[StarMeasurements], cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Pooled detections of all heads (heads in order): body-frame unit vectors (n, 3) and the head of each (n,)."""
    if len(stars) != len(cameras):
        raise ValueError(f"stars must hold one StarMeasurements per camera ({len(cameras)}), got {len(stars)}")
    vectors = [cam.unproject(s.xy) @ cam.mounting.as_matrix() for s, cam in zip(stars, cameras, strict=True)]
    heads = np.repeat(np.arange(len(stars)), [len(s) for s in stars])
    return np.concatenate(vectors) if vectors else np.zeros((0, 3)), heads


def same_cameras(kept: tuple[Camera, ...], cameras: list[Camera]) -> bool:
    """Whether ``cameras`` are the very objects of ``kept`` (cameras are frozen: constants made for them hold)."""
    if len(kept) != len(cameras):
        return False
    return kept[0] is cameras[0] if len(cameras) == 1 else all(map(operator.is_, kept, cameras))


def with_ids(stars: list[StarMeasurements], ids: np.ndarray) -> list[StarMeasurements]:
    """Copies of ``stars`` with catalogue ids from the pooled id array ``ids`` (heads in order)."""
    out, start = [], 0
    for s in stars:
        out.append(StarMeasurements(s.xy.copy(), s.flux.copy(), ids[start : start + len(s)].copy()))
        start += len(s)
    return out


def resolvable(unit: np.ndarray, magnitude: np.ndarray, merge_rad: float) -> np.ndarray:
    """Mask (n,) of the stars with no brighter star (or equal one listed earlier) within ``merge_rad``: a sensor sees
    each pair closer than that as one star, the brighter."""
    pairs = cKDTree(unit).query_pairs(chord(merge_rad), output_type="ndarray")
    a, b = pairs[:, 0], pairs[:, 1]
    fainter = np.where((magnitude[b] > magnitude[a]) | ((magnitude[b] == magnitude[a]) & (b > a)), b, a)
    keep = np.ones(len(unit), dtype=bool)
    keep[fainter] = False
    return keep


def closest_per_star(rows: np.ndarray, star: np.ndarray, distance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``rows`` (ascending) and their stars, of rows paired with star ``star[row]`` at ``distance[row]`` (arrays over
    all rows; any measure that grows with distance, such as minus the dot product of unit vectors); a star paired
    with several rows keeps only the closest, the first listed among equals."""
    stars = star[rows]
    if len(set(stars.tolist())) < len(stars):
        order = np.argsort(distance[rows], kind="stable")
        _, first = np.unique(stars[order], return_index=True)
        keep = np.sort(order[first])
        rows, stars = rows[keep], stars[keep]
    return rows, stars


def mask_pairs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``mask.nonzero()`` of a 2-d mask (rows and columns of its true entries, row-major), from the flat indices:
    numpy's 2-d nonzero costs several times more on small arrays."""
    return np.divmod(mask.ravel().nonzero()[0], mask.shape[1])


def sole_per_star(rows: np.ndarray, star: np.ndarray, near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``rows`` (ascending) and their stars, of rows paired with star ``star[row]``, less every row whose star has
    two detections or more near it, and every row with two stars or more near it (``near`` (rows, stars): the pairs
    within ``CLAIM_SIGMAS`` centroid sigmas).  Two detections by one star are a star the catalogue merged into it
    or left out and the star; two stars by one detection, a pair the sensor saw as one spot, or a star whose centroid
    noise took its detection past the pairing radius while its neighbour's lies within.  Which one is whose is then a
    guess (with centroid noise the nearer is often the other)."""
    counts = near.astype(np.float64)  # (the counts as products with ones: summing booleans costs several times more)
    alone = (np.ones(len(counts)).dot(counts)[star[rows]] <= 1.0) & (counts.dot(np.ones(counts.shape[1]))[rows] <= 1.0)
    return rows[alone], star[rows[alone]]


def claim_scale2(pairs: int) -> float:
    """The squared claim radius in units of a centroid variance per axis measured as the mean over ``pairs`` (8 or
    more) detection-star pairs under an attitude fitted on them: ``CLAIM_SIGMAS ** 2`` for a known variance, more for
    a measured one.  With ``k = 2 pairs - 3`` degrees of freedom (two axes a pair, three fitted), a detection's
    squared offset from its star over twice the unbiased variance is F(2, k): beyond ``c`` with probability
    ``(1 + 2c / k) ** (-k / 2)``.  For that to be 1e-4, as for ``CLAIM_SIGMAS``, ``2c = k (1e4 ** (2 / k) - 1)``;
    times ``2 pairs / k`` for the mean."""
    return 2.0 * pairs * (1e4 ** (2.0 / (2 * pairs - 3)) - 1.0)


def same_matches(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether two matchings (detections, star rows) are the same."""
    return a[0].tolist() == b[0].tolist() and a[1].tolist() == b[1].tolist()
