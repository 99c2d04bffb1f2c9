"""The spot size measured on a frame: the Gaussian sigma of its brightest isolated, unsaturated stars.

A detector's hot-pixel and cosmic-ray tests compare each blob with the spot the camera model carries; on a camera
whose spot was never calibrated that size is a guess, and a guess above the true spot throws real, sharp stars away.
:func:`measure_spot_sigma` replaces the guess by a measurement:

1. background level and noise on tiles (:func:`~starenv.agents.blocks.background_maps`);
2. candidates: local maxima (5 x 5) of the background-subtracted frame at least ``PEAK_SIGMA`` noise sigmas high
   whose four edge neighbours hold on average at least ``EDGE_FRACTION`` of the peak (a hot pixel or a cosmic-ray hit
   has none; a Gaussian spot of sigma 0.4 px centred on its pixel still puts about 0.13 of its peak there);
3. kept: the brightest ``MAX_STARS`` with no other maximum above ``NEIGHBOUR_SIGMA`` noise sigmas within the fit
   window, whole on the frame and unsaturated (the 3 x 3 core below the full-scale code, and without a flat top of
   pixels at the frame's maximum);
4. each fitted by Levenberg-Marquardt (all at once) with a pixel-integrated 2-D Gaussian (flux, centre, sigma) plus
   a constant on a square window (:func:`~starenv.agents.detect.centroid.pixel_gaussians`), first on a
   ``FIRST_HALF_PX`` window, then, for spots too wide for it, on one of ``WINDOW_SIGMAS`` measured sigmas;
5. the median of the fitted sigmas (the robust answer when a few blends or defects slip through).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from starenv.agents.blocks import background_maps
from starenv.agents.detect.centroid import full_scale, pixel_gaussians

PEAK_SIGMA = 20.0  # least peak height, in background noise sigmas, of a star worth fitting
NEIGHBOUR_SIGMA = 5.0  # another maximum this high within the window spoils the fit
EDGE_FRACTION = 0.08  # least mean edge-neighbour / peak ratio of a spot (not a one-pixel spike)
MAX_STARS = 30  # brightest isolated stars fitted
MIN_STARS = 3  # fewer fits than this: no measurement
FIRST_HALF_PX = 6  # half-size (px) of the first fit window
WINDOW_SIGMAS = 4.0  # half-size of the second window, in measured sigmas
HALF_PX_RANGE = (4, 24)
FIT_ITERATIONS = 40  # at most; the fit stops once no centre or log-sigma moves by FIT_TOLERANCE
FIT_TOLERANCE = 1e-4
SIGMA_RANGE_PX = (0.2, 20.0)  # fitted sigmas outside are failed fits (the detector's own range)


class SpotMeasurement(NamedTuple):
    """The measured spot: median Gaussian sigma (px), the stars fitted and the spread of their sigmas (px, median
    absolute deviation scaled to a Gaussian's sigma)."""

    sigma_px: float
    stars: int
    spread_px: float


def measure_spot_sigma(image: np.ndarray, tile_px: int = 32) -> SpotMeasurement | None:
    """The Gaussian sigma (px) of the spots of ``image`` (DN, 2-D) from its brightest isolated unsaturated stars
    (see the module docstring); None when fewer than ``MIN_STARS`` can be fitted."""
    data = np.asarray(image, dtype=np.float32)
    level, noise = background_maps(data, tile_px)
    resid = data - level
    is_max = resid >= cv2.dilate(resid, np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero(is_max & (resid > NEIGHBOUR_SIGMA * noise))
    bright = resid[ys, xs] > PEAK_SIGMA * noise[ys, xs]
    height, width = data.shape
    inner = (ys >= 1) & (ys < height - 1) & (xs >= 1) & (xs < width - 1)
    cand = np.flatnonzero(bright & inner)
    if len(cand) == 0:
        return None
    cy, cx = ys[cand], xs[cand]
    peak = resid[cy, cx]
    edge = (resid[cy - 1, cx] + resid[cy + 1, cx] + resid[cy, cx - 1] + resid[cy, cx + 1]) / 4.0
    cand = cand[edge >= EDGE_FRACTION * peak]
    cand = cand[np.argsort(-resid[ys[cand], xs[cand]], kind="stable")]
    saturation = full_scale(np.asarray(image)) if np.issubdtype(np.asarray(image).dtype, np.integer) else None
    top = float(data.max())
    core = np.stack([data[ys[cand] + dy, xs[cand] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])  # (9, n)
    core_top = core.max(axis=0)
    flat_top = np.count_nonzero(core >= top, axis=0) >= 2
    unsaturated = ~flat_top if saturation is None else (core_top < saturation) & ~flat_top
    cand = cand[unsaturated]
    maxima = np.column_stack([xs, ys])

    def fit_all(half: int) -> np.ndarray:
        windows = []
        for k in cand:
            x, y = int(xs[k]), int(ys[k])
            if x < half or y < half or x >= width - half or y >= height - half:
                continue
            if np.count_nonzero(np.abs(maxima - (x, y)).max(axis=1) <= half) > 1:  # another maximum in the window
                continue
            windows.append(resid[y - half: y + half + 1, x - half: x + half + 1])
            if len(windows) == MAX_STARS:
                break
        return _fit(np.array(windows, dtype=np.float64).reshape(len(windows), (2 * half + 1) ** 2), half)

    first = fit_all(FIRST_HALF_PX)
    if len(first) < MIN_STARS:
        return None
    half = int(np.clip(math.ceil(WINDOW_SIGMAS * float(np.median(first))), *HALF_PX_RANGE))
    sigmas = first
    if half > FIRST_HALF_PX:  # a spot too wide for the first window: fitted again on a wider one
        wider = fit_all(half)
        sigmas = wider if len(wider) >= MIN_STARS else first
    median = float(np.median(sigmas))
    return SpotMeasurement(median, len(sigmas), 1.4826 * float(np.median(np.abs(sigmas - median))))


def _fit(windows: np.ndarray, half: int) -> np.ndarray:
    """Sigmas (px) of pixel-integrated Gaussians plus a constant fitted by Levenberg-Marquardt, all at once, to
    windows (n, (2 half + 1)^2, row-major) centred on maxima; the failed fits (non-positive flux, centre off the
    central pixel's neighbourhood, sigma out of range or beyond the window) are left out."""
    if len(windows) == 0:
        return np.zeros(0)
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    n = len(windows)
    ones = np.ones((n, windows.shape[1], 1))

    def model(p):
        shape, jac = pixel_gaussians(p[:, :4], offsets)
        return shape + p[:, 4:], np.concatenate([jac, ones], axis=2)

    params = np.column_stack([np.maximum(windows.sum(axis=1), 1e-3), np.zeros((n, 4))])
    predicted, jac = model(params)
    res = windows - predicted
    cost = np.einsum("np,np->n", res, res)
    damping = np.full(n, 1e-3)
    for _ in range(FIT_ITERATIONS):
        jt = jac.transpose(0, 2, 1)
        normal = jt @ jac
        diag = np.einsum("nii->ni", normal)
        step = np.linalg.solve(normal + (damping[:, None] * diag + 1e-12)[:, :, None] * np.eye(5), jt @ res[:, :, None])
        trial = params + step[..., 0]
        trial_predicted, trial_jac = model(trial)
        trial_res = windows - trial_predicted
        trial_cost = np.einsum("np,np->n", trial_res, trial_res)
        better = trial_cost < cost  # False where NaN
        params[better], res[better], cost[better], jac[better] = (trial[better], trial_res[better],
                                                                  trial_cost[better], trial_jac[better])
        damping = np.where(better, damping / 3.0, damping * 4.0)
        if np.all(np.abs(step[:, 1:4, 0]) < FIT_TOLERANCE):
            break
    sigma = np.exp(params[:, 3])
    ok = ((params[:, 0] > 0) & (np.abs(params[:, 1:3]).max(axis=1) < 1.5) & (sigma >= SIGMA_RANGE_PX[0])
          & (sigma <= min(SIGMA_RANGE_PX[1], half)))
    return sigma[ok]
