"""The figures of docs/physics.md: the ephemeris against JPL's DE421 and astropy, and the aberration against astropy
(SOFA), over many epochs; ``--literals`` prints the DE421 values typed into tests/test_bodies.py and
tests/test_ephemeris.py.

    python docs/physics_checks.py [--literals]
        (needs astropy, jplephem and JPL's DE421: pip install "starenv[fits]" jplephem de421)
"""

from __future__ import annotations

import argparse
import warnings

import de421
import numpy as np
from astropy import units as u
from astropy.coordinates import GCRS, ICRS, CartesianRepresentation, SkyCoord, get_body
from astropy.time import Time
from jplephem.ephem import Ephemeris

from starenv.sim import ephemeris
from starenv.sim.conventions import ARCSEC_PER_RAD

warnings.simplefilter("ignore")  # ERFA's "dubious year" outside the leap-second table

DE421 = Ephemeris(de421)
DE421_YEARS = (1900.5, 2049.5)  # within the kernel's span, light time included
KM_PER_AU = ephemeris.AU_M / 1000.0
LITERAL_YEARS = (1910.3, 1955.7, 1987.2, 2003.9, 2026.0, 2044.6)


def angle_arcsec(a, b):
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=-1) / 2.0, 0, 1)) * ARCSEC_PER_RAD


def de421_barycentric(name: str, jd: np.ndarray) -> np.ndarray:
    """DE421 barycentric position (km, ICRF), (3, n), of the geocentre (``earth``), the Moon, the Sun or a planet
    (the system's barycentre) at TT (TDB) Julian dates ``jd``."""
    if name in ("earth", "moon"):
        moon = DE421.position("moon", jd)
        earth = DE421.position("earthmoon", jd) - moon / (1.0 + DE421.EMRAT)
        return earth if name == "earth" else earth + moon
    return DE421.position(name, jd)


def de421_astrometric(name: str, jd: np.ndarray) -> np.ndarray:
    """DE421 astrometric geocentric position (au, ICRF), (n, 3): ``B(t - tau) - E(t)``, three light-time steps."""
    earth = de421_barycentric("earth", jd)
    body = de421_barycentric(name, jd)
    for _ in range(3):
        tau_days = np.linalg.norm(body - earth, axis=0) * 1000.0 / ephemeris.C_M_S / ephemeris.DAY_S
        body = de421_barycentric(name, jd - tau_days)
    return ((body - earth) / KM_PER_AU).T


def de421_earth_velocity(jd: np.ndarray) -> np.ndarray:
    """DE421 barycentric velocity of the geocentre (m/s, ICRF), (n, 3)."""
    _, emb = DE421.position_and_velocity("earthmoon", jd)
    _, moon = DE421.position_and_velocity("moon", jd)
    return ((emb - moon / (1.0 + DE421.EMRAT)) * 1000.0 / ephemeris.DAY_S).T  # km/day -> m/s


def print_literals() -> None:
    jd = ephemeris.J2000_JD + (np.array(LITERAL_YEARS) - 2000.0) * 365.25
    print(f"DE421_YEARS = {LITERAL_YEARS}")
    for name in ephemeris.BODY_NAMES:
        p = de421_astrometric(name, jd)
        r = np.linalg.norm(p, axis=1)
        ra, dec = np.degrees(np.arctan2(p[:, 1], p[:, 0])) % 360.0, np.degrees(np.arcsin(p[:, 2] / r))
        print(f'    "{name}": (' + ", ".join(f"({a:.6f}, {d:.6f}, {x:.9f})" for a, d, x in zip(ra, dec, r, strict=True))
              + "),")
    v = de421_earth_velocity(jd)
    print("DE421_EARTH_VELOCITY = (" + ", ".join(f"({a:.3f}, {b:.3f}, {c:.3f})" for a, b, c in v) + ")")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--literals", action="store_true", help="print the tests' DE421 literals and stop")
    if parser.parse_args().literals:
        print_literals()
        return
    rng = np.random.default_rng(0)
    years = rng.uniform(*DE421_YEARS, 300)
    jd = ephemeris.J2000_JD + (years - 2000.0) * 365.25
    T = (years - 2000.0) / 100.0
    reference = de421_earth_velocity(jd)
    error = np.linalg.norm(ephemeris.earth_velocity(T) - reference, axis=1)
    print(f"Earth barycentric velocity vs DE421, {len(years)} epochs {DE421_YEARS[0]:g}-{DE421_YEARS[1]:g}: max "
          f"{error.max() * 1000:.1f} mm/s")

    worst = 0.0
    for year in rng.uniform(*ephemeris.EPHEMERIS_YEARS, 20):
        d = rng.normal(size=(300, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        sun = ephemeris.body_geocentric("sun", (year - 2000.0) / 100.0)
        d = d[d @ (sun / np.linalg.norm(sun)) < np.cos(np.radians(20.0))]
        ours = ephemeris.aberrate(d, ephemeris.observer_velocity(year, 0.0))
        time = Time(ephemeris.J2000_JD + (year - 2000.0) * 365.25, format="jd", scale="tt")
        gcrs = SkyCoord(CartesianRepresentation(*d.T), frame=ICRS()).transform_to(GCRS(obstime=time))
        worst = max(worst, float(angle_arcsec(ours, gcrs.cartesian.xyz.value.T).max()))
    print(f"apparent directions vs astropy ICRS -> GCRS (20 epochs 1900-2100, directions >= 20 deg from the Sun): max "
          f"{worst * 1000:.1f} mas")

    n_body = 200
    ours = ephemeris.solar_system(T[:n_body])
    velocity = ephemeris.earth_velocity(T[:n_body])
    time = Time(jd[:n_body], format="jd", scale="tt")
    print(f"body        vs DE421 astrometric: max / rms (arcsec), max |dr| / r   vs astropy get_body (apparent "
          f"GCRS): max (arcsec); {n_body} epochs {DE421_YEARS[0]:g}-{DE421_YEARS[1]:g}")
    for name in ephemeris.BODY_NAMES:
        reference = de421_astrometric(name, jd[:n_body]) * ephemeris.AU_M
        error = angle_arcsec(ours[name], reference)
        distance = np.abs(np.linalg.norm(ours[name], axis=1) / np.linalg.norm(reference, axis=1) - 1.0).max()
        unit = ours[name] / np.linalg.norm(ours[name], axis=1, keepdims=True)
        apparent = np.stack([ephemeris.aberrate(p[None], v)[0] for p, v in zip(unit, velocity, strict=True)])
        astropy_error = angle_arcsec(apparent, get_body(name, time).cartesian.xyz.to(u.m).value.T)
        print(f"{name:12s} {error.max():8.2f} / {np.sqrt(np.mean(error**2)):5.2f} {distance:10.1e} "
              f"{astropy_error.max():30.2f}")


if __name__ == "__main__":
    main()
