"""Paper 004's training samples: each navigation star's "three sides" under centroid noise.

A star's three sides are the angles (deg) star -> nearest star, star -> second-nearest star and nearest ->
second-nearest (the paper's d_i, in that order), between stars of one catalogue (the navigation stars).  A noisy sample
puts the three stars on the tangent plane of a camera pointed at the star (gnomonic projection, ``pixel_rad`` rad per
pixel at the centre), moves each by a Gaussian centroid error of ``sigma_px`` per axis and measures the sides again:
what a sensor with that centroid noise measures.  Draws are reproducible alone from ``(seed, star index)``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def nearest_two(unit: np.ndarray) -> np.ndarray:
    """Indices (n, 2) of the nearest and second-nearest other star of each unit vector (n, 3), ties by index."""
    _, idx = cKDTree(unit).query(unit, k=3)
    return idx[:, 1:]


def three_sides(star: np.ndarray, nearest: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The three sides (..., 3) deg of unit-vector triangles (each (..., 3)): star-nearest, star-second,
    nearest-second (angles from chords, accurate at small separations)."""

    def angle(a, b):
        return np.degrees(2.0 * np.arcsin(np.minimum(np.linalg.norm(a - b, axis=-1) / 2.0, 1.0)))

    return np.stack([angle(star, nearest), angle(star, second), angle(nearest, second)], axis=-1)


def noisy_three_sides(unit: np.ndarray, neighbours: np.ndarray, pixel_rad: float, sigmas_px: np.ndarray,
                      seed: int, stars: np.ndarray | None = None) -> np.ndarray:
    """Sides (m, k, 3) deg of stars ``stars`` (default all, m of them) measured with centroid noise ``sigmas_px``
    (k,) px per axis, one draw per sigma; ``neighbours`` (n, 2) from :func:`nearest_two`."""
    stars = np.arange(len(unit)) if stars is None else np.asarray(stars)
    sigmas = np.asarray(sigmas_px, dtype=np.float64)
    out = np.empty((len(stars), len(sigmas), 3))
    for row, i in enumerate(stars):
        rng = np.random.default_rng([seed, int(i)])
        centre = unit[i]
        east = np.cross([0.0, 0.0, 1.0], centre) if abs(centre[2]) < 0.9 else np.cross([1.0, 0.0, 0.0], centre)
        east /= np.linalg.norm(east)
        north = np.cross(centre, east)
        tri = unit[[i, *neighbours[i]]]  # (3, 3)
        depth = tri @ centre
        plane = np.stack([tri @ east, tri @ north], axis=1) / depth[:, None] / pixel_rad  # (3, 2) px
        noisy = plane[None] + rng.standard_normal((len(sigmas), 3, 2)) * sigmas[:, None, None]
        rays = (noisy[..., :1] * pixel_rad * east + noisy[..., 1:] * pixel_rad * north + centre)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        out[row] = three_sides(rays[:, 0], rays[:, 1], rays[:, 2])
    return out
