"""The solar system as a star sensor sees it: the Sun, Moon and planets from maintained ephemeris libraries, and
stellar aberration, in numpy.

Time
    A scenario's ``epoch`` (Julian year, TT: ``JD = 2451545.0 + 365.25 (epoch - 2000)``) is the instant of simulation
    time ``t = 0``; frame times are seconds after it, and functions take Julian centuries of TT from J2000.0
    (:func:`julian_centuries`).  The difference between TT and TDB (< 2 ms) is neglected.

Frames
    Every vector is in ICRS axes (the GCRS has the same axes): positions in m, velocities in m/s.  The libraries'
    J2000 mean equator differs from the ICRS by the frame bias (~0.02 arcsec), neglected.

The Earth and the Sun
    The IAU SOFA routine ``epv00`` (through ERFA, the ``pyerfa`` package): the geocentre's heliocentric and
    barycentric position and velocity, within a few km and 1e-2 m/s of DE405 over 1900-2100
    (:data:`EPHEMERIS_YEARS`).

The Moon
    ERFA's ``moon98`` (J. Meeus' full ELP-2000/82 series, *Astronomical Algorithms* ch. 47): geocentric, within 18
    arcsec of ELP/MPP02 over 1950-2100 (2.9 arcsec rms), against a disk ~1900 arcsec across.

The planets
    The ``ephem`` package (libastro: VSOP87, and for Jupiter to Neptune Chapront's 1995 series over 1945-2260):
    astrometric geocentric positions, arcsecond-level.  ERFA's ``plan94`` (Simon et al. 1994) is lighter but quotes
    up to 80 arcsec in Jupiter's and Saturn's heliocentric longitude, more than their disks.

Light time
    Every body is where it was when the light left it: the astrometric position ``B(t - tau) - E(t)`` (barycentric
    body ``B`` and geocentre ``E``), ``tau`` its distance over c; for the Moon this moves it by ``v_earth tau`` (~20
    arcsec), which the stars' aberration then cancels.

Aberration
    :func:`aberrate` gives the apparent direction of a star for an observer of velocity ``v`` (relativistic: the
    direction ``p`` becomes ``p / gamma + beta + gamma / (1 + gamma) (p . beta) beta``, normalised; IERS Conventions
    2010, the form of SOFA's ``iauAb`` without its solar-potential term, which is below 1e-11 rad).  Gravitational
    deflection of light by the Sun, ``4.07 mas cot(E / 2)`` at elongation E from the Sun, is neglected: 4 mas at 90
    degrees, 0.05 arcsec at 10 degrees, 1.75 arcsec at the Sun's limb.

``tests/test_ephemeris.py`` and ``tests/test_bodies.py`` check each part against astropy and against JPL's DE421;
``docs/physics.md`` lists the figures.
"""

from __future__ import annotations

import math
import warnings

import ephem
import erfa
import numpy as np

from starenv import checks

J2000_JD = 2451545.0
DAY_S = 86400.0
JULIAN_CENTURY_DAYS = 36525.0
EPHEMERIS_YEARS = (1900.0, 2100.0)  # Julian years epv00 is valid over
AU_M = 149597870700.0
C_M_S = 299792458.0
DUBLIN_JD = 2415020.0  # ephem's dates are Julian days from this one (UT)
# ephem's planets; its Body.compute takes UT, the TT instant less ephem's own delta T.
EPHEM_PLANETS = {"mercury": ephem.Mercury, "venus": ephem.Venus, "mars": ephem.Mars, "jupiter": ephem.Jupiter,
                 "saturn": ephem.Saturn, "uranus": ephem.Uranus, "neptune": ephem.Neptune}


def julian_centuries(epoch: float, t_s) -> np.ndarray:
    """Julian centuries of TT from J2000.0 at ``t_s`` seconds after the Julian-year ``epoch``."""
    return (epoch - 2000.0) / 100.0 + np.asarray(t_s, dtype=np.float64) / (DAY_S * JULIAN_CENTURY_DAYS)


def check_epoch(key: str, epoch: float, duration_s: float = 0.0) -> float:
    """``epoch`` (Julian year) if the span ``[epoch, epoch + duration_s]`` lies within :data:`EPHEMERIS_YEARS`, else
    a ``ValueError`` naming ``key``."""
    low, high = EPHEMERIS_YEARS
    end = epoch + duration_s / (DAY_S * 365.25)
    if not (low <= epoch and end <= high):
        raise ValueError(f"{key}: expected an epoch (and epoch + duration) within the ephemeris' range "
                         f"{low:g}-{high:g} (Julian years), got {epoch:g}" + (f" to {end:.6g}" if duration_s else ""))
    return epoch


def _days(T) -> np.ndarray:
    """Days of TT from J2000.0 at ``T`` Julian centuries (ERFA's second date part, J2000 the first)."""
    return np.asarray(T, dtype=np.float64) * JULIAN_CENTURY_DAYS


def _earth(days) -> tuple[np.ndarray, np.ndarray]:
    """epv00: the geocentre's heliocentric and barycentric (position au, velocity au/d), each a (..., 2, 3) array."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", erfa.ErfaWarning)  # "dubious year" outside 1900-2100: check_epoch's job
        heliocentric, barycentric = erfa.epv00(J2000_JD, days)
    return (np.stack([heliocentric["p"], heliocentric["v"]], axis=-2),
            np.stack([barycentric["p"], barycentric["v"]], axis=-2))


def _planet_astrometric(name: str, days: np.ndarray) -> np.ndarray:
    """ephem's astrometric geocentric position (au, ICRS axes), (..., 3), of planet ``name`` at TT ``days``."""
    body = EPHEM_PLANETS[name]()
    out = np.empty((*days.shape, 3))
    for index, day in np.ndenumerate(days):
        tt = float(day) + J2000_JD - DUBLIN_JD
        body.compute(ephem.Date(tt - ephem.delta_t(ephem.Date(tt)) / DAY_S), epoch=ephem.J2000)
        ra, dec, distance = float(body.a_ra), float(body.a_dec), float(body.earth_distance)
        out[index] = distance * np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    return out


BODY_NAMES = ("sun", "moon", "mercury", "venus", "mars", "jupiter", "saturn", "uranus", "neptune")


def solar_system(T) -> dict[str, np.ndarray]:
    """Astrometric geocentric positions (m, ICRS axes), each (..., 3), of every body of :data:`BODY_NAMES` at ``T``
    Julian centuries of TT from J2000 (light time included, aberration not), and under ``"earth_barycentric"`` the
    geocentre's barycentric position."""
    days = _days(T)
    earth_helio, earth_bary = _earth(days)
    c_au_d = C_M_S * DAY_S / AU_M
    # the Sun: B(t - tau) - E(t), tau = |E - S| / c; the Sun's own barycentric motion over tau (~10 km) is kept
    sun_tau = np.linalg.norm(earth_helio[..., 0, :], axis=-1) / c_au_d
    helio_then, bary_then = _earth(days - sun_tau)
    sun = bary_then[..., 0, :] - helio_then[..., 0, :] - earth_bary[..., 0, :]
    moon_now = erfa.moon98(J2000_JD, days)["p"]
    moon_tau = np.linalg.norm(moon_now, axis=-1) / c_au_d
    earth_then = earth_bary[..., 0, :] - earth_bary[..., 1, :] * moon_tau[..., None]  # 1.3 s: linear in time
    moon = erfa.moon98(J2000_JD, days - moon_tau)["p"] + earth_then - earth_bary[..., 0, :]
    out = {"sun": sun * AU_M, "moon": moon * AU_M}
    for name in EPHEM_PLANETS:
        out[name] = _planet_astrometric(name, days) * AU_M
    out["earth_barycentric"] = earth_bary[..., 0, :] * AU_M
    return out


def earth_barycentric(T) -> np.ndarray:
    """Barycentric position of the geocentre (m, ICRS axes), shape (..., 3)."""
    return _earth(_days(T))[1][..., 0, :] * AU_M


def body_geocentric(name: str, T) -> np.ndarray:
    """Astrometric geocentric position (m, ICRS axes), shape (..., 3), of a body of :data:`BODY_NAMES`."""
    return solar_system(T)[name]


def earth_velocity(T) -> np.ndarray:
    """Barycentric velocity of the geocentre (m/s, ICRS axes), shape (..., 3)."""
    return _earth(_days(T))[1][..., 1, :] * (AU_M / DAY_S)


def aberrate(directions: np.ndarray, velocity_m_s) -> np.ndarray:
    """Apparent unit directions (n, 3) of sources at ``directions`` (n, 3, unit vectors, the frame at rest) seen by
    an observer moving at ``velocity_m_s`` (3,) m/s in that frame (special-relativistic aberration)."""
    beta = np.asarray(velocity_m_s, dtype=np.float64) / C_M_S
    beta2 = float(beta @ beta)
    if not beta2 < 1.0:
        raise ValueError(f"velocity_m_s must be slower than light, got {np.sqrt(beta2) * C_M_S:g} m/s")
    inv_gamma = np.sqrt(1.0 - beta2)
    p = np.asarray(directions, dtype=np.float64)
    p_beta = p @ beta
    out = p * inv_gamma + (1.0 + p_beta / (1.0 + inv_gamma))[..., None] * beta
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def observer_velocity(epoch: float, t_s, orbit_velocity=None) -> np.ndarray:
    """The observer's barycentric velocity (m/s, ICRS axes) at ``t_s`` seconds after ``epoch``: the Earth's plus
    ``orbit_velocity`` (a callable of ``t_s`` giving the geocentric velocity, m/s), if any, added as vectors (the
    relativistic composition differs by ``v1 v2 / c^2`` ~ 1e-8 of the speed)."""
    velocity = earth_velocity(julian_centuries(epoch, checks.finite("t_s", t_s)))
    return velocity if orbit_velocity is None else velocity + orbit_velocity(t_s)


class ObserverVelocity:
    """:func:`observer_velocity` as a callable of time (s after ``epoch``) for one scenario (``orbit_velocity``: the
    orbit's geocentric velocity, a callable of time, or None), remembering the last instants asked for (a frame's
    heads, the frame itself and its bodies ask for the same ones).  Returns read-only (3,) arrays, m/s."""

    REMEMBERED = 8

    def __init__(self, epoch: float, orbit_velocity=None):
        self.epoch = epoch
        self.orbit_velocity = orbit_velocity
        self._known: dict[float, np.ndarray] = {}

    def __call__(self, t_s: float) -> np.ndarray:
        t_s = float(t_s)
        velocity = self._known.get(t_s)
        if velocity is None:
            velocity = observer_velocity(self.epoch, t_s, self.orbit_velocity)
            velocity.flags.writeable = False
            if len(self._known) >= self.REMEMBERED:
                self._known.pop(next(iter(self._known)))
            self._known[t_s] = velocity
        return velocity
