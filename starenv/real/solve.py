"""Real frames solved: a frame (array) and a camera in, the attitude and the identified stars out, no prior.

:func:`solve_frame` runs the pipeline's detector, lost-in-space identifier and solver on one grey frame of one camera:
detections (measured pixel positions) -> ids (HIP) -> the ICRS -> camera attitude by the pipeline's solver from the
identified stars' camera-frame directions (``camera.unproject``) and catalogue directions at ``epoch``.  A frame is
solved when at least ``MIN_IDENTIFIED`` stars are identified and the solver gives an attitude.

Spot size: when the camera's spot is not calibrated (``spot_calibrated=False``: a camera from :func:`camera_from_fov`,
or a camera file without ``psf_sigma_px``), the spot sigma is measured on each frame
(:func:`~starenv.agents.detect.spot.measure_spot_sigma`) and the detector is handed the camera with that sigma, so
its hot-pixel / cosmic-ray tests judge sharpness against the frame's own stars; the identifier and the solver keep the
camera as given.  A frame on which the spot cannot be measured keeps the camera's.

Field of view: the camera's focal length may be off by up to ``fov_tolerance`` (a fraction, ``FOV_TOLERANCE`` by
default).  The identifier's edge ratios do not depend on the scale, but its pattern edges and verification radius
do: it takes a scale within ``scale_tolerance``, its edge tolerance (``N_SIGMA sqrt 2 centroid_noise_px``) over the
largest pattern edge (at most the field's shorter side).  A frame not solved with the camera as given is identified
again with the focal length (``fx`` and ``fy`` together) scaled by each factor of a grid over ``1 +- fov_tolerance``
in steps of twice that tolerance (so the true scale is within it of a grid point), and the grid point that
identifies the most stars wins (several tries multiply the chances of a false match; the true scale identifies the
most).  The search's identifier is the pipeline's (a :class:`~starenv.agents.identify.LostInSpaceIdentifier`: the
same options and database) drawing its patterns from the ``SEARCH_PATTERN_STARS`` brightest detections only, so that
a scale that identifies nothing costs a seventh of the lookups.  Then, and wherever a solution's scale fitted to its
stars (:func:`fit_focal_scale`: focal length and attitude by least squares) is off by more than ``scale_tolerance``,
the frame is identified again (by the pipeline's identifier) at the fitted scale, up to ``REFIT_ROUNDS`` times; a
searched field ends at the scale fitted to its final stars, which the solution uses.  Every
solved frame reports the field of the focal length fitted to its identified stars (``fov_fitted_deg``, with its 1
sigma); a frame solved with the camera as given keeps that camera's solution when the fitted scale is within the
tolerance.

Residuals: each identified star's distance (px) between its measured position and its catalogue star projected
through the camera under the solved attitude; ``residual_rms_px`` is the root mean square of those distances.
``time_ms`` is the wall time of detection, spot measurement, identification and solution on the frame (the pattern
database and the catalogue are loaded once per camera, before).
"""

from __future__ import annotations

import dataclasses
import math
import operator
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.agents.base import SensorInfo, StarMeasurements
from starenv.agents.blocks import wahba_svd
from starenv.agents.detect.spot import measure_spot_sigma
from starenv.agents.identify import LostInSpaceIdentifier
from starenv.agents.identify.database import N_SIGMA
from starenv.agents.pipeline import Pipeline
from starenv.sim.conventions import DEG, pointing
from starenv.sim.optics import Camera

MIN_IDENTIFIED = 3  # identified stars needed to call a frame solved
DEFAULT_EPOCH = 2026.0  # Julian year of the catalogue positions when none is given (the scenarios' default)
NOMINAL_PITCH_M = 5e-6  # pixel pitch of a camera known by its field of view only (enters photometry alone)
SPOT_STEP_PX = 0.05  # measured sigmas are rounded to this step, so the detector's per-sigma constants are reused
FOV_TOLERANCE = 0.1  # default: the focal length searched over +- this fraction when the given one does not solve
DEFAULT_CENTROID_NOISE_PX = 0.5  # the pattern tolerance assumed of an identifier that does not state one
FIT_ITERATIONS = 4  # focal-scale fit: rounds of attitude, then scale (a pinhole's scale is exact in one), at most
FIT_TOLERANCE = 1e-9  # ... ending once the scale moves less than this (a nanometre a metre of focal length)
REFIT_ROUNDS = 3  # at most: identified again at the fitted focal scale while it moves beyond the tolerance
SEARCH_PATTERN_STARS = 8  # the search's identifier takes patterns of this many brightest stars (70 quads, not 495)
MIN_FIT_STARS = 4  # identified stars needed for the focal-scale fit (3 attitude angles and the scale)
LOST_IN_SPACE = {"predictor": None, "identifier": "starenv.agents.identify:LostInSpaceIdentifier"}


@dataclass(frozen=True)
class IdentifiedStar:
    """One identified star: measured position (px, (0, 0) the centre of the top-left pixel), HIP number and the
    distance (px) to its catalogue star projected under the solved attitude."""

    x_px: float
    y_px: float
    hip: int
    residual_px: float


@dataclass
class FrameSolution:
    """What :func:`solve_frame` found on one frame.  ``attitude_xyzw``: ICRS -> camera, scalar last; ``ra_deg``,
    ``dec_deg``: the boresight (camera +Z); ``roll_deg``: the roll of :func:`starenv.sim.conventions.pointing`
    (0: north up); ``fov_deg``: the field across columns of the camera the solution used; ``spot_sigma_px``: the
    spot sigma the detector used, ``spot_measured`` whether it was measured on this frame; ``fov_searched``: the
    solution is not the given camera's but one whose field was found (by the search, or the given one refitted
    beyond the tolerance); ``fov_fitted_deg`` and ``fov_fitted_sigma_deg``: the field of the focal length fitted to
    the identified stars and its 1 sigma (None unsolved or with fewer than ``MIN_FIT_STARS`` stars).  Unsolved frames
    have None attitude fields."""

    solved: bool
    attitude_xyzw: list[float] | None
    ra_deg: float | None
    dec_deg: float | None
    roll_deg: float | None
    fov_deg: float
    stars_detected: int
    stars_identified: int
    residual_rms_px: float | None
    time_ms: float
    spot_sigma_px: float
    spot_measured: bool
    stars: list[IdentifiedStar] = field(default_factory=list)
    file: str | None = None
    fov_searched: bool = False
    fov_fitted_deg: float | None = None
    fov_fitted_sigma_deg: float | None = None

    @property
    def attitude(self) -> Rotation | None:
        """The solved ICRS -> camera rotation (None when unsolved)."""
        return None if self.attitude_xyzw is None else Rotation.from_quat(self.attitude_xyzw)

    def to_dict(self) -> dict:
        """The solution as JSON-ready types (``starenv solve --json``), the file first."""
        out = {"file": self.file, **dataclasses.asdict(self)}
        out["stars"] = [dataclasses.asdict(s) for s in self.stars]
        return out


def camera_from_fov(fov_deg: float, shape: tuple[int, int]) -> Camera:
    """A pinhole camera for frames of ``shape`` (rows, columns) whose field across the columns is ``fov_deg``
    degrees, principal point at the centre, no distortion, a nominal pixel pitch; its spot size is a default (not
    calibrated: :func:`solve_frame` measures it when given ``spot_calibrated=False``)."""
    height, width = (int(n) for n in shape)
    return Camera.from_fov(fov_deg, width, height, NOMINAL_PITCH_M)


class FrameSolver:
    """Solves frames of one camera (see the module docstring): the pipeline is prepared once (catalogue, pattern
    database), then :meth:`solve` takes frames.  ``pipeline``: a :class:`~starenv.agents.pipeline.Pipeline` (its
    detector, identifier and solver are used; its identifier must work without a prior), None for the built-in one
    with the lost-in-space identifier; ``epoch``: Julian year of the catalogue positions (None: ``DEFAULT_EPOCH``);
    ``fov_tolerance``: the fraction by which the camera's focal length may be off (0: no search)."""

    def __init__(self, camera: Camera, pipeline: Pipeline | None = None, *, spot_calibrated: bool = True,
                 epoch: float | None = None, fov_tolerance: float = FOV_TOLERANCE):
        if not 0.0 <= fov_tolerance < 0.5:
            raise ValueError(f"fov_tolerance must be a fraction in [0, 0.5), got {fov_tolerance}")
        if not isinstance(camera, Camera):
            raise ValueError(f"camera must be a starenv Camera, got {type(camera).__name__}")
        self.camera = camera
        self.spot_calibrated = bool(spot_calibrated)
        self.pipeline = Pipeline(**LOST_IN_SPACE) if pipeline is None else pipeline
        self.epoch = DEFAULT_EPOCH if epoch is None else float(epoch)
        self.pipeline.reset(SensorInfo([camera], 0.0, self.epoch))
        self.catalog = self.pipeline.catalog
        identifier = self.pipeline.agents["identifier"]
        noise_px = getattr(identifier, "centroid_noise_px", DEFAULT_CENTROID_NOISE_PX)
        self.scale_tolerance = N_SIGMA * math.sqrt(2.0) * noise_px / min(camera.width, camera.height)
        self.scales = focal_scales(self.scale_tolerance, fov_tolerance)
        self._search_identifier = identifier
        if self.scales and type(identifier) is LostInSpaceIdentifier:  # the same one on fewer pattern stars
            options = {k: getattr(identifier, k) for k in ("mag_limit", "pattern_stars_per_region",
                                                            "centroid_noise_px", "match_radius_px", "match_threshold")}
            self._search_identifier = LostInSpaceIdentifier(
                **options, max_pattern_stars=min(SEARCH_PATTERN_STARS, identifier.max_pattern_stars))
            self._search_identifier.reset([camera], self.catalog)

    def solve(self, image: np.ndarray, file: str | None = None) -> FrameSolution:
        """The solution of one frame (DN, shape (camera.height, camera.width))."""
        agents, cam = self.pipeline.agents, self.camera
        start = time.perf_counter()
        detector_camera, measured = cam, False
        if not self.spot_calibrated:
            spot = measure_spot_sigma(image)
            if spot is not None:
                sigma = max(SPOT_STEP_PX * round(spot.sigma_px / SPOT_STEP_PX), 0.2)
                detector_camera, measured = dataclasses.replace(cam, psf_sigma_px=sigma), True
        stars = agents["detector"].detect(image, detector_camera)
        labelled = agents["identifier"].identify([stars], [cam], None, [image])[0]
        attitude = self._attitude(labelled, cam)
        grid_point = False
        if attitude is None:  # the scale search: the grid's solution with the most identified stars
            best = 0
            for scale in self.scales:
                trial = scaled_camera(cam, scale)
                found = self._search_identifier.identify([stars], [trial], None, [image])[0]
                count = int(np.count_nonzero(found.catalog_id >= 0))
                if count > best and (solved := self._attitude(found, trial)) is not None:
                    best, labelled, attitude, cam, grid_point = count, found, solved, trial, True
        fit = None  # the last focal-scale fit: (camera, stars, attitude) and its result
        for _ in range(REFIT_ROUNDS if self.scales else 0):
            # Identified again at the scale fitted to the stars: after the search (a grid point is up to the
            # tolerance off), or while the scale is off by more than the identifier tolerates.
            ok = labelled.catalog_id >= 0
            if attitude is None or np.count_nonzero(ok) < MIN_FIT_STARS:
                break
            fit = (cam, labelled, attitude), fit_focal_scale(cam, labelled.xy[ok], self._units(labelled.catalog_id[ok]),
                                                             attitude)
            scale = fit[1][0]
            if not grid_point and abs(scale - 1.0) <= self.scale_tolerance:
                if cam is not self.camera:  # a searched field: the attitude at the fitted one, the same stars
                    fitted = scaled_camera(cam, scale)
                    if (solved := self._attitude(labelled, fitted)) is not None:
                        attitude, cam = solved, fitted
                break
            trial, grid_point = scaled_camera(cam, scale), False
            found = agents["identifier"].identify([stars], [trial], None, [image])[0]
            if (solved := self._attitude(found, trial)) is None:
                break
            labelled, attitude, cam = found, solved, trial
        searched = cam is not self.camera
        elapsed_ms = 1e3 * (time.perf_counter() - start)
        same = fit is not None and all(map(operator.is_, fit[0], (cam, labelled, attitude)))
        known_fit = fit[1] if same else None
        return self._solution(attitude, stars, labelled, cam, searched, elapsed_ms, detector_camera.psf_sigma_px,
                              measured, file, known_fit)

    def _units(self, hip: np.ndarray) -> np.ndarray:
        """ICRS unit vectors (n, 3) of the catalogue stars ``hip`` (n,)."""
        return self.catalog.unit[np.searchsorted(self.catalog.hip, hip)]

    def _attitude(self, labelled: StarMeasurements, camera: Camera) -> Rotation | None:
        ok = labelled.catalog_id >= 0
        if np.count_nonzero(ok) < MIN_IDENTIFIED:
            return None
        try:
            return self.pipeline.agents["solver"].solve(camera.unproject(labelled.xy[ok]),
                                                        self._units(labelled.catalog_id[ok]), None)
        except ValueError:  # degenerate geometry (stars nearly parallel)
            return None

    def _solution(self, attitude, stars, labelled, camera, searched, elapsed_ms, sigma, measured, file,
                  known_fit=None) -> FrameSolution:
        fov_deg = math.degrees(camera.fov[0])
        common = dict(fov_deg=fov_deg, stars_detected=len(stars), time_ms=elapsed_ms, spot_sigma_px=float(sigma),
                      spot_measured=measured, file=file)
        ok = labelled.catalog_id >= 0
        if attitude is None:
            return FrameSolution(False, None, None, None, None, stars_identified=int(ok.sum()), residual_rms_px=None,
                                 **common)
        xy, hip = labelled.xy[ok], labelled.catalog_id[ok]
        units = self._units(hip)
        predicted, _ = camera.project(attitude.apply(units))
        residual = np.linalg.norm(xy - predicted, axis=1)
        ra, dec, roll = radec_roll(attitude)
        found = [IdentifiedStar(float(x), float(y), int(h), float(r))
                 for (x, y), h, r in zip(xy, hip, residual, strict=True)]
        fitted = fitted_sigma = None
        if len(xy) >= MIN_FIT_STARS:
            scale, scale_sigma, _ = known_fit or fit_focal_scale(camera, xy, units, attitude)
            fitted = math.degrees(scaled_camera(camera, scale).fov[0])
            # d fov / d scale: the field of a pinhole, 2 atan(w / 2 f k), over k near 1 (the columns' half-widths)
            half = (camera.cx + 0.5, camera.width - 0.5 - camera.cx)
            slope = sum(h * camera.fx / (camera.fx**2 + h * h) for h in half)
            fitted_sigma = math.degrees(slope * scale_sigma)
        return FrameSolution(True, [float(q) for q in attitude.as_quat()], ra, dec, roll, stars_identified=len(found),
                             residual_rms_px=float(np.sqrt(np.mean(residual**2))), stars=found, fov_searched=searched,
                             fov_fitted_deg=fitted, fov_fitted_sigma_deg=fitted_sigma, **common)


def scaled_camera(camera: Camera, scale: float) -> Camera:
    """``camera`` with its focal length (``fx`` and ``fy``) times ``scale``; 1: ``camera`` itself."""
    return camera if scale == 1.0 else dataclasses.replace(camera, fx=camera.fx * scale, fy=camera.fy * scale)


def focal_scales(scale_tolerance: float, fov_tolerance: float) -> list[float]:
    """The focal-length factors tried when the camera as given does not solve a frame, nearest to 1 first (1 left
    out): steps of twice the identifier's relative scale tolerance ``scale_tolerance`` (its edge tolerance over the
    field's shorter side) up to ``1 +- fov_tolerance``; empty for a ``fov_tolerance`` of 0."""
    step = 2.0 * scale_tolerance
    count = int(fov_tolerance / step + 1e-9)
    return [1.0 + sign * k * step for k in range(1, count + 1) for sign in (1.0, -1.0)]


def fit_focal_scale(camera: Camera, xy: np.ndarray, units: np.ndarray,
                    attitude: Rotation) -> tuple[float, float, Rotation]:
    """Least-squares factor of ``camera``'s focal length, and the attitude, that best project the catalogue stars
    ``units`` (n, 3, ICRS) onto their measured positions ``xy`` (n, 2) px: the attitude (:func:`wahba_svd` of the
    stars unprojected at the current scale) and the scale (the linear least squares of the residuals on the projected
    positions' derivative by the scale, taken numerically) in turn, from ``attitude`` (ICRS -> camera), until the
    scale moves by less than ``FIT_TOLERANCE`` (at most ``FIT_ITERATIONS`` rounds).  Returns the scale, its 1 sigma
    (the residuals' rms over the root sum of squared derivatives, the attitude taken as known) and the attitude."""
    scale, step = 1.0, 1e-6
    for _ in range(FIT_ITERATIONS):
        trial = scaled_camera(camera, scale)
        attitude = Rotation.from_matrix(wahba_svd(trial.unproject(xy), units))
        in_camera = attitude.apply(units)
        predicted, _ = trial.project(in_camera)
        derivative = (scaled_camera(camera, scale * (1.0 + step)).project(in_camera)[0] - predicted) / (scale * step)
        residual = xy - predicted
        update = float(np.vdot(derivative, residual) / np.vdot(derivative, derivative))
        scale += update
        if abs(update) < FIT_TOLERANCE:
            break
    trial = scaled_camera(camera, scale)
    residual = xy - trial.project(attitude.apply(units))[0]
    dof = max(2 * len(xy) - 4, 1)
    sigma = math.sqrt(float(np.vdot(residual, residual)) / dof / float(np.vdot(derivative, derivative)))
    return scale, sigma, attitude


def radec_roll(attitude: Rotation) -> tuple[float, float, float]:
    """Boresight RA, Dec and roll (degrees; RA and roll in [0, 360)) of an ICRS -> camera rotation, the roll as
    :func:`starenv.sim.conventions.pointing` defines it."""
    boresight = attitude.as_matrix()[2]
    ra = math.atan2(boresight[1], boresight[0]) % (2.0 * math.pi)
    dec = math.asin(max(-1.0, min(1.0, float(boresight[2]))))
    about_boresight = (attitude * pointing(ra, dec, 0.0).inv()).as_rotvec()
    return ra / DEG, dec / DEG, (-about_boresight[2] / DEG) % 360.0


_LAST: list[tuple[tuple, FrameSolver]] = []  # the last call's settings and its prepared solver


def solve_frame(image: np.ndarray, camera: Camera, pipeline: Pipeline | None = None, *, spot_calibrated: bool = True,
                epoch: float | None = None, fov_tolerance: float = FOV_TOLERANCE) -> FrameSolution:
    """Solve one frame (see the module docstring and :class:`FrameSolver`); the solver prepared for the last call's
    camera, pipeline (the same object, or the built-in one for None), spot flag, epoch and field tolerance serves the
    next such call."""
    settings = (camera, pipeline, bool(spot_calibrated), epoch, float(fov_tolerance))
    if not _LAST or _LAST[0][0][0] != camera or _LAST[0][0][1] is not pipeline or _LAST[0][0][2:] != settings[2:]:
        _LAST[:] = [(settings, FrameSolver(camera, pipeline, spot_calibrated=spot_calibrated, epoch=epoch,
                                           fov_tolerance=fov_tolerance))]
    return _LAST[0][1].solve(image)


def write_wcs_fits(image: np.ndarray, solution: FrameSolution, camera: Camera, path, replace: bool = False) -> None:
    """``image`` as FITS (one primary HDU, the stored pixel type) with the solved gnomonic WCS of ``camera``
    (:func:`starenv.record.frames.tan_wcs_keys`: the pinhole, no distortion terms) and the solution's figures in the
    header; written whole and moved into place (an existing file only with ``replace``)."""
    from starenv.files import atomic_file
    from starenv.record.frames import _astropy, tan_wcs_keys

    if not solution.solved:
        raise ValueError(f"{solution.file or 'frame'}: not solved, no WCS to write")
    fits, _ = _astropy()
    header = fits.Header()
    header.update(tan_wcs_keys(camera, camera.mounting.inv() * solution.attitude))
    for key, value, comment in (("SOLVED", True, "solved by starenv solve"),
                                ("NSTARS", solution.stars_identified, "identified stars"),
                                ("RESIDRMS", solution.residual_rms_px, "[px] rms residual of the identified stars"),
                                ("SPOTSIG", solution.spot_sigma_px, "[px] spot sigma the detector used")):
        header[key] = (value, comment)
    for k, v in zip(("Q_X", "Q_Y", "Q_Z", "Q_W"), solution.attitude_xyzw, strict=True):
        header[k] = (v, "solved ICRS->camera quaternion")
    with atomic_file(path, "wb", replace=replace) as f:
        fits.PrimaryHDU(np.asarray(image), header).writeto(f)
