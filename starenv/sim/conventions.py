"""Frames, rotations and units: the conventions every module shares.

* Attitude ``A`` is the rotation from the inertial frame (ICRS/J2000) to the body frame: ``v_body = A.apply(v_icrs)``.
  It is a :class:`scipy.spatial.transform.Rotation`; quaternions cross API edges scalar-last ``[x, y, z, w]``.
* Body angular rate ``w`` (rad/s) is expressed in the body frame.  Kinematics: ``dA/dt = -[w x] A``, so over a short
  step ``A(t + dt) = Rotation.from_rotvec(-w dt) * A(t)``.
* Each camera head has a fixed body -> camera mounting rotation ``M``; inertial -> camera is ``M * A``.
* Camera frame: +Z along the boresight out of the lens, +X along image columns (right), +Y along image rows (down).
  Pixel centres sit at integer coordinates; (0, 0) is the centre of the top-left pixel.
* SI units and radians inside.  Time in float64 seconds inside, integer nanoseconds in recordings.
* Exposure: row ``r`` of a frame opening at ``t_start`` integrates over ``[t_start + r * line_time_s, ... +
  exposure_s]`` (:func:`row_window`): a rolling shutter, a global one with ``line_time_s = 0``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0
DEG = np.pi / 180.0
ARCSEC = DEG / 3600.0


def skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[w x]`` of a 3-vector (or stack of them, shape (..., 3, 3))."""
    w = np.asarray(w, dtype=np.float64)
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def radec_to_unit(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    """ICRS unit vectors (..., 3) from right ascension and declination in radians."""
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def unit_to_radec(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right ascension in [0, 2 pi) and declination (radians) of unit vectors (..., 3)."""
    v = np.asarray(v, dtype=np.float64)
    ra = np.mod(np.arctan2(v[..., 1], v[..., 0]), 2 * np.pi)
    dec = np.arcsin(np.clip(v[..., 2], -1.0, 1.0))
    return ra, dec


def pointing(ra: float, dec: float, roll: float) -> Rotation:
    """Inertial -> camera rotation whose +Z (boresight) looks at (ra, dec), radians.

    At zero roll the image +Y axis (rows, down) points towards the celestial south pole projected on the image, so
    north is up.  Positive roll turns the camera about its boresight by ``roll`` (right-handed about +Z): the sky then
    appears rotated by ``-roll`` in the image.
    """
    z = radec_to_unit(np.asarray(ra), np.asarray(dec))
    north = np.array([0.0, 0.0, 1.0])
    east = np.cross(north, z)
    if np.linalg.norm(east) < 1e-12:  # boresight at a pole: pick RA = 0 direction as "east" reference
        east = np.array([-np.sin(ra), np.cos(ra), 0.0])
    east /= np.linalg.norm(east)
    up = np.cross(z, east)  # towards the north pole
    # Rows of the inertial -> camera matrix are the camera axes in inertial coordinates.
    # North up and +X to the right means east lies to the left, as on the sky seen from inside the sphere.
    x_cam, y_cam = -east, -up
    cam0 = Rotation.from_matrix(np.stack([x_cam, y_cam, z]))
    return Rotation.from_rotvec([0.0, 0.0, -roll]) * cam0 if roll else cam0


def angle_between(a: Rotation, b: Rotation) -> np.ndarray:
    """Angle (rad) of ``a * b^-1``: the attitude error between two rotations."""
    return (a * b.inv()).magnitude()


def row_window(t_start, exposure_s: float, line_time_s: float = 0.0, row=0.0) -> tuple:
    """Exposure window of an image row.

    Parameters
    ----------
    t_start : float or ndarray
        When the frame's first row (row 0, the top) opens its exposure (s).
    exposure_s : float
        How long each row integrates (s).
    line_time_s : float
        Delay between the openings of consecutive rows (s): a rolling shutter; 0 a global shutter.
    row : float or ndarray
        The row (0 .. height - 1, fractional for a position between rows).

    Returns
    -------
    opens, closes : float or ndarray
        The row's window ``[t_start + row * line_time_s, ... + exposure_s]`` (s), broadcast over the arguments.
        The frame's span, first row opening to last row closing, is :func:`frame_span_s`.
    """
    opens = t_start + row * line_time_s
    return opens, opens + exposure_s


def frame_span_s(exposure_s: float, line_time_s: float, height: int) -> float:
    """Time (s) from the first row's opening to the last row's closing, ``exposure_s + line_time_s * (height - 1)``:
    :func:`row_window` of row ``height - 1`` of a frame opening at 0."""
    return row_window(0.0, exposure_s, line_time_s, height - 1)[1]
