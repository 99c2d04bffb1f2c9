"""Raw frames out for star-tracker and astronomy tools: 16-bit FITS with a truth WCS, and npz with the frame's truth.

FITS (``write_fits``, needs astropy: ``pip install "starenv[fits]"``): one image HDU per head (the primary is head 0,
then ``HEAD1``, ...), the raw uint16 counts (ADU) as delivered (astropy stores them as int16 + ``BZERO = 32768``,
the FITS convention for unsigned 16-bit), row 0 of the image is FITS row 1, so starenv pixel ``(u, v)`` is FITS pixel
``(u + 1, v + 1)``.  The WCS is a gnomonic (``RA---TAN`` / ``DEC--TAN``, ICRS) projection built from the *true*
camera and the true attitude at mid-exposure: ``CRVAL`` is the boresight's RA/Dec, ``CRPIX`` the principal point
(+1), and ``CD`` maps pixel offsets through the pinhole ``X/Z = (u - cx)/fx``, ``Y/Z = (v - cy)/fy`` onto the
tangent plane's east/north axes at the boresight.  No SIP or other distortion terms are written: for a head with
lens distortion (paper 000's per-axis radial, paper 003's Legendre field, Brown-Conrady) the WCS is the ideal pinhole
and departs from the star images by the distortion (~0 at the principal point, growing outward); a rolling shutter
likewise shifts rows away from the mid-exposure attitude.  Header keys also give the exposure (``EXPTIME``, s), the
start of the exposure on the scenario's epoch (``DATE-OBS``, as for MCAP recordings), the frame index, the drop flag
and the truth attitude quaternion (``Q_X`` ... ``Q_W``, ICRS -> body, scalar last).

npz (``write_npz``): ``images`` uint16 (heads, H, W) as delivered (each head's own size: heads of unequal size are
stored as ``image{h}`` instead), ``frame_valid`` (heads,), ``time_s`` (mid-exposure, s), ``exposure_s``,
``attitude`` ``[x, y, z, w]`` (ICRS -> body), ``body_rate`` (rad/s, body), per head ``head{h}_<field>`` for every
field of the star truth (``catalog_id``, ``magnitude``, ``xy_mid``, ``xy_centroid``, ``xy_start``, ``xy_end`` px,
``electrons``, ``peak_electrons`` e-, ``detectable``), ``head{h}_K`` (3 x 3 true intrinsics, px) and
``head{h}_mounting`` (body -> camera quaternion), and ``scenario_toml`` (the scenario with overrides applied).
"""

from __future__ import annotations

import os
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.record.mcap import time_origin_ns
from starenv.sim.optics import Camera

RAD2DEG = 180.0 / np.pi
MJD_UNIX0 = 40_587.0  # MJD of 1970-01-01T00:00:00


def _astropy():
    try:
        from astropy.io import fits
        from astropy.wcs import WCS
    except ModuleNotFoundError as exc:
        raise ModuleNotFoundError('FITS export needs astropy: pip install "starenv[fits]"') from exc
    return fits, WCS


def tan_wcs_keys(camera: Camera, attitude: Rotation) -> dict[str, object]:
    """FITS WCS keys (TAN, ICRS, degrees) of ``camera`` for body attitude ``attitude`` (ICRS -> body)."""
    r_cam = camera.inertial_to_camera(attitude)  # ICRS -> camera
    axes = r_cam.inv().apply(np.eye(3))  # camera +X, +Y, +Z (boresight) as ICRS unit vectors
    b = axes[2]
    ra = np.arctan2(b[1], b[0]) % (2 * np.pi)
    dec = np.arcsin(np.clip(b[2], -1.0, 1.0))
    east = np.array([-np.sin(ra), np.cos(ra), 0.0])
    north = np.array([-np.sin(dec) * np.cos(ra), -np.sin(dec) * np.sin(ra), np.cos(dec)])
    m = np.array([[east @ axes[0], east @ axes[1]], [north @ axes[0], north @ axes[1]]])
    cd = RAD2DEG * m @ np.diag([1.0 / camera.fx, 1.0 / camera.fy])
    return {
        "WCSAXES": 2, "CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN", "CUNIT1": "deg", "CUNIT2": "deg",
        "RADESYS": "ICRS", "CRPIX1": camera.cx + 1.0, "CRPIX2": camera.cy + 1.0,
        "CRVAL1": float(ra * RAD2DEG), "CRVAL2": float(dec * RAD2DEG),
        "CD1_1": float(cd[0, 0]), "CD1_2": float(cd[0, 1]), "CD2_1": float(cd[1, 0]), "CD2_2": float(cd[1, 1]),
    }


def _date_obs(ns: int) -> str:
    """ISO time (microseconds) of Unix time ``ns``."""
    return datetime.fromtimestamp(ns // 10**9, tz=UTC).strftime("%Y-%m-%dT%H:%M:%S") + f".{ns % 10**9:09d}"[:7]


def write_fits(frame, scenario, path: str | os.PathLike) -> Path:
    """Write ``frame`` (a ``starenv.sim.sensor.Frame`` of ``scenario``) to ``path`` (see the module docstring)."""
    fits, _ = _astropy()
    hdus = []
    q = frame.attitude.as_quat()
    for h, (head, spec) in enumerate(zip(frame.heads, scenario.heads, strict=True)):
        hdr = fits.Header()
        hdr.update(tan_wcs_keys(spec.camera, frame.attitude))
        hdr["EXTNAME"] = f"HEAD{h}"
        hdr["BUNIT"] = ("adu", "raw counts as delivered")
        hdr["EXPTIME"] = (scenario.exposure_s, "[s] exposure")
        start_ns = time_origin_ns(scenario.epoch) + int(round(frame.t_start * 1e9))
        hdr["DATE-OBS"] = (_date_obs(start_ns), "start of exposure")
        hdr["MJD-OBS"] = (MJD_UNIX0 + start_ns / 86_400e9, "[d] start of exposure")
        hdr["TSIM"] = (frame.t_mid, "[s] simulation time at mid-exposure")
        hdr["FRAME"] = (frame.index, "frame index")
        hdr["DROPPED"] = (bool(head.dropped), "frame dropped (image all zeros)")
        for k, v in zip(("Q_X", "Q_Y", "Q_Z", "Q_W"), q, strict=True):
            hdr[k] = (float(v), "truth ICRS->body quaternion")
        hdr["SCENARIO"] = scenario.name
        data = np.asarray(head.image, dtype=np.uint16)
        hdus.append(fits.PrimaryHDU(data, hdr) if h == 0 else fits.ImageHDU(data, hdr))
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fits.HDUList(hdus).writeto(out, overwrite=True)
    return out


def write_npz(frame, scenario, path: str | os.PathLike) -> Path:
    """Write ``frame`` and its truth to ``path`` (``.npz``; see the module docstring)."""
    arrays: dict[str, np.ndarray] = {
        "frame_valid": np.array([not h.dropped for h in frame.heads], dtype=np.int8),
        "time_s": np.array(frame.t_mid), "exposure_s": np.array(scenario.exposure_s),
        "attitude": frame.attitude.as_quat(), "body_rate": np.asarray(frame.body_rate, dtype=np.float64),
        "scenario_toml": np.array(scenario.to_toml()),
    }
    shapes = {h.image.shape for h in frame.heads}
    if len(shapes) == 1:
        arrays["images"] = np.stack([h.image for h in frame.heads]).astype(np.uint16)
    else:
        arrays.update({f"image{h}": head.image.astype(np.uint16) for h, head in enumerate(frame.heads)})
    for h, (head, spec) in enumerate(zip(frame.heads, scenario.heads, strict=True)):
        arrays.update({f"head{h}_{k}": np.asarray(v) for k, v in head.truth.as_dict().items()})
        cam = spec.camera
        arrays[f"head{h}_K"] = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
        arrays[f"head{h}_mounting"] = cam.mounting.as_quat()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as f:
        np.savez_compressed(f, **arrays)
    return out
