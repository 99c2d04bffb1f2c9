"""A camera's digital twin fitted from solved star frames: geometry, spot, background and noise, zero point.

Input: frames (DN arrays) and, for each, a solution (ICRS -> camera attitude and the identified stars' pixel
positions and HIP numbers), from :func:`starenv.real.solve.solve_frame` for files (:func:`calibrate_files`) or any
source (:func:`calibrate_frames`).  The fit, every step by least squares (``scipy.optimize.least_squares``):

1. **Stars, measured again on the pixels** (:func:`measure_stars`): each identified star's window gets a
   pixel-integrated Gaussian (flux, centre, sigma) over its local background (the median of a ring around the
   window), and an aperture flux (radius ``APERTURE_SIGMAS`` spot sigmas; the light a Gaussian of the fitted sigma
   puts beyond it added back).  A star with another catalogue star of comparable brightness near its window is not
   *isolated*; a window reaching the frames' clipping level (:func:`saturation_dn`) is *saturated*; both are left
   out of the spot and photometry fits.  The windows are sized from the solver's spot, then again from the median
   of the fitted sigmas.
2. **Geometry** (:func:`fit_geometry`): per-frame attitude (3 angles each) and shared intrinsics jointly, the
   residuals the fitted centroids minus the catalogue directions projected through the camera
   (:meth:`~starenv.sim.optics.Camera.project`, so the fitted model is the simulator's own).  Models: the pinhole
   (focal length ``f = fx = fy``, principal point), Brown-Conrady (``k1, k2, p1, p2`` with the pinhole's) and paper
   003's 2-D Legendre field (:class:`~starenv.sim.optics.LegendreField`, the modes of total order 2 to ``order``:
   order 0 and 1 are a shift, a scale and a turn, which the attitude and the focal length already are; its principal
   point is the Brown fit's).  The principal point has a Gaussian prior at the sensor's centre, 1 sigma
   ``PRINCIPAL_PRIOR_FRACTION`` of its larger side: across a narrow field a shift of it is nearly a turn of the
   attitude, which only perspective tells apart, and with few stars the distortion would run away with it (the
   prior's pull on a well-measured point is the ratio of the variances, small).  Stars whose residual is beyond
   ``REJECT_SIGMAS`` robust standard deviations (wrong identifications, blends) are dropped and the fit repeated.
   Uncertainties are 1 sigma from the Jacobian (``s^2 (J^T J)^-1``, attitudes marginalised), the table per model
   gives the residual RMS and the Bayesian information criterion that picks the twin's model (``auto``).
3. **Spot** (:func:`fit_spot`): the isolated, unsaturated stars' fitted sigmas against field position,
   ``sigma = a0 + a1 x + a2 y + a3 r^2`` (``x, y`` from the principal point over the half-diagonal, so ``r = 1`` at
   a corner).  The twin takes ``a0`` on axis and a field curvature (:class:`~starenv.sim.optics.FieldSpot`) that
   gives ``a0 + a3`` in the corners where the growth is significant (:meth:`SpotFit.field_spot`), else the model's
   mean over the sensor, ``a0 + a3 / 3``, everywhere.
4. **Background and noise** (:func:`fit_noise`): the level and noise (:func:`~starenv.agents.blocks.frame_background`)
   of tiles of every frame, and the photon-transfer line ``noise^2 = a + level / gain`` through them.  The gain is
   measured only when the tiles' levels spread enough for the slope to be significant (stray light, twilight,
   different exposures); otherwise it is the value given (``gain_e_per_dn``), or 1 e-/DN, and the noise report says
   so.  The intercept holds read noise and bias together (``a = r^2 / g^2 + (0.5 - bias) / g + 1/12``, with the
   ADC's rounding down, -0.5 DN on average and 1/12 DN^2 of variance): read noise needs the bias (``bias_dn``, e.g.
   from a dark frame); without it the twin takes the smallest bias (>= 0) that makes both non-negative, which gives
   the frames' level and noise but not the split.
5. **Zero point** (:func:`fit_zero_point`): ``Hp + 2.5 log10(F / t) = ZP + c (B - V)`` over the isolated,
   unsaturated stars of known colour (``F`` the aperture flux in DN, ``t`` the exposure in s), so ``ZP`` is the
   magnitude giving 1 DN/s; the colour term is kept when it lowers the BIC.  The twin (no colour) takes the zero
   point at the stars' median B-V.

:func:`camera_toml` writes the result as a camera file (``[camera]``: a scenario head's keys, which
:func:`starenv.scenario.load_camera` reads, as ``starenv solve --camera`` and ``starenv compare --camera`` do) and
:func:`scenario_toml` as a scenario that :func:`starenv.scenario.load` accepts (that head, still, at the first frame's
attitude): the camera's digital twin, the fitted values with their 1 sigma in comments.  What the frames cannot give
(pixel pitch, f-number, the split of the throughput between pupil, transmission and quantum efficiency; hot pixels
and cosmic rays, left out; colour) is said there too.  The background (sky and dark together) goes into the dark
current: a camera file has no sky.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from starenv import checks
from starenv.agents.blocks import frame_background
from starenv.agents.detect.centroid import pixel_gaussians
from starenv.config import toml_value
from starenv.real.solve import radec_roll
from starenv.sim.optics import BrownConrady, Camera, FieldSpot, LegendreField, NoDistortion, legendre_mode_count
from starenv.sim.photometry import ZERO_POINT_PHOTONS_M2_S, Photometry
from starenv.sim.sky import StarCatalog, load_catalog

MODELS = ("pinhole", "brown", "legendre")
LEGENDRE_ORDER = 4  # total order of the Legendre field (paper 003 uses 5 on 2048^2 px with hundreds of stars)
APERTURE_SIGMAS = 3.0  # aperture radius for fluxes, in spot sigmas (a Gaussian's 98.9 % of the light)
WINDOW_SIGMAS = 3.5  # half-size of the Gaussian-fit window, in spot sigmas
ISOLATION_MAG = 2.5  # a catalogue star within the window and at most this much fainter spoils a star's isolation
REJECT_SIGMAS = 5.0  # geometry: residuals beyond this many robust standard deviations are dropped
PRINCIPAL_PRIOR_FRACTION = 0.05  # geometry: the principal point's prior 1 sigma, a fraction of the larger side
SPOT_GROWTH_SIGMAS = 3.0  # the twin's spot grows to the corners where the fitted r^2 term exceeds this many 1 sigma
MIN_SNR = 20.0  # spot and photometry fits use stars with at least this aperture signal-to-noise
TILE_PX = 64  # background tiles for the photon-transfer line
GAIN_SIGNIFICANCE = 5.0  # the photon-transfer slope must exceed its 1 sigma this many times for a measured gain
GAIN_SPAN_SIGMAS = 3.0  # ... and the tiles' levels span this many background noise sigmas (not noise alone)
CLIPPED_SIGMAS = 3.0  # a background closer than this many noise sigmas to 0 DN is cut by the floor
QUANTISATION_VAR_DN2 = 1.0 / 12.0  # variance of rounding to integer DN
FLOOR_OFFSET_DN = 0.5  # the ADC rounds down: the mean read-out lies half a DN below the mean signal


@dataclass
class SolvedFrame:
    """One frame with its solution: the image (DN, (H, W)), the ICRS -> camera attitude, the identified stars'
    measured pixel positions (n, 2) and HIP numbers (n,), and the file it came from (for reports)."""

    image: np.ndarray
    attitude: Rotation
    xy: np.ndarray
    hip: np.ndarray
    name: str = ""


@dataclass
class StarSample:
    """The identified stars of one frame measured on its pixels (:func:`measure_stars`), all arrays (n,): fitted
    centroid ``xy`` (n, 2) px (NaN where the fit failed), Gaussian ``sigma_px`` and its 1 sigma ``sigma_err_px``,
    aperture ``flux_dn`` and its background-limited 1 sigma ``flux_err_dn``, local ``background_dn`` and ``noise_dn``
    (per pixel), ``peak_dn`` (brightest pixel above the background), ``saturated``, ``isolated``; with each star's
    ``hip``, ``magnitude`` (Hp), ``b_v`` (NaN unknown) and ICRS ``unit`` (n, 3)."""

    hip: np.ndarray
    magnitude: np.ndarray
    b_v: np.ndarray
    unit: np.ndarray
    xy: np.ndarray
    sigma_px: np.ndarray
    sigma_err_px: np.ndarray
    flux_dn: np.ndarray
    flux_err_dn: np.ndarray
    background_dn: np.ndarray
    noise_dn: np.ndarray
    peak_dn: np.ndarray
    saturated: np.ndarray
    isolated: np.ndarray

    @property
    def good(self) -> np.ndarray:
        """Stars fit for the spot and photometry fits: fitted, isolated, unsaturated, aperture SNR >= MIN_SNR."""
        snr = self.flux_dn / np.maximum(self.flux_err_dn, 1e-12)
        return np.isfinite(self.sigma_px) & self.isolated & ~self.saturated & (snr >= MIN_SNR)


def saturation_dn(images: list[np.ndarray]) -> float | None:
    """The level (DN) where the frames clip, if they reach it: their largest value when it is a full-scale code
    ``2^n - 1`` (n = 8 .. 16) or when three pixels of a frame hold it (a clipped plateau); else None."""
    top = max(float(np.max(im)) for im in images)
    if any(top == 2**bits - 1 for bits in range(8, 17)) or any(np.count_nonzero(im == top) >= 3 for im in images):
        return top
    return None


def adc_bits(images: list[np.ndarray]) -> int:
    """The fewest ADC bits (8 .. 16) that hold the frames' largest value."""
    top = max(float(np.max(im)) for im in images)
    return next((b for b in range(8, 17) if top <= 2**b - 1), 16)


def _window(image: np.ndarray, centre: np.ndarray, half: int) -> np.ndarray | None:
    """The (2 half + 1)^2 window of ``image`` around the pixel nearest ``centre`` (x, y); None off the image."""
    col, row = (int(round(float(c))) for c in centre)
    h, w = image.shape
    if col - half < 0 or row - half < 0 or col + half >= w or row + half >= h:
        return None
    return image[row - half:row + half + 1, col - half:col + half + 1].astype(np.float64)


def _fit_gaussian(data: np.ndarray, start: np.ndarray, sigma_px: float) -> tuple[np.ndarray, float, float] | None:
    """Pixel-integrated Gaussian fitted to a background-subtracted square window ``data`` (DN) whose middle pixel
    is the origin: centre (2,) px relative to it, sigma (px) and sigma's 1 sigma; None when the fit fails."""
    half = data.shape[0] // 2
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    target = data.ravel()

    def resid(p):
        return pixel_gaussians(p[None, :], offsets)[0][0] - target

    def jac(p):
        return pixel_gaussians(p[None, :], offsets)[1][0]

    p0 = np.array([max(float(target.sum()), 1.0), start[0], start[1], math.log(sigma_px)])
    lo = [0.0, -half, -half, math.log(0.2)]
    hi = [np.inf, half, half, math.log(max(10.0, 2 * sigma_px))]
    try:
        fit = least_squares(resid, np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9)), jac=jac, bounds=(lo, hi),
                            method="trf", x_scale="jac", max_nfev=60)
    except (ValueError, np.linalg.LinAlgError):
        return None
    j = fit.jac
    dof = max(len(target) - 4, 1)
    cov = np.linalg.pinv(j.T @ j) * (2.0 * fit.cost / dof)
    sigma = math.exp(fit.x[3])
    if not fit.success or np.hypot(*(fit.x[1:3] - start)) > 2.0 + sigma_px or fit.x[0] <= 0:
        return None
    return fit.x[1:3], sigma, sigma * math.sqrt(max(cov[3, 3], 0.0))


def measure_stars(image: np.ndarray, xy: np.ndarray, hip: np.ndarray, catalog: StarCatalog, camera: Camera,
                  attitude: Rotation, sigma_px: float, saturation: float | None) -> StarSample:
    """The stars ``hip`` identified at ``xy`` (n, 2) px on ``image`` (DN) measured on its pixels (module docstring,
    step 1), with a spot sigma ``sigma_px`` (px) to size the windows; ``camera`` and ``attitude`` (ICRS -> camera)
    place the catalogue's other stars for the isolation test; ``saturation`` (DN) the level where the frame clips
    (:func:`saturation_dn`), None for none."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    rows = np.searchsorted(catalog.hip, hip)
    if np.any(rows >= len(catalog.hip)) or np.any(catalog.hip[np.minimum(rows, len(catalog.hip) - 1)] != hip):
        raise ValueError("identified stars missing from the catalogue (HIP numbers not in it)")
    n = len(xy)
    half = int(np.clip(math.ceil(WINDOW_SIGMAS * sigma_px), 3, 20))
    ring = half + 3
    radius = max(APERTURE_SIGMAS * sigma_px, 2.5)
    out = {k: np.full(n, np.nan) for k in ("sigma_px", "sigma_err_px", "flux_dn", "flux_err_dn", "background_dn",
                                            "noise_dn", "peak_dn")}
    fitted_xy = np.full((n, 2), np.nan)
    saturated = np.zeros(n, bool)
    # Isolation: catalogue stars near each star, no more than ISOLATION_MAG fainter.
    boresight = attitude.inv().apply([0.0, 0.0, 1.0])
    near = catalog.cone(boresight, camera.half_diagonal + 0.01)
    others, front = camera.project(attitude.apply(catalog.unit[near]))
    keep = front & camera.in_frame(others, ring)
    others, other_mag, other_hip = others[keep], catalog.magnitude[near][keep], catalog.hip[near][keep]
    tree = cKDTree(others) if len(others) else None
    isolated = np.ones(n, bool)
    for i in range(n):
        box = _window(image, xy[i], ring)
        if box is None:
            isolated[i] = False
            continue
        if tree is not None:
            for j in tree.query_ball_point(xy[i], 2.0 * half):
                if other_hip[j] != hip[i] and other_mag[j] <= catalog.magnitude[rows[i]] + ISOLATION_MAG:
                    isolated[i] = False
        edge = np.ones(box.shape, bool)
        edge[3:-3, 3:-3] = False
        bg = float(np.median(box[edge]))
        noise = max(1.4826 * float(np.median(np.abs(box[edge] - bg))), math.sqrt(QUANTISATION_VAR_DN2))
        data = box[3:-3, 3:-3] - bg
        middle = np.rint(xy[i])
        if saturation is not None and float(np.max(box[3:-3, 3:-3])) >= saturation:
            saturated[i] = True
        fit = _fit_gaussian(data, xy[i] - middle, sigma_px)
        centre = xy[i] if fit is None else middle + fit[0]
        if fit is not None:
            fitted_xy[i] = centre
            out["sigma_px"][i], out["sigma_err_px"][i] = fit[1], fit[2]
        offsets = np.arange(-half, half + 1)
        dist = np.hypot(offsets[None, :] + middle[0] - centre[0], offsets[:, None] + middle[1] - centre[1])
        inside = dist <= radius
        # The light of a Gaussian spot beyond the aperture, put back (its sigma widened by the pixel's 1/12 px^2).
        spot2 = (out["sigma_px"][i] if fit is not None else sigma_px) ** 2 + 1.0 / 12.0
        kept = 1.0 - math.exp(-0.5 * radius * radius / spot2)
        out["flux_dn"][i] = float(data[inside].sum()) / kept
        out["flux_err_dn"][i] = noise * math.sqrt(inside.sum()) / kept
        out["background_dn"][i], out["noise_dn"][i] = bg, noise
        out["peak_dn"][i] = float(data.max())
    b_v = catalog.b_v[rows] if catalog.b_v is not None else np.full(n, np.nan)
    return StarSample(np.asarray(hip, np.int64), catalog.magnitude[rows], b_v, catalog.unit[rows], fitted_xy,
                      saturated=saturated, isolated=isolated, **out)


# --------------------------------------------------------------------------------------------- geometry


@dataclass
class GeometryFit:
    """One distortion model fitted jointly over frames: the camera (mounting identity: camera = body), the frames'
    ICRS -> camera attitudes, the shared parameters' names, values and 1 sigma, each frame's residuals (n, 2) px
    (measured - model; NaN for a star left out) and the fit's statistics."""

    model: str
    camera: Camera
    attitudes: list[Rotation]
    names: list[str]
    values: np.ndarray
    errors: np.ndarray
    residuals: list[np.ndarray]
    stars_used: int
    rejected: int
    rms_px: float
    bic: float

    def row(self) -> dict:
        """The residual table's row for this model."""
        r = np.concatenate([x[np.isfinite(x[:, 0])] for x in self.residuals])
        return {"model": self.model, "params": len(self.names), "stars": self.stars_used, "rejected": self.rejected,
                "rms_x_px": float(np.sqrt(np.mean(r[:, 0] ** 2))), "rms_y_px": float(np.sqrt(np.mean(r[:, 1] ** 2))),
                "rms_px": self.rms_px, "max_px": float(np.max(np.hypot(*r.T))), "bic": self.bic}


def _legendre_free(order: int) -> np.ndarray:
    """Indices of the Legendre modes of total order 2 .. ``order`` (:func:`~starenv.sim.optics.legendre_basis`)."""
    return np.arange(legendre_mode_count(1), legendre_mode_count(order))


def _distortion(model: str, p: np.ndarray, order: int):
    if model == "pinhole":
        return NoDistortion()
    if model == "brown":
        return BrownConrady(k1=p[0], k2=p[1], p1=p[2], p2=p[3])
    free = _legendre_free(order)
    cx, cy = np.zeros(legendre_mode_count(order)), np.zeros(legendre_mode_count(order))
    cx[free], cy[free] = p[: len(free)], p[len(free):]
    return LegendreField(tuple(cx), tuple(cy))


def _shared_names(model: str, order: int) -> list[str]:
    base = ["f_px"] if model == "legendre" else ["f_px", "cx_px", "cy_px"]
    if model == "brown":
        return base + ["k1", "k2", "p1", "p2"]
    if model == "legendre":
        free = _legendre_free(order)
        return base + [f"wx{m}_px" for m in free] + [f"wy{m}_px" for m in free]
    return base


def fit_geometry(frames_xy: list[np.ndarray], units: list[np.ndarray], attitudes: list[Rotation], start: Camera,
                 model: str = "brown", order: int = LEGENDRE_ORDER) -> GeometryFit:
    """Joint fit over frames of per-frame attitudes and the shared camera ``model`` (module docstring, step 2).

    ``frames_xy[i]`` (n_i, 2) px measured positions of stars whose ICRS unit vectors are ``units[i]`` (n_i, 3);
    ``attitudes[i]`` the starting ICRS -> camera attitude; ``start`` the starting camera (its focal length and
    principal point; for ``legendre`` they are held at the start's principal point).
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    names = _shared_names(model, order)
    n_dist = len(names) - (1 if model == "legendre" else 3)
    keep = [np.all(np.isfinite(xy), axis=1) for xy in frames_xy]
    rejected = 0
    shared0 = np.concatenate([[start.fx] if model == "legendre" else [start.fx, start.cx, start.cy], np.zeros(n_dist)])

    def camera_of(shared):
        if model == "legendre":
            f, cx, cy, dist = shared[0], start.cx, start.cy, shared[1:]
        else:
            f, cx, cy, dist = shared[0], shared[1], shared[2], shared[3:]
        return replace(start, fx=f, fy=f, cx=cx, cy=cy, distortion=_distortion(model, dist, order),
                       mounting=Rotation.identity())

    atts = list(attitudes)
    attempts, noise_px = 3, 0.2
    for attempt in range(attempts):
        xy = [f[k] for f, k in zip(frames_xy, keep, strict=True)]
        uv = [u[k] for u, k in zip(units, keep, strict=True)]
        counts = [len(x) for x in xy]
        n_frames, n_res = len(xy), 2 * sum(counts)
        n_par = 3 * n_frames + len(names)
        if n_res <= n_par:
            raise ValueError(f"{model}: {sum(counts)} stars over {n_frames} frames are too few for "
                             f"{len(names)} camera parameters and {n_frames} attitudes")
        prior = None
        if model != "legendre":  # the principal point's prior, in units of the stars' noise (module docstring)
            weight = noise_px / (PRINCIPAL_PRIOR_FRACTION * max(start.width, start.height))
            prior = (3 * n_frames + np.array([1, 2]), np.array([(start.width - 1) / 2, (start.height - 1) / 2]),
                     weight)
        fit = _joint_fit(np.concatenate(xy), uv, atts, np.concatenate([np.zeros(3 * n_frames), shared0]), camera_of,
                         "soft_l1" if attempt == 0 else "linear", prior)
        r = fit.fun[:n_res].reshape(-1, 2)
        robust = 1.4826 * float(np.median(np.abs(r)))
        noise_px = max(robust, 1e-3)
        bad = np.hypot(*r.T) > REJECT_SIGMAS * max(robust, 1e-3) * math.sqrt(2.0)
        if attempt == attempts - 1 or (attempt > 0 and not bad.any()):
            break
        # Drop the outliers (in every frame) and refit from this solution.
        offset = 0
        for i, c in enumerate(counts):
            idx = np.flatnonzero(keep[i])
            keep[i][idx[bad[offset:offset + c]]] = False
            offset += c
        rejected += int(bad.sum())
        atts = [Rotation.from_rotvec(fit.x[3 * i:3 * i + 3]) * atts[i] for i in range(n_frames)]
        shared0 = fit.x[3 * n_frames:]
    atts = [Rotation.from_rotvec(fit.x[3 * i:3 * i + 3]) * atts[i] for i in range(n_frames)]
    shared = fit.x[3 * n_frames:]
    j = fit.jac.toarray() if sparse.issparse(fit.jac) else np.asarray(fit.jac)
    rss = float(np.sum(fit.fun[:n_res] ** 2))
    dof = max(n_res - n_par, 1)
    cov = np.linalg.pinv(j.T @ j) * (rss / dof)
    errors = np.sqrt(np.maximum(np.diag(cov)[3 * n_frames:], 0.0))
    residual_frames, offset = [], 0
    for i, c in enumerate(counts):
        full = np.full((len(frames_xy[i]), 2), np.nan)
        full[keep[i]] = fit.fun[2 * offset:2 * (offset + c)].reshape(-1, 2)
        residual_frames.append(full)
        offset += c
    bic = n_res * math.log(rss / n_res) + n_par * math.log(n_res)
    rms = math.sqrt(rss / sum(counts))
    return GeometryFit(model, camera_of(shared), atts, names, shared, errors, residual_frames, sum(counts),
                       rejected, rms, bic)


def _joint_fit(measured: np.ndarray, units: list[np.ndarray], attitudes: list[Rotation], x0: np.ndarray, camera_of,
               loss: str, prior: tuple[np.ndarray, np.ndarray, float] | None = None):
    """``least_squares`` of measured positions (n, 2) px against the catalogue directions ``units`` (per frame) through
    the attitudes turned by their parameters (a rotation vector per frame, first in ``x0``) and ``camera_of(rest)``;
    ``prior`` (parameter indices, their prior values, weight) appends ``weight (p - value)`` to the residuals."""
    n_frames, counts = len(units), [len(u) for u in units]
    n_res = 2 * len(measured)
    n_prior = 0 if prior is None else len(prior[0])

    def residuals(p):
        extra = [] if prior is None else [prior[2] * (p[prior[0]] - prior[1])]
        try:
            cam = camera_of(p[3 * n_frames:])
        except ValueError:  # a step outside the camera's valid range
            return np.full(n_res + n_prior, 1e6)
        vecs = [(Rotation.from_rotvec(p[3 * i:3 * i + 3]) * attitudes[i]).apply(units[i]) for i in range(n_frames)]
        proj, _ = cam.project(np.concatenate(vecs))
        return np.concatenate([np.nan_to_num((measured - proj).ravel(), nan=1e6), *extra])

    sparsity = sparse.lil_matrix((n_res + n_prior, len(x0)), dtype=np.int8)
    row = 0
    for i, c in enumerate(counts):
        sparsity[row:row + 2 * c, 3 * i:3 * i + 3] = 1
        row += 2 * c
    sparsity[:n_res, 3 * n_frames:] = 1
    for k in range(n_prior):
        sparsity[n_res + k, prior[0][k]] = 1
    return least_squares(residuals, x0, jac_sparsity=sparsity, x_scale="jac", method="trf", loss=loss, f_scale=1.0)


# --------------------------------------------------------------------------------------------- spot


@dataclass
class SpotFit:
    """The spot's Gaussian sigma over the field: ``sigma = a0 + a1 x + a2 y + a3 r^2`` (px; ``x, y`` from the
    principal point over the half-diagonal ``scale_px``), 1 sigma errors, the stars' scatter about the model (px),
    the stars used, and the field mean (the twin's one sigma, ``a0 + a3 / 3``) with its 1 sigma."""

    coeffs: np.ndarray
    errors: np.ndarray
    scatter_px: float
    stars: int
    scale_px: float
    mean_px: float
    mean_err_px: float

    def field_spot(self) -> tuple[float, FieldSpot | None]:
        """The spot as the simulator draws it: the on-axis sigma (px) and a
        :class:`~starenv.sim.optics.FieldSpot` whose field curvature gives the model's corner sigma, ``a0 + a3``,
        where the r^2 term exceeds ``SPOT_GROWTH_SIGMAS`` of its 1 sigma; else the field mean and None (the linear
        terms, a tilted focal plane, have no counterpart there)."""
        a0, a3 = float(self.coeffs[0]), float(self.coeffs[3])
        if a3 > SPOT_GROWTH_SIGMAS * self.errors[3] and a0 > 0.1:
            curvature = math.sqrt((a0 + a3) ** 2 - a0**2)
            return float(np.clip(a0, 0.1, 20.0)), FieldSpot(field_curvature_sigma_px=min(curvature, 20.0))
        return float(np.clip(self.mean_px, 0.1, 20.0)), None

    def at(self, xy: np.ndarray, camera: Camera) -> np.ndarray:
        """The model's sigma (px) at pixel positions ``xy`` (n, 2)."""
        return _spot_design(np.asarray(xy, np.float64).reshape(-1, 2), camera, self.scale_px) @ self.coeffs


def _spot_design(xy: np.ndarray, camera: Camera, scale: float) -> np.ndarray:
    x, y = (xy[:, 0] - camera.cx) / scale, (xy[:, 1] - camera.cy) / scale
    return np.column_stack([np.ones(len(xy)), x, y, x * x + y * y])


def fit_spot(xy: np.ndarray, sigma_px: np.ndarray, camera: Camera) -> SpotFit:
    """The spot model of module docstring step 3 from stars' positions (n, 2) px and fitted sigmas (n,) px, robust
    to a few bad fits (Huber loss at 3 robust standard deviations)."""
    xy, sigma_px = np.asarray(xy, np.float64).reshape(-1, 2), np.asarray(sigma_px, np.float64)
    if len(sigma_px) < 8:
        raise ValueError(f"spot: {len(sigma_px)} isolated, unsaturated stars with SNR >= {MIN_SNR:g}, need >= 8")
    scale = FieldSpot.field_radius_px(camera.intrinsics)
    a = _spot_design(xy, camera, scale)
    spread = 1.4826 * float(np.median(np.abs(sigma_px - np.median(sigma_px))))
    fit = least_squares(lambda c: a @ c - sigma_px, np.array([np.median(sigma_px), 0, 0, 0]), loss="huber",
                        f_scale=max(3.0 * spread, 1e-3))
    resid = a @ fit.x - sigma_px
    scatter = 1.4826 * float(np.median(np.abs(resid)))
    cov = np.linalg.pinv(a.T @ a) * scatter**2 * len(a) / max(len(a) - 4, 1)
    mean_vec = np.array([1.0, 0.0, 0.0, 1.0 / 3.0])
    return SpotFit(fit.x, np.sqrt(np.diag(cov)), scatter, len(a), scale, float(mean_vec @ fit.x),
                   float(math.sqrt(mean_vec @ cov @ mean_vec)))


# --------------------------------------------------------------------------------------------- noise


@dataclass
class NoiseFit:
    """Background and noise of the frames: per-frame level and noise (DN), the photon-transfer line
    ``noise^2 = intercept + level * slope`` over tiles with its 1 sigma, the gain (e-/DN) and whether it was
    measured, the bias (DN) and read noise (e-) the twin takes and whether they were measured, and a sentence
    saying what the frames allowed."""

    levels_dn: np.ndarray
    noises_dn: np.ndarray
    intercept_dn2: float
    slope: float
    slope_err: float
    level_span_dn: float
    gain_e_per_dn: float
    gain_err: float
    gain_measured: bool
    bias_dn: float
    read_noise_e: float
    read_noise_err_e: float
    read_noise_measured: bool
    note: str

    @property
    def level_dn(self) -> float:
        return float(np.median(self.levels_dn))

    @property
    def noise_dn(self) -> float:
        return float(np.median(self.noises_dn))


def tile_statistics(image: np.ndarray, tile_px: int = TILE_PX) -> tuple[np.ndarray, np.ndarray]:
    """Background level and noise (DN) of each ``tile_px`` square tile of ``image`` (stars clipped away), (n,)."""
    h, w = image.shape
    levels, noises = [], []
    for r in range(0, h - tile_px + 1, tile_px):
        for c in range(0, w - tile_px + 1, tile_px):
            level, noise = frame_background(image[r:r + tile_px, c:c + tile_px])
            levels.append(level)
            noises.append(noise)
    return np.array(levels), np.array(noises)


def fit_noise(images: list[np.ndarray], gain_e_per_dn: float | None = None, bias_dn: float | None = None,
              tile_px: int = TILE_PX) -> NoiseFit:
    """Background, noise, gain and read noise of ``images`` (module docstring, step 4); ``gain_e_per_dn`` and
    ``bias_dn``: known values (a datasheet, a dark frame) that replace the estimates."""
    whole = np.array([frame_background(im) for im in images])
    stats = [tile_statistics(im, min(tile_px, *im.shape)) for im in images]
    level = np.concatenate([s[0] for s in stats])
    var = np.concatenate([s[1] for s in stats]) ** 2
    # Weighted line: a variance estimated from m differences has a relative 1 sigma of about sqrt(1.5 / m) x 2.
    m = tile_px * (tile_px - 1) / 4.0
    w = 1.0 / (var * 2.0 * math.sqrt(1.5 / m)) ** 2
    a = np.column_stack([np.ones_like(level), level])
    normal = a.T @ (a * w[:, None])
    coef = np.linalg.solve(normal, a.T @ (w * var)) if len(level) >= 3 and np.ptp(level) > 0 else np.array(
        [float(np.mean(var)), 0.0])
    resid = var - a @ coef
    chi2 = float(np.sum(w * resid**2)) / max(len(level) - 2, 1)
    cov = np.linalg.pinv(normal) * max(chi2, 1.0)
    intercept, slope = float(coef[0]), float(coef[1])
    slope_err = float(math.sqrt(max(cov[1, 1], 0.0)))
    span = float(np.ptp(level)) if len(level) else 0.0
    noise_med = float(np.median(whole[:, 1]))
    # A background within CLIPPED_SIGMAS noise sigmas of 0 DN is cut by the ADC's floor: its statistics are biased.
    clipped = float(np.median(whole[:, 0])) < CLIPPED_SIGMAS * noise_med
    measured = (slope > GAIN_SIGNIFICANCE * slope_err and slope > 0 and span > GAIN_SPAN_SIGMAS * noise_med
                and not clipped)
    notes = []
    if measured and gain_e_per_dn is None:
        gain, gain_err, gain_measured = 1.0 / slope, slope_err / slope**2, True
        notes.append(f"gain from the photon-transfer line over {len(level)} tiles spanning {span:.1f} DN")
    else:
        gain, gain_err, gain_measured = float(gain_e_per_dn or 1.0), 0.0, False
        if gain_e_per_dn is not None:
            notes.append(f"gain given ({gain:g} e-/DN)")
        elif clipped:
            notes.append(f"gain not measurable: the background ({float(np.median(whole[:, 0])):.2f} DN, noise "
                         f"{noise_med:.2f} DN) is cut by the floor at 0 DN; 1 e-/DN assumed")
        else:
            notes.append(f"gain not measurable: the tiles' background levels span {span:.1f} DN, too little for the "
                         f"photon-transfer slope ({slope:.3g} +- {slope_err:.2g} per DN); 1 e-/DN assumed")
        intercept = float(np.median(whole[:, 1])) ** 2 - float(np.median(whole[:, 0])) / gain
    # intercept = r^2 / g^2 + (0.5 - bias) / g + 1/12  (module docstring)
    if bias_dn is not None:
        r2 = gain**2 * (intercept - QUANTISATION_VAR_DN2) + gain * (bias_dn - FLOOR_OFFSET_DN)
        bias, read, read_measured = float(bias_dn), math.sqrt(max(r2, 0.0)), gain_measured or gain_e_per_dn is not None
        d_r2 = gain**2 * math.sqrt(max(cov[0, 0], 0.0))
        read_err = d_r2 / (2 * read) if read > 0 else float("nan")
        notes.append(f"read noise from the intercept with the bias given ({bias:g} DN)")
    else:
        # Smallest bias >= 0 with r^2 >= 0: r^2 = g^2 (a - 1/12) + g (bias - 0.5).
        bias = max(0.0, FLOOR_OFFSET_DN - gain * (intercept - QUANTISATION_VAR_DN2))
        bias = min(bias, max(float(np.median(whole[:, 0])), 0.0))
        read = math.sqrt(max(gain**2 * (intercept - QUANTISATION_VAR_DN2) + gain * (bias - FLOOR_OFFSET_DN), 0.0))
        read_measured, read_err = False, float("nan")
        notes.append("bias and read noise not separable from light frames without a known bias (bias_dn): the twin "
                     f"takes bias {bias:.1f} DN and read noise {read:.2f} e-, which give the frames' level and noise")
    return NoiseFit(whole[:, 0], whole[:, 1], intercept, slope, slope_err, span, gain, gain_err, gain_measured, bias,
                    read, read_err, read_measured, "; ".join(notes))


# --------------------------------------------------------------------------------------------- photometry


@dataclass
class ZeroPointFit:
    """``Hp + 2.5 log10(F / t) = zp + colour (B - V)`` over ``stars`` (F in DN, t in s): ``zp`` the magnitude giving
    1 DN/s (at B - V = 0 with the colour term, else for the stars' colours), its 1 sigma, the colour term (0 when not
    kept), its 1 sigma and whether it was kept (lower BIC), the scatter (mag) with and without it, and ``zp_twin``,
    the zero point at the stars' median B - V (the twin has no colour)."""

    zp_mag: float
    zp_err_mag: float
    colour: float
    colour_err: float
    colour_kept: bool
    scatter_mag: float
    scatter_no_colour_mag: float
    stars: int
    median_b_v: float
    zp_twin_mag: float


def fit_zero_point(magnitude: np.ndarray, b_v: np.ndarray, flux_dn: np.ndarray, exposure_s: float) -> ZeroPointFit:
    """The zero point of module docstring step 5 (robust: Huber loss at 3 robust standard deviations)."""
    ok = np.isfinite(magnitude) & np.isfinite(b_v) & (flux_dn > 0)
    mag, bv, flux = magnitude[ok], b_v[ok], flux_dn[ok]
    if len(mag) < 5:
        raise ValueError(f"zero point: {len(mag)} isolated, unsaturated stars of known colour, need >= 5")
    y = mag + 2.5 * np.log10(flux / exposure_s)
    fits, inlier = {}, None
    for cols in (1, 2):
        a = np.column_stack([np.ones_like(bv), bv][:cols])
        spread = 1.4826 * float(np.median(np.abs(y - np.median(y))))
        fit = least_squares(lambda c, a=a: a @ c - y, np.r_[np.median(y), np.zeros(cols - 1)], loss="huber",
                            f_scale=max(3.0 * spread, 1e-3))
        resid = a @ fit.x - y
        scatter = 1.4826 * float(np.median(np.abs(resid)))
        cov = np.linalg.pinv(a.T @ a) * scatter**2 * len(a) / max(len(a) - cols, 1)
        if inlier is None:  # both models' BIC over the same stars: those within 3 scatters of the first
            inlier = np.abs(resid) < 3 * max(scatter, 1e-3)
        rss = float(np.sum(resid[inlier] ** 2))
        n = int(inlier.sum())
        bic = n * math.log(max(rss, 1e-300) / n) + cols * math.log(n)
        fits[cols] = (fit.x, np.sqrt(np.diag(cov)), scatter, bic)
    keep = fits[2][3] < fits[1][3]
    coef, err, scatter, _ = fits[2 if keep else 1]
    med_bv = float(np.median(bv))
    colour = float(coef[1]) if keep else 0.0
    return ZeroPointFit(float(coef[0]), float(err[0]), colour, float(fits[2][1][1]), bool(keep), scatter,
                        fits[1][2], len(mag), med_bv, float(coef[0]) + colour * med_bv)


# --------------------------------------------------------------------------------------------- the whole fit


@dataclass
class Calibration:
    """Everything fitted from a set of frames (module docstring) and what the twin needs besides."""

    shape: tuple[int, int]
    exposure_s: float
    epoch: float
    geometry: dict[str, GeometryFit]
    chosen: str
    spot: SpotFit
    noise: NoiseFit
    zero_point: ZeroPointFit
    samples: list[StarSample]
    names: list[str]
    adc_bits: int
    faintest_mag: float
    saturated_stars: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def camera(self) -> Camera:
        """The chosen model's camera with the spot: :meth:`SpotFit.field_spot` where the spot measurably grows
        towards the corners, else the field mean everywhere."""
        sigma, field_spot = self.spot.field_spot()
        return replace(self.geometry[self.chosen].camera, psf_sigma_px=sigma, spot=field_spot)

    @property
    def attitudes(self) -> list[Rotation]:
        """The frames' ICRS -> camera attitudes under the chosen model."""
        return self.geometry[self.chosen].attitudes


def check_options(exposure_s: float, legendre_order: int, gain_e_per_dn: float | None, bias_dn: float | None) -> None:
    """Refuse an exposure (s), Legendre order, gain (e-/DN) or bias (DN) out of range, naming it."""
    checks.in_range("exposure_s", exposure_s, 0.0, 3600.0, low_open=True, unit="s")
    checks.integer("legendre_order", legendre_order, 2, 8)
    if gain_e_per_dn is not None:
        checks.in_range("gain_e_per_dn", gain_e_per_dn, 1e-3, 1e4, unit="e-/DN")
    if bias_dn is not None:
        checks.in_range("bias_dn", bias_dn, 0.0, 65535.0, unit="DN")


def calibrate_frames(frames: list[SolvedFrame], start: Camera, exposure_s: float = 1.0, epoch: float = 2026.0,
                     models: tuple[str, ...] = MODELS, choose: str = "auto", legendre_order: int = LEGENDRE_ORDER,
                     gain_e_per_dn: float | None = None, bias_dn: float | None = None,
                     catalog: StarCatalog | None = None) -> Calibration:
    """Fit the twin from solved frames (module docstring).  ``start``: the camera the frames were solved with (its
    focal length, principal point and spot sigma start the fit); ``exposure_s``: the frames' exposure (s);
    ``epoch``: the catalogue epoch (Julian year); ``choose``: the twin's distortion model, one of ``models`` or
    ``"auto"`` (the lowest BIC); ``gain_e_per_dn``, ``bias_dn``: known values, else estimated where the frames allow
    (:func:`fit_noise`)."""
    if not frames:
        raise ValueError("calibrate: no solved frames")
    check_options(exposure_s, legendre_order, gain_e_per_dn, bias_dn)
    shapes = {f.image.shape for f in frames}
    if len(shapes) != 1:
        raise ValueError(f"calibrate: the frames differ in size ({sorted(shapes)}): one camera at a time")
    if choose != "auto" and choose not in models:
        raise ValueError(f"choose must be 'auto' or one of {models}, got {choose!r}")
    catalog = catalog if catalog is not None else load_catalog(14.0, epoch)
    images = [np.asarray(f.image) for f in frames]
    saturation = saturation_dn(images)
    samples = [measure_stars(f.image, f.xy, f.hip, catalog, start, f.attitude, start.psf_sigma_px, saturation)
               for f in frames]
    # Size the windows with the measured spot and measure again: the start's sigma may be a guess.
    good_sigma = np.concatenate([s.sigma_px[s.good] for s in samples])
    if len(good_sigma) >= 8:
        start = replace(start, psf_sigma_px=float(np.clip(np.median(good_sigma), 0.1, 20.0)))
        samples = [measure_stars(f.image, f.xy, f.hip, catalog, start, f.attitude, start.psf_sigma_px, saturation)
                   for f in frames]
    xy = [np.where(np.isfinite(s.xy), s.xy, np.asarray(f.xy, np.float64)) for s, f in zip(samples, frames, strict=True)]
    units = [s.unit for s in samples]
    attitudes = [f.attitude for f in frames]
    geometry: dict[str, GeometryFit] = {}
    for model in [m for m in MODELS if m in models and m != "legendre"]:
        geometry[model] = fit_geometry(xy, units, attitudes, start, model)
    if "legendre" in models:
        base = geometry.get("brown") or geometry.get("pinhole")
        seed_camera = replace(start, cx=base.camera.cx, cy=base.camera.cy) if base else start
        geometry["legendre"] = fit_geometry(xy, units, attitudes, seed_camera, "legendre", legendre_order)
    chosen = min(geometry, key=lambda m: geometry[m].bic) if choose == "auto" else choose
    cam = geometry[chosen].camera
    good = [s.good for s in samples]
    spot = fit_spot(np.concatenate([s.xy[g] for s, g in zip(samples, good, strict=True)]),
                    np.concatenate([s.sigma_px[g] for s, g in zip(samples, good, strict=True)]), cam)
    noise = fit_noise(images, gain_e_per_dn, bias_dn)
    zp = fit_zero_point(*(np.concatenate([getattr(s, k)[g] for s, g in zip(samples, good, strict=True)])
                          for k in ("magnitude", "b_v", "flux_dn")), exposure_s)
    faintest = float(max(np.max(s.magnitude) for s in samples if len(s.magnitude)))
    return Calibration(images[0].shape, exposure_s, epoch, geometry, chosen, spot, noise, zp, samples,
                       [f.name for f in frames], adc_bits(images), faintest,
                       int(sum(s.saturated.sum() for s in samples)))


def calibrate_files(paths: list[str | Path], fov_deg: float, epoch: float = 2026.0,
                    **options) -> tuple[Calibration, list]:
    """Read and solve each file (:func:`starenv.real.read.read_frame`, :func:`starenv.real.solve.solve_frame` on
    :func:`starenv.real.solve.camera_from_fov`, the spot measured), then :func:`calibrate_frames` on the solved ones
    (``options`` go there).  Returns the calibration and the per-file solutions (:class:`FrameSolution`)."""
    from starenv.real.read import read_frame
    from starenv.real.solve import camera_from_fov, solve_frame

    check_options(options.get("exposure_s", 1.0), options.get("legendre_order", LEGENDRE_ORDER),
                  options.get("gain_e_per_dn"), options.get("bias_dn"))  # before the frames are solved
    frames, solutions, camera, spots = [], [], None, []
    for path in paths:
        image = read_frame(path)
        if camera is None:
            camera = camera_from_fov(fov_deg, image.shape)
        elif (camera.height, camera.width) != image.shape:
            raise ValueError(f"{path}: {image.shape[1]} x {image.shape[0]} px, the first frame is {camera.width} x "
                             f"{camera.height}: one camera at a time")
        solution = solve_frame(image, camera, spot_calibrated=False, epoch=epoch)
        solution.file = str(path)
        solutions.append(solution)
        if solution.solved:
            frames.append(solved_frame(image, solution))
            spots.append(solution.spot_sigma_px)
    if not frames:
        raise ValueError(f"calibrate: none of the {len(paths)} frames solved with --fov {fov_deg:g}")
    start = replace(camera, psf_sigma_px=float(np.median(spots)))
    return calibrate_frames(frames, start, epoch=epoch, **options), solutions


def solved_frame(image: np.ndarray, solution) -> SolvedFrame:
    """A :class:`SolvedFrame` from a solved :class:`starenv.real.solve.FrameSolution`."""
    xy = np.array([(s.x_px, s.y_px) for s in solution.stars], np.float64).reshape(-1, 2)
    hip = np.array([s.hip for s in solution.stars], np.int64)
    return SolvedFrame(np.asarray(image), solution.attitude, xy, hip, solution.file or "")


# --------------------------------------------------------------------------------------------- reports, twin


def residual_table(cal: Calibration) -> str:
    """Markdown table: one row per distortion model (module docstring step 2), the twin's model marked."""
    lines = ["| model | camera params | stars | rejected | RMS x (px) | RMS y (px) | RMS (px) | max (px) | BIC |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, g in cal.geometry.items():
        r = g.row()
        mark = " (twin)" if name == cal.chosen else ""
        lines.append(f"| {name}{mark} | {r['params']} | {r['stars']} | {r['rejected']} | {r['rms_x_px']:.3f} | "
                     f"{r['rms_y_px']:.3f} | {r['rms_px']:.3f} | {r['max_px']:.3f} | {r['bic']:.1f} |")
    return "\n".join(lines)


def report_markdown(cal: Calibration) -> str:
    """The calibration's report: frames, the residual table per model, the fitted values with their 1 sigma."""
    g = cal.geometry[cal.chosen]
    spot, noise, zp = cal.spot, cal.noise, cal.zero_point
    out = [f"# Camera calibration from {len(cal.names)} frames", "",
           f"{cal.shape[1]} x {cal.shape[0]} px, exposure {cal.exposure_s:g} s, catalogue epoch {cal.epoch:g}.", "",
           "## Geometry: residuals per distortion model", "", residual_table(cal), "",
           f"The twin takes `{cal.chosen}`.  Its parameters (1 sigma):", "",
           "| parameter | value | 1 sigma |", "|---|---|---|"]
    out += [f"| {n} | {v:.6g} | {e:.2g} |" for n, v, e in zip(g.names, g.values, g.errors, strict=True)]
    out += ["", "## Spot", "",
            f"Gaussian sigma over {spot.stars} isolated stars: {spot.coeffs[0]:.3f} +- {spot.errors[0]:.3f} px at the "
            f"principal point, x slope {spot.coeffs[1]:+.3f} +- {spot.errors[1]:.3f}, y slope {spot.coeffs[2]:+.3f} +- "
            f"{spot.errors[2]:.3f}, r^2 term {spot.coeffs[3]:+.3f} +- {spot.errors[3]:.3f} px (r = 1 at a corner); "
            f"field mean {spot.mean_px:.3f} +- {spot.mean_err_px:.3f} px; stars' scatter about the model "
            f"{spot.scatter_px:.3f} px.", "", "## Background and noise", "",
            f"Level {noise.level_dn:.2f} DN, noise {noise.noise_dn:.3f} DN (medians over the frames); photon-transfer "
            f"slope {noise.slope:.4g} +- {noise.slope_err:.2g} per DN, intercept {noise.intercept_dn2:.3f} DN^2; gain "
            f"{noise.gain_e_per_dn:.3f}" + (f" +- {noise.gain_err:.3f}" if noise.gain_measured else "") + " e-/DN, "
            f"bias {noise.bias_dn:.1f} DN, read noise {noise.read_noise_e:.2f}"
            + (f" +- {noise.read_noise_err_e:.2f}" if noise.read_noise_measured else "") + f" e-.  {noise.note}.",
            "", "## Zero point", "",
            f"Hp + 2.5 log10(F / t) = {zp.zp_mag:.3f} +- {zp.zp_err_mag:.3f} "
            f"{f'+ {zp.colour:.3f} (B-V)' if zp.colour_kept else ''} over {zp.stars} stars (F in DN, t in s); colour "
            f"term {zp.colour:+.3f} +- {zp.colour_err:.3f} mag per mag of B-V "
            f"{'kept (lower BIC)' if zp.colour_kept else 'not kept (no lower BIC)'}; scatter {zp.scatter_mag:.3f} mag "
            f"({zp.scatter_no_colour_mag:.3f} without colour).  Twin zero point (median B-V {zp.median_b_v:.2f}): "
            f"{zp.zp_twin_mag:.3f} mag for 1 DN/s."]
    return "\n".join(out) + "\n"


def _twin_head(cal: Calibration, pixel_pitch_um: float, f_number: float) -> list[tuple[str, str, str]]:
    """The twin's head as (table, key, value-with-comment) lines, table "" for the head's own keys."""
    g, spot, noise, zp = cal.geometry[cal.chosen], cal.spot, cal.noise, cal.zero_point
    cam = cal.camera
    err = dict(zip(g.names, g.errors, strict=True))
    pp_err = g if "cx_px" in err else next((m for m in cal.geometry.values() if "cx_px" in m.names), None)
    focal_mm = cam.fx * pixel_pitch_um * 1e-3
    # Throughput: electrons per second of a magnitude-0 star = gain x 10^(0.4 zp).
    e0 = noise.gain_e_per_dn * 10.0 ** (0.4 * zp.zp_twin_mag)
    pupil_for_unit = math.sqrt(4.0 * e0 / (math.pi * ZERO_POINT_PHOTONS_M2_S))  # pupil (m) at throughput 1
    f_number = min(f_number, focal_mm * 1e-3 / pupil_for_unit * 0.999)
    if f_number < 0.5:
        raise ValueError(f"the zero point needs a pupil of {pupil_for_unit * 1e3:.1f} mm at full throughput, more than "
                         f"f/0.5 of the {focal_mm:.1f} mm focal length allows: check --exposure-s and --gain")
    qe = e0 / Photometry(focal_mm * 1e-3 / f_number, 1.0, 1.0).electrons_per_s_mag0
    # Background electrons per pixel over the exposure: the level above bias (with the floor's half DN) x gain.
    bg_e = max((noise.level_dn - noise.bias_dn + FLOOR_OFFSET_DN) * noise.gain_e_per_dn, 0.0)
    max_dn = 2**cal.adc_bits - 1

    def v(x):
        return toml_value(float(x))

    def pm(name):
        return f"{pp_err.values[pp_err.names.index(name)]:.3f} +- {pp_err.errors[pp_err.names.index(name)]:.3f}" \
            if pp_err is not None else "held"

    rows = [
        ("", "width", f"{cam.width}"),
        ("", "height", f"{cam.height}"),
        ("", "pixel_pitch_um", f"{v(pixel_pitch_um)}  # assumed: the frames give focal length / pitch only"),
        ("", "focal_length_mm", f"{v(focal_mm)}  # f = {cam.fx:.3f} +- {err['f_px']:.3f} px"),
        ("", "principal_point_px", f"[{v(cam.cx)}, {v(cam.cy)}]  # cx {pm('cx_px')}, cy {pm('cy_px')} px"),
        ("", "f_number", f"{v(f_number)}  # assumed (lowered where the throughput needs a larger pupil)"),
        ("", "psf_sigma_px", f"{v(cam.psf_sigma_px)}  # "
                             + ("on axis" if cam.spot else f"field mean +- {spot.mean_err_px:.3f}") + "; fitted "
                             f"{spot.coeffs[0]:.3f} +- {spot.errors[0]:.3f} at the principal point, r^2 term "
                             f"{spot.coeffs[3]:+.3f} +- {spot.errors[3]:.3f} px at a corner"),
        ("", "transmission", "1.0  # with quantum_efficiency: only their product is measured"),
        ("", "quantum_efficiency", f"{v(qe)}  # zero point {zp.zp_twin_mag:.3f} +- {zp.zp_err_mag:.3f} mag "
                                   "for 1 DN/s" + (f"; colour term {zp.colour:+.3f} per B-V, not rendered"
                                                   if zp.colour_kept else "")),
    ]
    if cam.spot is not None:
        rows.append(("spot", "field_curvature_sigma_px", f"{v(cam.spot.field_curvature_sigma_px)}  # the fitted "
                     f"corner sigma {spot.coeffs[0] + spot.coeffs[3]:.3f} px, added in quadrature"))
    dist = g.camera.distortion
    if isinstance(dist, BrownConrady):
        rows += [("distortion", "kind", '"brown_conrady"')] + [
            ("distortion", k, f"{v(getattr(dist, k))}" + (f"  # +- {err[k]:.3g}" if k in err else "  # not fitted"))
            for k in ("k1", "k2", "k3", "p1", "p2")]
    elif isinstance(dist, LegendreField):
        rows += [("distortion", "kind", f'"legendre"  # order {dist.order}; the modes of order 0 and 1 are the '
                                        "attitude and the focal length (zero here)"),
                 ("distortion", "coeffs_x_px", toml_value([float(c) for c in dist.coeffs_x]) + "  # +- "
                  + ", ".join(f"{err.get(f'wx{m}_px', 0.0):.2g}" for m in range(len(dist.coeffs_x)))),
                 ("distortion", "coeffs_y_px", toml_value([float(c) for c in dist.coeffs_y]) + "  # +- "
                  + ", ".join(f"{err.get(f'wy{m}_px', 0.0):.2g}" for m in range(len(dist.coeffs_y))))]
    else:
        rows += [("distortion", "kind", '"none"')]
    rows += [
        ("detector", "read_noise_e", f"{v(noise.read_noise_e)}" + (
            f"  # +- {noise.read_noise_err_e:.2g}" if noise.read_noise_measured else "  # not measured (see below)")),
        ("detector", "dark_current_e_per_s", f"{v(bg_e / cal.exposure_s)}  # the frames' whole background (sky and "
                                             f"dark): {noise.level_dn:.2f} DN over {cal.exposure_s:g} s"),
        ("detector", "gain_e_per_dn", f"{v(noise.gain_e_per_dn)}" + (
            f"  # +- {noise.gain_err:.2g}" if noise.gain_measured else "  # not measured (see below)")),
        ("detector", "bias_dn", f"{v(min(noise.bias_dn, max_dn))}"),
        ("detector", "full_well_e", f"{v(min(1e8, (max_dn + 1) * noise.gain_e_per_dn * 4))}  # the ADC clips first"),
        ("detector", "adc_bits", f"{cal.adc_bits}"),
        ("detector", "hot_pixel_fraction", "0.0  # not calibrated"),
        ("detector", "cosmic_ray_rate_per_cm2_s", "0.0  # not calibrated"),
    ]
    return rows


def _header(cal: Calibration) -> list[str]:
    return [f"# Digital twin of a camera, fitted by `starenv calibrate` from {len(cal.names)} frames "
            f"({cal.chosen} distortion):", *(f"#   {n}" for n in cal.names[:20]),
            *(["#   ..."] if len(cal.names) > 20 else []),
            "# Values after '+-' are 1 sigma.  Not in the frames: pixel pitch and f-number (only focal length / pitch",
            "# and the throughput are), the split of the throughput between transmission and quantum efficiency, hot",
            "# pixels and cosmic rays (off here), colour (the simulator renders Hp).",
            f"# noise: {cal.noise.note}.", f"# exposure of the frames: {cal.exposure_s:g} s"]


def _tables(rows: list[tuple[str, str, str]], head: str) -> list[str]:
    out = []
    for table in ("", "distortion", "spot", "detector"):
        if not any(t == table for t, _, _ in rows):
            continue
        if table:
            out += ["", f"[{head.strip('[]')}.{table}]"]
        out += [f"{k} = {val}" for t, k, val in rows if t == table]
    return out


def camera_toml(cal: Calibration, pixel_pitch_um: float = 5.0, f_number: float = 2.0) -> str:
    """The calibration as a camera file (a ``[camera]`` table of a scenario head's keys, what
    :func:`starenv.scenario.load_camera` reads and ``starenv solve --camera`` / ``starenv compare --camera`` take),
    1 sigma in comments.  ``pixel_pitch_um`` and ``f_number`` are not in the frames (only ``f / pitch`` and the
    throughput are); the f-number is lowered where the throughput needs a larger pupil."""
    rows = _twin_head(cal, pixel_pitch_um, f_number)
    return "\n".join(_header(cal) + ["[camera]"] + _tables(rows, "camera")) + "\n"


def scenario_toml(cal: Calibration, pixel_pitch_um: float = 5.0, f_number: float = 2.0, name: str = "twin",
                  attitude: Rotation | None = None) -> str:
    """The calibration as a scenario (:func:`starenv.scenario.load` accepts it): the head of :func:`camera_toml`,
    still at ``attitude`` (ICRS -> camera; default the first frame's) for ``starenv render`` / ``run``."""
    ra, dec, roll = radec_roll(attitude if attitude is not None else cal.attitudes[0])
    frame_rate = min(1.0, 1.0 / cal.exposure_s)

    def v(x):
        return toml_value(float(x))

    lines = _header(cal) + [
        f"name = {toml_value(name)}",
        f"description = {toml_value(f'Twin fitted from {len(cal.names)} frames ({cal.chosen} distortion)')}",
        "seed = 0",
        f"duration_s = {v(2.0 / frame_rate)}",
        f"frame_rate_hz = {v(frame_rate)}",
        f"exposure_s = {v(cal.exposure_s)}",
        f"mag_limit = {v(min(12.0, math.ceil(cal.faintest_mag + 1.0)))}  # the faintest identified star + 1",
        f"epoch = {v(cal.epoch)}",
        "sky_mag_per_arcsec2 = 30.0  # the darkest: the frames' background is the detector's dark current",
        "",
        "[motion]",
        'kind = "constant_rate"',
        "rate_dps = [0.0, 0.0, 0.0]",
        f"initial_ra_deg = {v(ra)}",
        f"initial_dec_deg = {v(dec)}",
        f"initial_roll_deg = {v(roll)}",
        "",
        "[[heads]]",
    ] + _tables(_twin_head(cal, pixel_pitch_um, f_number), "heads")
    return "\n".join(lines) + "\n"
