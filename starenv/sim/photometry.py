"""Photometry: photo-electrons from star magnitudes, the sky background and stray light.

A star of magnitude ``m`` delivers ``Phi0 * 10^(-0.4 m)`` photons per second per square metre of entrance pupil above
the optics, where ``Phi0`` is the zero-point flux of a magnitude-0 star integrated over the sensor's band.  The
default, 1.9e10 photons s^-1 m^-2, is the value commonly used in star-tracker design for a solar-type star over a
silicon detector's response; the catalog magnitudes are Hipparcos Hp, whose broad band (~340-890 nm) is close to a
silicon sensor's.  Electrons per second are that flux times the pupil area, the optics' transmission and the
detector's quantum efficiency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from starenv import checks

ZERO_POINT_PHOTONS_M2_S = 1.9e10


@dataclass(frozen=True)
class Photometry:
    """Throughput of one head: pupil diameter (m), optics transmission and quantum efficiency (0-1)."""

    aperture_m: float
    transmission: float = 0.8
    quantum_efficiency: float = 0.6
    zero_point_photons_m2_s: float = ZERO_POINT_PHOTONS_M2_S

    def __post_init__(self):
        checks.in_range("aperture_m", self.aperture_m, 0.0, 1.0, low_open=True, unit="m")
        checks.in_range("transmission", self.transmission, 0.0, 1.0, low_open=True)
        checks.in_range("quantum_efficiency", self.quantum_efficiency, 0.0, 1.0, low_open=True)
        checks.positive("zero_point_photons_m2_s", self.zero_point_photons_m2_s, "photons/s/m^2")

    @property
    def electrons_per_s_mag0(self) -> float:
        """Photo-electrons per second from a magnitude-0 star."""
        area = math.pi * (self.aperture_m / 2.0) ** 2
        return self.zero_point_photons_m2_s * area * self.transmission * self.quantum_efficiency

    def star_electrons_per_s(self, magnitude: np.ndarray) -> np.ndarray:
        """Photo-electrons per second collected from stars of the given magnitudes."""
        return self.electrons_per_s_mag0 * np.power(10.0, -0.4 * np.asarray(magnitude, dtype=np.float64))

    def sky_electrons_per_px_s(self, mag_per_arcsec2: float, pixel_solid_angle_arcsec2: float) -> float:
        """Photo-electrons per second per pixel from a diffuse sky of the given surface brightness (mag/arcsec^2)."""
        checks.in_range("sky_mag_per_arcsec2", mag_per_arcsec2, 10.0, 30.0, unit="mag/arcsec^2")
        return float(self.star_electrons_per_s(mag_per_arcsec2)) * pixel_solid_angle_arcsec2


@dataclass(frozen=True)
class StrayLight:
    """Glow from a bright source (Sun, Earth limb, Moon) just outside the field of view.

    The source direction is ``off_axis_deg`` from the boresight, towards image position angle ``position_angle_deg``
    (0 = +X, 90 = +Y).  The irradiance falls off as the inverse square of the distance, on the focal plane, from the
    source's pinhole image ``f tan(off_axis)`` away from the principal point; ``level_e_per_px_s`` is its value at the
    principal point.
    """

    level_e_per_px_s: float = 0.0
    off_axis_deg: float = 30.0
    position_angle_deg: float = 0.0

    def __post_init__(self):
        checks.non_negative("stray_light.level_e_per_px_s", self.level_e_per_px_s, "e-/px/s")
        checks.in_range("stray_light.off_axis_deg", self.off_axis_deg, 0.0, 85.0, low_open=True, unit="deg")
        checks.finite("stray_light.position_angle_deg", self.position_angle_deg, shape=())

    def map(self, width: int, height: int, fx: float, cx: float, cy: float) -> np.ndarray:
        """Stray-light rate per pixel, e-/px/s, float32 (height, width)."""
        d0 = fx * math.tan(math.radians(self.off_axis_deg))
        pa = math.radians(self.position_angle_deg)
        sx, sy = cx + d0 * math.cos(pa), cy + d0 * math.sin(pa)
        u = np.arange(width, dtype=np.float64)[None, :] - sx
        v = np.arange(height, dtype=np.float64)[:, None] - sy
        d2 = np.maximum(u * u + v * v, 1.0)
        return (self.level_e_per_px_s * d0 * d0 / d2).astype(np.float32)
