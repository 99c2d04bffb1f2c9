"""Classical star detection and centroiding on one head's frame: :class:`CentroidDetector`.

The pipeline is vectorised (numpy / OpenCV); Python loops run only over the saddles of blobs being split and over
the iterations of a Gaussian fit made for all stars at once.

1. Local background and noise on a grid of tiles (:func:`~starenv.agents.blocks.background_maps`): the
   sigma-clipped mean of the pixels (a mean, as a median of integer DN moves in whole DN) and the sigma-clipped
   spread of differences between neighbouring pixels (blind to gradients), interpolated bilinearly between the tile
   centres and extrapolated linearly to the border, so stray-light gradients are followed.
2. Spikes: a pixel standing far above the median of its 3 x 3 neighbourhood, further than a PSF allows (a hot pixel,
   a cosmic-ray hit or track, alone or on a star), takes that median; so do its neighbours that stand out likewise.
3. Detection: the cleaned background-subtracted image, smoothed by a Gaussian matched to the PSF (optional), is
   thresholded at ``threshold_sigma`` times its local noise; 8-connected components of ``min_area_px`` to
   ``max_area_px`` pixels are the candidates (:func:`~starenv.agents.blocks.pixels_above`,
   :func:`~starenv.agents.blocks.components`).
4. Deblending: a blob holding several maxima of the detection image is split, each pixel following its steepest
   ascent to a maximum; a maximum whose rise above the highest saddle towards a brighter one is below the detection
   threshold or below ``deblend_contrast`` times its height is merged into that brighter one.
5. Rejection of what is sharper than the PSF allows (what step 2 left of hot pixels and cosmic rays): the 8
   neighbours of a blob's peak pixel must hold at least half the light (per unit peak) that a PSF centred on the
   pixel puts there; and where a blob is bright enough to tell, the pixels beside its ridge (those of at least half
   the peak), across its principal axis, must hold at least half of what a PSF puts beside its peak (a cosmic-ray
   track is one pixel wide).  A blob that lost more light to step 2, within 1 px of it, than it holds is what is
   left of a cosmic-ray track, and is dropped too.
6. Centroids over the blob grown by ``window_margin_px`` (so faint wings count), in background-subtracted DN:
   ``"cog"`` the centre of gravity of the positive pixels, ``"iwcog"`` each pixel weighted by its intensity times the
   matched-filter response, ``"gaussian"`` a pixel-integrated 2-D Gaussian (flux, centre, width) fitted by
   Levenberg-Marquardt on a square window.  Smeared streaks (elongated blobs) always take the centre of gravity, the
   flux-weighted trail centroid; saturated blobs are not fitted (the centre of gravity of a clipped symmetric spot is
   still its centre).

7. Streak linking (``link_streaks=True``): the pieces into which noise breaks a faint trail, lying along the local
   direction of motion that the nearest long streak gives, with short breaks between them, are joined into one
   star (see :func:`_link_streaks`).  Off by default: it matters only where trails are many PSF widths long.

Flux is the sum of background-subtracted DN over the grown blob.  Stars whose blob reaches the image border are cut
by it (centroid pulled inwards, flux short) and are left out unless ``keep_edge=True``; a bright star whose faint
wings reach it is kept when the light on the border's outermost pixels bounds the pull to ``EDGE_BIAS_PX``.  Stars
closer than about 5 PSF sigmas merge into one detection.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.special import erf, ndtr

from starenv import checks
from starenv.agents.base import StarMeasurements
from starenv.agents.blocks import (
    Workspace,
    background_maps,
    component_peaks,
    components,
    components_above,
    pixels_above,
    run_starts,
)
from starenv.sim.optics import Camera

METHODS = ("cog", "iwcog", "gaussian")
SPIKE_MARGIN = 0.75  # a spike's 3 x 3 median is below this fraction of the least a PSF pixel's can be
SPIKE_SIGMA = 3.0  # significance (noise sigmas) of the excess over the local median that marks a pixel as a spike
SPIKE_GROW_SIGMA = 1.5  # the same for the neighbours of spikes, on the cleaned image
TRACK_PIECES = 5  # pixels taken off near a blob that make a track, beyond a lone spike and the neighbours grown to it
MEDIAN_RATIO_FLOOR = 0.01  # PSF pixels below this fraction of the peak are left out of the spike limit
MEDIAN_NOISE = 0.42  # noise of the median of 9 pixels, in pixel-noise sigmas
LINE_SIGNIFICANCE = 3.0  # the track test decides only where a star would pass it by this many errors
PAIR_STEPS = np.array([(1, 0), (1, 1), (0, 1), (-1, 1)])  # pixel steps along 0, 45, 90, 135 deg (x right, y down)
STREAK_ANISOTROPY_PX2 = 2.0  # blob-mask variance along minus across its axis above which a blob is a streak
LINK_ACROSS_SIGMAS = 1.5  # streak linking: the most a piece's centre may lie off the streak's axis, in PSF sigmas
LINK_GAP_SIGMAS = 6.0  # streak linking: the longest break between two pieces of one trail, in PSF sigmas
LINK_ANGLE_DEG = 15.0  # streak linking: the most two streak pieces' axes may differ
LINK_MIN_HALF_SIGMAS = 3.0  # streak linking: the least half-length (PSF sigmas) of a streak giving the motion's way
EDGE_BIAS_PX = 0.01  # the most the light a blob loses beyond the image border may pull its centroid
FIT_ITERATIONS = 30  # at most; the fit stops once no centre moves by FIT_TOLERANCE_PX
FIT_TOLERANCE_PX = 1e-4
MAX_LABELS = 2**24  # labels are carried in float32 images, exact up to here
# Where the camera's spot varies, the matched filter changes by zones of the field whose spot sigmas lie within this
# ratio of each other: a Gaussian filter of sigma s on a Gaussian spot of sigma s r keeps 2 r / (1 + r^2) of the
# matched filter's signal-to-noise, >= 0.994 for the zone's geometric middle (r <= sqrt(1.25) either way).
ZONE_SIGMA_RATIO = 1.25
BOX = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]  # a 3 x 3 neighbourhood
FORWARD_NEIGHBOURS = [(0, 1), (1, -1), (1, 0), (1, 1)]  # each 8-connected pixel pair once
_CENTRE_FIRST = [BOX.index((0, 0))] + [k for k, step in enumerate(BOX) if step != (0, 0)]  # rows of _box's result


def _flag(name: str, value) -> bool:
    """``value`` as a bool, refusing anything but True or False."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def _box(index: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Flat indices (9, n) of the 3 x 3 neighbourhoods (BOX order, clipped at the border) of flat pixel indices."""
    height, width = shape
    y, x = np.divmod(index, width)
    rows = [np.minimum(np.maximum(y + dy, 0), height - 1) * width for dy in (-1, 0, 1)]
    cols = [np.minimum(np.maximum(x + dx, 0), width - 1) for dx in (-1, 0, 1)]
    return np.stack([rows[dy + 1] + cols[dx + 1] for dy, dx in BOX])


def _unique(values: np.ndarray) -> np.ndarray:
    """The sorted distinct values of an integer array (numpy's own unique hashes, slower on a few thousand)."""
    values = np.sort(values, axis=None)
    return values[run_starts(values)]


def _pixel_fractions(sigma_px: float) -> tuple[float, float]:
    """Fractions of a 1-D Gaussian (sigma in px) centred on a pixel that fall in that pixel and in one neighbour."""
    centre = erf(0.5 / (math.sqrt(2.0) * sigma_px))
    return float(centre), float(0.5 * (erf(1.5 / (math.sqrt(2.0) * sigma_px)) - centre))


def _least_median_ratio(sigma_px: float) -> float:
    """Least ratio of the median of a pixel's 3 x 3 neighbourhood to the pixel's value, over the pixels of a
    pixel-integrated Gaussian PSF (sigma in px) holding at least MEDIAN_RATIO_FLOOR of its peak, and over the PSF's
    sub-pixel phase."""
    reach = math.ceil(4.0 * sigma_px) + 2
    edges = np.arange(-reach, reach + 2) - 0.5
    phase = np.linspace(0.0, 0.5, 6)
    profile = 0.5 * np.diff(erf((edges[None, :] - phase[:, None]) / (math.sqrt(2.0) * sigma_px)), axis=1)
    least = 1.0
    for gy in profile:
        for gx in profile:
            psf = np.outer(gy, gx)
            bright = psf >= MEDIAN_RATIO_FLOOR * psf.max()
            least = min(least, float(np.min(ndimage.median_filter(psf, size=3)[bright] / psf[bright])))
    return least


def local_sigma(camera: Camera, xy: np.ndarray, option: float | None = None) -> np.ndarray | None:
    """Sigma (n,) px of the isotropic Gaussian with the mean variance of the camera's spot at ``xy`` (n, 2) px,
    ``sqrt(sigma^2 + radial_sigma^2 / 2)``; None where the spot is the same everywhere or a detector's
    ``psf_sigma_px`` ``option`` overrides the camera's."""
    if camera.spot is None or option is not None:
        return None
    shape = camera.spot_shape(xy)
    return np.sqrt(shape.sigma**2 + 0.5 * shape.radial_sigma**2)


def full_scale(image: np.ndarray) -> int | None:
    """The saturation code (DN) of an integer frame: its maximum when that is a full-scale code ``2^n - 1`` (n = 8 ..
    16); None otherwise and for float (restored) frames, which have no full-scale code."""
    if not np.issubdtype(image.dtype, np.integer):
        return None
    top = int(image.max())
    return top if top >= 255 and (top + 1) & top == 0 else None


class _Psf:
    """What follows from a Gaussian PSF sigma (px): the matched filter and its noise gain, the sharpness limits and
    the window margin."""

    def __init__(self, sigma_px: float, matched_filter: bool, window_margin_px: int | None):
        self.sigma_px = sigma_px
        # The pixel-integrated PSF has variance sigma^2 + 1/12 px^2 at the pixel centres.
        self.sigma_eff = math.sqrt(sigma_px**2 + 1.0 / 12.0)
        self.radius_px = math.ceil(3.0 * self.sigma_eff)
        self.kernel = cv2.getGaussianKernel(2 * self.radius_px + 1, self.sigma_eff, cv2.CV_32F)
        # Noise of the smoothed image per unit pixel noise: the root of the sum of the 2-D kernel's squares.
        self.filter_noise = float(np.sum(self.kernel.astype(np.float64) ** 2)) if matched_filter else 1.0
        self.margin_px = math.ceil(2.0 * sigma_px) if window_margin_px is None else window_margin_px
        # Sharpness: light in the 8 neighbours of the peak pixel per unit peak for a PSF centred on the pixel, halved.
        centre, neighbour = _pixel_fractions(sigma_px)
        self.min_neighbour_ratio = 0.5 * ((centre + 2.0 * neighbour) ** 2 / centre**2 - 1.0)
        # Spikes: the least ratio of a PSF pixel's 3 x 3 median to its value.
        self.median_ratio = _least_median_ratio(sigma_px)
        rho = neighbour / centre
        # Track test: light in the two pixels beside a centred PSF's peak, per unit peak, along PAIR_STEPS.
        self.pair_ratio = np.array([2.0 * rho, 2.0 * rho**2, 2.0 * rho, 2.0 * rho**2])


class CentroidDetector:
    """Finds stars on a frame (integer DN, or float such as a restored one) and centroids them (a
    :class:`~starenv.agents.base.StarDetector`).

    Options (checked; a bad one raises ``ValueError`` naming it):

    * ``method``: ``"cog"``, ``"iwcog"`` or ``"gaussian"`` (see the module docstring).
    * ``threshold_sigma``: detection threshold, in noise sigmas of the (smoothed) background-subtracted image.
    * ``psf_sigma_px``: Gaussian PSF sigma (px) that the matched filter, the sharpness tests and the fit assume;
      None (the default): the spot size the camera model carries (``camera.psf_sigma_px``).
    * ``matched_filter``: smooth with the PSF-matched Gaussian before thresholding (finds fainter stars).
    * ``tile_px``: background tile size (px); smaller follows steeper gradients, larger is less noisy.
    * ``clip_sigma``: sigma-clipping limit of the background statistics.
    * ``min_area_px``, ``max_area_px``: accepted blob areas (pixels above the threshold).
    * ``deblend_contrast``: least rise of a maximum above its saddle, as a fraction of its height, for it to count
      as a star of its own (together with the detection threshold); 1 turns deblending off.
    * ``window_margin_px``: growth (px) of each blob for centroid and flux; None: ``ceil(2 psf_sigma_px)``.
    * ``reject_sharp``: clean spikes and drop blobs sharper than the PSF allows (hot pixels, cosmic rays).
    * ``keep_edge``: also report stars cut by the image border.
    * ``saturation_dn``: pixel value (DN) at and above which a pixel is saturated; None: the image's maximum when it
      is a full-scale code ``2^n - 1`` (n = 8 .. 16), else none.
    * ``max_stars``: report at most this many stars (the brightest); None: all.
    * ``link_streaks``: join the pieces of faint trails that noise broke (step 7 of the module docstring).

    The constants that follow from a PSF sigma (matched filter, sharpness limits) are computed once per sigma.
    """

    def __init__(
        self,
        method: str = "iwcog",
        threshold_sigma: float = 5.0,
        psf_sigma_px: float | None = None,
        matched_filter: bool = True,
        tile_px: int = 32,
        clip_sigma: float = 3.0,
        min_area_px: int = 2,
        max_area_px: int = 20000,
        deblend_contrast: float = 0.2,
        window_margin_px: int | None = None,
        reject_sharp: bool = True,
        keep_edge: bool = False,
        saturation_dn: int | None = None,
        max_stars: int | None = None,
        link_streaks: bool = False,
    ):
        self.method = checks.choice("method", method, METHODS)
        self.threshold_sigma = checks.in_range("threshold_sigma", threshold_sigma, 0.0, 100.0, low_open=True)
        self.psf_sigma_px = (
            None if psf_sigma_px is None else checks.in_range("psf_sigma_px", psf_sigma_px, 0.2, 20.0, unit="px")
        )
        self.matched_filter = _flag("matched_filter", matched_filter)
        self.tile_px = checks.integer("tile_px", tile_px, 8, 4096)
        self.clip_sigma = checks.in_range("clip_sigma", clip_sigma, 1.5, 10.0)
        self.min_area_px = checks.integer("min_area_px", min_area_px, 1, 10**8)
        self.max_area_px = checks.integer("max_area_px", max_area_px, self.min_area_px, 10**8)
        self.deblend_contrast = checks.in_range("deblend_contrast", deblend_contrast, 0.0, 1.0, low_open=True)
        self.window_margin_px = (
            None if window_margin_px is None else checks.integer("window_margin_px", window_margin_px, 0, 100)
        )
        self.reject_sharp = _flag("reject_sharp", reject_sharp)
        self.keep_edge = _flag("keep_edge", keep_edge)
        self.saturation_dn = None if saturation_dn is None else checks.integer("saturation_dn", saturation_dn, 1, 65535)
        self.max_stars = None if max_stars is None else checks.integer("max_stars", max_stars, 1, 10**8)
        self.link_streaks = _flag("link_streaks", link_streaks)

        self._psf_constants: dict[float, _Psf] = {}
        self._zone_cache: dict[tuple, tuple[np.ndarray, list[tuple[_Psf, tuple[slice, slice]]]]] = {}
        self._work: Workspace | None = None

    def _psf(self, camera: Camera) -> _Psf:
        """The constants that follow from the PSF sigma in force (this detector's, else the camera's)."""
        return self._psf_for(float(self.psf_sigma_px if self.psf_sigma_px is not None else camera.psf_sigma_px))

    def _psf_for(self, sigma: float) -> _Psf:
        """The constants that follow from a PSF sigma (px), computed once per sigma."""
        if sigma not in self._psf_constants:
            if not 0.2 <= sigma <= 20.0:
                raise ValueError(f"psf_sigma_px must be in [0.2, 20] px, got the camera's {sigma}")
            self._psf_constants[sigma] = _Psf(sigma, self.matched_filter, self.window_margin_px)
        return self._psf_constants[sigma]

    def detect(self, image: np.ndarray, camera: Camera) -> StarMeasurements:
        """Stars on ``image`` (DN, integer or float such as a restored frame; shape (camera.height, camera.width)),
        brightest first: positions (px) and flux (DN above background)."""
        self._check(image, camera)
        psf = self._psf(camera)
        height, width = image.shape
        work = self._workspace(image.shape)
        level, noise = background_maps(image, self.tile_px, self.clip_sigma, work)
        resid = np.subtract(image, level, out=work.array("data", np.float32), dtype=np.float32, casting="unsafe")
        removed = self._clean_spikes(resid, noise, psf, work) if self.reject_sharp else None
        smooth = work.array("smooth", np.float32)
        zones = self._zones(camera)
        signal = smooth if self.matched_filter else resid
        if zones is None:
            cv2.sepFilter2D(resid, cv2.CV_32F, psf.kernel, psf.kernel, dst=smooth, borderType=cv2.BORDER_REFLECT)
            factor = np.float32(self.threshold_sigma * psf.filter_noise)  # the limit: factor times the noise
            found = components(pixels_above(signal, noise, factor, work), image.shape, self.min_area_px,
                               self.max_area_px)
        else:
            limit = self._zoned_filter(resid, noise, zones, smooth, work.array("limit"))
            found = components_above(signal, limit, self.min_area_px, self.max_area_px, work)
        n_label, pixel, component, kept = found.count, found.pixel, found.label, found.kept
        if len(kept) == 0:
            return StarMeasurements(np.zeros((0, 2)))
        if len(kept) >= MAX_LABELS:
            raise ValueError(f"{len(kept)} blobs above the threshold: raise threshold_sigma or min_area_px")
        # Blob labels 1 .. n, 0 elsewhere; deblending makes at most one blob per pixel, and OpenCV dilates 16-bit
        # images faster than float ones.
        dtype = np.uint16 if len(pixel) < 2**16 else np.float32
        lut = np.zeros(n_label, dtype)
        lut[kept] = np.arange(1, len(kept) + 1)
        core = work.array("core", dtype)
        core.fill(0)
        core.ravel()[pixel] = lut[component]
        pixel = pixel[lut[component] > 0]
        n = len(kept)
        if self.deblend_contrast < 1.0:
            limit_there = noise.ravel()[pixel] * factor if zones is None else limit.ravel()[pixel]
            n = self._deblend(core, pixel, signal, limit_there, n, work)
        grown = core
        if m := psf.margin_px:
            disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
            grown = cv2.dilate(core, disk, dst=work.array("grown", dtype))
            grown.ravel()[pixel] = core.ravel()[pixel]  # a blob's own pixels keep its label
        blobs = _Blobs(grown, core, resid, smooth, n)

        good = np.ones(n, bool)
        if self.reject_sharp:
            good &= self._not_sharp(blobs, resid, noise, psf) & ~self._track_remnant(grown, removed, blobs)

        centre, axis, var_major, var_minor = blobs.mask_axes()
        streak = var_major - var_minor > STREAK_ANISOTROPY_PX2
        xy = blobs.centroid(blobs.positive)
        if self.method == "iwcog":
            weighted = ~streak
            xy[weighted] = blobs.centroid(blobs.positive * np.maximum(blobs.smooth, 0.0))[weighted]
        saturated = np.zeros(n, bool)
        if (saturation := self._saturation(image)) is not None and (self.method == "gaussian" or not self.keep_edge):
            saturated = np.bincount(blobs.label, image.ravel()[blobs.pixel] >= saturation, n) > 0
        if not self.keep_edge:
            spot = local_sigma(camera, xy, self.psf_sigma_px)  # the pixel-integrated spot's sigma, as _Psf's
            sigma = psf.sigma_eff if spot is None else np.sqrt(spot**2 + 1.0 / 12.0)
            good &= ~_cut_by_border(blobs, xy, noise, m, ~streak & ~saturated, sigma)
        if self.method == "gaussian":
            fit = np.flatnonzero(good & ~streak & ~saturated)
            xy[fit] = self._fit_gaussians(resid, grown, fit, xy[fit], blobs.flux[fit], psf,
                                          local_sigma(camera, xy[fit], self.psf_sigma_px))
        flux = blobs.flux
        if self.link_streaks:
            xy, flux, good = _link_streaks(xy, flux, good, streak, centre, axis, var_major, psf.sigma_eff)
        order = np.flatnonzero(good)[np.argsort(-flux[good], kind="stable")][: self.max_stars]
        return StarMeasurements(xy[order], flux[order])

    def _zones(self, camera: Camera) -> tuple[np.ndarray, list[tuple[_Psf, tuple[slice, slice]]]] | None:
        """Where the camera's spot varies across the field (and neither this detector's ``psf_sigma_px`` nor
        ``matched_filter=False`` says otherwise): each pixel's zone (H, W), and per zone the filter of its middle spot
        sigma (:func:`local_sigma`, zones ``ZONE_SIGMA_RATIO`` wide) with the box (rows, cols) its pixels and the
        filter's reach span.  None otherwise.  Computed once per camera."""
        if camera.spot is None or self.psf_sigma_px is not None or not self.matched_filter:
            return None
        key = (camera.spot, camera.psf_sigma_px, camera.cx, camera.cy, camera.width, camera.height)
        if key not in self._zone_cache:
            rows, cols = np.mgrid[: camera.height, : camera.width]
            sigma = local_sigma(camera, np.stack([cols.ravel(), rows.ravel()], axis=1)).reshape(rows.shape)
            low = float(sigma.min())
            zone = np.floor(np.log(sigma / low) / math.log(ZONE_SIGMA_RATIO) + 1e-9).astype(np.intp)
            filters = []
            for k in range(int(zone.max()) + 1):
                inside = zone == k
                if not inside.any():
                    filters.append((None, (slice(0, 0), slice(0, 0))))
                    continue
                zone_psf = self._psf_for(min(low * ZONE_SIGMA_RATIO ** (k + 0.5), float(sigma[inside].max())))
                r = zone_psf.radius_px
                ys, xs = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
                box = (slice(max(ys[0] - r, 0), ys[-1] + r + 1), slice(max(xs[0] - r, 0), xs[-1] + r + 1))
                filters.append((zone_psf, box))
            self._zone_cache[key] = (zone, filters)
        return self._zone_cache[key]

    def _zoned_filter(self, resid: np.ndarray, noise: np.ndarray, zones, smooth: np.ndarray,
                      limit: np.ndarray) -> np.ndarray:
        """The matched filter zone by zone into ``smooth`` (each zone's box, grown by its kernel's reach, filtered as
        the whole frame would be) and the detection limit per pixel into ``limit`` (its zone's filter noise)."""
        zone, filters = zones
        for k, (zone_psf, box) in enumerate(filters):
            if zone_psf is None:
                continue
            part = cv2.sepFilter2D(resid[box], cv2.CV_32F, zone_psf.kernel, zone_psf.kernel,
                                   borderType=cv2.BORDER_REFLECT)
            inside = zone[box] == k
            smooth[box][inside] = part[inside]
            limit[box][inside] = noise[box][inside] * np.float32(self.threshold_sigma * zone_psf.filter_noise)
        return limit

    def background(self, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local background level and noise (DN) of a float32 image, both float32 (H, W): the block
        :func:`~starenv.agents.blocks.background_maps` on tiles of about ``tile_px`` with ``clip_sigma``."""
        level, noise = background_maps(data, self.tile_px, self.clip_sigma)
        return np.array(level), noise

    def _check(self, image, camera: Camera) -> None:
        """Refuse anything but a 2-D integer or finite float array of the camera's size."""
        numeric = isinstance(image, np.ndarray) and (np.issubdtype(image.dtype, np.integer)
                                                      or np.issubdtype(image.dtype, np.floating))
        if not numeric or image.ndim != 2:
            got = f"a {image.dtype} array of shape {image.shape}" if isinstance(image, np.ndarray) else type(image)
            raise ValueError(f"image must be a 2-D integer or float array (DN), got {got}")
        if image.shape != (camera.height, camera.width):
            raise ValueError(f"image shape {image.shape} does not match the camera's {(camera.height, camera.width)}")
        if np.issubdtype(image.dtype, np.floating) and not np.all(np.isfinite(image)):
            raise ValueError("image must be finite (no NaN or inf)")

    def _workspace(self, shape: tuple[int, int]) -> Workspace:
        """The frame-sized working arrays for images of ``shape``, kept between calls (allocating them anew for
        every frame costs more than filling them)."""
        if self._work is None or self._work.shape != shape:
            self._work = Workspace(shape)
        return self._work

    def _saturation(self, image: np.ndarray) -> int | None:
        """The saturation level (DN) in force for ``image``; None when no pixel counts as saturated."""
        return self.saturation_dn if self.saturation_dn is not None else full_scale(image)

    def _clean_spikes(
        self, resid: np.ndarray, noise: np.ndarray, psf: _Psf, work: Workspace
    ) -> tuple[np.ndarray, np.ndarray]:
        """Replace, in place, spikes (hot pixels, cosmic-ray hits and tracks, alone or on a star) by the median of
        their 3 x 3 neighbourhood; return their flat indices and the DN taken off each.

        A spike stands above its median, scaled by SPIKE_MARGIN times the least ratio of median to value that a PSF
        pixel shows, by SPIKE_SIGMA noise sigmas.  A second pass, on the cleaned image, adds the spikes' neighbours
        standing out by SPIKE_GROW_SIGMA (a track's ragged edge) and renews every replacement from cleaned
        neighbourhoods.  Only pixels whose scaled value alone passes the first test are examined.
        """
        flat, noise_flat = resid.ravel(), noise.ravel()
        gain = SPIKE_MARGIN * psf.median_ratio
        unit = math.hypot(gain, MEDIAN_NOISE)

        def excess(index, median):
            """Significance (noise sigmas) of each pixel's excess over what its 3 x 3 median allows."""
            return (flat[index] * gain - median) / (noise_flat[index] * unit)

        candidate = pixels_above(resid, noise, np.float32(SPIKE_SIGMA * unit / gain), work)
        median = np.median(flat[_box(candidate, resid.shape)], axis=0)
        is_spike = excess(candidate, median) > SPIKE_SIGMA
        first = candidate[is_spike]
        original = flat[first].astype(np.float64)
        flat[first] = median[is_spike]
        near = _unique(_box(first, resid.shape))
        median = np.median(flat[_box(near, resid.shape)], axis=0)
        was_first = np.isin(near, first)
        is_spike = was_first | (excess(near, median) > SPIKE_GROW_SIGMA)
        index = near[is_spike]
        before = flat[index].astype(np.float64)
        before[was_first[is_spike]] = original  # first and index are both sorted
        flat[index] = median[is_spike]
        return index, before - flat[index]

    def _deblend(self, core: np.ndarray, pixel: np.ndarray, signal: np.ndarray, limit: np.ndarray, n: int,
                 work: Workspace) -> int:
        """Split blobs of ``core`` (labels 1 .. n, 0 elsewhere; ``pixel``: the sorted flat indices of its blob
        pixels, ``limit`` the detection limit at each) holding several significant maxima of ``signal``; relabels
        ``core`` in place and returns the new number of blobs."""
        height, width = core.shape
        core_flat, value = core.ravel(), signal.ravel()
        label = core_flat[pixel].astype(np.intp)
        y, x = np.divmod(pixel, width)
        # Steepest ascent: each pixel points to its highest 8-neighbour in the same blob (itself if none is higher;
        # of equals, the first in BOX order): the first maximum over itself, then its neighbours in BOX order.
        box = _box(pixel, core.shape)[_CENTRE_FIRST]
        best = np.take_along_axis(box, np.where(core_flat[box] == label, value[box], -np.inf).argmax(axis=0)[None],
                                  axis=0)[0]
        split = np.bincount(label[best == pixel], minlength=n + 1)[label] >= 2
        if not split.any():
            return n
        position = work.array("position", np.int32).ravel()  # each blob pixel's position in pixel (read there only)
        position[pixel] = np.arange(len(pixel), dtype=np.int32)
        top = position[best]
        while not np.array_equal(top[top], top):
            top = top[top]

        # Saddles: the highest pixel pair (the lower of the two values) joining two basins of a blob being split.
        pairs = []
        for dy, dx in FORWARD_NEIGHBOURS:
            i = np.flatnonzero(split & (y + dy < height) & (x + dx >= 0) & (x + dx < width))
            q = (y[i] + dy) * width + x[i] + dx
            same = core_flat[q] == label[i]
            i, q = i[same], q[same]
            j = position[q]
            i, j = i[top[i] != top[j]], j[top[i] != top[j]]
            pairs.append(np.column_stack([top[i], top[j], np.minimum(value[pixel[i]], value[pixel[j]])]))
        pairs = np.concatenate(pairs)
        # Only the highest saddle between two basins can join them: a lower one would ask the lower peak to rise
        # less above a lower point.  Keep that one per pair of basins.
        low_basin, high_basin = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
        key = low_basin * len(pixel) + high_basin
        order = np.lexsort((-pairs[:, 2], key))
        key = key[order]
        pairs = pairs[order[run_starts(key)]]
        pairs = pairs[np.argsort(-pairs[:, 2], kind="stable")]
        height_at = value[pixel]
        rise_needed = np.maximum(limit, self.deblend_contrast * height_at)
        a, b = pairs[:, 0].astype(np.intp), pairs[:, 1].astype(np.intp)

        # Highest saddles first: the lower of the two maxima merges into the higher unless it rises enough.  A
        # maximum's first saddle in that order is its highest, and nothing has joined it yet: where the maximum on
        # the other side is higher, that saddle alone decides, so those merges are made at once and only the
        # saddles between what is left go through the loop (same result as the loop over all saddles).
        end, partner = np.concatenate([a, b]), np.concatenate([b, a])
        first = np.lexsort((np.tile(np.arange(len(a)), 2), end))
        first = first[run_starts(end[first])]
        end, partner, saddle = end[first], partner[first], np.tile(pairs[:, 2], 2)[first]
        merge = (height_at[end] < height_at[partner]) & (height_at[end] - saddle < rise_needed[end])
        basin = np.arange(len(pixel))
        basin[end[merge]] = partner[merge]
        while not np.array_equal(basin[basin], basin):
            basin = basin[basin]
        rest = basin[a] != basin[b]
        basin = basin.tolist()
        heights, needed = height_at.tolist(), rise_needed.tolist()

        def root(k):
            while basin[k] != k:
                basin[k] = basin[basin[k]]
                k = basin[k]
            return k

        for i, j, level in zip(a[rest].tolist(), b[rest].tolist(), pairs[rest, 2].tolist(), strict=True):
            ri, rj = root(i), root(j)
            if ri != rj:
                low, high = (ri, rj) if heights[ri] < heights[rj] else (rj, ri)
                if heights[low] - level < needed[low]:
                    basin[low] = high
        basin = np.array(basin)
        while not np.array_equal(basin[basin], basin):
            basin = basin[basin]
        # A new label for each surviving maximum of a split blob; then labels 1 .. n again.
        label[split] = n + 1 + basin[top[split]]
        used = np.zeros(label.max() + 1, bool)
        used[label] = True
        compact = np.cumsum(used)  # labels 1 .. n again, in the same order
        core_flat[pixel] = compact[label]
        return int(compact[-1])

    @staticmethod
    def _track_remnant(grown: np.ndarray, removed: tuple[np.ndarray, np.ndarray], blobs: _Blobs) -> np.ndarray:
        """Mask of the blobs (labels in ``grown``) that are what is left of a cosmic-ray track after cleaning:
        more light was taken off (``removed``: flat indices, DN) within 1 px of their grown region than they
        hold, and either a pixel taken off touches their peak or ``TRACK_PIECES`` pixels or more were taken off
        there.  What is left of a track is its ragged edge, brightest beside the track, or pieces of a track of
        several pixels; a star with a lone hot pixel or a single-pixel hit a few px from its centre keeps its own
        peak, and is kept however bright the spike was."""
        index, amount = removed
        n = blobs.n
        if len(index) == 0:
            return np.zeros(n, bool)
        owner = grown.ravel()[_box(index, grown.shape)].astype(np.intp)  # (9, spikes)
        pairs = _unique(owner * len(index) + np.arange(len(index)))  # (blob label, spike) once each
        blob, spike = np.divmod(pairs[pairs >= len(index)], len(index))
        beside = _box(blobs.peak, grown.shape)  # (9, n)
        touched = np.isin(beside, index).any(axis=0)
        track = np.bincount(blob - 1, minlength=n) >= TRACK_PIECES
        return (np.bincount(blob - 1, amount[spike], n) >= blobs.flux) & (touched | track)

    def _not_sharp(self, blobs: _Blobs, resid: np.ndarray, noise: np.ndarray, psf: _Psf) -> np.ndarray:
        """Mask of blobs no sharper than the PSF: enough light around the peak, and not a one-pixel-wide track."""
        height, width = resid.shape
        peak = resid.ravel()[blobs.peak]
        around = resid.ravel()[_box(blobs.peak, resid.shape)].sum(axis=0) - peak
        spread = around >= psf.min_neighbour_ratio * peak

        # Light beside the ridge (pixels of at least half the peak) across the blob's principal axis, along the
        # pixel direction nearest the normal: a one-pixel-wide track has none there.
        lab, w = blobs.label, blobs.positive
        cx, cy = blobs.centroid(w).T
        dx, dy = blobs.x - cx[lab], blobs.y - cy[lab]
        sxx, syy, sxy = (np.bincount(lab, w * a * b, blobs.n) for a, b in ((dx, dx), (dy, dy), (dx, dy)))
        normal = np.rint((0.5 * np.arctan2(2.0 * sxy, sxx - syy) + 0.5 * np.pi) / (0.25 * np.pi)).astype(int) % 4
        ridge = np.flatnonzero(blobs.in_core & (blobs.resid >= 0.5 * resid.ravel()[blobs.peak][lab]))
        rl = lab[ridge]
        sx, sy = PAIR_STEPS[normal[rl]].T
        rx, ry = blobs.x[ridge].astype(np.intp), blobs.y[ridge].astype(np.intp)
        beside = (
            resid[np.clip(ry + sy, 0, height - 1), np.clip(rx + sx, 0, width - 1)]
            + resid[np.clip(ry - sy, 0, height - 1), np.clip(rx - sx, 0, width - 1)]
        )
        ridge_light = np.bincount(rl, blobs.resid[ridge], blobs.n)
        ratio = np.bincount(rl, beside, blobs.n) / ridge_light
        error = np.sqrt(np.bincount(rl, 2.0 * noise.ravel()[blobs.pixel[ridge]].astype(np.float64) ** 2, blobs.n))
        expected = psf.pair_ratio[normal]
        track = (ratio < 0.5 * expected) & (error / ridge_light < expected / (2.0 * LINE_SIGNIFICANCE))
        return spread & ~track

    def _fit_gaussians(
        self, resid: np.ndarray, grown: np.ndarray, which: np.ndarray, start: np.ndarray, flux: np.ndarray, psf: _Psf,
        spot_sigma: np.ndarray | None = None,
    ) -> np.ndarray:
        """Centres (n, 2) px of pixel-integrated Gaussians fitted (Levenberg-Marquardt, all blobs at once) on square
        windows around ``start``, leaving out pixels off the image or in another blob.  A fit that fails (centre
        moved by more than a PSF sigma + 1 px, width outside [0.5, 3] PSF sigmas) keeps ``start``.  ``spot_sigma``
        (n,): each star's spot sigma where it is (a field-dependent spot, :func:`local_sigma`), which the fit starts
        from and is bounded by, and whose largest sets the window; None: the PSF's everywhere."""
        if len(which) == 0:
            return start
        if spot_sigma is None:
            sigma0, log0 = psf.sigma_px, np.full(len(which), math.log(psf.sigma_px))
            reach, radius = psf.sigma_eff, psf.radius_px
        else:
            sigma0, log0, reach = spot_sigma, np.log(spot_sigma), np.sqrt(spot_sigma**2 + 1.0 / 12.0)
            radius = max(psf.radius_px, math.ceil(3.0 * float(reach.max())))
        height, width = resid.shape
        offsets = np.arange(-radius, radius + 1)
        middle = np.rint(start).astype(np.intp)
        cols, rows = middle[:, 0, None] + offsets, middle[:, 1, None] + offsets  # (n, k)
        on = ((cols >= 0) & (cols < width))[:, None, :] & ((rows >= 0) & (rows < height))[:, :, None]
        rr, cc = np.clip(rows, 0, height - 1)[:, :, None], np.clip(cols, 0, width - 1)[:, None, :]
        owner = grown[rr, cc]
        weight = (on & ((owner == 0) | (owner == (which + 1)[:, None, None]))).reshape(len(which), -1).astype(float)
        data = resid[rr, cc].reshape(len(which), -1).astype(np.float64)

        params = np.column_stack(
            [np.maximum(flux, 1e-3), start - middle, log0]
        )
        model, jac = pixel_gaussians(params, offsets)
        res = (data - model) * weight
        cost = np.einsum("np,np->n", res, res)
        damping = np.full(len(which), 1e-3)
        for _ in range(FIT_ITERATIONS):
            jw_t = (jac * weight[:, :, None]).transpose(0, 2, 1)
            normal = jw_t @ jw_t.transpose(0, 2, 1)
            grad = jw_t @ res[:, :, None]
            diag = np.einsum("nii->ni", normal)
            step = np.linalg.solve(normal + (damping[:, None] * diag + 1e-12)[:, :, None] * np.eye(4), grad)
            trial = params + step[..., 0]
            trial_model, trial_jac = pixel_gaussians(trial, offsets)
            trial_res = (data - trial_model) * weight
            trial_cost = np.einsum("np,np->n", trial_res, trial_res)
            better = trial_cost < cost  # False where NaN
            params[better], res[better], cost[better] = trial[better], trial_res[better], trial_cost[better]
            jac[better] = trial_jac[better]
            damping = np.where(better, damping / 3.0, damping * 4.0)
            if np.all(np.abs(step[:, 1:3, 0]) < FIT_TOLERANCE_PX):
                break
        centre = params[:, 1:3] + middle
        sigma = np.exp(params[:, 3])
        ok = (
            (np.hypot(*(centre - start).T) < reach + 1.0)
            & (sigma > 0.5 * sigma0)
            & (sigma < 3.0 * sigma0)
            & (params[:, 0] > 0)
        )
        return np.where(ok[:, None], centre, start)


def pixel_gaussians(params: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-integrated 2-D Gaussians on square windows, and their Jacobians.

    ``params`` (n, 4): flux (DN), centre x and y relative to the window's middle pixel (px), ln(sigma / 1 px);
    ``offsets`` (k,): pixel offsets of the window's columns and rows.  Returns the model (n, k * k), row-major, and
    its derivatives (n, k * k, 4).
    """
    n, k = len(params), len(offsets)
    flux, sigma = params[:, :1], np.exp(params[:, 3:])

    def profile(centre):
        hi = (offsets + 0.5 - centre[:, None]) / sigma
        lo = (offsets - 0.5 - centre[:, None]) / sigma
        dens_hi, dens_lo = np.exp(-0.5 * hi * hi), np.exp(-0.5 * lo * lo)
        d_centre = -(dens_hi - dens_lo) / (math.sqrt(2.0 * math.pi) * sigma)
        d_log_sigma = -(dens_hi * hi - dens_lo * lo) / math.sqrt(2.0 * math.pi)
        return ndtr(hi) - ndtr(lo), d_centre, d_log_sigma

    gx, gx_c, gx_s = profile(params[:, 1])
    gy, gy_c, gy_s = profile(params[:, 2])

    def outer(a, b):
        return (a[:, :, None] * b[:, None, :]).reshape(n, k * k)

    shape = outer(gy, gx)
    d_sigma = outer(gy_s, gx) + outer(gy, gx_s)
    jac = np.stack([shape, flux * outer(gy, gx_c), flux * outer(gy_c, gx), flux * d_sigma], axis=-1)
    return flux * shape, jac


def _link_streaks(xy, flux, good, streak, centre, axis, var_major, sigma_px):
    """Join the pieces of one trail that noise broke below the threshold.

    Every good blob takes the direction of the nearest streak at least LINK_MIN_HALF_SIGMAS PSF sigmas in
    half-length (a blob's mask taken as a uniform segment of half-length sqrt(3 var_major)): the local direction of
    motion.  Two good blobs are pieces of one trail when the line between their mask centres runs along the direction
    of either (off it by no more than LINK_ACROSS_SIGMAS PSF sigmas) with no more than LINK_GAP_SIGMAS PSF sigmas
    between their ends, and, where both are streaks, their own axes agree within LINK_ANGLE_DEG.  A joined trail keeps
    its first piece's index, with the flux-weighted mean of its pieces' centroids (their union's centre of gravity)
    and the sum of their fluxes; the other pieces are marked not good.  Arrays are returned anew."""
    index = np.flatnonzero(good)
    half = np.sqrt(3.0 * np.maximum(var_major, 0.0))
    guide = index[streak[index] & (half[index] >= LINK_MIN_HALF_SIGMAS * sigma_px)]
    if len(guide) == 0 or len(index) < 2:
        return xy, flux, good
    direction = axis.copy()
    direction[index] = axis[guide[cKDTree(centre[guide]).query(centre[index])[1]]]
    gap = LINK_GAP_SIGMAS * sigma_px
    pairs = cKDTree(centre[index]).query_pairs(2.0 * float(half[index].max()) + gap, output_type="ndarray")
    i, j = index[pairs[:, 0]], index[pairs[:, 1]]
    d = centre[j] - centre[i]
    link = np.zeros(len(i), bool)
    for u in (direction[i], direction[j]):
        along = np.abs(np.einsum("ij,ij->i", d, u))
        across = np.abs(d[:, 0] * u[:, 1] - d[:, 1] * u[:, 0])
        link |= (across <= max(LINK_ACROSS_SIGMAS * sigma_px, 1.0)) & (along - half[i] - half[j] <= gap)
    aligned = np.abs(np.einsum("ij,ij->i", axis[i], axis[j])) >= math.cos(math.radians(LINK_ANGLE_DEG))
    link &= aligned | ~(streak[i] & streak[j])
    if not link.any():
        return xy, flux, good
    n = len(xy)
    graph = sparse.coo_matrix((np.ones(int(link.sum())), (i[link], j[link])), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    weight = np.where(good, np.maximum(flux, 0.0), 0.0)
    total = np.bincount(group, weight, n)
    first = np.full(n, n)
    np.minimum.at(first, group[index], index)
    joined_xy = np.column_stack([np.bincount(group, weight * xy[:, k], n) for k in (0, 1)])
    joined_xy /= np.where(total > 0, total, 1.0)[:, None]
    xy, flux, good = xy.copy(), flux.copy(), good.copy()
    flux[index] = np.bincount(group, np.where(good, flux, 0.0), n)[group[index]]
    several = np.bincount(group[index], minlength=n)[group[index]] > 1
    usable = several & (total[group[index]] > 0)
    xy[index[usable]] = joined_xy[group[index[usable]]]
    good[index] = first[group[index]] == index
    return xy, flux, good


def _cut_by_border(blobs: _Blobs, xy: np.ndarray, noise: np.ndarray, margin: int, point: np.ndarray,
                   sigma: np.ndarray | float) -> np.ndarray:
    """Whether each blob is cut by the image border (n,): its un-grown pixels reach within ``margin`` px of it and
    what it loses beyond the border may pull its centroid ``xy`` (px) by more than EDGE_BIAS_PX.

    A ``point`` blob (an unsaturated spot, not a streak) is the PSF, a Gaussian of ``sigma`` px: cutting it at a
    distance d from its centre pulls the centroid by ``sigma phi(d / sigma) / Phi(d / sigma)`` (the truncated
    normal's mean).  Any other blob's light is taken to fall off outwards where it meets the border, so what lies
    beyond is at most what its pixels on the outermost row or column hold (plus 2 noise sigmas), pulling the
    centroid by that fraction of the flux times the distance to the first pixel centre beyond the border plus half
    a pixel: a trail that runs off the frame fails this bound, a saturated star whose wings reach it passes."""
    height, width = noise.shape
    n, c = blobs.n, blobs.in_core
    x, y = blobs.x[c], blobs.y[c]
    near = np.bincount(blobs.label[c], (x <= margin) | (y <= margin) | (x >= width - 1 - margin)
                       | (y >= height - 1 - margin), n) > 0
    if not near.any():
        return near
    x, y = blobs.x, blobs.y
    rim = np.flatnonzero((x == 0) | (y == 0) | (x == width - 1) | (y == height - 1))  # the outermost pixels
    x, y, label, resid = x[rim], y[rim], blobs.label[rim], blobs.resid[rim]
    variance = noise.ravel()[blobs.pixel[rim]].astype(np.float64) ** 2
    flux = np.maximum(blobs.flux, 0.0)
    pull = np.zeros(n)
    for on_edge, distance in ((x == 0, xy[:, 0] + 1.5), (y == 0, xy[:, 1] + 1.5),
                              (x == width - 1, width + 0.5 - xy[:, 0]), (y == height - 1, height + 0.5 - xy[:, 1])):
        light = np.bincount(label[on_edge], resid[on_edge], n)
        spread = np.sqrt(np.bincount(label[on_edge], variance[on_edge], n))
        measured = (np.maximum(light, 0.0) + 2.0 * spread) * distance / np.maximum(flux, 1e-300)
        t = np.maximum(distance - 1.0, 0.0) / sigma  # the border lies half a pixel beyond the outermost centres
        modelled = sigma * np.exp(-0.5 * t**2) / math.sqrt(2.0 * math.pi) / np.maximum(ndtr(t), 1e-300)
        pull = np.maximum(pull, np.where(point, modelled, measured))
    return near & ~((pull <= EDGE_BIAS_PX) & (flux > 0.0))


class _Blobs:
    """The pixels of the grown blobs as flat arrays (blob index, pixel index, x, y, residual and smoothed DN, whether
    in the un-grown blob), with each blob's flux (DN) and peak pixel (brightest of the un-grown blob)."""

    def __init__(self, grown: np.ndarray, core: np.ndarray, resid: np.ndarray, smooth: np.ndarray, n: int):
        self.n = n
        self.pixel = np.flatnonzero(grown.ravel() > 0)
        self.label = grown.ravel()[self.pixel].astype(np.intp) - 1
        y, x = np.divmod(self.pixel, grown.shape[1])
        self.x, self.y = x.astype(np.float64), y.astype(np.float64)
        self.resid = resid.ravel()[self.pixel].astype(np.float64)
        self.smooth = smooth.ravel()[self.pixel].astype(np.float64)
        self.positive = np.maximum(self.resid, 0.0)
        self.flux = np.bincount(self.label, self.resid, n)
        self.in_core = core.ravel()[self.pixel] > 0
        # Peak: the brightest pixel of the un-grown blob, the last in raster order among equals.
        _, self.peak = component_peaks(self.label[self.in_core], self.resid[self.in_core], self.pixel[self.in_core], n)

    def centroid(self, weight: np.ndarray) -> np.ndarray:
        """Weighted centroids (n, 2) px of the blobs; a blob with no positive weight gets its pixels' mean."""
        total = np.bincount(self.label, weight, self.n)
        flat = total <= 0
        weight = np.where(flat[self.label], 1.0, weight)
        total = np.where(flat, np.bincount(self.label, minlength=self.n), total)
        sums = [np.bincount(self.label, weight * c, self.n) for c in (self.x, self.y)]
        return np.column_stack(sums) / total[:, None]

    def mask_axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Shape of each un-grown blob's pixel mask: centre (n, 2) px, unit major axis (n, 2), variance (px^2) along
        the major axis and along the minor one (n,)."""
        lab = self.label[self.in_core]
        x, y = self.x[self.in_core], self.y[self.in_core]
        count = np.bincount(lab, minlength=self.n)
        centre = np.column_stack([np.bincount(lab, x, self.n), np.bincount(lab, y, self.n)]) / count[:, None]
        dx, dy = x - centre[lab, 0], y - centre[lab, 1]
        sxx, syy, sxy = (np.bincount(lab, a * b, self.n) / count for a, b in ((dx, dx), (dy, dy), (dx, dy)))
        half_spread = 0.5 * np.hypot(sxx - syy, 2.0 * sxy)
        angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
        mean = 0.5 * (sxx + syy)
        return centre, np.column_stack([np.cos(angle), np.sin(angle)]), mean + half_spread, mean - half_spread
