"""Centroid sets with truth ids: the stars a multi-head sensor sees at an attitude, as an ideal detector with
Gaussian centroid noise would report them (paper 004's simulation; no image is rendered).

Every catalogue star in front of a head that projects onto its sensor is kept, at its (distorted) pixel position plus
``N(0, noise_px)`` per axis; its flux is ``10^(-0.4 mag)`` (relative), so brightness ranks follow magnitudes.
Options add what a real detector does: ``false_stars`` spurious detections per head at uniform positions with the
faintest star's flux, ``drop_fraction`` of the stars missing, ``mag_noise`` (mag, Gaussian) on the fluxes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog


@dataclass
class CentroidSet:
    """Per head: positions (n, 2) px, relative fluxes (n,) and truth HIP numbers (n,; -1 for a false star)."""

    xy: list[np.ndarray]
    flux: list[np.ndarray]
    hip: list[np.ndarray]


def random_attitude(rng: np.random.Generator) -> Rotation:
    """An attitude drawn uniformly on SO(3)."""
    q = rng.standard_normal(4)
    return Rotation.from_quat(q / np.linalg.norm(q))


def centroid_set(catalog: StarCatalog, cameras: list[Camera], attitude: Rotation, noise_px: float,
                 rng: np.random.Generator, false_stars: int = 0, drop_fraction: float = 0.0,
                 mag_noise: float = 0.0) -> CentroidSet:
    """The stars of ``catalog`` each head of ``cameras`` sees at ``attitude`` (inertial -> body), module docstring."""
    xy_all, flux_all, hip_all = [], [], []
    for cam in cameras:
        axis = cam.inertial_to_camera(attitude).inv().apply([0.0, 0.0, 1.0])
        rows = catalog.cone(axis, cam.half_diagonal * 1.01)
        xy, front = cam.project(cam.inertial_to_camera(attitude).apply(catalog.unit[rows]))
        on = front & cam.in_frame(np.nan_to_num(xy, nan=-1e9))
        rows, xy = rows[on], xy[on] + rng.normal(0.0, noise_px, (np.count_nonzero(on), 2))
        mag = catalog.magnitude[rows] + (rng.normal(0.0, mag_noise, len(rows)) if mag_noise > 0 else 0.0)
        flux, hip = 10.0 ** (-0.4 * mag), catalog.hip[rows]
        if drop_fraction > 0:
            keep = rng.random(len(rows)) >= drop_fraction
            xy, flux, hip = xy[keep], flux[keep], hip[keep]
        if false_stars:
            fake = rng.uniform([0.0, 0.0], [cam.width - 1.0, cam.height - 1.0], (false_stars, 2))
            faint = flux.min() if len(flux) else 1.0
            xy, flux = np.vstack([xy, fake]), np.concatenate([flux, np.full(false_stars, faint)])
            hip = np.concatenate([hip, np.full(false_stars, -1)])
        xy_all.append(xy)
        flux_all.append(flux)
        hip_all.append(hip)
    return CentroidSet(xy_all, flux_all, hip_all)
