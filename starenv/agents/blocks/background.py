"""Background level and noise of a frame: sigma-clipped statistics over the whole frame, or over tiles interpolated
into maps that follow stray-light gradients.  A tile whose background is cut by the read-out's floor
(``CLIPPED_FRACTION`` to ``CENSORED_MAX_FRACTION`` of its values exactly 0 DN, none below) takes the Gaussian behind
the cut instead (:func:`censored_mean_std`): there the sigma-clipped spread sees the pile at 0 and comes out far too
small.  A frame that does not reach 0 DN goes through the sigma-clipped statistics alone, as before."""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage
from scipy.special import erf, ndtri

from starenv.agents.blocks.workspace import Workspace

START_SUBSAMPLE = 3  # every n-th value of a sample gives the robust start (median, IQR) of the clipping
CLIP_ITERATIONS = 2
MIN_TILE_KEPT = 0.25  # a tile whose clipping keeps less than this fraction of its pixels takes its neighbour's value
QUANTISATION_NOISE_DN = 1.0 / math.sqrt(12.0)  # noise floor: the rounding of an integer read-out
# A sample with at least this share of its values at exactly 0 DN and none below is cut by the floor: a Gaussian
# background reaches it there only 2 standard deviations below its mean, where sigma clipping starts to feel it.
CLIPPED_FRACTION = 0.02
CENSORED_MAX_FRACTION = 0.8  # beyond this share at 0 (a dropped, all-zero frame) too few values place the quantiles
CENSORED_UPPER_QUANTILE = 0.9  # the higher of the two quantiles of a cut sample (below the stars' share of a tile)


def clipped_mean_std(values: np.ndarray, clip_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sigma-clipped mean and standard deviation of each row of a sample.

    Parameters
    ----------
    values : (m, k) ndarray of float32
        ``m`` samples of ``k`` values each (e.g. DN).
    clip_sigma : float
        Values further than this many standard deviations from the mean are left out.

    Returns
    -------
    mean, std : (m,) ndarray of float64
        In the units of ``values``; the deviation is divided by that of a unit Gaussian cut at ``+-clip_sigma``, so
        that it estimates the uncut Gaussian's, and is at least ``QUANTISATION_NOISE_DN``.
    count : (m,) ndarray of int32
        Values kept in each row (at least 1).

    Notes
    -----
    Started from the median and ``IQR / 1.349`` of every ``START_SUBSAMPLE``-th value, then ``CLIP_ITERATIONS``
    rounds of clipping about the mean.  A mean rather than a median: on an integer read-out with a noise of a DN or
    two, the median and the MAD move in whole DN.
    """
    sample = np.sort(values[:, ::START_SUBSAMPLE], axis=1)
    q25, q50, q75 = (sample[:, (sample.shape[1] - 1) * q // 4] for q in (1, 2, 3))
    centre = q50.astype(np.float64)
    scale = np.maximum((q75 - q25) / 1.349, 0.5)
    # Standard deviation of a unit normal clipped at +- clip_sigma: corrects the spread of the kept values.
    c = clip_sigma
    truncation = math.sqrt(1.0 - c * math.sqrt(2.0 / math.pi) * math.exp(-0.5 * c * c) / erf(c / math.sqrt(2.0)))
    dev = np.empty(values.shape, np.float32)
    inside = np.empty(values.shape, bool)
    for _ in range(CLIP_ITERATIONS):
        np.subtract(values, centre.astype(np.float32)[:, None], out=dev)
        np.less_equal(np.abs(dev), (c * scale).astype(np.float32)[:, None], out=inside)
        np.multiply(dev, inside, out=dev)
        # Sums of at most a few thousand deviations of a few sigmas: float32 holds them to ~1e-6.
        count = np.maximum(inside.view(np.uint8).sum(axis=1, dtype=np.int32), 1)
        mean_dev = dev.sum(axis=1).astype(np.float64) / count
        centre = centre + mean_dev
        var = np.einsum("ij,ij->i", dev, dev).astype(np.float64) / count - mean_dev**2
        scale = np.maximum(np.sqrt(np.maximum(var, 0.0)) / truncation, QUANTISATION_NOISE_DN)
    return centre, scale, count


def censored_mean_std(values: np.ndarray, clip_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and standard deviation of the Gaussian behind each row of a sample whose values below 0 read 0.

    Parameters
    ----------
    values : (m, k) ndarray of float
        ``m`` samples of ``k`` values each (DN), >= 0: a background cut at the read-out's floor, at most
        ``CENSORED_MAX_FRACTION`` of each at 0.
    clip_sigma : float
        Sets the kept fraction returned (values no more than this many standard deviations above the mean).

    Returns
    -------
    mean, std : (m,) ndarray of float64
        The Gaussian's (DN), the deviation at least ``QUANTISATION_NOISE_DN``.
    kept : (m,) ndarray of float64
        Fraction of each row's values at most ``mean + clip_sigma std`` (the floor's pile among them).

    Notes
    -----
    The cut leaves the quantiles above the share ``p0`` of values at 0 as they were: the quantile ``x_q`` at
    probability ``q > p0`` is ``mean + std z_q``, ``z_q`` the unit normal's.  Two of them, at ``max(0.5, p0 +
    (1 - p0) / 4)`` and ``max(CENSORED_UPPER_QUANTILE, p0 + 3 (1 - p0) / 4)``, give both (stars and other outliers,
    a small share of the values, sit above the second).  On a row of integers each quantile is interpolated within
    its value's bin ``[v - 1/2, v + 1/2)`` by the empirical distribution function, so that a read-out with a noise of
    a DN or two does not move it in whole DN.
    """
    values = np.asarray(values)
    k = values.shape[1]
    at_floor = np.count_nonzero(values <= 0, axis=1) / k
    probability = np.column_stack([np.maximum(0.5, at_floor + 0.25 * (1.0 - at_floor)),
                                   np.maximum(CENSORED_UPPER_QUANTILE, at_floor + 0.75 * (1.0 - at_floor))])  # (m, 2)
    ordered = np.sort(values, axis=1)
    index = np.minimum((probability * k).astype(np.intp), k - 1)
    value = np.take_along_axis(ordered, index, axis=1).astype(np.float64)  # (m, 2)
    below = np.count_nonzero(ordered[:, None, :] < value[:, :, None], axis=2) / k
    at = np.count_nonzero(ordered[:, None, :] == value[:, :, None], axis=2) / k
    integer = np.all(ordered == np.floor(ordered), axis=1)[:, None]
    quantile = np.where(integer, value - 0.5 + (probability - below) / np.maximum(at, 1.0 / k), value)
    z = ndtri(probability)
    std = np.maximum((quantile[:, 1] - quantile[:, 0]) / (z[:, 1] - z[:, 0]), QUANTISATION_NOISE_DN)
    mean = quantile[:, 0] - z[:, 0] * std
    kept = np.count_nonzero(ordered <= (mean + clip_sigma * std)[:, None], axis=1) / k
    return mean, std, kept


def _clipped_rows(values: np.ndarray) -> np.ndarray:
    """Mask (m,) of the rows of a sample (m, k) cut at 0: the sample's least value is 0 (a floor: none below it in
    any row) and ``CLIPPED_FRACTION`` to ``CENSORED_MAX_FRACTION`` of the row's values are 0."""
    if values.min() != 0:  # one pass over the sample of a frame that does not reach the floor
        return np.zeros(len(values), bool)
    clipped = values.min(axis=1) == 0
    if clipped.any():
        at_zero = np.count_nonzero(values[clipped] == 0, axis=1) / values.shape[1]
        clipped[clipped] = (at_zero >= CLIPPED_FRACTION) & (at_zero <= CENSORED_MAX_FRACTION)
    return clipped


def _tile_statistics(tiles: np.ndarray, clip_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Level (DN), noise (DN) and the kept fraction of the level sample, each (ny * nx,), of tiles (ny, th, nx, tw)
    (their values taken as float32): the sigma-clipped mean of a quarter of each tile's pixels and the sigma-clipped
    spread of differences of horizontal neighbours over sqrt 2; for a tile cut at 0 DN (:func:`_clipped_rows` of its
    level sample), :func:`censored_mean_std` of all its pixels."""
    ny, _, nx, _ = tiles.shape
    # Level from a quarter of the pixels, every other one on every other row, the rows alternating between the
    # even and the odd columns (a sample centred on the tile, as a gradient needs); noise from differences of
    # horizontal neighbours (blind to gradients) on every fourth row.  Both as (tiles, values) arrays.
    level_sample = np.concatenate(
        [tiles[:, i::4, :, j::2].transpose(0, 2, 1, 3).reshape(ny * nx, -1) for i, j in ((0, 0), (3, 1))], axis=1
    ).astype(np.float32, copy=False)
    rows = tiles[:, 1::4].transpose(0, 2, 1, 3).astype(np.float32, copy=False)
    centre, _, count = clipped_mean_std(level_sample, clip_sigma)
    _, spread, _ = clipped_mean_std((rows[..., 1:] - rows[..., :-1]).reshape(ny * nx, -1), clip_sigma)
    scale = np.maximum(spread / math.sqrt(2.0), QUANTISATION_NOISE_DN)
    kept = count / level_sample.shape[1]
    clipped = _clipped_rows(level_sample)
    if clipped.any():
        whole = tiles.transpose(0, 2, 1, 3).reshape(ny * nx, -1)[clipped].astype(np.float32, copy=False)
        centre[clipped], scale[clipped], kept[clipped] = censored_mean_std(whole, clip_sigma)
    return centre, scale, kept


def _checked(image) -> np.ndarray:
    """``image`` as a real array of at least 2 x 2 pixels (the last two axes: rows, columns)."""
    data = np.asarray(image)
    if not np.issubdtype(data.dtype, np.integer) and not np.issubdtype(data.dtype, np.floating):
        raise ValueError(f"image must hold integer or float values (DN), got {data.dtype}")
    if data.ndim < 2 or data.shape[-2] < 2 or data.shape[-1] < 2:
        raise ValueError(f"image must have at least 2 x 2 pixels (rows, columns), got shape {data.shape}")
    return data


def frame_background(image: np.ndarray, clip_sigma: float = 3.0) -> tuple[float, float]:
    """Background level and noise of a whole frame.

    Parameters
    ----------
    image : (H, W) or (..., H, W) array_like
        A frame in DN (integer counts, or float such as a restored frame); a stack of frames is taken as one, its
        frames one above the other.
    clip_sigma : float
        Sigma-clipping limit of the statistics.

    Returns
    -------
    level : float
        Background level (DN): the sigma-clipped mean of a quarter of the pixels (every other pixel of two rows in
        four, the second row's shifted by a column).
    noise : float
        Pixel noise (DN): the sigma-clipped standard deviation of the differences between horizontal neighbours on
        every fourth row, over sqrt 2; blind to gradients across the frame, at least ``QUANTISATION_NOISE_DN``.

    Notes
    -----
    The statistics of :func:`background_maps` with a single tile covering the frame.  Stars, hot pixels and cosmic
    rays on a small share of the pixels are clipped away (:func:`clipped_mean_std`).  For Gaussian noise the level's
    standard error is about ``noise / sqrt(n)``, ``n = H W / 4`` values, and the noise's relative one about
    ``sqrt(1.5 / (2 m))``, ``m = (W - 1) H / 4`` differences (adjacent differences share a pixel: correlation -1/2).
    A frame cut at 0 DN (module docstring) gives the Gaussian behind the cut (:func:`censored_mean_std`, all pixels).
    """
    data = _checked(image)
    data = data.reshape(-1, data.shape[-1])
    centre, scale, _ = _tile_statistics(data.reshape(1, data.shape[0], 1, data.shape[1]), clip_sigma)
    return float(centre[0]), float(scale[0])


def background_maps(data: np.ndarray, tile_px: int = 32, clip_sigma: float = 3.0,
                    workspace: Workspace | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Background level and noise maps of a frame, following gradients (stray light).

    Parameters
    ----------
    data : (H, W) ndarray
        The frame (DN), integer or float; its values are taken as float32.
    tile_px : int
        Tile size (px): the frame is cut into ``round(H / tile_px)`` by ``round(W / tile_px)`` tiles (at least one),
        the last row and column of tiles ending at the border and overlapping the ones before.  Smaller tiles follow
        steeper gradients; larger ones are less noisy.
    clip_sigma : float
        Sigma-clipping limit of each tile's statistics.
    workspace : Workspace, optional
        Arrays kept between calls on frames of one shape; the maps returned are then views of its arrays.

    Returns
    -------
    level, noise : (H, W) ndarray of float32
        Each tile's level and noise as in :func:`frame_background` (DN), at its centre, interpolated bilinearly between
        the tile centres and extrapolated linearly to the border; the noise at least ``QUANTISATION_NOISE_DN`` (to
        float32 rounding), its extrapolated tiles cut there first.  A tile whose clipping keeps less than
        ``MIN_TILE_KEPT`` of its level sample (a large star, a bright trail) takes the nearest good tile's values.
    """
    work = Workspace(data.shape) if workspace is None else workspace
    height, width = data.shape
    ny, nx = max(1, round(height / tile_px)), max(1, round(width / tile_px))
    th, tw = -(-height // ny), -(-width // nx)
    # The last row and column of tiles end at the image border, overlapping the ones before.
    if ny * th != height or nx * tw != width:
        rows = np.r_[0 : (ny - 1) * th, height - th : height]
        cols = np.r_[0 : (nx - 1) * tw, width - tw : width]
        data = data[np.ix_(rows, cols)]
    centre, scale, kept = _tile_statistics(data.reshape(ny, th, nx, tw), clip_sigma)

    grid = np.stack([centre, scale], axis=-1).reshape(ny, nx, 2)
    bad = (kept < MIN_TILE_KEPT).reshape(ny, nx)
    if bad.any() and not bad.all():
        grid = grid[tuple(ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True))]
    # cv2.resize takes the tile centres to be every th (tw) px from (th - 1) / 2.  The last tile's centre lies
    # short of that: extrapolate the last row / column linearly to it.  A ring of linearly extrapolated tiles
    # around the grid carries the gradients out to the image border.
    for axis, (n, step, size) in enumerate(((ny, th, height), (nx, tw, width))):
        if n > 1 and n * step > size:
            last, before = np.take(grid, n - 1, axis=axis), np.take(grid, n - 2, axis=axis)
            index = [slice(None)] * 3
            index[axis] = n - 1
            grid[tuple(index)] = before + (last - before) * (step / (size - (n - 1) * step))
    grid = np.pad(grid, ((1, 1), (1, 1), (0, 0)), mode="reflect", reflect_type="odd").astype(np.float32)
    # The noise map is a weighted mean of its grid's values with weights in [0, 1]: at least the floor if they are.
    np.maximum(grid[..., 1], np.float32(QUANTISATION_NOISE_DN), out=grid[..., 1])
    # Interpolated onto the padded frame ((ny + 2) th by (nx + 2) tw) one axis at a time, as cv2.resize does it
    # (the same values): the columns first, on the grid's rows only, cut to the frame's; then the rows.  Each map is
    # then a run of whole rows of its array, contiguous.
    level, noise = (
        cv2.resize(np.ascontiguousarray(cv2.resize(grid[..., k], ((nx + 2) * tw, ny + 2),
                                                   interpolation=cv2.INTER_LINEAR)[:, tw : tw + width]),
                   (width, (ny + 2) * th), dst=work.array(name, np.float32, ((ny + 2) * th, width)),
                   interpolation=cv2.INTER_LINEAR)[th : th + height]
        for k, name in enumerate(("level_map", "noise_map"))
    )
    return level, noise
