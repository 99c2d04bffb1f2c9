"""Exposure-integrated star images along the true attitude path.

Each star's image is the time integral over the exposure of a Gaussian PSF (``psf_sigma_px``) integrated over every
pixel's area, centred on the star's distorted pixel position at that instant.  The integral is a midpoint sum over
``S`` instants at which the *exact* attitude is evaluated, so trails follow the true path (arcs for roll about the
boresight, curves for non-uniform motion) with no linear-kernel approximation.  ``S`` is set from the largest image
motion the exposure can produce (body-rate bound x exposure x plate scale at the field corner) so that consecutive
instants are at most ``min(sigma, 0.5)`` px apart: every instant lies exactly on the path, and the ripple a discrete
sum of Gaussians spaced ``d`` leaves on a continuous trail, ``2 exp(-2 pi^2 sigma^2 / d^2)``, is below 1e-8.

With a rolling shutter (``line_time_s > 0``) row ``r`` integrates over ``[t0 + r * line_time, ... + exposure]``;
each star is integrated over the window of the row it sits on at its window's middle (found by fixed-point
iteration), i.e. the row shift of the window across one star's PSF is neglected.

The result is sparse: the expected electrons (before any noise) of every pixel the stars touch, plus their truth.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erf

from starenv import checks
from starenv.sim.conventions import frame_span_s, row_window
from starenv.sim.ephemeris import aberrate
from starenv.sim.optics import SPOT_SPAN_SIGMA, Camera, SpotShape, check_camera_field
from starenv.sim.photometry import Photometry
from starenv.sim.sky import StarCatalog

PSF_RADIUS_SIGMA = 4.5  # half-width of the PSF footprint, in sigma
MIN_ELECTRONS = 1e-9  # expected e- below which a pixel's signal is left out
DETECTABLE_SNR = 5.0  # peak-pixel signal-to-noise at which a star counts as detectable in the scores
BAND_TABLE_STEPS = 4096  # sub-pixel phases at which the PSF's pixel fractions are tabulated
# A batch's patches are scattered instant by instant when the window area exceeds this many times n_band^2: numpy's
# batched matmul costs far less per (instant, window pixel) than np.bincount per (instant, band pixel), so the matmul
# wins until the window is many band areas wide (benchmarks/render_speed.py times both paths; the ratio is set
# inside the crossover range it finds).
SCATTER_AREA_RATIO = 40
SCATTER_CHUNK = 1 << 21  # (instant, band pixel) terms scattered per np.bincount call, bounding its memory (~40 MB)
BATCH_BYTES = 1 << 28  # stars are rendered in batches whose estimated working memory stays under this (256 MiB)


@dataclass
class StarSignal:
    """Expected star signal (e-, before noise) on the pixels it touches: flat pixel indices (row * width + col,
    unique) and float32 electrons.  Pixels below ``MIN_ELECTRONS`` are left out (their Poisson draw is zero
    with probability > 1 - 1e-9)."""

    index: np.ndarray
    electrons: np.ndarray
    shape: tuple[int, int]

    def image(self) -> np.ndarray:
        """Dense float32 image (height, width) of the signal."""
        img = np.zeros(self.shape[0] * self.shape[1], dtype=np.float32)
        img[self.index] = self.electrons
        return img.reshape(self.shape)


@dataclass
class StarTruth:
    """Truth of the stars rendered on one head's frame (positions are distorted pixel coordinates).

    ``xy_mid``: position at the middle of the star's exposure window; ``xy_centroid``: intensity-weighted centroid of
    the whole trail (mean over the exposure of the position, the quantity a centroider of the smeared spot should
    find); ``xy_start``/``xy_end``: trail end points; ``electrons``: expected signal landing on the sensor;
    ``peak_electrons``: expected signal in the star's brightest pixel; ``detectable``: whether that peak reaches
    ``DETECTABLE_SNR`` against the pixel's noise (set by the sensor, which knows the noise; all True until then).
    """

    catalog_id: np.ndarray
    magnitude: np.ndarray
    xy_mid: np.ndarray
    xy_centroid: np.ndarray
    xy_start: np.ndarray
    xy_end: np.ndarray
    electrons: np.ndarray
    peak_electrons: np.ndarray
    detectable: np.ndarray

    def __len__(self) -> int:
        return len(self.catalog_id)

    def as_dict(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass
class RenderedFrame:
    """Noise-free star signal of one head for one exposure, and its truth."""

    signal: StarSignal
    truth: StarTruth
    t_mid: float
    n_instants: int


class StarRenderer:
    """Renders one head's stars for an exposure along a trajectory (inertial -> body attitude over time)."""

    def __init__(
        self,
        catalog: StarCatalog,
        camera: Camera,
        photometry: Photometry,
        psf_sigma_px: float = 1.0,
        line_time_s: float = 0.0,
    ):
        self.catalog = catalog
        self.camera = camera
        self.photometry = photometry
        self.psf_sigma_px = check_camera_field("psf_sigma_px", psf_sigma_px, "px")
        self.line_time_s = checks.in_range("line_time_s", line_time_s, 0.0, 1e-3, unit="s")
        self.electrons_per_s = photometry.star_electrons_per_s(catalog.magnitude)
        self.max_step_px = min(self.psf_sigma_px, 0.5)
        self.use_camera(camera)

    def use_camera(self, camera: Camera) -> None:
        """Render through ``camera`` from now on (a camera whose focal length or distortion drifts along the run; same
        sensor size)."""
        if (camera.width, camera.height) != (self.camera.width, self.camera.height):
            raise ValueError("use_camera: the camera must keep the sensor's size")
        self.camera = camera
        # Image speed bound per unit body rate: a rotation by d(theta) moves an image point by at most
        # f (1 + tan^2(alpha)) d(theta) (paper 000, Eq. 11) at field angle alpha <= the corner angle.
        self._px_per_rad = max(camera.fx, camera.fy) * (1.0 + math.tan(camera.half_diagonal) ** 2)

    def _instants(self, trajectory, t0: float, t1: float) -> int:
        """Number of midpoint instants so that a star moves at most ``max_step_px`` between two."""
        path_px = trajectory.motion.max_rate(t0, t1) * (t1 - t0) * self._px_per_rad
        return max(1, math.ceil(path_px / self.max_step_px))

    def render(self, trajectory, t_start: float, exposure_s: float, observer_velocity=None) -> RenderedFrame:
        """Expected star signal for the exposure opening at ``t_start`` (s) and lasting ``exposure_s`` (s).

        ``observer_velocity``: None (stars at their catalogue directions) or a callable of time (s) giving the
        observer's velocity (m/s, ICRS axes); the stars are then rendered at their apparent directions for the velocity
        at the head's mid-exposure (its change over one exposure, ``a * exposure / c`` for an acceleration ``a``, is
        neglected: 3 mas for a 0.1 s exposure in low Earth orbit)."""
        t_start = float(checks.finite("t_start", t_start, shape=()))
        exposure = checks.in_range("exposure_s", exposure_s, 0.0, 10.0, low_open=True, unit="s")
        cam = self.camera
        t_mid = t_start + 0.5 * frame_span_s(exposure, self.line_time_s, cam.height)
        sigma = self.psf_sigma_px
        margin_px = PSF_RADIUS_SIGMA * sigma + 1.0
        if cam.spot is not None:
            widest, beyond = cam.spot.reach_px(cam.intrinsics, sigma)
            margin_px = PSF_RADIUS_SIGMA * widest + beyond + 1.0

        # Candidate stars: a cone around the boresight at mid-exposure wide enough for the motion during the frame.
        _, t_end_all = row_window(t_start, exposure, self.line_time_s, cam.height - 1)  # the last row closes
        sweep = trajectory.motion.max_rate(t_start, t_end_all) * (t_end_all - t_start)
        n_inst = self._instants(trajectory, t_start, t_end_all)
        # the frame's start, middle, end and midpoint instants, as fractions of a star's exposure window
        steps = np.concatenate([[0.0, 0.5, 1.0], (np.arange(n_inst) + 0.5) / n_inst])
        if self.line_time_s == 0:  # one window for all stars: its rotations serve the boresight and every star
            rot = self._rotations(trajectory, t_start + exposure * steps)
            boresight = rot[1, 2]  # camera +z in ICRS at mid-exposure
        else:
            boresight = self._rotations(trajectory, t_mid)[2]
        radius = min(math.pi, cam.half_diagonal + sweep + margin_px / min(cam.fx, cam.fy) + 1e-3)
        idx = self.catalog.cone(boresight, radius)
        units = self.catalog.unit[idx]
        if observer_velocity is not None:
            units = aberrate(units, observer_velocity(t_mid))

        # Exposure window of each star: the global shutter shares one; a rolling shutter follows the star's row.
        window_start = np.full(len(idx), t_start)
        if self.line_time_s > 0 and len(idx):
            for _ in range(3):
                middle = self._rotations(trajectory, window_start + 0.5 * exposure)[:, None]  # (stars, 1, 3, 3)
                xy = self._positions(middle, units)[:, 0]
                row = np.clip(np.nan_to_num(xy[:, 1], nan=0.0), 0.0, cam.height - 1)
                window_start, _ = row_window(t_start, exposure, self.line_time_s, row)

        if self.line_time_s > 0:
            times = window_start[:, None] + exposure * steps[None, :]
            rot = self._rotations(trajectory, times.reshape(-1)).reshape(*times.shape, 3, 3)
        xy_all = self._positions(rot, units)  # (stars, 3 + n_inst, 2)
        xy_start, xy_mid, xy_end, path = xy_all[:, 0], xy_all[:, 1], xy_all[:, 2], xy_all[:, 3:]

        visible = np.flatnonzero(np.all(np.isfinite(path), axis=(1, 2)) & np.any(cam.in_frame(path, margin_px), 1))
        path = path[visible]
        weight = self.electrons_per_s[idx[visible]] * exposure / n_inst  # electrons per instant
        # A field-dependent spot is taken where the star is at mid-exposure, the same over its trail.
        spot = None if cam.spot is None else cam.spot_shape(path[:, n_inst // 2])
        signal, electrons, peak = self._signal(path, weight, spot)
        sel = idx[visible]
        truth = StarTruth(
            catalog_id=self.catalog.hip[sel],
            magnitude=self.catalog.magnitude[sel],
            xy_mid=xy_mid[visible],
            xy_centroid=path.mean(axis=1) if spot is None else path.mean(axis=1) + spot.offset,
            xy_start=xy_start[visible],
            xy_end=xy_end[visible],
            electrons=electrons,
            peak_electrons=peak,
            detectable=np.ones(len(sel), dtype=bool),
        )
        return RenderedFrame(signal=signal, truth=truth, t_mid=t_mid, n_instants=n_inst)

    def _rotations(self, trajectory, times) -> np.ndarray:
        """Inertial -> camera rotation matrices at ``times`` (s): (3, 3) for one time, (k, 3, 3) for k."""
        return self.camera.inertial_to_camera(trajectory.attitude(times)).as_matrix()

    def _positions(self, rot: np.ndarray, units: np.ndarray) -> np.ndarray:
        """Distorted pixel positions (stars, instants, 2) of inertial unit vectors ``units`` (stars, 3) under
        inertial -> camera rotations ``rot``: (instants, 3, 3) shared by all stars, or (stars, instants, 3, 3)."""
        if rot.ndim == 3:
            v = np.einsum("kij,nj->nki", rot, units)
        else:
            v = np.einsum("nkij,nj->nki", rot, units)
        xy, _ = self.camera.project(v.reshape(-1, 3))
        return xy.reshape(len(units), rot.shape[-3], 2)

    def _signal(self, paths: np.ndarray, weight: np.ndarray,
                spot: SpotShape | None = None) -> tuple[StarSignal, np.ndarray, np.ndarray]:
        """Pixel-integrated Gaussian PSF summed over each star's instants; ``paths`` is (stars, instants, 2) px.
        ``spot``: each star's field-dependent spot (:func:`spread_points`), None for ``psf_sigma_px`` everywhere.

        At instant k the PSF covers a band of ``n_band`` columns and rows around the star; the fraction of light in
        each (a difference of ``erf`` at the pixel edges) comes from :func:`band_fractions`.  Stars are batched by
        window size (rounded up to 8 px) and each batch's patches come from :func:`_patches_matmul` (cost ~ window
        area per instant: short trails) or :func:`_patches_scatter` (cost ~ ``n_band^2`` per instant: long trails),
        whichever is cheaper by ``SCATTER_AREA_RATIO``; both give the same sums to float64 rounding.  Returns the
        merged sparse signal, each star's on-sensor electrons and its peak pixel's electrons.
        """
        cam = self.camera
        n = len(paths)
        if n == 0:
            empty = StarSignal(np.zeros(0, np.int64), np.zeros(0, np.float32), (cam.height, cam.width))
            return empty, np.zeros(0), np.zeros(0)
        if spot is not None:
            return self._spot_signal(paths, weight, spot)
        # Working memory per star: bands and fractions (~6 float64 per instant and band pixel) and ~4 float64
        # arrays the size of its window; consecutive stars are batched under BATCH_BYTES.
        n_band = _band_table(float(self.psf_sigma_px)).shape[0]
        low, high = _span(paths)
        extent = high - low + n_band + 16
        cost = 48.0 * paths.shape[1] * n_band + 32.0 * extent[:, 0] * extent[:, 1]
        batch = np.cumsum(cost) // BATCH_BYTES
        parts = [self._signal_batch(paths[batch == b], weight[batch == b]) for b in np.unique(batch)]
        if len(parts) == 1:
            index, values, electrons, peak = parts[0]
        else:
            index, values, electrons, peak = (np.concatenate(x) for x in zip(*parts, strict=True))
        return self._merge(index, values), electrons, peak

    def _spot_signal(self, paths: np.ndarray, weight: np.ndarray,
                     spot: SpotShape) -> tuple[StarSignal, np.ndarray, np.ndarray]:
        """:meth:`_signal` with a field-dependent spot: stars grouped by how many points their radial spread takes
        (:func:`spread_points`), each group batched as there under ``BATCH_BYTES``."""
        n = len(paths)
        points_needed = spread_count(spot.radial_sigma / spot.sigma)
        parts, members = [], []
        for count in np.unique(points_needed):
            group = np.flatnonzero(points_needed == count)
            points, spread = spread_points(paths[group], spot.subset(group))
            point_weight = weight[group, None] * spread
            sigma = np.repeat(spot.sigma[group, None], points.shape[1], axis=1)
            n_band = _band_count(float(sigma.max()))
            low, high = _span(points)
            extent = high - low + n_band + 16
            cost = 48.0 * points.shape[1] * n_band + 32.0 * extent[:, 0] * extent[:, 1]
            batch = np.cumsum(cost) // BATCH_BYTES
            for b in np.unique(batch):
                parts.append(self._signal_batch(points[batch == b], point_weight[batch == b], sigma[batch == b]))
                members.append(group[batch == b])
        index, values, electrons, peak = (np.concatenate(x) for x in zip(*parts, strict=True))
        order = np.concatenate(members)
        star_electrons, star_peak = np.empty(n), np.empty(n)
        star_electrons[order], star_peak[order] = electrons, peak
        return self._merge(index, values), star_electrons, star_peak

    def _signal_batch(self, paths: np.ndarray, weight: np.ndarray,
                      sigma: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """:meth:`_signal` for one batch of stars: pixel indices and electrons (unmerged), electrons and peaks.
        ``weight``: electrons per star's instant (n,) or per point (n, k); ``sigma``: per point (n, k) or None."""
        cam = self.camera
        n = len(paths)
        band, frac = band_fractions(paths, self.psf_sigma_px if sigma is None else sigma)
        n_band = frac.shape[-1]
        frac[:, :, 1, :] *= weight[:, None, None] if weight.ndim == 1 else weight[:, :, None]
        lo, hi = _span(band)  # (n, 2) window origin x, y; last band start
        size = -(-(hi + n_band - lo) // 8) * 8  # (n, 2) window width, height
        offset = band - lo[:, None, :]  # band start inside the window
        indices, values = [], []
        electrons = np.zeros(n)
        peak = np.zeros(n)
        keys = size[:, 0] * 65536 + size[:, 1]
        for key in np.unique(keys):
            group = np.flatnonzero(keys == key)
            w, h = int(size[group[0], 0]), int(size[group[0], 1])
            patch_fn = _patches_scatter if h * w > SCATTER_AREA_RATIO * n_band**2 else _patches_matmul
            patches = patch_fn(offset[group], frac[group], h, w)  # (m, h, w) expected electrons
            rows = lo[group, 1, None, None] + np.arange(h)[None, :, None]  # (m, h, 1)
            cols = lo[group, 0, None, None] + np.arange(w)[None, None, :]  # (m, 1, w)
            edge = np.flatnonzero(np.any((lo[group] < 0) | (lo[group] + (w, h) > (cam.width, cam.height)), axis=1))
            if len(edge):  # windows over an edge: the light beyond it is lost
                r, c = rows[edge], cols[edge]
                patches[edge] = np.where((r >= 0) & (r < cam.height) & (c >= 0) & (c < cam.width), patches[edge], 0.0)
            electrons[group] = patches.sum(axis=(1, 2))
            peak[group] = patches.max(axis=(1, 2))
            keep = patches > MIN_ELECTRONS
            indices.append(np.broadcast_to(rows * cam.width + cols, keep.shape)[keep])
            values.append(patches[keep])
        return np.concatenate(indices), np.concatenate(values), electrons, peak

    def _merge(self, index: np.ndarray, electrons: np.ndarray) -> StarSignal:
        """Sum the electrons of repeated pixel indices (where star windows overlap) without sorting."""
        cam = self.camera
        owner = self._owner
        slot = np.arange(len(index), dtype=np.int32)
        owner[index] = slot  # the last occurrence of each pixel owns it
        first = owner[index]
        kept = first == slot
        summed = np.bincount(first, weights=electrons, minlength=len(index))
        return StarSignal(index[kept], summed[kept].astype(np.float32), (cam.height, cam.width))

    @functools.cached_property
    def _owner(self) -> np.ndarray:
        """Scratch (height * width) int32 array for :meth:`_merge`; its contents are never read unwritten."""
        return np.empty(self.camera.height * self.camera.width, dtype=np.int32)


def _span(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each star's lowest and highest x and y, (n, 2) each, over its instants of ``a`` (n, k, 2): reduced along
    the last axis of an (n, 2, k) copy, which numpy does several times faster than along the middle axis."""
    per_axis = np.ascontiguousarray(a.transpose(0, 2, 1))
    return per_axis.min(axis=2), per_axis.max(axis=2)


def _patches_matmul(offset: np.ndarray, frac: np.ndarray, h: int, w: int) -> np.ndarray:
    """Patches (m, h, w) of m stars from their bands' window offsets ``offset`` (m, k, 2: column, row) and fractions
    ``frac`` (m, k, 2, n_band; rows carry the weights): the bands scattered into (k, w) and (k, h) matrices Wx, Wy,
    each patch is the product ``Wy^T Wx``."""
    m, k, _, n_band = frac.shape
    wx = np.zeros((m, k, w))
    wy = np.zeros((m, k, h))
    row = np.arange(m * k).reshape(m, k, 1)  # (star, instant) row of the flattened matrices
    cols_band = np.arange(n_band)
    wx.reshape(-1)[(row * w + offset[:, :, 0, None] + cols_band).reshape(-1)] = frac[:, :, 0].reshape(-1)
    wy.reshape(-1)[(row * h + offset[:, :, 1, None] + cols_band).reshape(-1)] = frac[:, :, 1].reshape(-1)
    return np.matmul(wy.transpose(0, 2, 1), wx)


def _patches_scatter(offset: np.ndarray, frac: np.ndarray, h: int, w: int) -> np.ndarray:
    """Same patches as :func:`_patches_matmul`, summing each instant's ``n_band^2`` outer product
    ``frac[1, j] * frac[0, i]`` into the star's window with ``np.bincount`` (float64, instant order), a few stars at a
    time (``SCATTER_CHUNK``)."""
    m, k, _, n_band = frac.shape
    patches = np.empty((m, h * w))
    band = np.arange(n_band)
    per_call = max(1, SCATTER_CHUNK // (k * n_band**2))
    for first in range(0, m, per_call):
        part = slice(first, min(first + per_call, m))
        n_part = part.stop - first
        rows = (offset[part, :, 1, None] + band) * w + (np.arange(n_part) * (h * w))[:, None, None]  # (p, k, n_band)
        flat = rows[..., :, None] + (offset[part, :, 0, None] + band)[..., None, :]  # (p, k, n_band, n_band)
        values = frac[part, :, 1, :, None] * frac[part, :, 0, None, :]
        patches[part] = np.bincount(flat.ravel(), values.ravel(), n_part * h * w).reshape(n_part, h * w)
    return patches.reshape(m, h, w)


def _band_count(psf_sigma_px: float) -> int:
    """Pixels of an instant's band for a PSF sigma (px): ``PSF_RADIUS_SIGMA`` sigmas either side."""
    return math.ceil(2 * PSF_RADIUS_SIGMA * psf_sigma_px) + 2


def spread_count(ratio: np.ndarray) -> np.ndarray:
    """Points :func:`spread_points` draws a spot with, per ratio of its radial to its isotropic sigma: 1 without a
    radial spread, 3 (Gauss-Hermite) up to ``1 / sqrt(3)``, else ``2 max(3, ceil(SPOT_SPAN_SIGMA ratio)) + 1``."""
    ratio = np.asarray(ratio, dtype=np.float64)
    steps = np.maximum(3, np.ceil(SPOT_SPAN_SIGMA * ratio - 1e-9))
    return np.where(ratio <= 0, 1, np.where(ratio <= 1 / math.sqrt(3.0), 3, 2 * steps + 1)).astype(np.int64)


def spread_points(paths: np.ndarray, spot: SpotShape, with_offset: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Each star's instants (n, m, 2) px spread into ``K`` points along its spot's radial direction, (n, m K, 2), with
    their weights (n, m K) (each instant's ``K`` sum to 1), so that isotropic Gaussians of ``spot.sigma`` on the
    points make the spot's covariance; ``with_offset`` moves them by the spot's centroid offset too.

    The points sample a Gaussian of unit variance along the radial direction, times the radial sigma, with a variance
    of exactly 1 (the mean is 0 by symmetry), so the drawn spot's second moments are the model's exactly, and at most
    about one isotropic sigma apart (:func:`spread_count` for the largest ratio of the stars given): the 3-point
    Gauss-Hermite rule (``0, +-sqrt(3)``, weights ``2/3, 1/6, 1/6``: exact to the fifth moment) while
    ``sqrt(3) radial_sigma <= sigma``; beyond, ``2J + 1`` equal steps of at most 1 over +-``SPOT_SPAN_SIGMA``
    (``J >= 3``) weighted ``exp(-u^2/2)`` and rescaled by ~1.002 to unit variance, <= 1.002 isotropic sigmas apart,
    where the ripple of a sum of Gaussians (the renderer's bound for trails) is below 1e-8."""
    n, m, _ = paths.shape
    offset = spot.offset[:, None, None, :] if with_offset else 0.0
    count = int(spread_count(np.max(spot.radial_sigma / spot.sigma, initial=0.0)))
    if count == 1:
        u, w = np.zeros(1), np.ones(1)
    elif count == 3:
        u, w = np.array([-math.sqrt(3.0), 0.0, math.sqrt(3.0)]), np.array([1.0, 4.0, 1.0]) / 6.0
    else:
        u = np.linspace(-SPOT_SPAN_SIGMA, SPOT_SPAN_SIGMA, count)
        w = np.exp(-0.5 * u * u)
        w /= w.sum()
        u /= math.sqrt(float(np.sum(w * u * u)))
    step = (u[None, :, None] * spot.radial_sigma[:, None, None]) * spot.radial[:, None, :]  # (n, K, 2)
    points = paths[:, :, None, :] + offset + step[:, None, :, :]
    return points.reshape(n, m * len(u), 2), np.broadcast_to(np.tile(w, m), (n, m * len(u)))


CDF_TABLE_STEP = 1e-3  # step of the tabulated normal CDF (linear interpolation error <= step^2 / 8 x 0.242 < 3.1e-8)
CDF_TABLE_REACH = 9.0  # the table spans +-this many sigmas; beyond, the CDF is 0 or 1 to within 1e-19


@functools.cache
def _cdf_table() -> np.ndarray:
    z = np.arange(-CDF_TABLE_REACH, CDF_TABLE_REACH + CDF_TABLE_STEP / 2, CDF_TABLE_STEP)
    table = 0.5 * (1.0 + erf(z / math.sqrt(2.0)))
    table.flags.writeable = False
    return table


def normal_cdf(z: np.ndarray) -> np.ndarray:
    """The standard normal CDF at ``z`` (any shape), from a table interpolated linearly (error < 3.1e-8), many
    times faster than ``erf`` on large arrays."""
    table = _cdf_table()
    pos = (np.clip(z, -CDF_TABLE_REACH, CDF_TABLE_REACH) + CDF_TABLE_REACH) * (1.0 / CDF_TABLE_STEP)
    i0 = np.minimum(pos.astype(np.int64), len(table) - 2)
    pos -= i0
    lo = table[i0]
    return lo + (table[i0 + 1] - lo) * pos


@functools.lru_cache(maxsize=16)
def _band_table(psf_sigma_px: float) -> np.ndarray:
    """Fraction of a pixel-integrated Gaussian in each of the ``n_band`` pixels of an instant's band (rows),
    tabulated over the PSF centre's sub-pixel phase (columns: ``BAND_TABLE_STEPS`` steps, linear interpolation:
    error < 1e-8)."""
    radius = PSF_RADIUS_SIGMA * psf_sigma_px
    n_band = math.ceil(2 * radius) + 2
    phase = np.linspace(0.0, 1.0, BAND_TABLE_STEPS + 1)
    edges = np.arange(n_band + 1) - 0.5  # pixel edges relative to the band start
    centre = radius + phase  # PSF centre relative to the band start
    cdf = erf((edges[None, :] - centre[:, None]) / (math.sqrt(2.0) * psf_sigma_px))
    table = np.ascontiguousarray(0.5 * np.diff(cdf, axis=1).T)
    table.flags.writeable = False
    return table


def band_fractions(points: np.ndarray, psf_sigma_px: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixel-integrated Gaussian PSF (sigma ``psf_sigma_px`` px) of point sources at ``points`` (..., 2) px,
    separated per axis: ``band`` (..., 2) int64, the first column / row of the ``n_band`` pixels each covers
    (``PSF_RADIUS_SIGMA`` sigmas either side), and ``frac`` (..., 2, n_band), the fraction of the light in each
    of those columns (index 0) and rows (index 1).  A source's pixel (col, row) gets ``frac[0, i] * frac[1, j]``.
    One sigma for all comes from a table of sub-pixel phases; a sigma per point (an array of ``points.shape[:-1]``)
    is integrated with ``erf`` directly, every band as wide as the largest sigma's."""
    if np.ndim(psf_sigma_px):
        sigma = np.broadcast_to(np.asarray(psf_sigma_px, dtype=np.float64), points.shape[:-1])
        radius = PSF_RADIUS_SIGMA * float(sigma.max())
        start = np.floor(points - radius)
        edges = start[..., None] + (np.arange(_band_count(float(sigma.max())) + 1) - 0.5)  # (..., 2, n_band + 1)
        edges -= points[..., None]
        edges /= sigma[..., None, None]
        return start.astype(np.int64), np.diff(normal_cdf(edges), axis=-1)
    table = _band_table(float(psf_sigma_px))  # (n_band, phases)
    radius = PSF_RADIUS_SIGMA * psf_sigma_px
    start = np.floor(points - radius)
    pos = (points - start - radius) * (table.shape[1] - 1)  # sub-pixel phase in table steps
    i0 = np.minimum(pos.astype(np.int64), table.shape[1] - 2)
    w1 = pos - i0
    # table[:, i0] (1 - w1) + table[:, i0 + 1] w1, band pixels first so that every product runs over all points
    frac = np.take(table, i0, axis=1)
    frac *= 1.0 - w1
    i0 += 1
    above = np.take(table, i0, axis=1)
    above *= w1
    frac += above
    return start.astype(np.int64), np.moveaxis(frac, 0, -1)


def still_image(xy: np.ndarray, electrons: np.ndarray, shape: tuple[int, int], psf_sigma_px: float,
                spot: SpotShape | None = None) -> np.ndarray:
    """Noise-free float64 image (height, width) in e- of still point sources: each star's ``electrons`` spread by the
    renderer's pixel-integrated Gaussian PSF (:func:`band_fractions`) about its position ``xy`` (n, 2) px; ``spot``:
    each star's field-dependent spot there instead (drawn as the renderer draws it, :func:`spread_points`)."""
    xy = checks.finite("xy", xy).reshape(-1, 2)
    electrons = checks.finite("electrons", electrons).reshape(-1)
    if len(electrons) != len(xy):
        raise ValueError(f"electrons must hold one value per position: {len(xy)} positions, {len(electrons)} values")
    height, width = shape
    if spot is None:
        band, frac = band_fractions(xy, psf_sigma_px)  # (n, 2), (n, 2, n_band)
    else:
        points, spread = spread_points(xy[:, None, :], spot)  # (n, K, 2), (n, K)
        electrons = (electrons[:, None] * spread).reshape(-1)
        band, frac = band_fractions(points.reshape(-1, 2), np.repeat(spot.sigma, points.shape[1]))
    n_band = frac.shape[-1]
    cols = band[:, 0, None] + np.arange(n_band)  # (n, n_band)
    rows = band[:, 1, None] + np.arange(n_band)
    values = electrons[:, None, None] * frac[:, 1, :, None] * frac[:, 0, None, :]  # (n, rows, cols)
    r = np.broadcast_to(rows[:, :, None], values.shape)
    c = np.broadcast_to(cols[:, None, :], values.shape)
    on = (r >= 0) & (r < height) & (c >= 0) & (c < width)
    image = np.zeros(height * width)
    np.add.at(image, r[on] * width + c[on], values[on])
    return image.reshape(height, width)
