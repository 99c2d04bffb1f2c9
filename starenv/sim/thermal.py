"""A head's temperature along the run and what follows from it: dark current, focal length and distortion.

The sensor temperature is fixed or a schedule (piecewise linear between ``(time, temperature)`` points, held
constant before the first and after the last).  Dark current (the detector's uniform rate, its hot pixels and its
DSNU pattern alike) doubles every ``dark_doubling_c`` deg C above ``reference_c``, the temperature at which the
detector's rates, the camera's focal length and its distortion are given: ``D(T) = D_ref 2^((T - T_ref) / N)``.  The
optics follow the same temperature: the focal length scales by ``1 + focal_length_ppm_per_c 1e-6 (T - T_ref)`` and a
distortion ``distortion_per_c`` is added ``(T - T_ref)`` times (:class:`ScaledDistortion`), so a camera calibrated at
``T_ref`` drifts away from its calibration as the run warms or cools it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from starenv import checks
from starenv.sim.optics import Camera, Composite, Distortion

# Temperatures are deg C; above this a value is taken for kelvin given by mistake (no star sensor runs at 150 C).
MAX_TEMPERATURE_C = 150.0
MIN_TEMPERATURE_C = -150.0


def check_temperature_c(name: str, value) -> float:
    """A temperature in deg C, refused (naming ``name``) outside [-150, 150]: above, it reads as kelvin."""
    v = float(checks.finite(name, value, shape=()))
    if v > MAX_TEMPERATURE_C:
        raise ValueError(f"{name} must be in deg C, at most {MAX_TEMPERATURE_C:g}, got {v:g} (kelvin? "
                         f"{v:g} K is {v - 273.15:.2f} C)")
    if v < MIN_TEMPERATURE_C:
        raise ValueError(f"{name} must be in deg C, at least {MIN_TEMPERATURE_C:g}, got {v:g}")
    return v


@dataclass(frozen=True)
class ScaledDistortion(Distortion):
    """``model``'s offset times ``factor``: ``p + factor (model.distort(p) - p)``."""

    model: Distortion
    factor: float

    def distort(self, xy, k):
        xy = np.asarray(xy, dtype=np.float64)
        return xy + self.factor * (self.model.distort(xy, k) - xy)


@dataclass(frozen=True)
class Thermal:
    """A head's temperature schedule (``times_s`` s, ``temperatures_c`` deg C, one point for a fixed temperature)
    and its effects (module docstring)."""

    times_s: tuple[float, ...] = (0.0,)
    temperatures_c: tuple[float, ...] = (20.0,)
    reference_c: float = 20.0
    dark_doubling_c: float = 6.0
    focal_length_ppm_per_c: float = 0.0
    distortion_per_c: Distortion | None = None

    def __post_init__(self):
        times = checks.finite("thermal.times_s", self.times_s)
        temps = checks.finite("thermal.temperatures_c", self.temperatures_c)
        if times.ndim != 1 or len(times) == 0 or times.shape != temps.shape:
            raise ValueError(f"thermal.times_s and temperatures_c must be lists of the same length >= 1, got "
                             f"{times.shape} and {temps.shape}")
        if np.any(np.diff(times) <= 0):
            raise ValueError(f"thermal.times_s must increase, got {times.tolist()}")
        for i, t in enumerate(temps):
            check_temperature_c(f"thermal.temperatures_c[{i}]", t)
        check_temperature_c("thermal.reference_c", self.reference_c)
        checks.in_range("thermal.dark_doubling_c", self.dark_doubling_c, 0.5, 100.0, unit="deg C")
        checks.in_range("thermal.focal_length_ppm_per_c", self.focal_length_ppm_per_c, -1000.0, 1000.0, unit="ppm/C")
        if self.distortion_per_c is not None and not isinstance(self.distortion_per_c, Distortion):
            raise ValueError("thermal.distortion_per_c must be a Distortion model or None")
        object.__setattr__(self, "times_s", tuple(float(t) for t in times))
        object.__setattr__(self, "temperatures_c", tuple(float(t) for t in temps))

    def temperature_c(self, t: float) -> float:
        """Sensor temperature (deg C) at time ``t`` (s)."""
        return float(np.interp(t, self.times_s, self.temperatures_c))

    def dark_factor(self, t: float) -> float:
        """Dark current at ``t`` over its value at ``reference_c``: ``2^((T - T_ref) / N)``."""
        return 2.0 ** ((self.temperature_c(t) - self.reference_c) / self.dark_doubling_c)

    @property
    def moves_optics(self) -> bool:
        """Whether the temperature changes the camera (focal length or distortion)."""
        return self.focal_length_ppm_per_c != 0.0 or self.distortion_per_c is not None

    def camera(self, camera: Camera, t: float) -> Camera:
        """``camera`` (as at ``reference_c``) at the temperature of time ``t``: focal length scaled, the
        temperature's distortion applied after its own."""
        delta = self.temperature_c(t) - self.reference_c
        if not self.moves_optics or delta == 0.0:
            return camera
        scale = 1.0 + self.focal_length_ppm_per_c * 1e-6 * delta
        distortion = camera.distortion
        if self.distortion_per_c is not None:
            distortion = Composite((distortion, ScaledDistortion(self.distortion_per_c, delta)))
        return dataclasses.replace(camera, fx=camera.fx * scale, fy=camera.fy * scale, distortion=distortion)

