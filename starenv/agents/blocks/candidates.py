"""Candidate stars and streaks: the pixels where a matched filter's response stands above its noise, grouped into
8-connected components, with each component's peak."""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from starenv.agents.blocks.workspace import Workspace

POINT_TEST_MAX_OVERLAP = 0.4  # the point test runs where a trail gives the spot filter at most this share of its own
# pixels_above tests the pixels above the least noise's limit one by one while they are at most this share of all
MAX_CANDIDATE_SHARE = 0.05


class Components(NamedTuple):
    """The 8-connected components of the pixels above a limit (:func:`components_above`)."""

    shape: tuple[int, int]  # (H, W) of the image
    count: int  # labels in use, the background's included
    pixel: np.ndarray  # (p,) flat indices (row-major) of the pixels above the limit, ascending
    label: np.ndarray  # (p,) int32: each such pixel's component, 1 .. count - 1 (raster order of first pixel)
    area: np.ndarray  # (count,) pixels of each component (area[0]: none, the background's are not counted)
    kept: np.ndarray  # (k,) ascending labels of the components within the area limits

    @property
    def labels(self) -> np.ndarray:
        """The label image (H, W) of int32: 0 below the limit, each pixel's ``label`` above it."""
        labels = np.zeros(self.shape, np.int32)
        labels.ravel()[self.pixel] = self.label
        return labels


def components_above(signal: np.ndarray, limit, min_area_px: int = 1, max_area_px: int | None = None,
                     workspace: Workspace | None = None) -> Components:
    """Connected components of the pixels where ``signal`` exceeds ``limit``.

    Parameters
    ----------
    signal : (H, W) ndarray
        The detection image, e.g. a background-subtracted frame (DN) through a matched filter.
    limit : float or (H, W) ndarray
        The threshold, in the units of ``signal`` (a scalar, or a map such as ``k`` times a local noise map).
    min_area_px, max_area_px : int
        Components of fewer or more pixels are not ``kept`` (None: no upper limit).
    workspace : Workspace, optional
        Arrays kept between calls on frames of one shape.

    Returns
    -------
    Components
        As :func:`components` gives them for those pixels.
    """
    above = np.greater(signal, limit, out=None if workspace is None else workspace.array("above", bool))
    return components(np.flatnonzero(above.ravel()), above.shape, min_area_px, max_area_px)


def components(pixel: np.ndarray, shape: tuple[int, int], min_area_px: int = 1,
               max_area_px: int | None = None) -> Components:
    """Connected components of a set of pixels.

    Parameters
    ----------
    pixel : (p,) int ndarray
        Flat indices (row-major, ascending) of the pixels, e.g. those above a limit (:func:`pixels_above`).
    shape : (int, int)
        The image's (H, W).
    min_area_px, max_area_px : int
        Components of fewer or more pixels are not ``kept`` (None: no upper limit).

    Returns
    -------
    Components
        Labels, pixels and areas; two pixels are in one component when a chain of the pixels, each one of the 8
        neighbours of the one before, joins them.  Labels follow the raster order (row-major) of each component's
        first pixel.
    """
    count, label = _label_pixels(pixel, shape[1])
    area = np.bincount(label, minlength=count)
    within = area[1:] >= min_area_px
    if max_area_px is not None:
        within &= area[1:] <= max_area_px
    return Components(shape, count, pixel, label, area, np.flatnonzero(within) + 1)


def pixels_above(signal: np.ndarray, noise: np.ndarray, factor: float,
                 workspace: Workspace | None = None) -> np.ndarray:
    """Flat indices (row-major, ascending) of the pixels where ``signal`` (H, W) exceeds ``factor`` times ``noise``
    (H, W), the product in ``noise``'s float type as a map of it would hold it.

    Only a pixel above ``factor`` times the least noise can pass: those are found first, in one pass over
    ``signal`` against a number, and tested one by one; the map of the products is never made.  Where more than
    ``MAX_CANDIDATE_SHARE`` of the pixels pass that first test (a noise far from uniform: a saturated bright body
    holds the quantisation floor's), the products are compared pixel by pixel instead.  Either way the same pixels.
    """
    factor = np.float32(factor)
    above = np.greater(signal, noise.min() * factor,  # the least product: rounding keeps the products' order
                       out=None if workspace is None else workspace.array("above", bool))
    if np.count_nonzero(above) > MAX_CANDIDATE_SHARE * above.size:
        return np.flatnonzero(np.greater(signal, noise * factor, out=above).ravel())
    candidate = np.flatnonzero(above.ravel())
    return candidate[signal.ravel()[candidate] > noise.ravel()[candidate] * factor]


def _label_pixels(pixel: np.ndarray, width: int) -> tuple[int, np.ndarray]:
    """8-connected components of the pixels at flat indices ``pixel`` (ascending, row-major) of an image ``width``
    px wide: the labels in use (with 0, none's) and each pixel's label (p,) int32, 1 .. count - 1 in the raster
    order of each component's first pixel.  A graph of the pixels alone, each joined to its forward neighbours
    present (right, below left, below, below right; itself where one is missing): it costs the pixels found, not
    the frame."""
    n = len(pixel)
    if n == 0:
        return 1, np.zeros(0, np.int32)
    neighbour = pixel[:, None] + np.array([1, width - 1, width, width + 1])  # (p, 4)
    at = np.minimum(np.searchsorted(pixel, neighbour), n - 1)
    joined = pixel[at] == neighbour
    column = pixel % width
    joined[:, [0, 3]] &= (column < width - 1)[:, None]  # not across the right border
    joined[:, 1] &= column > 0  # nor the left
    own = np.arange(n)
    graph = csr_matrix((np.ones(4 * n), np.where(joined, at, own[:, None]).ravel(), np.arange(0, 4 * n + 1, 4)),
                       shape=(n, n))
    count, component = connected_components(graph, directed=False)
    # Numbered by their first pixel (the graph's numbering follows it too, but does not promise to).
    first = np.full(count, n)
    np.minimum.at(first, component, own)
    rank = np.empty(count, np.int32)
    rank[np.argsort(first)] = np.arange(1, count + 1, dtype=np.int32)
    return count + 1, rank[component]


def component_peaks(label: np.ndarray, value: np.ndarray, pixel: np.ndarray, count: int) -> tuple[np.ndarray,
                                                                                                  np.ndarray]:
    """Each component's largest value and where it is.

    Parameters
    ----------
    label : (p,) int ndarray
        Component (0 .. count - 1) of each pixel.
    value : (p,) ndarray
        The pixels' values.
    pixel : (p,) int ndarray
        Their flat indices (row-major).
    count : int
        Number of components.

    Returns
    -------
    peak : (count,) ndarray
        Largest value of each component (-inf where it has no pixel), in ``value``'s dtype.
    at : (count,) ndarray of intp
        Flat index of the pixel holding it, the last in raster order among equals (0 where none).
    """
    peak = np.full(count, -np.inf, dtype=value.dtype)
    np.maximum.at(peak, label, value)
    at_peak = value == peak[label]
    at = np.zeros(count, np.intp)
    np.maximum.at(at, label[at_peak], pixel[at_peak])
    return peak, at


def streak_candidates(data: np.ndarray, level: float, noise: float, streak: np.ndarray, threshold_sigma: float,
                      min_area_px: int, spot: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate streaks of a frame: its matched filter with the expected trail, thresholded in noise sigmas.

    Parameters
    ----------
    data : (H, W) ndarray
        The frame (DN).
    level, noise : float
        Its background level and pixel noise (DN), e.g. from :func:`~starenv.agents.blocks.background`.
    streak : (kh, kw) ndarray
        The expected trail (the matched filter's kernel), any positive scale.
    threshold_sigma : float
        Detection threshold, in noise sigmas of the filter's response (white pixel ``noise`` through the filter).
    min_area_px : int
        Components of fewer pixels above the threshold are left out.
    spot : (sh, sw) ndarray, optional
        The still star's kernel (normalised): components that a lone bright pixel explains (a hot pixel, a
        cosmic-ray hit) are left out (Notes).  None: all kept.

    Returns
    -------
    centroids : (k, 2) ndarray
        Each candidate's centroid (x, y px): the mean position of its pixels above the threshold.
    peaks : (k, 2) ndarray
        Position (x, y px) of its strongest response, the last in raster order on a tie.
    responses : (k,) ndarray
        That response, in noise sigmas.

    Notes
    -----
    The response is ``(data - level)`` correlated with ``streak`` (edges reflected), over ``noise |streak|``.
    Either position is the trail's centre where the trail matches ``streak`` (the response is then symmetric about
    it, and the peak is not moved by a trail cut by the frame's edge); where the trail is longer than ``streak`` the
    response has a plateau and only the centroid is its centre.

    The point test: over a component, ``P`` is the peak of the spot's matched filter and ``R`` the trail's, both in
    noise sigmas; a trail gives ``P / R = rho``, the normalised cross-correlation peak of ``streak`` and ``spot``, a
    lone pixel ``P / R = 1 / kappa``, ``kappa = (max(streak) / |streak|) / (max(spot) / |spot|)``.  A component is a
    point when ``P > R`` and ``R - kappa P`` (the response left once the point's is taken away) is below
    ``threshold_sigma``.  The test runs only where ``rho <= POINT_TEST_MAX_OVERLAP`` (trails of about 20 px and more
    with a 1 px spot): for shorter trails the two hypotheses are too close to tell apart in the noise.
    """
    signal = data.astype(np.float32)
    signal -= np.float32(level)
    streak_norm = float(np.sqrt(np.sum(streak**2)))
    response = cv2.filter2D(signal, cv2.CV_32F, streak.astype(np.float32), borderType=cv2.BORDER_REFLECT)
    response /= noise * streak_norm
    found = components_above(response, threshold_sigma, min_area_px)
    n, lab, flat = found.count, found.label, found.pixel
    keep = np.zeros(n, bool)
    keep[found.kept] = True
    best, top = component_peaks(lab, response.ravel()[flat], flat, n)
    if spot is not None:
        spot_norm = float(np.sqrt(np.sum(spot**2)))
        pad = max(spot.shape)
        rho = cv2.filter2D(np.pad(streak, pad), -1, spot, borderType=cv2.BORDER_CONSTANT).max() / (streak_norm
                                                                                                   * spot_norm)
        if rho <= POINT_TEST_MAX_OVERLAP:
            kappa = float(streak.max() / streak_norm) / float(spot.max() / spot_norm)
            point = cv2.sepFilter2D(signal, cv2.CV_32F, spot.sum(axis=0).astype(np.float32),
                                    spot.sum(axis=1).astype(np.float32), borderType=cv2.BORDER_REFLECT)
            point_peak = np.zeros(n, dtype=np.float32)
            np.maximum.at(point_peak, lab, point.ravel()[flat] / np.float32(noise * spot_norm))
            keep &= ~((point_peak > best) & (best - kappa * point_peak < threshold_sigma))
    keep = np.flatnonzero(keep)
    if len(keep) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    y, x = np.divmod(flat, data.shape[1])
    area = found.area[keep]
    centroids = np.stack([np.bincount(lab, x, n)[keep] / area, np.bincount(lab, y, n)[keep] / area], axis=1)
    peak_xy = np.stack([top[keep] % data.shape[1], top[keep] // data.shape[1]], axis=1).astype(np.float64)
    return centroids, peak_xy, best[keep].astype(np.float64)
