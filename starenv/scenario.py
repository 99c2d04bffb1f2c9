"""Scenario files: a mission described in TOML, validated on load and built into the simulator's models.

Every key carries its unit in its name (``exposure_s``, ``rate_dps``, ``arw_deg_rthr``).  Loading checks every key:
an unknown key, a wrong type, a missing field or an out-of-range value raises one :class:`ScenarioError` naming the
file, the dotted key path and the expected form.  ``overrides`` (dotted key paths, list items by index, e.g.
``{"motion.rate_dps": [0, 0, 10], "heads.0.width": 256}``) are applied to the file's contents before validation;
an override to ``None`` is refused like any other wrong type.  A file a scenario names (a star catalogue, an
attitude history, a gyro log) is resolved against the scenario file's folder (a bundled scenario's or a parsed dict's:
the current folder), stored in the scenario's data as an absolute path, and read and checked at load.  What drives
memory and time is bounded at load, with the limit in the message (``MAX_TRAIL_PX``, ``MAX_FRAME_PIXELS``,
``MAX_EPISODE_PIXELS``, ``MAX_STAR_INSTANTS``, ``MAX_GYRO_PER_STEP``, at least two frames), so a run that would not
fit fails before it allocates.  A scenario is data: the only code it can name is an agent class in ``[pipeline]``,
loaded under the rules of ``starenv.agents.pipeline.load_agent``.

Layout (see the bundled files in ``scenarios/`` for complete, commented examples)::

    name, description, seed, duration_s, frame_rate_hz, exposure_s, mag_limit, epoch,
    sky_mag_per_arcsec2, lost_after_steps,
    availability_threshold_arcsec = number (total angle) | {cross_boresight = ..., roll = ...} (per axis, per head)
    [motion]        kind = constant_rate | slew | tumble | coning | leo_nadir | sequence | attitude_file, with
                    its keys (attitude_file: file = a CCSDS AEM or CSV t, qx, qy, qz, qw, start_s, max_step_s),
                    initial_ra_deg / initial_dec_deg / initial_roll_deg (boresight of head 0 and its roll),
                    optional [motion.jitter] superposed on any kind
    [gyro]          GyroSpec fields, or replay_file = a recorded gyro log (CSV t, wx, wy, wz) delivered instead
    [drops]         DropModel fields
    [catalog]       optional star files: file (+ epoch for a CSV) the rendered sky, onboard_file (+ onboard_epoch)
                    the sensor's own list (default: file); hip2.dat format or CSV (starenv.sim.sky)
    [sky]           aberration, bodies = true | false (default false: geometric stars, no Sun, Moon, Earth or
                    planets), earth_albedo
    [pipeline]      optional agents, role = "module:Class" or "none" (roles: predictor, deblurrer, detector,
                    corrector, identifier, solver), catalog_mag_limit, and [pipeline.options.ROLE] constructor options
    [[heads]]       optics and mounting, with [heads.distortion], [heads.spot] (FieldSpot: a spot varying across
                    the field), [heads.thermal] (sensor temperature: dark current, focal length and distortion drift),
                    [heads.detector], [heads.stray_light], [heads.baffle] (stray light of the Sun, Moon and
                    Earth, exclusion angles) and
                    [heads.calibration] (what the sensor believes its camera is; defaults to the truth)
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.config import (
    REQUIRED,
    ConfigError,
    Table,
    apply_override,
    dataclass_from_table,
    dump_toml,
    is_number,
    parse_toml,
)
from starenv.sim.attitude_files import (
    GYRO_JITTER,
    AttitudeHistory,
    GyroRecord,
    attitude_motion,
    read_attitude,
    read_gyro_csv,
)
from starenv.sim.bodies import Baffle, SkySpec
from starenv.sim.conventions import ARCSEC, DEG, frame_span_s, pointing
from starenv.sim.drops import DropModel
from starenv.sim.ephemeris import check_epoch
from starenv.sim.gyro import GyroSpec
from starenv.sim.imager import DetectorSpec
from starenv.sim.motion import (
    ConstantRate,
    LeoNadir,
    Motion,
    Oscillation,
    Sequence,
    Slew,
    Superposed,
    TorqueFree,
    Trajectory,
)
from starenv.sim.optics import (
    CAMERA_RANGES,
    DISTORTION_PRESETS,
    BrownConrady,
    Camera,
    Composite,
    Distortion,
    FieldSpot,
    LegendreField,
    NoDistortion,
    Perspective,
    Radial,
    RadialXY,
    Shear,
    Tangential,
    ThinPrism,
)
from starenv.sim.photometry import Photometry, StrayLight
from starenv.sim.sensor import HeadSpec
from starenv.sim.sky import HIP_EPOCH, CatalogFile, StarCatalog, hipparcos_table, is_csv
from starenv.sim.thermal import MAX_TEMPERATURE_C, MIN_TEMPERATURE_C, Thermal

SCENARIO_DIR = Path(str(resources.files("starenv.scenarios")))  # package data: the repository's scenarios/


class ScenarioError(ConfigError):
    """A scenario file (or override) that does not describe a valid mission."""


# Bounds on what one scenario may ask of the simulator, checked at load (before anything is allocated).
MAX_TRAIL_PX = 1024.0  # longest star trail in one exposure (render time and memory grow with its square)
MAX_FRAME_PIXELS = 2**25  # pixels of one step's frames, all heads (~12 bytes each while a frame is made)
MAX_EPISODE_PIXELS = 10**12  # frames x pixels per frame over an episode (render time)
MAX_STAR_INSTANTS = 2**23  # stars that may cross a frame x exposure instants (the renderer's path arrays)
MAX_GYRO_PER_STEP = 2**18  # gyro samples one observation holds (the env's fixed gyro layout, 32 bytes each)
# Hipparcos-2 stars with Hp <= m for m = -2 .. 14 (counted from the bundled catalogue), to bound stars in view.
HIP_COUNT_AT_MAG = (0, 1, 2, 15, 46, 165, 480, 1471, 4559, 13943, 37622, 78352, 106261, 114825, 117325, 117915,
                    117953)
# Stars in one cone <= GALACTIC_EXCESS x the sky's mean + CLUSTER_STARS: the excess covers the galactic plane, the
# densest part of the bundled catalogue's sky for cones of 2-20 deg; bright cones exceed it several times over
# (clusters) but then hold a few tens of stars, which CLUSTER_STARS covers.
GALACTIC_EXCESS = 3.0
CLUSTER_STARS = 30

DISTORTION_KINDS = ("none", "brown_conrady", "radial_xy", "legendre", "radial", "tangential", "thin_prism", "shear",
                    "perspective", "preset", "composite")
RENAMED_DISTORTION_KINDS = {"seed003": "preset"}  # former kind -> its name now (its other keys are unchanged)


MAX_SEGMENTS = 10_000  # segments of a sequence motion (each is built and chained when the scenario loads)
MAX_COMPOSITE_DEPTH = 8  # composite distortions inside composites (each level one Python call deeper)


def _distortion(tbl: Table | None, depth: int = 0) -> Distortion:
    """A ``[heads.distortion]`` table.  Paper 003's types (``radial`` q1, q2; ``tangential`` p1, p2; ``thin_prism``
    s1, s2; ``shear`` phi_x_deg, phi_y_deg; ``perspective`` h = [h11, h12, h13, h21, h22, h23, h31, h32]) take
    normalised coefficients (focal plane over half the sensor width); kind ``preset`` names one of
    :data:`~starenv.sim.optics.DISTORTION_PRESETS` (a type at a typical magnitude) in its key ``preset``;
    ``composite`` applies its ``[[models]]`` tables in turn."""
    if tbl is None:
        return NoDistortion()
    old = tbl.data.get("kind")
    if isinstance(old, str) and old in RENAMED_DISTORTION_KINDS:
        tbl.fail("kind", f"kind = {RENAMED_DISTORTION_KINDS[old]!r} (the kind {old!r} was renamed)", old)
    kind = tbl.string("kind", choices=DISTORTION_KINDS)
    if kind == "none":
        model = NoDistortion()
    elif kind == "brown_conrady":
        names = ("k1", "k2", "k3", "p1", "p2")
        model = tbl.build("distortion", BrownConrady, **{k: tbl.number(k, 0.0) for k in names})
    elif kind == "radial_xy":
        kx, ky = tbl.number("kx_per_px2", 0.0), tbl.number("ky_per_px2", 0.0)
        model = tbl.build("distortion", RadialXY, kx=kx, ky=ky, center=tbl.vector("center_px", 2, None))
    elif kind == "legendre":
        cx, cy = tbl.vector("coeffs_x_px", None), tbl.vector("coeffs_y_px", None)
        model = tbl.build("distortion", LegendreField, coeffs_x=cx, coeffs_y=cy)
    elif kind in ("radial", "tangential", "thin_prism"):
        cls, names = {"radial": (Radial, ("q1", "q2")), "tangential": (Tangential, ("p1", "p2")),
                      "thin_prism": (ThinPrism, ("s1", "s2"))}[kind]
        model = tbl.build("distortion", cls, **{k: tbl.number(k, 0.0) for k in names})
    elif kind == "shear":
        phi = [tbl.number(k, 0.0, low=-44.9, high=44.9) * DEG
               for k in ("phi_x_deg", "phi_y_deg")]
        model = tbl.build("distortion", Shear, *phi)
    elif kind == "perspective":
        model = tbl.build("distortion", Perspective, tuple(tbl.vector("h", 8)))
    elif kind == "preset":
        model = DISTORTION_PRESETS[tbl.string("preset", choices=tuple(DISTORTION_PRESETS))]
    else:
        if depth >= MAX_COMPOSITE_DEPTH:
            tbl.fail("models", f"composite models nested at most {MAX_COMPOSITE_DEPTH} deep", "deeper")
        models = [_distortion(t, depth + 1) for t in tbl.tables("models")]
        model = tbl.build("distortion", Composite, tuple(models))
    tbl.finish()
    return model


def _mounting(tbl: Table) -> Rotation:
    """Body -> camera rotation from ``mounting_matrix`` (rows: camera axes in body) or ``mounting_euler_deg``."""
    matrix = tbl.matrix("mounting_matrix", None)
    euler = tbl.vector("mounting_euler_deg", 3, None)
    if matrix is not None and euler is not None:
        tbl.fail("mounting_matrix", "either mounting_matrix or mounting_euler_deg, not both", "both")
    if matrix is not None:
        if not np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-9) or np.linalg.det(matrix) < 0:
            tbl.fail("mounting_matrix", "a proper rotation matrix (orthonormal, det +1)", matrix.tolist())
        return Rotation.from_matrix(matrix)
    if euler is not None:
        return Rotation.from_euler("xyz", euler, degrees=True)
    return Rotation.identity()


def _camera_key(tbl: Table, key: str, field_name: str, default: Any = REQUIRED, scale: float = 1.0) -> Any:
    """The camera key ``key`` of a head table, in its range :data:`~starenv.sim.optics.CAMERA_RANGES` ``[field_name]``
    (times ``scale``: the key's unit over the field's)."""
    low, high, low_open = CAMERA_RANGES[field_name]
    integer = isinstance(low, int)
    return tbl.number(key, default, low=low if integer else low * scale, high=high if integer else high * scale,
                      low_open=low_open, integer=integer)


def _head(tbl: Table, index: int) -> HeadSpec:
    name = tbl.string("name", f"head{index}")
    focal_mm = _camera_key(tbl, "focal_length_mm", "focal_length_m", scale=1e3)
    pitch_um = _camera_key(tbl, "pixel_pitch_um", "pixel_pitch_m", scale=1e6)
    width = _camera_key(tbl, "width", "width")
    height = _camera_key(tbl, "height", "height")
    f_number = _camera_key(tbl, "f_number", "f_number", 1.4)
    principal = tbl.vector("principal_point_px", 2, None)
    psf_sigma = _camera_key(tbl, "psf_sigma_px", "psf_sigma_px", 1.0)
    transmission = tbl.number("transmission", 0.8, low=0.0, high=1.0, low_open=True)
    qe = tbl.number("quantum_efficiency", 0.6, low=0.0, high=1.0, low_open=True)
    mounting = _mounting(tbl)
    distortion = _distortion(tbl.table("distortion"))
    spot = None if tbl.table("spot") is None else dataclass_from_table(tbl.table("spot"), FieldSpot)
    thermal = _thermal(tbl.table("thermal"))
    pp = {} if principal is None else {"cx": principal[0], "cy": principal[1]}
    camera = tbl.build(
        "heads", Camera.from_focal_length, focal_mm * 1e-3, pitch_um * 1e-6, width, height, f_number,
        distortion=distortion, mounting=mounting, psf_sigma_px=psf_sigma, spot=spot, **pp,
    )
    detector = dataclass_from_table(tbl.table("detector"), DetectorSpec)
    stray = dataclass_from_table(tbl.table("stray_light"), StrayLight)
    calibrated = _calibration(tbl.table("calibration"), camera)
    baffle = _baffle(tbl.table("baffle"))
    tbl.finish()
    photometry = tbl.build("heads", Photometry, camera.aperture_m, transmission, qe)
    return HeadSpec(name, camera, calibrated, photometry, detector, stray, thermal, baffle)


def _temperature(tbl: Table, key: str, value: Any) -> float:
    """A temperature (deg C) of ``tbl[key]``, refused outside [-150, 150] (above: kelvin by mistake)."""
    if not is_number(value) or not MIN_TEMPERATURE_C <= value <= MAX_TEMPERATURE_C:
        hint = f" ({value:g} K would be {value - 273.15:.2f} C)" if is_number(value) and value > 150 else ""
        tbl.fail(key, f"a temperature in deg C in [{MIN_TEMPERATURE_C:g}, {MAX_TEMPERATURE_C:g}] (not kelvin){hint}",
                 value)
    return float(value)


def _thermal(tbl: Table | None) -> Thermal | None:
    """``[heads.thermal]`` (:class:`~starenv.sim.thermal.Thermal`): ``temperature_c``, a number (fixed) or a list
    with ``times_s`` (a schedule, linear between its points, s from the episode's start), ``reference_c`` (default
    20, where the camera and detector are as given), ``dark_doubling_c`` (default 6), ``focal_length_ppm_per_c``
    (default 0) and a ``[distortion_per_c]`` distortion table (default none)."""
    if tbl is None:
        return None
    raw = tbl.raw("temperature_c", REQUIRED, "a temperature in deg C, or a list of them with times_s")
    if isinstance(raw, list):
        temps = tuple(_temperature(tbl, "temperature_c", v) for v in raw)
        times = tbl.vector("times_s", len(temps), low=0.0, high=1e7)
        if not temps or any(b <= a for a, b in zip(times, times[1:], strict=False)):
            tbl.fail("times_s", f"{len(temps)} increasing times (s), one per temperature_c", list(times))
    else:
        temps, times = (_temperature(tbl, "temperature_c", raw),), (0.0,)
    reference = _temperature(tbl, "reference_c", tbl.raw("reference_c", 20.0, "a temperature in deg C"))
    doubling = tbl.number("dark_doubling_c", 6.0, low=0.5, high=100.0)
    ppm = tbl.number("focal_length_ppm_per_c", 0.0, low=-1000.0, high=1000.0)
    drift = tbl.table("distortion_per_c")
    drift_model = None if drift is None else _distortion(drift)
    tbl.finish()
    return tbl.build("thermal", Thermal, times, temps, reference, doubling, ppm, drift_model)


def _calibration(tbl: Table | None, camera: Camera) -> Camera:
    """The camera model the sensor knows: the truth with any of focal length, principal point, distortion or
    mounting replaced by the calibration's (imperfect) values."""
    if tbl is None:
        return camera
    changes: dict[str, Any] = {}
    focal_mm = _camera_key(tbl, "focal_length_mm", "focal_length_m", None, scale=1e3)
    if focal_mm is not None:
        changes["fx"] = changes["fy"] = focal_mm * 1e-3 / camera.pixel_pitch_m
    principal = tbl.vector("principal_point_px", 2, None)
    if principal is not None:
        changes["cx"], changes["cy"] = principal
    dist = tbl.table("distortion")
    if dist is not None:
        changes["distortion"] = _distortion(dist)
    err = tbl.vector("mounting_error_arcsec", 3, None)
    if err is not None:
        changes["mounting"] = Rotation.from_rotvec(np.array(err) * ARCSEC) * camera.mounting
    tbl.finish()
    return tbl.build("calibration", dataclasses.replace, camera, **changes)


MAX_INERTIA_KGM2 = 1e12  # far above any spacecraft; keeps Euler's equations in floating-point range
MOTION_KINDS = ("constant_rate", "slew", "tumble", "coning", "leo_nadir", "sequence", "attitude_file")


def _initial_pointing(tbl: Table) -> tuple[float, float, float]:
    ra = tbl.number("initial_ra_deg", low=-360.0, high=360.0)
    dec = tbl.number("initial_dec_deg", low=-90.0, high=90.0)
    roll = tbl.number("initial_roll_deg", 0.0, low=-360.0, high=360.0)
    return ra, dec, roll


def _motion_kind(tbl: Table, kind: str, head0: Camera, initial: Rotation | None) -> Motion:
    """One motion of the given kind from its table (``initial`` = inertial -> body at its start, for slews)."""
    if kind == "constant_rate":
        rate = tbl.vector("rate_dps", 3)
        return tbl.build("motion", ConstantRate, np.array(rate) * DEG)
    if kind == "slew":
        target = pointing(
            tbl.number("target_ra_deg", low=-360.0, high=360.0) * DEG,
            tbl.number("target_dec_deg", low=-90.0, high=90.0) * DEG,
            tbl.number("target_roll_deg", 0.0, low=-360.0, high=360.0) * DEG,
        )
        max_rate = tbl.number("max_rate_dps", low=0.0, high=1000.0, low_open=True) * DEG
        max_accel = tbl.number("max_accel_dps2", low=0.0, high=1e4, low_open=True) * DEG
        start = tbl.number("start_s", 0.0, low=0.0, high=1e6)
        target_body = head0.mounting.inv() * target
        return tbl.build("motion", Slew.between, initial, target_body, max_rate, max_accel, start)
    if kind == "tumble":
        inertia = tbl.raw("inertia_kgm2", REQUIRED, "3 principal moments or a 3x3 tensor, kg m^2")
        rows = inertia if isinstance(inertia, list) and all(isinstance(r, list) for r in inertia) else [inertia]
        ok = all(isinstance(r, list) and r and all(is_number(x) for x in r) for r in rows)
        arr = np.array(inertia, dtype=np.float64) if ok and len({len(r) for r in rows}) == 1 else None
        if arr is None or arr.shape not in ((3,), (3, 3)) or not np.all(np.abs(arr) <= MAX_INERTIA_KGM2):
            tbl.fail("inertia_kgm2", f"3 principal moments or a 3x3 tensor, kg m^2, each |value| <= "
                                     f"{MAX_INERTIA_KGM2:g}", inertia)
        tensor = np.diag(arr) if arr.shape == (3,) else arr
        rate = np.array(tbl.vector("rate_dps", 3)) * DEG
        return tbl.build("motion", TorqueFree, tensor, rate)
    if kind == "coning":
        half_angle = tbl.number("half_angle_deg", low=0.0, high=45.0, low_open=True) * DEG
        freq = tbl.number("frequency_hz", low=0.0, high=1000.0, low_open=True)
        return tbl.build("motion", Oscillation.coning, half_angle, freq)
    if kind == "leo_nadir":
        return tbl.build(
            "motion",
            LeoNadir,
            tbl.number("altitude_km", low=100.0, high=50000.0) * 1e3,
            tbl.number("inclination_deg", low=0.0, high=180.0) * DEG,
            tbl.number("raan_deg", 0.0, low=-360.0, high=360.0) * DEG,
            tbl.number("arg_latitude_deg", 0.0, low=-360.0, high=360.0) * DEG,
        )
    segments, att = [], initial
    tables = tbl.tables("segments")
    if len(tables) > MAX_SEGMENTS:
        tbl.fail("segments", f"at most {MAX_SEGMENTS} segments", f"{len(tables)} segments")
    for k, seg in enumerate(tables):
        seg_kind = seg.string("kind", choices=tuple(k for k in MOTION_KINDS if k not in ("sequence", "leo_nadir",
                                                                                   "attitude_file")))
        duration = seg.number("duration_s", low=0.0, high=1e7)
        motion = _motion_kind(seg, seg_kind, head0, att)
        seg.finish()
        segments.append((motion, duration))
        att = motion.delta(duration) * (motion.delta(0.0).inv() if k else Rotation.identity()) * att
    return tbl.build("motion", Sequence, segments)


def data_file(tbl: Table, key: str, base: Path | None) -> Path:
    """The file named by ``key`` (a path relative to ``base``, the scenario's folder; None: the current folder),
    which must exist; the table's value becomes its absolute path (so the scenario's TOML loads anywhere)."""
    value = tbl.string(key)
    try:
        path = Path(value)
        path = (path if path.is_absolute() or base is None else base / path).resolve()
        found = path.is_file()
    except (OSError, ValueError):  # a name no file system holds (a NUL byte, too long)
        found = False
    if not found:
        tbl.fail(key, "the path of a file (relative to the scenario's folder)", value)
    tbl.data[key] = str(path)
    return path


def _attitude_history(tbl: Table, base: Path | None, duration_s: float | None) -> AttitudeHistory:
    """``kind = "attitude_file"``: ``file`` (a CCSDS AEM, or a CSV ``t, qx, qy, qz, qw``), ``start_s`` (simulation
    time 0 that many seconds after the file's start), ``max_step_s`` (the longest step between samples, default 10 s,
    beyond which a step is a gap); the file must cover ``[0, duration_s]``."""
    path = data_file(tbl, "file", base)
    start = tbl.number("start_s", 0.0, low=-1e9, high=1e9)
    max_step = tbl.number("max_step_s", 10.0, low=0.0, high=1e9, low_open=True)
    history = tbl.build("motion", lambda: attitude_motion(read_attitude(path, start, max_step)))
    lo, hi = history.span
    if duration_s is not None and not (lo <= 0.0 and hi >= duration_s):
        tbl.fail("file", f"a file covering the episode's simulation times [0, {duration_s:g}] s (motion.start_s "
                         f"shifts its start)", f"{path} covering [{lo:.9g}, {hi:.9g}] s")
    return history


def _trajectory(tbl: Table, head0: Camera, base: Path | None = None, duration_s: float | None = None) -> Trajectory:
    kind = tbl.string("kind", choices=MOTION_KINDS)
    if kind == "attitude_file":
        motion = _attitude_history(tbl, base, duration_s)
        initial = motion.initial
    elif kind == "leo_nadir":
        motion = _motion_kind(tbl, kind, head0, None)
        initial = motion.initial_attitude()
    else:
        ra, dec, roll = _initial_pointing(tbl)
        initial = head0.mounting.inv() * pointing(ra * DEG, dec * DEG, roll * DEG)
        motion = _motion_kind(tbl, kind, head0, initial)
    jitter = tbl.table("jitter")
    if jitter is not None:
        amp = np.array(jitter.vector("amplitude_arcsec", 3)) * ARCSEC
        freq = jitter.vector("frequency_hz", 3)
        phase = np.array(jitter.vector("phase_deg", 3, (0.0, 0.0, 0.0))) * DEG
        jitter.finish()
        motion = Superposed(motion, jitter.build("jitter", Oscillation, amp, freq, phase))
    tbl.finish()
    return Trajectory(motion, initial)


def _catalog_files(tbl: Table | None, base: Path | None) -> tuple[CatalogFile | None, CatalogFile | None]:
    """The ``[catalog]`` table: ``file`` the rendered stars and ``onboard_file`` the sensor's own list (default:
    ``file``), each a hip2.dat-format file or a CSV (``.csv``) with its positions' Julian year in ``epoch`` /
    ``onboard_epoch``; each file is parsed here, so that a bad row is a load error naming its line."""
    if tbl is None:
        return None, None
    found = []
    for file_key, epoch_key in (("file", "epoch"), ("onboard_file", "onboard_epoch")):
        if file_key not in tbl.data:
            if epoch_key in tbl.data:
                tbl.fail(epoch_key, f"no {epoch_key} without {file_key}", tbl.data[epoch_key])
            found.append(None)
            continue
        path = data_file(tbl, file_key, base)
        if is_csv(path):
            epoch = tbl.number(epoch_key, low=1900.0, high=2100.0)
        elif epoch_key in tbl.data:
            tbl.fail(epoch_key, f"no epoch for a hip2.dat-format file (its positions are J{HIP_EPOCH})",
                     tbl.data[epoch_key])
        tbl.build("catalog", hipparcos_table, path)
        found.append(CatalogFile(str(path), epoch if is_csv(path) else HIP_EPOCH))
    tbl.finish()
    sky, onboard = found
    return sky, onboard or sky


def _gyro_replay(tbl: Table | None, base: Path | None) -> GyroRecord | None:
    """``[gyro] replay_file``: a recorded gyro log (CSV ``t, wx, wy, wz``, s and rad/s body frame) delivered instead
    of the gyro model; ``rate_hz`` defaults to the log's rate.  The model's other keys are then unused."""
    if tbl is None or "replay_file" not in tbl.data:
        return None
    record = tbl.build("gyro", read_gyro_csv, data_file(tbl, "replay_file", base))
    tbl.data.setdefault("rate_hz", 1.0 / record.dt)
    return record


def _check_replay(source: str, record: GyroRecord, gyro: GyroSpec, last_window_end_s: float) -> None:
    """A gyro log at the scenario's ``gyro.rate_hz`` whose samples cover the episode: its first within one interval
    of t = 0, its last within one interval of the last frame's exposure end (s)."""
    reach = record.dt * (1.0 + GYRO_JITTER)
    if abs(gyro.rate_hz * record.dt - 1.0) > GYRO_JITTER:
        raise ScenarioError(f"{source}: gyro.rate_hz: expected the log's rate {1.0 / record.dt:.9g} Hz "
                            f"({record.source}), got {gyro.rate_hz:g}")
    if record.t[0] > reach or record.t[-1] < last_window_end_s - reach:
        raise ScenarioError(f"{source}: gyro.replay_file: expected samples from t <= {record.dt:.6g} s to t >= "
                            f"{last_window_end_s - record.dt:.6g} s (the last frame's exposure end), got "
                            f"{record.source} covering [{record.t[0]:.9g}, {record.t[-1]:.9g}] s")


AGENT_ROLES = ("predictor", "deblurrer", "detector", "corrector", "identifier", "solver")


@dataclass(frozen=True)
class PipelineSpec:
    """Agents a scenario (or a bench pipeline, :class:`starenv.bench.spec.NamedPipeline`) asks for: role ->
    ``"module:Class"`` or None (empty), constructor options per role, the onboard catalogue's magnitude limit; roles
    not named keep the defaults.  The one pipeline record of scenarios and bench files."""

    agents: dict[str, str | None] = field(default_factory=dict)
    options: dict[str, dict[str, Any]] = field(default_factory=dict)
    catalog_mag_limit: float | None = None

    def replaced_by(self, other: PipelineSpec) -> PipelineSpec:
        """This pipeline with ``other`` taking precedence: its agents, its options merged role by role (its keys
        win), its catalogue limit where it sets one.  The one place pipeline choices are merged."""
        options = {role: dict(opts) for role, opts in self.options.items()}
        for role, opts in other.options.items():
            options[role] = {**options.get(role, {}), **opts}
        limit = self.catalog_mag_limit if other.catalog_mag_limit is None else other.catalog_mag_limit
        return PipelineSpec({**self.agents, **other.agents}, options, limit)


def parse_pipeline(tbl: Table | None) -> PipelineSpec:
    """A ``[pipeline]`` table: ``role = "module:Class" | "none"``, ``catalog_mag_limit``, ``[options.ROLE]``."""
    if tbl is None:
        return PipelineSpec()
    agents: dict[str, str | None] = {}
    for role in AGENT_ROLES:
        if role in tbl.data:
            value = tbl.string(role)
            module, sep, cls = value.partition(":")
            if value.lower() == "none":
                agents[role] = None
            elif not (sep and module and cls):
                tbl.fail(role, "'module:Class' (e.g. 'starenv.agents.solve:SvdSolver') or 'none'", value)
            else:
                agents[role] = value
    limit = tbl.number("catalog_mag_limit", None, low=-2.0, high=14.0)
    options: dict[str, dict[str, Any]] = {}
    options_tbl = tbl.table("options")
    if options_tbl is not None:
        for role in AGENT_ROLES:
            role_options = options_tbl.table(role)
            if role_options is not None:
                options[role] = dict(role_options.data)
                role_options.used.update(role_options.data)
        options_tbl.finish()
    tbl.used.update(AGENT_ROLES)  # a misspelt role is told apart from the roles, which its error lists
    tbl.finish()
    return PipelineSpec(agents, options, limit)


def densest_cone(sky: StarCatalog, radius: float) -> int:
    """An upper bound of the stars any cone of ``radius`` (rad) holds: a cone holding a star lies within twice its
    radius of that star, so the most stars within ``2 radius`` of a star bounds it (the catalogue's size when that
    is cheaper)."""
    if len(sky) > MAX_COUNTED_STARS or 2.0 * radius >= math.pi:
        return len(sky)
    chord = 2.0 * math.sin(radius)  # chord of 2 radius
    return int(np.max(sky.tree.query_ball_point(sky.unit, chord, return_length=True), initial=0))


MAX_COUNTED_STARS = 2**16  # a custom sky with more stars is bounded by its size (the count costs n x neighbours)


def _check_bounds(source: str, duration: float, frame_rate: float, exposure: float, mag_limit: float,
                  heads: list[HeadSpec], trajectory: Trajectory, gyro: GyroSpec,
                  sky: StarCatalog | None = None) -> None:
    """Refuse a scenario whose frames, trails or episode would need more memory or time than the bounds allow
    (``sky``: a custom catalogue's stars at ``mag_limit``, counted instead of Hipparcos-2's density)."""
    per_step = math.ceil(gyro.rate_hz / frame_rate) + 1
    if per_step > MAX_GYRO_PER_STEP:
        raise ScenarioError(f"{source}: frame_rate_hz: expected at most {MAX_GYRO_PER_STEP} gyro samples per frame "
                            f"(frame_rate_hz >= {gyro.rate_hz / (MAX_GYRO_PER_STEP - 2):.3g} at gyro.rate_hz = "
                            f"{gyro.rate_hz:g}), got {per_step}")
    pixels = sum(h.camera.width * h.camera.height for h in heads)
    if pixels > MAX_FRAME_PIXELS:
        raise ScenarioError(f"{source}: heads: expected at most {MAX_FRAME_PIXELS} pixels per step over all heads "
                            f"(e.g. two 4096 x 4096 heads), got {pixels}")
    steps = math.floor(duration * frame_rate + 1e-9)
    if steps < 2:
        raise ScenarioError(f"{source}: duration_s: expected at least two frame periods "
                            f"(>= {2.0 / frame_rate:g} s: a step scores frame k while frame k + 1 is made), "
                            f"got {duration:g} s")
    if steps * pixels > MAX_EPISODE_PIXELS:
        raise ScenarioError(f"{source}: duration_s: expected frames x pixels per frame <= {MAX_EPISODE_PIXELS:.0e} "
                            f"(render time), got {steps} frames x {pixels} px = {steps * pixels:.3g}")
    rate = trajectory.motion.max_rate(0.0, duration)
    n_mag = HIP_COUNT_AT_MAG[min(len(HIP_COUNT_AT_MAG) - 1, max(0, math.ceil(mag_limit) + 2))]
    for i, h in enumerate(heads):
        cam = h.camera
        window = frame_span_s(exposure, h.detector.line_time_s, cam.height)
        px_per_rad = max(cam.fx, cam.fy) * (1.0 + math.tan(cam.half_diagonal) ** 2)  # the renderer's bound
        trail = rate * window * px_per_rad
        if not trail <= MAX_TRAIL_PX:
            raise ScenarioError(
                f"{source}: motion: expected star trails of at most {MAX_TRAIL_PX:g} px in one exposure, got "
                f"{trail:.4g} px on heads.{i} (body rate up to {math.degrees(rate):.4g} deg/s x {window:g} s x "
                f"{px_per_rad:.4g} px/rad): lower the rate, the exposure or the focal length")
        instants = max(1, math.ceil(trail / min(cam.psf_sigma_px, 0.5)))
        cone = min(math.pi, cam.half_diagonal + rate * window + 0.01)
        stars = math.ceil(GALACTIC_EXCESS * n_mag * 0.5 * (1.0 - math.cos(cone))) + CLUSTER_STARS
        if sky is not None:
            stars = densest_cone(sky, cone)
        if stars * instants > MAX_STAR_INSTANTS:
            raise ScenarioError(
                f"{source}: mag_limit: expected stars in view x render instants <= {MAX_STAR_INSTANTS}, got up to "
                f"{stars} stars x {instants} instants on heads.{i}: lower mag_limit, the field or the trail length")


def _sky(tbl: Table | None, epoch: float, duration_s: float) -> SkySpec:
    """The ``[sky]`` table: ``aberration`` and ``bodies`` (bools, default false), ``earth_albedo`` (0-1).  With
    either the episode must lie within the ephemeris' range (the error names ``epoch``)."""
    if tbl is None:
        return SkySpec()
    flags = {}
    for key in ("aberration", "bodies"):
        flags[key] = tbl.raw(key, False, "true or false")
        if not isinstance(flags[key], bool):
            tbl.fail(key, "true or false", flags[key])
    albedo = tbl.number("earth_albedo", SkySpec.earth_albedo, low=0.0, high=1.0)
    tbl.finish()
    if any(flags.values()):
        try:
            check_epoch("epoch", epoch, duration_s)
        except ValueError as exc:
            raise tbl.error(f"{tbl.source}: {exc}") from exc
    return SkySpec(earth_albedo=albedo, **flags)


def _baffle(tbl: Table | None) -> Baffle:
    """A ``[heads.baffle]`` table: ``pst_angles_deg`` and ``pst`` (lists of equal length), the exclusion angles
    ``sun_exclusion_deg``, ``earth_exclusion_deg``, ``moon_exclusion_deg``; defaults: :class:`Baffle`'s."""
    if tbl is None:
        return Baffle()
    kwargs = {key: tbl.vector(key, None, None) for key in ("pst_angles_deg", "pst")}
    for key in ("sun_exclusion_deg", "earth_exclusion_deg", "moon_exclusion_deg"):
        kwargs[key] = tbl.number(key, None, low=0.0, high=180.0)
    tbl.finish()
    try:
        return Baffle(**{k: v for k, v in kwargs.items() if v is not None})
    except ValueError as exc:  # the check names the field first: "pst must not increase ..."
        key = str(exc).split(" ", 1)[0]
        raise tbl.error(f"{tbl.source}: {tbl.where(key if key in kwargs else '')}: {exc}") from exc


THRESHOLD_AXES = ("cross_boresight", "roll")  # the axes of a per-axis availability threshold, all required


@dataclass(frozen=True)
class AvailabilityThreshold:
    """``availability_threshold_arcsec``: a step's attitude is within it when its total error angle is under
    ``total_arcsec`` (a number in the file) or, per axis (a table; ``total_arcsec`` None), when every head's
    cross-boresight error is under ``cross_boresight_arcsec`` and the size of its roll error under ``roll_arcsec``
    (``starenv.scoring.threshold_errors``)."""

    total_arcsec: float | None = None
    cross_boresight_arcsec: float | None = None
    roll_arcsec: float | None = None

    def describe(self) -> str:
        """The condition in words, for summaries."""
        if self.total_arcsec is not None:
            return f"total error < {self.total_arcsec:g} arcsec"
        return (f"every head's cross-boresight error < {self.cross_boresight_arcsec:g} arcsec and |roll error| < "
                f"{self.roll_arcsec:g} arcsec")


def _availability_threshold(top: Table) -> AvailabilityThreshold:
    """``availability_threshold_arcsec``: a number in (0, 1e6] (default 60), or a table of every axis of
    :data:`THRESHOLD_AXES`, each such a number."""
    key, low, high = "availability_threshold_arcsec", 0.0, 1e6
    if not isinstance(top.data.get(key), dict):
        return AvailabilityThreshold(total_arcsec=float(top.number(key, 60.0, low=low, high=high, low_open=True)))
    tbl = top.table(key)
    tbl.used.update(THRESHOLD_AXES)
    tbl.finish()  # an unknown axis first: it may be a misspelt required one
    axes = {axis: tbl.number(axis, low=low, high=high, low_open=True) for axis in THRESHOLD_AXES}
    return AvailabilityThreshold(cross_boresight_arcsec=float(axes["cross_boresight"]), roll_arcsec=float(axes["roll"]))


@dataclass
class Scenario:
    """A validated mission: timing, motion, gyro, drops and camera heads, plus its source for reproduction."""

    name: str
    description: str
    seed: int
    duration_s: float
    frame_rate_hz: float
    exposure_s: float
    mag_limit: float
    epoch: float
    sky_mag_per_arcsec2: float
    lost_after_steps: int
    availability_threshold_arcsec: AvailabilityThreshold
    trajectory: Trajectory
    gyro: GyroSpec
    drops: DropModel
    heads: list[HeadSpec]
    pipeline: PipelineSpec
    source: str
    data: dict = field(repr=False)
    sky: SkySpec = field(default_factory=SkySpec)
    sky_catalog: CatalogFile | None = None  # [catalog] file: the rendered stars (None: the bundled Hipparcos-2)
    onboard_catalog: CatalogFile | None = None  # [catalog] onboard_file (or file): the sensor's own list
    gyro_replay: GyroRecord | None = None  # [gyro] replay_file: a recorded log delivered instead of the gyro model

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.frame_rate_hz

    @property
    def n_steps(self) -> int:
        """Frames in an episode: the first at t = 0, then one per frame period up to ``duration_s``."""
        return int(math.floor(self.duration_s * self.frame_rate_hz + 1e-9))

    def to_toml(self) -> str:
        """The scenario (overrides applied) as TOML text that loads back to the same mission."""
        return dump_toml(self.data)


FILE_KEYS = ("file", "onboard_file", "replay_file")  # keys whose value names a data file (data_file)


def named_files(data: dict, prefix: str = "") -> dict[str, str]:
    """Dotted key -> absolute path of every data file a loaded scenario's ``data`` names (a star catalogue, an
    attitude history, a gyro log)."""
    out = {}
    items = enumerate(data) if isinstance(data, list) else data.items()
    for key, value in items:
        if isinstance(value, dict | list):
            out.update(named_files(value, f"{prefix}{key}."))
        elif key in FILE_KEYS and isinstance(value, str):
            out[f"{prefix}{key}"] = value
    return out


def file_digests(scenario: Scenario) -> dict[str, str]:
    """Dotted key -> SHA-256 of the bytes of each data file the scenario names: what its results depend on beyond
    its own text."""
    import hashlib

    return {key: hashlib.sha256(Path(path).read_bytes()).hexdigest()
            for key, path in sorted(named_files(scenario.data).items())}


def resolve(scenario: str | Path) -> Path:
    """Path of a scenario given by path or by the name of a bundled one (``paper_002``)."""
    path = Path(scenario)
    if path.suffix != ".toml":
        bundled = SCENARIO_DIR / f"{scenario}.toml"
        if bundled.is_file():
            return bundled
    if path.is_file():
        return path
    names = ", ".join(bundled_names())
    raise ScenarioError(f"scenario {str(scenario)!r} is neither a file nor a bundled scenario ({names})")


def bundled_names() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def _shown(value: Any) -> str:
    """An override's value as its errors show it: a string as is, anything else as JSON (repr if not JSON)."""
    if isinstance(value, str):
        return value
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)


def load(scenario: str | Path | dict, overrides: dict[str, Any] | None = None, *,
         base: str | Path | None = None) -> Scenario:
    """Load, override and validate a scenario (bundled name, path, or an already-parsed TOML dict; ``base``: the
    folder a dict's relative file names are relative to, the current folder when None)."""
    if isinstance(scenario, dict):
        source, data = "<scenario>", copy.deepcopy(scenario)
    elif not isinstance(scenario, str | os.PathLike):
        raise ScenarioError(f"scenario: expected a bundled scenario name, a .toml path or a parsed scenario dict, "
                            f"got {type(scenario).__name__} {scenario!r}")
    else:
        path = resolve(scenario)
        source = str(path)
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise ScenarioError(f"{source}: not valid TOML: {exc}") from exc
        data = parse_toml(text, source, ScenarioError)
        data.setdefault("name", path.stem)
    # the folder the files a scenario names are relative to (None: the current folder)
    if isinstance(scenario, dict):
        base = None if base is None else Path(base)
    else:
        base = None if path.parent.resolve() == SCENARIO_DIR.resolve() else path.parent
    if overrides:
        if not isinstance(overrides, dict):
            raise ScenarioError(f"{source}: overrides must be a dict of dotted key paths, got {overrides!r}")
        for key, value in overrides.items():
            apply_override(data, str(key), copy.deepcopy(value), source, ScenarioError)  # kept as given
    # errors in what an override set name the override, not the file (config.Table.located)
    given = {str(k): f"override {k}={_shown(v)}" for k, v in (overrides or {}).items()}
    top = Table(data, "", source, ScenarioError, given)
    name = top.string("name", "scenario")
    description = top.string("description")
    seed = top.number("seed", 0, low=0, high=2**63 - 1, integer=True)
    duration = top.number("duration_s", low=0.0, high=1e7, low_open=True)
    frame_rate = top.number("frame_rate_hz", low=0.0, high=1000.0, low_open=True)
    exposure = top.number("exposure_s", low=0.0, high=1.0 / frame_rate, low_open=True)
    mag_limit = top.number("mag_limit", 6.5, low=-2.0, high=12.0)
    epoch = top.number("epoch", 2026.0, low=1900.0, high=2100.0)
    sky = top.number("sky_mag_per_arcsec2", 22.0, low=10.0, high=30.0)
    lost_after = top.number("lost_after_steps", 10, low=1, high=10**9, integer=True)
    avail = _availability_threshold(top)
    heads = [_head(t, i) for i, t in enumerate(top.tables("heads"))]
    for h in heads:
        span = frame_span_s(exposure, h.detector.line_time_s, h.camera.height)
        if span > 1.0 / frame_rate + 1e-12:
            raise top.located("exposure_s", f"expected exposure + rolling-shutter readout ({span:g} s) "
                                            f"<= the frame period {1.0 / frame_rate:g} s")
    trajectory = _trajectory(top.table("motion", required=True), heads[0].camera, base, duration)
    gyro_tbl = top.table("gyro")
    gyro_replay = _gyro_replay(gyro_tbl, base)
    gyro = dataclass_from_table(gyro_tbl, GyroSpec)
    drops = dataclass_from_table(top.table("drops"), DropModel)
    pipeline = parse_pipeline(top.table("pipeline"))
    sky_spec = _sky(top.table("sky"), epoch, duration)
    sky_catalog, onboard_catalog = _catalog_files(top.table("catalog"), base)
    top.finish()
    with_overrides = f"{source} with the overrides {', '.join(given)}" if given else source
    _check_bounds(with_overrides, duration, frame_rate, exposure, mag_limit, heads, trajectory, gyro,
                  None if sky_catalog is None else sky_catalog.load(mag_limit, epoch))
    if gyro_replay is not None:
        last_start = (math.floor(duration * frame_rate + 1e-9) - 1) / frame_rate
        window = frame_span_s(exposure, heads[0].detector.line_time_s, heads[0].camera.height)
        _check_replay(with_overrides, gyro_replay, gyro, last_start + window)
    return Scenario(
        name, description, seed, duration, frame_rate, exposure, mag_limit, epoch, sky, lost_after, avail,
        trajectory, gyro, drops, heads, pipeline, source, data, sky_spec,
        sky_catalog=sky_catalog, onboard_catalog=onboard_catalog, gyro_replay=gyro_replay,
    )


def with_motion(scenario: Scenario, motion: dict) -> Scenario:
    """``scenario`` with its ``[motion]`` table replaced by ``motion``, validated and bounded as :func:`load` does,
    without parsing the rest again: the mission ``load(data, {"motion": motion})`` gives (dataset generators vary
    only the motion from sample to sample)."""
    motion = copy.deepcopy(motion)
    trajectory = _trajectory(Table(motion, "motion", scenario.source, ScenarioError), scenario.heads[0].camera)
    _check_bounds(scenario.source, scenario.duration_s, scenario.frame_rate_hz, scenario.exposure_s,
                  scenario.mag_limit, scenario.heads, trajectory, scenario.gyro)
    return dataclasses.replace(scenario, trajectory=trajectory, data={**scenario.data, "motion": motion})


@dataclass(frozen=True)
class CameraFile:
    """A camera file (``starenv solve --camera``): its head, built by the scenario loader from the file's ``[camera]``
    table, and whether the file gives the spot size (``psf_sigma_px``); without it the spot is measured on each
    frame."""

    head: HeadSpec
    spot_calibrated: bool

    @property
    def camera(self) -> Camera:
        """The camera as calibrated (what the sensor believes it is: ``[camera.calibration]`` applied)."""
        return self.head.calibrated


def load_camera(path: str | os.PathLike) -> CameraFile:
    """A camera file: one ``[camera]`` table holding the keys of a scenario's ``[[heads]]`` table (optics, mounting,
    distortion, detector, stray light, calibration), validated as a scenario's head is; errors name
    ``file: camera.key``."""
    top = _toml_file(path)
    tbl = top.table("camera", required=True)
    top.finish()
    spot_calibrated = "psf_sigma_px" in tbl.data
    return CameraFile(_head(tbl, 0), spot_calibrated)


def load_pipeline(path: str | os.PathLike) -> PipelineSpec:
    """The ``[pipeline]`` table of a TOML file (a scenario's, or a file holding only that table), validated as a
    scenario's; the file's other tables are not read."""
    return parse_pipeline(_toml_file(path).table("pipeline", required=True))


def _toml_file(path: str | os.PathLike) -> Table:
    """The top table of a TOML file; a file that is not UTF-8 TOML is a :class:`ScenarioError` naming it."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ScenarioError(f"{source}: not valid TOML: {exc}") from exc
    return Table(parse_toml(text, source, ScenarioError), "", source, ScenarioError)
