"""The sky beyond the stars: the Sun, the Moon, the Earth and the planets as a star sensor's heads see them.

Which effects a scenario simulates is its ``[sky]`` table (:class:`SkySpec`); each head's baffle is its
``[heads.baffle]`` table (:class:`Baffle`).  Positions come from :mod:`starenv.sim.ephemeris` (astrometric: where
each body was when its light left it), seen from the spacecraft: the geocentre, or the orbit's position when the
trajectory has one.  With ``aberration`` the bodies are aberrated as the stars are.

Brightness
    Magnitudes (V, used as the photometry's band like the catalogue's Hp): the Sun -26.74 at 1 au; the Moon
    ``0.23 + 5 log10(r D) + 0.026 i + 4e-9 i^4`` (Allen, *Astrophysical Quantities*; r, D the Moon's distances to the
    Sun and the observer in au, i its phase angle in deg); the planets ``a + 5 log10(r D) + b i + c i^2 + d i^3``
    (J. Meeus, *Astronomical Algorithms*, ch. 41; Saturn without its rings).  The sunlit Earth, seen from an orbit, is
    a Lambert sphere of ``earth_albedo``: its irradiance is ``(2/3) albedo E_sun sin^2(rho) phi(alpha)`` with ``rho``
    the Earth's angular radius, ``alpha`` the Sun-Earth-spacecraft angle and ``phi(a) = (sin a + (pi - a) cos a) / pi``.

In the field
    The Moon is a disk of its angular radius, lit where the Sun shines on the sphere (its phase), of uniform surface
    brightness carrying the magnitude's whole flux, integrated over each pixel on a ``MOON_SUBSAMPLES`` grid; a
    planet is a point source through the head's PSF.  Both are drawn at the head's mid-exposure (no smear) and add
    their expected electrons to the stars' before the noise; the detector's full well saturates them.  A body hidden
    by the Earth (from an orbit) is not drawn and sheds no stray light.

Stray light and blinding
    A source of photon irradiance ``E`` (from its magnitude and the photometry's zero point) at ``theta`` from a
    head's boresight puts ``PST(theta) E`` on the focal plane, ``PST`` the baffle's point-source transmittance (the
    optics' transmission included), so ``PST(theta) E pitch^2 QE`` e-/px/s, spread uniformly over the frame: the Sun
    and the Moon at their centre's angle, the Earth at its limb's.  A head whose boresight is within its baffle's
    exclusion angle of the Sun, the Moon or the Earth's limb is *blinded*: its frame is delivered (saturated or
    fogged, as the stray light makes it) and flagged in the observation (``blinded``) and the truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from starenv import checks
from starenv.sim import ephemeris
from starenv.sim.conventions import DEG
from starenv.sim.motion import R_EARTH
from starenv.sim.render import StarSignal, band_fractions

SUN_MAGNITUDE = -26.74  # V at 1 au
SUN_RADIUS_M = 6.957e8
MOON_RADIUS_M = 1.7374e6
# Meeus ch. 41: V = a + 5 log10(r D) + b i + c i^2 + d i^3, i the phase angle in degrees.
PLANET_MAGNITUDE = {"mercury": (-0.42, 0.0380, -0.000273, 0.000002), "venus": (-4.40, 0.0009, 0.000239, -0.00000065),
                    "mars": (-1.52, 0.016, 0.0, 0.0), "jupiter": (-9.40, 0.005, 0.0, 0.0),
                    "saturn": (-8.88, 0.044, 0.0, 0.0), "uranus": (-7.19, 0.0, 0.0, 0.0),
                    "neptune": (-6.87, 0.0, 0.0, 0.0)}
MOON_SUBSAMPLES = 4  # per pixel side: the disk's edge and terminator are integrated over 16 points a pixel
MAX_MOON_BOX_PX = 4096  # largest side of the box a Moon disk is sampled in (a long focal length's huge Moon)
EARTH_ALBEDO = 0.3

# A two-stage star-tracker baffle (a representative curve: veiling glare ~1e-3 for a source in a ~20 deg field, 1e-6
# at 20 deg, 1e-8 at a 30 deg Sun exclusion, 1e-10 beyond 60 deg); log-log interpolation between the points, held
# flat outside them.
DEFAULT_PST_ANGLES_DEG = (5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 90.0, 180.0)
DEFAULT_PST = (1e-3, 3e-4, 1e-4, 1e-6, 1e-8, 1e-9, 1e-10, 1e-11, 1e-11)


@dataclass(frozen=True)
class SkySpec:
    """A scenario's ``[sky]`` table.

    ``aberration``: stars (and bodies) at their apparent directions for the observer's velocity
    (:func:`starenv.sim.ephemeris.aberrate`); off, at their geometric directions and the observation's observer
    velocity is zero.  ``bodies``: the Sun, Moon, planets (and the Earth, from an orbit) drawn, shedding stray light
    and blinding heads.  ``earth_albedo``: the sunlit Earth's (Lambert) albedo."""

    aberration: bool = False
    bodies: bool = False
    earth_albedo: float = EARTH_ALBEDO

    def __post_init__(self):
        checks.in_range("earth_albedo", self.earth_albedo, 0.0, 1.0)


@dataclass(frozen=True)
class Baffle:
    """A head's ``[heads.baffle]``: the point-source transmittance ``pst`` (focal-plane over incident irradiance,
    in (0, 1]) at off-axis angles ``pst_angles_deg`` (increasing), not increasing with the angle; and the exclusion
    angles (deg) from the boresight to the Sun, the Earth's limb and the Moon within which the head is blinded (none
    for the Moon by default: a sensor tracks with the Moon in its field, its disk drawn and its stray light added)."""

    pst_angles_deg: tuple[float, ...] = DEFAULT_PST_ANGLES_DEG
    pst: tuple[float, ...] = DEFAULT_PST
    sun_exclusion_deg: float = 30.0
    earth_exclusion_deg: float = 20.0
    moon_exclusion_deg: float = 0.0

    def __post_init__(self):
        angles = checks.finite("pst_angles_deg", self.pst_angles_deg)
        values = checks.finite("pst", self.pst)
        if angles.ndim != 1 or len(angles) < 2 or values.shape != angles.shape:
            raise ValueError(f"pst must hold one value per angle of pst_angles_deg (at least two), got {len(values)} "
                             f"values for {len(angles)} angles")
        if not (np.all(np.diff(angles) > 0) and angles[0] > 0 and angles[-1] <= 180.0):
            raise ValueError(f"pst_angles_deg must increase within (0, 180] deg, got {angles.tolist()}")
        if not (np.all(values > 0) and np.all(values <= 1.0)):
            raise ValueError(f"pst must lie in (0, 1], got {values.tolist()}")
        if np.any(np.diff(values) > 0):
            raise ValueError(f"pst must not increase with the angle (a baffle attenuates more off axis), got "
                             f"{values.tolist()}")
        for name in ("sun_exclusion_deg", "earth_exclusion_deg", "moon_exclusion_deg"):
            checks.in_range(name, getattr(self, name), 0.0, 180.0, unit="deg")

    def transmittance(self, angle_rad) -> np.ndarray:
        """PST at off-axis angles ``angle_rad`` (rad): log-log interpolation, flat beyond the tabulated angles."""
        angle = np.maximum(np.asarray(angle_rad, dtype=np.float64) / DEG, 1e-6)
        return np.exp(np.interp(np.log(angle), np.log(self.pst_angles_deg), np.log(self.pst)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between unit vectors, stable at small angles."""
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=-1) / 2.0, 0.0, 1.0))


@dataclass
class BodiesNow:
    """The bodies seen from the spacecraft at one instant: names, unit directions (n, 3, ICRS axes, apparent when
    the stars are aberrated), distances (m), angular radii (rad), V magnitudes, whether the Earth hides each, and the
    unit vector from the Moon to the Sun.  With an orbit, the Earth's direction (None without), angular radius and
    irradiance at the spacecraft over the Sun's (``earth_to_sun``)."""

    names: tuple[str, ...]
    direction: np.ndarray
    distance_m: np.ndarray
    radius_rad: np.ndarray
    magnitude: np.ndarray
    hidden: np.ndarray
    moon_to_sun: np.ndarray
    earth_direction: np.ndarray | None = None
    earth_radius_rad: float = 0.0
    earth_to_sun: float = 0.0


@dataclass
class HeadBodies:
    """What the bodies do to one head's frame: their expected electrons on its pixels (flat indices, e-), the
    uniform stray light (e-/px/s) and the blinding; ``truth`` holds one row per body (``name``, ``xy_mid`` px
    distorted, NaN behind the camera, ``angle_deg`` from the boresight (the Earth's: its limb's), ``magnitude``,
    ``electrons`` on the sensor, ``in_field``)."""

    index: np.ndarray
    electrons: np.ndarray
    stray_e_per_px_s: float
    blinded: bool
    blinded_by: str
    truth: dict[str, np.ndarray] = field(default_factory=dict)


class SkyBodies:
    """The bodies of a scenario frame by frame: its ``epoch`` (Julian year), ``orbit`` (a
    :class:`~starenv.sim.motion.LeoNadir` or None: the geocentre), ``[sky]`` and, when the sky is aberrated, the
    observer's velocity (a callable of time, s -> m/s, ICRS axes)."""

    def __init__(self, epoch: float, orbit, sky: SkySpec, observer_velocity=None):
        self.epoch = epoch
        self.orbit = orbit
        self.sky = sky
        self.observer_velocity = observer_velocity
        self._cache: tuple[float, BodiesNow] | None = None

    def at(self, t_s: float) -> BodiesNow:
        """The bodies at ``t_s`` seconds after the epoch (the last instant asked for is cached)."""
        if self._cache is not None and self._cache[0] == t_s:
            return self._cache[1]
        positions = ephemeris.solar_system(ephemeris.julian_centuries(self.epoch, t_s))
        spacecraft = np.zeros(3) if self.orbit is None else self.orbit.position(t_s)
        names = ephemeris.BODY_NAMES
        geocentric = np.stack([positions[n] for n in names])
        seen = geocentric - spacecraft
        distance = np.linalg.norm(seen, axis=1)
        direction = seen / distance[:, None]
        radius = np.zeros(len(names))
        radius[0] = math.asin(SUN_RADIUS_M / distance[0])
        radius[1] = math.asin(MOON_RADIUS_M / distance[1])
        sun_geo = geocentric[0]
        heliocentric = geocentric - sun_geo  # the bodies' positions from the Sun (the Sun's own row is zero)
        au = ephemeris.AU_M
        magnitude = np.empty(len(names))
        magnitude[0] = SUN_MAGNITUDE + 5.0 * math.log10(distance[0] / au)
        for k, name in enumerate(names[1:], start=1):
            r = float(np.linalg.norm(heliocentric[k]))
            phase = math.degrees(_angle(_unit(-heliocentric[k]), _unit(-seen[k])))
            log_rd = 5.0 * math.log10(r * distance[k] / au**2)
            if name == "moon":
                magnitude[k] = 0.23 + log_rd + 0.026 * phase + 4e-9 * phase**4
            else:
                a, b, c, d = PLANET_MAGNITUDE[name]
                magnitude[k] = a + log_rd + b * phase + c * phase**2 + d * phase**3
        hidden = np.zeros(len(names), dtype=bool)
        now = BodiesNow(names, direction, distance, radius, magnitude, hidden, _unit(-heliocentric[1]))
        if self.orbit is not None:
            r_sc = float(np.linalg.norm(spacecraft))
            now.earth_direction = -spacecraft / r_sc
            now.earth_radius_rad = math.asin(min(1.0, R_EARTH / r_sc))
            # hidden: in front of the Earth's disk and beyond the spacecraft's horizon distance
            behind = _angle(direction, now.earth_direction) < now.earth_radius_rad
            now.hidden = behind & (distance > math.sqrt(max(r_sc**2 - R_EARTH**2, 0.0)))
            alpha = float(_angle(_unit(sun_geo), spacecraft / r_sc))
            lambert = (math.sin(alpha) + (math.pi - alpha) * math.cos(alpha)) / math.pi
            now.earth_to_sun = (2.0 / 3.0) * self.sky.earth_albedo * math.sin(now.earth_radius_rad) ** 2 * lambert
        if self.observer_velocity is not None:
            now.direction = ephemeris.aberrate(now.direction, self.observer_velocity(t_s))
        self._cache = (t_s, now)
        return now

    def head_view(self, head, camera, attitude, t_s: float, exposure_s: float) -> HeadBodies:
        """The bodies on head ``head`` (a :class:`~starenv.sim.sensor.HeadSpec`: photometry, baffle, PSF) through its
        true ``camera`` at the body ``attitude`` (ICRS -> body) of its mid-exposure ``t_s`` (s)."""
        now = self.at(t_s)
        to_camera = camera.inertial_to_camera(attitude)
        boresight = to_camera.inv().apply([0.0, 0.0, 1.0])
        baffle = head.baffle
        angle = _angle(now.direction, boresight)
        photometry = head.photometry
        pixel_e = camera.pixel_pitch_m**2 * photometry.quantum_efficiency
        photons = photometry.zero_point_photons_m2_s * np.power(10.0, -0.4 * now.magnitude)  # photons s^-1 m^-2
        stray = 0.0
        blinded_by = []
        for k, (name, exclusion) in enumerate((("sun", baffle.sun_exclusion_deg),
                                               ("moon", baffle.moon_exclusion_deg))):
            if now.hidden[k]:
                continue
            stray += float(baffle.transmittance(angle[k]) * photons[k]) * pixel_e
            if angle[k] < exclusion * DEG:
                blinded_by.append(name)
        names, angles, magnitudes = list(now.names), angle.copy(), now.magnitude.copy()
        if now.earth_direction is not None:
            limb = max(0.0, float(_angle(now.earth_direction, boresight)) - now.earth_radius_rad)
            stray += float(baffle.transmittance(limb)) * now.earth_to_sun * photons[0] * pixel_e
            if limb < baffle.earth_exclusion_deg * DEG:
                blinded_by.append("earth")
            names.append("earth")
            angles = np.append(angles, limb)
            magnitudes = np.append(magnitudes, np.nan)
        xy, _ = camera.project(to_camera.apply(now.direction))
        electrons = np.zeros(len(names))
        index_parts, value_parts = [], []
        field_radius = camera.half_diagonal
        for k, name in enumerate(now.names):
            if name == "sun" or now.hidden[k] or angle[k] > field_radius + now.radius_rad[k] + 0.01:
                continue
            total = float(photometry.star_electrons_per_s(now.magnitude[k])) * exposure_s
            if name == "moon":
                index, values, _ = moon_disk(camera, to_camera, now, total)
            else:
                index, values = _point_source(camera, xy[k], total, head.psf_sigma_px)
            index_parts.append(index)
            value_parts.append(values)
            electrons[k] = values.sum()
        truth = {
            "name": np.array(names),
            "xy_mid": np.vstack([xy, np.full((len(names) - len(xy), 2), np.nan)]),
            "angle_deg": angles / DEG,
            "magnitude": magnitudes,
            "electrons": electrons,
            "in_field": np.append(np.isfinite(xy).all(axis=1) & camera.in_frame(xy) & ~now.hidden,
                                  np.zeros(len(names) - len(xy), dtype=bool)),
        }
        index = np.concatenate(index_parts) if index_parts else np.zeros(0, np.int64)
        values = np.concatenate(value_parts) if value_parts else np.zeros(0)
        return HeadBodies(index, values, stray, bool(blinded_by), ",".join(blinded_by), truth)


def moon_disk(camera, to_camera, now: BodiesNow, total_e: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The lit Moon's expected electrons per pixel (flat indices, e-) through ``camera`` (ICRS -> camera rotation
    ``to_camera``): ``total_e`` spread uniformly over the lit part of the disk, sampled ``MOON_SUBSAMPLES`` x
    ``MOON_SUBSAMPLES`` per pixel; and the lit area (px^2, on and off the sensor).  Nothing if the disk misses the
    sensor or lies partly behind the camera."""
    centre = to_camera.apply(now.direction[1]) * now.distance_m[1]
    sun = to_camera.apply(now.moon_to_sun)
    # The disk's box: the limb's projection (a ring just outside the angular radius).
    axis = _unit(centre)
    side = _unit(np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0]))
    up = np.cross(axis, side)
    phi = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)[:, None]
    rim = axis + 1.05 * math.tan(now.radius_rad[1]) * (np.cos(phi) * side + np.sin(phi) * up)
    ring, front = camera.project(rim)
    if not front.all():
        return np.zeros(0, np.int64), np.zeros(0), 0.0
    lo = np.floor(ring.min(axis=0)).astype(int)
    hi = np.ceil(ring.max(axis=0)).astype(int)
    off_sensor = hi[0] < 0 or hi[1] < 0 or lo[0] >= camera.width or lo[1] >= camera.height
    if np.any(hi - lo > MAX_MOON_BOX_PX) or off_sensor:
        return np.zeros(0, np.int64), np.zeros(0), 0.0
    cols, rows = np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1)
    offsets = (np.arange(MOON_SUBSAMPLES) + 0.5) / MOON_SUBSAMPLES - 0.5
    sx = (cols[:, None] + offsets[None, :]).ravel()
    sy = (rows[:, None] + offsets[None, :]).ravel()
    grid = np.stack(np.meshgrid(sx, sy), axis=-1).reshape(-1, 2)
    rays = camera.unproject(grid)
    # Ray-sphere: the nearest hit of u t on |P - C| = R, lit where the outward normal faces the Sun.
    b = rays @ centre
    disc = b**2 - (centre @ centre - MOON_RADIUS_M**2)
    hit = disc >= 0.0
    t_hit = b - np.sqrt(np.where(hit, disc, 0.0))
    normal = rays * t_hit[:, None] - centre
    lit = hit & (normal @ sun > 0.0)
    n_lit = int(lit.sum())
    if n_lit == 0:
        return np.zeros(0, np.int64), np.zeros(0), 0.0
    per_pixel = lit.reshape(len(rows), MOON_SUBSAMPLES, len(cols), MOON_SUBSAMPLES).sum(axis=(1, 3))
    values = per_pixel * (total_e / n_lit)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    keep = (per_pixel > 0) & (rr >= 0) & (rr < camera.height) & (cc >= 0) & (cc < camera.width)
    return (rr[keep] * camera.width + cc[keep]).astype(np.int64), values[keep], n_lit / MOON_SUBSAMPLES**2


def _point_source(camera, xy: np.ndarray, total_e: float, psf_sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """A point source's expected electrons per pixel (flat indices, e-) through the renderer's pixel-integrated
    Gaussian PSF at ``xy`` (px)."""
    band, frac = band_fractions(np.asarray(xy, dtype=np.float64).reshape(1, 2), psf_sigma_px)
    n_band = frac.shape[-1]
    cols = band[0, 0] + np.arange(n_band)
    rows = band[0, 1] + np.arange(n_band)
    values = total_e * frac[0, 1][:, None] * frac[0, 0][None, :]
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    keep = (rr >= 0) & (rr < camera.height) & (cc >= 0) & (cc < camera.width)
    return (rr[keep] * camera.width + cc[keep]).astype(np.int64), values[keep]


def add_signal(signal, index: np.ndarray, electrons: np.ndarray):
    """The star signal (:class:`~starenv.sim.render.StarSignal`) with ``electrons`` added on the flat pixel
    ``index`` (repeats summed)."""
    if len(index) == 0:
        return signal
    merged, inverse = np.unique(np.concatenate([signal.index, index]), return_inverse=True)
    values = np.bincount(inverse, np.concatenate([signal.electrons.astype(np.float64), electrons]), len(merged))
    return StarSignal(merged, values.astype(np.float32), signal.shape)


def body_directions(scenario):
    """For a scenario that draws the bodies (``[sky] bodies``): a callable of time (s after the epoch) giving the
    bodies' names and unit directions (n, 3, ICRS axes) seen from the spacecraft, the Earth's centre included from an
    orbit and the bodies the Earth hides left out; None for any other scenario."""
    if not scenario.sky.bodies:
        return None
    sky = SkyBodies(scenario.epoch, scenario.trajectory.orbit, scenario.sky)

    def directions(t_s: float) -> tuple[list[str], np.ndarray]:
        now = sky.at(t_s)
        names = [n for n, hidden in zip(now.names, now.hidden, strict=True) if not hidden]
        unit = now.direction[~now.hidden]
        if now.earth_direction is not None:
            names.append("earth")
            unit = np.vstack([unit, now.earth_direction])
        return names, unit

    return directions
