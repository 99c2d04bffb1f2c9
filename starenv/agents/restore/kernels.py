"""The blur kernel of a star under rotation, in pixels of one head's image (camera frame).

Kinematics.  The attitude ``A`` (inertial -> body) obeys ``dA/dt = -[w x] A`` with ``w`` the body rate (rad/s,
body frame), so a star's camera-frame direction ``c = M A r`` (``M`` the body -> camera mounting) turns as
``dc/dt = -w_c x c`` with ``w_c = M w``.  With ``x = (u - cx)/fx``, ``y = (v - cy)/fy`` (ideal pinhole) this moves
the image at ``du/dt = fx (-w_y (1 + x^2) + w_x x y + w_z y)`` and ``dv/dt = fy (w_x (1 + y^2) - w_y x y - w_z x)``.

Two models:

* paper 000's *linear* kernels (its Sec. 3.1): :func:`cross_boresight_blur` (Eqs. 9-15: rotation about the camera X
  and Y axes; each axis moves the star along one image axis by ``f [tan(alpha + w T) - tan(alpha)]``, Eq. 9, with
  ``alpha`` the star's field angle along that axis) and :func:`boresight_blur` (Eqs. 16-21: roll about the boresight
  moves the star on a circle about the principal point; the arc is replaced by its chord).  Each gives a straight
  trail (:class:`LinearBlur`) centred on the mid-exposure position, in ideal pinhole pixels (no distortion, as in the
  paper).  Signs follow the kinematics above (the paper's "clockwise" rotations have the opposite sense).
* the exact, space-variant path: :func:`star_paths` integrates the gyro's average rates as rotations and maps each
  star's mid-exposure direction through the calibrated camera (distortion included), so arcs, curved trails of
  non-uniform motion and the field-angle stretching are all in it.

:func:`path_kernel` rasterises a path into a normalised kernel with the same pixel-integrated Gaussian as the
renderer (:func:`starenv.sim.render.band_fractions`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from starenv import checks
from starenv.agents.base import StepInput
from starenv.agents.blocks import frame_background, row_window, streak_candidates
from starenv.agents.restore.algorithms import checked_image
from starenv.sim.gyro import GyroSamples
from starenv.sim.optics import Camera, SpotShape
from starenv.sim.render import band_fractions, spread_points

MAX_STEP_PX = 0.5  # largest image motion (px) between two consecutive path samples when n_samples is None
MAX_SAMPLES = 20001
KERNEL_CHUNK_VALUES = 1 << 22  # path_kernels builds its factors in chunks of at most this many values


@dataclass
class LinearBlur:
    """Straight trails of ``n`` stars: ``start`` and ``end`` (n, 2) px, ideal pinhole pixel coordinates, at the
    opening and closing of the exposure; the mid-exposure position is their midpoint."""

    start: np.ndarray
    end: np.ndarray

    @property
    def length(self) -> np.ndarray:
        """Trail length (n,) px (paper 000, Eqs. 13 and 18)."""
        return np.linalg.norm(self.end - self.start, axis=1)

    @property
    def angle(self) -> np.ndarray:
        """Trail direction (n,) rad from +u (columns) towards +v (rows), ``atan2(dv, du)`` (paper 000, Eqs. 14, 17)."""
        d = self.end - self.start
        return np.arctan2(d[:, 1], d[:, 0])

    def paths(self, n_samples: int | None = None) -> np.ndarray:
        """Each trail sampled at ``n_samples`` midpoint instants (n, m, 2) px; None: at most ``MAX_STEP_PX`` apart."""
        m = _odd_samples(float(self.length.max(initial=0.0)), n_samples)
        frac = (np.arange(m) + 0.5) / m
        return self.start[:, None, :] + frac[None, :, None] * (self.end - self.start)[:, None, :]

    def kernels(self, sigma_px: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """The uniform line PSF of each trail (paper 000, Eqs. 15 and 21) convolved with the pixel-integrated Gaussian:
        one :func:`path_kernel` result per star."""
        return [path_kernel(p, sigma_px) for p in self.paths()]


def cross_boresight_blur(xy_mid, rate_xy, exposure_s: float, camera: Camera) -> LinearBlur:
    """Paper 000's linear kernel for rotation about the camera's X and Y axes (Eqs. 9-15).

    ``xy_mid`` (n, 2) ideal pinhole px: the stars at mid-exposure; ``rate_xy`` (2,) rad/s: camera-frame rates about
    X and Y (paper 000's Eq. 23 maps gyro body rates through the mounting); ``exposure_s`` (s).  Rotation about X
    moves a star along v by ``fy [tan(alpha_y + w_x tau) - tan(alpha_y)]``, with ``tan(alpha_y) = (v - cy)/fy``;
    rotation about Y moves it along u by ``fx [tan(alpha_x - w_y tau) - tan(alpha_x)]``; ``tau`` runs over
    ``[-T/2, T/2]``.  To first order the length is Eq. 13, ``f (tan^2 alpha + 1) w T``, and the direction Eq. 14.
    """
    xy, rate, t = _linear_inputs(xy_mid, rate_xy, (2,), exposure_s)
    ax = np.arctan((xy[:, 0] - camera.cx) / camera.fx)
    ay = np.arctan((xy[:, 1] - camera.cy) / camera.fy)

    def at(tau: float) -> np.ndarray:
        return np.stack([camera.cx + camera.fx * np.tan(ax - rate[1] * tau),
                         camera.cy + camera.fy * np.tan(ay + rate[0] * tau)], axis=1)

    return LinearBlur(at(-0.5 * t), at(0.5 * t))


def boresight_blur(xy_mid, rate_z: float, exposure_s: float, camera: Camera) -> LinearBlur:
    """Paper 000's linear kernel for roll about the boresight (Eqs. 16-21).

    A star at ``(u', v') = (u - cx, v - cy)`` (ideal pinhole px, mid-exposure) turns about the principal point by
    ``-w_z tau`` (image axes x right, y down; ``rate_z`` rad/s about the camera's +Z); the trail is the chord between
    ``tau = -T/2`` and ``+T/2``, of length ``2 r sin(|w_z| T / 2)`` (Eq. 18, ``|w_z| T r``, is its first order), in
    direction ``(v', -u') sign(w_z)`` (Eq. 16).  Exact for pure roll of an undistorted pinhole with ``fx = fy``.
    """
    xy, rate, t = _linear_inputs(xy_mid, rate_z, (), exposure_s)
    rel = xy - [camera.cx, camera.cy]

    def at(tau: float) -> np.ndarray:
        phi = float(rate) * tau
        c, s = math.cos(phi), math.sin(phi)
        return np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], axis=1) + [camera.cx,
                                                                                                     camera.cy]

    return LinearBlur(at(-0.5 * t), at(0.5 * t))


def _linear_inputs(xy_mid, rate, rate_shape: tuple[int, ...], exposure_s: float):
    xy = checks.finite("xy_mid", xy_mid)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"xy_mid must be an (n, 2) array of pixel positions, got shape {xy.shape}")
    r = checks.finite("rate", rate, shape=rate_shape)
    t = checks.in_range("exposure_s", exposure_s, 0.0, 10.0, unit="s")
    return xy, r, t


def gyro_rotation(gyro: GyroSamples, times: np.ndarray, t_ref: float) -> Rotation:
    """Body rotations ``D(t)`` with ``A(t) = D(t) A(t_ref)``, from the gyro's average rates (one Rotation per time).

    Sample ``i`` holds the average body rate over ``(t_i - dt, t_i]``; inside that interval the rate is taken as
    constant, so the attitude advances by ``Rotation.from_rotvec(-w_i h)`` over a time ``h``.  Times before the
    first interval take the first sample's rate, times after the last the last sample's (a frame carries samples
    only up to the end of its exposure, so its last fraction of a sample interval is held).
    """
    t = checks.finite("gyro.t", gyro.t)
    rate = checks.finite("gyro.rate", gyro.rate)
    if t.ndim != 1 or len(t) == 0 or rate.shape != (len(t), 3):
        raise ValueError(f"gyro must hold n >= 1 timestamps (n,) and rates (n, 3), got {t.shape} and {rate.shape}")
    if np.any(np.diff(t) <= 0):
        raise ValueError("gyro.t must be strictly increasing")
    dt = checks.positive("gyro.dt", gyro.dt, "s")
    times = np.asarray(times, dtype=np.float64)
    # Knots: start of the first interval, then every sample's end; G(knot_k) turns A(knot_0) into A(knot_k).
    knots = np.concatenate([[t[0] - dt], t])
    steps = Rotation.from_rotvec(-rate * np.diff(knots)[:, None])
    cumulative = [Rotation.identity()]
    for step in steps:
        cumulative.append(step * cumulative[-1])
    g_knots = Rotation.concatenate(cumulative)

    def at(ts: np.ndarray) -> Rotation:
        k = np.clip(np.searchsorted(knots, ts, side="right") - 1, 0, len(t) - 1)  # interval (knot k, knot k + 1]
        return Rotation.from_rotvec(-rate[k] * (ts - knots[k])[:, None]) * g_knots[k]

    return at(times) * at(np.array([float(t_ref)])).inv()


def star_paths(camera: Camera, gyro: GyroSamples, t_start: float, t_end: float, xy_mid,
               n_samples: int | None = None, line_time_s: float = 0.0) -> np.ndarray:
    """Image paths (n, m, 2) distorted px of ``n`` stars over the exposure ``[t_start, t_end]`` (s).

    ``xy_mid`` (n, 2): the stars' distorted pixel positions at mid-exposure ``(t_start + t_end) / 2``.  The gyro's
    body rotations (:func:`gyro_rotation`) are carried into the camera frame by the mounting and applied to each
    star's direction (``camera.unproject``), then projected (``camera.project``), so distortion and arcs are exact.
    Samples are at ``m`` midpoint instants ``t_start + (j + 1/2) T / m`` (the renderer's rule); ``m`` is odd, so
    sample ``m // 2`` is the mid-exposure position itself.  None: the smallest odd ``m`` with consecutive samples at
    most ``MAX_STEP_PX`` apart.

    Rolling shutter: with ``line_time_s > 0`` a star on row ``r`` (its ``xy_mid`` row) is exposed over
    ``[t_start, t_end] + r * line_time_s`` and ``xy_mid`` is taken at the middle of that window (as the renderer
    does).  ``StepInput`` does not carry the line time, so the deblurrers use the global-shutter window.
    """
    lt = checks.in_range("line_time_s", line_time_s, 0.0, 1e-3, unit="s")
    xy = _positions(xy_mid)
    motion = ExposureMotion(camera, gyro, t_start, t_end, n_samples)
    if lt == 0:
        return motion.paths(xy)
    rows = np.clip(xy[:, 1], 0.0, camera.height - 1)
    out = np.empty((len(xy), len(motion.offsets), 2))
    for row in np.unique(rows):  # one exposure window per row
        sel = np.flatnonzero(rows == row)
        opens, closes = row_window(t_start, t_end - t_start, lt, row)
        out[sel] = ExposureMotion(camera, gyro, opens, closes, len(motion.offsets)).paths(xy[sel])
    return out


def _positions(xy_mid) -> np.ndarray:
    xy = checks.finite("xy_mid", xy_mid)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"xy_mid must be an (n, 2) array of pixel positions, got shape {xy.shape}")
    return xy


class ExposureMotion:
    """The camera's rotations over one exposure ``[t_start, t_end]`` (s) from the gyro, found once; :meth:`paths`
    gives the image paths of any stars (:func:`star_paths` with a global shutter).  ``n_samples``: as there."""

    def __init__(self, camera: Camera, gyro: GyroSamples, t_start: float, t_end: float,
                 n_samples: int | None = None):
        t0 = float(checks.finite("t_start", t_start, shape=()))
        t1 = checks.in_range("t_end", t_end, t0, unit="s")
        if n_samples is None:
            # Largest image speed: |w| f (1 + tan^2(alpha)) at the field corner (paper 000, Eq. 11).
            w_max = float(np.abs(checks.finite("gyro.rate", gyro.rate)).sum(axis=1).max(initial=0.0))
            px_per_rad = max(camera.fx, camera.fy) * (1.0 + math.tan(camera.half_diagonal) ** 2)
            m = _odd_samples(w_max * (t1 - t0) * px_per_rad, None)
        else:
            m = _odd_samples(0.0, n_samples)
        t_mid = 0.5 * (t0 + t1)
        offsets = t0 + (t1 - t0) * (np.arange(m) + 0.5) / m - t_mid  # (m,) s from mid-exposure
        self.camera, self.gyro, self.t_mid, self.offsets = camera, gyro, t_mid, offsets
        self._rotations = None

    def paths(self, xy_mid) -> np.ndarray:
        """Paths (n, m, 2) distorted px of stars at ``xy_mid`` (n, 2) px at mid-exposure."""
        xy = _positions(xy_mid)
        m = len(self.offsets)
        if len(xy) == 0:
            return np.zeros((0, m, 2))
        if self._rotations is None:
            mount = self.camera.mounting
            rot = gyro_rotation(self.gyro, self.t_mid + self.offsets, self.t_mid)  # body: A(t) = D A(t_mid)
            self._rotations = (mount * rot * mount.inv()).as_matrix()  # camera frame: c(t) = M D M^T c(t_mid)
        v = np.einsum("kij,nj->nki", self._rotations, self.camera.unproject(xy))
        p, _ = self.camera.project(v.reshape(-1, 3))
        return p.reshape(len(xy), m, 2)


def sparse_paths(camera: Camera, gyro: GyroSamples, t_start: float, t_end: float, xy_mid) -> np.ndarray:
    """:func:`star_paths` with the fewest samples that keep every path's consecutive samples at most ``MAX_STEP_PX``
    apart (star_paths' own count bounds the image speed by the summed rates at the field's corner: up to twice as
    many, and kernels cost in proportion)."""
    paths = star_paths(camera, gyro, t_start, t_end, xy_mid)
    if len(paths) == 0 or paths.shape[1] < 3:
        return paths
    widest = float(np.linalg.norm(np.diff(paths, axis=1), axis=2).max())  # px between samples: ~1 / count
    m = _odd_samples(widest * paths.shape[1], None)
    return star_paths(camera, gyro, t_start, t_end, xy_mid, n_samples=m) if m < paths.shape[1] else paths


def _odd_samples(length_px: float, n_samples: int | None) -> int:
    if n_samples is not None:
        m = checks.integer("n_samples", n_samples, 1, MAX_SAMPLES)
    else:
        m = max(1, math.ceil(length_px / MAX_STEP_PX))
        m = min(m, MAX_SAMPLES)
    return m if m % 2 else m + 1


def path_kernel(path, sigma_px: float, xy_mid=None) -> tuple[np.ndarray, np.ndarray]:
    """Normalised blur kernel of a star that travelled along ``path`` (m, 2) px during the exposure.

    Each sample is a pixel-integrated Gaussian of ``sigma_px`` (the renderer's PSF, :func:`band_fractions`) with
    weight ``1/m``.  The path is shifted so that the mid-exposure position ``xy_mid`` (default: the middle sample,
    ``path[m // 2]``, as :func:`star_paths` returns it) falls on the centre of the kernel pixel ``origin``, so
    ``blurred = sharp (x) kernel`` with the kernel's ``origin`` at the sharp star's pixel.  The kernel is zero-padded
    to odd sizes with ``origin`` at its centre ``(kw // 2, kh // 2)``: ready for 'same'-mode convolution.

    Returns ``kernel`` (kh, kw) float64 summing to 1 and ``origin`` (2,) int as (x = column, y = row).
    """
    p = checks.finite("path", path)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) == 0:
        raise ValueError(f"path must be an (m, 2) array of pixel positions with m >= 1, got shape {p.shape}")
    mid = None if xy_mid is None else checks.finite("xy_mid", xy_mid, shape=(2,))[None]
    kernels, origins = path_kernels(p[None], sigma_px, mid)
    return kernels[0], origins[0]


def path_kernels(paths, sigma_px: float, xy_mid=None, spot: SpotShape | None = None) -> tuple[list[np.ndarray],
                                                                                               np.ndarray]:
    """:func:`path_kernel` of each of ``n`` paths (n, m, 2) px at once (``xy_mid`` (n, 2) or None): the kernels (a
    list, each its own odd size) and their origins (n, 2).  ``spot``: each star's spot where it is (a camera's
    field-dependent spot, :meth:`~starenv.sim.optics.Camera.spot_shape`) drawn as the renderer draws it (its
    centroid offset left out: the kernel is centred on the light), instead of ``sigma_px`` everywhere."""
    p = checks.finite("paths", paths)
    if p.ndim != 3 or p.shape[2] != 2 or p.shape[1] == 0:
        raise ValueError(f"paths must be an (n, m, 2) array of pixel positions with m >= 1, got shape {p.shape}")
    sigma = checks.in_range("sigma_px", sigma_px, 0.1, 20.0, unit="px")
    n, m = p.shape[:2]
    mid = p[:, m // 2] if xy_mid is None else checks.finite("xy_mid", xy_mid, shape=(n, 2))
    if spot is None:
        band, frac = band_fractions(p - mid[:, None], sigma)  # (n, m, 2), (n, m, 2, n_band), relative to mid-exposure
    else:
        points, spread = spread_points(p - mid[:, None], spot, with_offset=False)
        band, frac = band_fractions(points, np.repeat(spot.sigma[:, None], points.shape[1], axis=1))
        frac[:, :, 1, :] *= spread[:, :, None]
        m = points.shape[1]
    n_band = frac.shape[-1]
    half = np.maximum(-band.min(axis=1), band.max(axis=1) + n_band - 1)  # (n, 2): each spans [-half, half]
    w, h = (2 * half + 1).T
    # Each sample's spot is separable: kernel = sum_s outer(rows_s, cols_s) = R^T C, with R (m, kh) and C (m, kw)
    # holding each sample's row and column fractions at their places: one matrix product per kernel, in chunks of
    # kernels that keep R and C under KERNEL_CHUNK_VALUES values each.
    places = [band[..., axis, None] + half[:, None, axis, None] + np.arange(n_band) for axis in (0, 1)]  # (n, m, nb)
    kernels = []
    chunk = max(1, KERNEL_CHUNK_VALUES // (m * int(max(h.max(), w.max()))))
    for a in range(0, n, chunk):
        b = min(a + chunk, n)
        factors = []
        for axis, size in ((1, int(h[a:b].max())), (0, int(w[a:b].max()))):
            placed = np.zeros(((b - a) * m, size))
            placed[np.arange((b - a) * m)[:, None], places[axis][a:b].reshape(-1, n_band)] = (
                frac[a:b, :, axis].reshape(-1, n_band))
            factors.append(placed.reshape(b - a, m, size))
        full = np.matmul(factors[0].transpose(0, 2, 1), factors[1])  # (b - a, largest kh, largest kw)
        kernels += [k[:hh, :ww] for k, hh, ww in zip(full, h[a:b], w[a:b], strict=True)]
    return [k / k.sum() for k in kernels], half.astype(np.int64)


def spot_sigma(option: float | None) -> float | None:
    """A deblurrer's ``psf_sigma_px`` option checked: None (the calibrated camera's ``psf_sigma_px``) or px."""
    return None if option is None else checks.in_range("psf_sigma_px", option, 0.1, 20.0, unit="px")


def sigma_for(option: float | None, camera: Camera) -> float:
    """The spot sigma (px) a deblurrer draws still stars with: its option, else the calibrated camera's."""
    return camera.psf_sigma_px if option is None else option


def window(step: StepInput) -> tuple[float, float]:
    """The exposure window (opens, closes) s of ``step``'s frames, a global shutter's (:func:`row_window` of the frame
    opening half an exposure before the mid-exposure time ``step.time_s``)."""
    exposure = float(step.exposure_s)
    return row_window(step.time_s - 0.5 * exposure, exposure)


def exposure_path(step: StepInput, head: int, xy_mid=None) -> np.ndarray:
    """The path (m, 2) px over the exposure of a star at ``xy_mid`` (px) at mid-exposure on head ``head``, from the
    step's gyro samples; None: the centre of the frame."""
    cam = step.cameras[head]
    t0, t1 = window(step)
    xy = [(cam.width - 1) / 2.0, (cam.height - 1) / 2.0] if xy_mid is None else xy_mid
    return star_paths(cam, step.gyro, t0, t1, np.reshape(xy, (1, 2)))[0]


def frame_kernel(step: StepInput, head: int, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The kernel of a star at the centre of head ``head``'s frame (a :func:`path_kernel` result)."""
    return path_kernel(exposure_path(step, head), sigma_px)


def centre_kernel(step, head: int, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The motion kernel (normalised, centred) of a star at head ``head``'s principal point over the exposure
    ``time_s -/+ exposure_s / 2``, from the step's gyro samples (:func:`star_paths`), and its extent (2,) px (x, y)."""
    camera = step.cameras[head]
    path = exposure_path(step, head, (camera.cx, camera.cy))
    kernel, _ = path_kernel(path, sigma_px)
    return kernel, np.ptp(path, axis=0)


@dataclass
class FrameStreaks:
    """One head's frame ready for restoration: the checked frame ``data`` (DN), the spot ``sigma`` (px), the
    background ``level`` and ``noise`` (DN, :func:`~starenv.agents.blocks.frame_background`), and the candidate
    streaks of :func:`~starenv.agents.blocks.streak_candidates` (``centroids`` and ``peaks`` (k, 2) px, peak
    ``responses`` (k,) in noise sigmas) found with the frame centre's kernel, drawn from its path ``streak_path``
    (m, 2) px (:func:`exposure_path`), its kernel ``streak``, the still ``spot`` kernel (None: lone bright pixels
    kept), and the finder's ``threshold_sigma`` and ``min_area_px``."""

    data: np.ndarray
    sigma: float
    level: float
    noise: float
    centroids: np.ndarray
    peaks: np.ndarray
    responses: np.ndarray
    streak_path: np.ndarray
    streak: np.ndarray
    spot: np.ndarray | None
    threshold_sigma: float
    min_area_px: int

    @property
    def reach_px(self) -> np.ndarray:
        """How far (x, y px) the filter's response reaches from a pixel: half the kernel, rounded up."""
        return np.array(self.streak.shape[::-1]) // 2 + 1

    def search(self, data: np.ndarray, lo, hi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The candidate streaks (centroids, peaks, responses) whose peak lies in the box ``lo`` .. ``hi`` (x, y px,
        inclusive) of ``data`` (DN), a frame of this one's shape (e.g. it with some trails taken off), found as on
        this frame: its background, noise, kernels and thresholds.  The filter reads half a kernel beyond the box,
        so the response in it is the whole frame's; a component reaching beyond that has its centroid from the
        part read."""
        x0, y0 = np.maximum(np.asarray(lo) - self.reach_px, 0)
        x1, y1 = np.minimum(np.asarray(hi) + self.reach_px, [data.shape[1] - 1, data.shape[0] - 1])
        centroids, peaks, responses = streak_candidates(data[y0 : y1 + 1, x0 : x1 + 1], self.level, self.noise,
                                                        self.streak, self.threshold_sigma, self.min_area_px, self.spot)
        centroids, peaks = centroids + [x0, y0], peaks + [x0, y0]
        inside = np.all((peaks >= lo) & (peaks <= hi), axis=1)
        return centroids[inside], peaks[inside], responses[inside]


def frame_streaks(image, head: int, step: StepInput, psf_sigma_option: float | None, threshold_sigma: float,
                  min_area_px: int, drop_points: bool = False) -> FrameStreaks:
    """The :class:`FrameStreaks` of head ``head``'s ``image`` at ``step`` (``psf_sigma_option``: a deblurrer's
    ``psf_sigma_px``, None for the calibrated camera's; ``drop_points``: candidates that a lone bright pixel explains
    are left out, :func:`~starenv.agents.blocks.streak_candidates` with the still spot)."""
    cam = step.cameras[head]
    data = checked_image(image, cam)
    sigma = sigma_for(psf_sigma_option, cam)
    level, noise = frame_background(data)
    path = exposure_path(step, head)
    streak, _ = path_kernel(path, sigma)  # as frame_kernel draws it
    spot = path_kernel(np.zeros((1, 2)), sigma)[0] if drop_points else None
    centroids, peaks, responses = streak_candidates(data, level, noise, streak, threshold_sigma, min_area_px, spot)
    return FrameStreaks(data, sigma, level, noise, centroids, peaks, responses, path, streak, spot, threshold_sigma,
                        min_area_px)
