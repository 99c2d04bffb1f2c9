"""The baselines paper 003 compares its network with (its Table 6), fitted on the same measured/reference pairs.

* :class:`PiecewiseLinearMap` -- piecewise-linear mapping on the Delaunay triangulation of the measured positions
  (scipy's ``LinearNDInterpolator``), nearest neighbour outside their convex hull;
* :class:`PolynomialMap` -- ordinary polynomial mapping: the offsets fitted by least squares on the monomials
  ``x^i y^j`` (``i + j <= order``) of the normalised coordinates.  The paper fits it with an improved genetic
  algorithm; the closed form is its optimum.  At the same order it spans the same functions as the Legendre network,
  so it differs only in conditioning (and in nothing a correction can see).

Both return offsets (measured - reference, px) at measured positions, like
:meth:`starenv.agents.correct.legendre.LegendreModel.offset`.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

from starenv.agents.correct.legendre import ORDER, scale_px
from starenv.sim.optics import Camera


class PiecewiseLinearMap:
    """Offsets interpolated linearly on the Delaunay triangles of the measured positions ``measured`` (n, 2) px."""

    def __init__(self, measured: np.ndarray, reference: np.ndarray):
        measured = np.asarray(measured, dtype=np.float64)
        offsets = measured - np.asarray(reference, dtype=np.float64)
        if len(measured) < 3:
            raise ValueError(f"a piecewise-linear map needs at least 3 stars, got {len(measured)}")
        self._linear = LinearNDInterpolator(measured, offsets)
        self._nearest = NearestNDInterpolator(measured, offsets)

    def offset(self, xy: np.ndarray, camera: Camera | None = None) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = self._linear(xy)
        outside = ~np.all(np.isfinite(out), axis=1)
        if outside.any():
            out[outside] = self._nearest(xy[outside])
        return out


class PolynomialMap:
    """Offsets as ordinary polynomials of total order ``order`` in the normalised measured coordinates."""

    def __init__(self, measured: np.ndarray, reference: np.ndarray, camera: Camera, order: int = ORDER):
        self.order = order
        a = self._monomials(measured, camera)
        if len(a) < a.shape[1]:
            raise ValueError(f"a polynomial map of order {order} needs at least {a.shape[1]} stars, got {len(a)}")
        offsets = (np.asarray(measured, np.float64) - np.asarray(reference, np.float64)) / scale_px(camera)
        self.coeffs, *_ = np.linalg.lstsq(a, offsets, rcond=None)

    def _monomials(self, xy: np.ndarray, camera: Camera) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        s = scale_px(camera)
        x, y = (xy[:, 0] - camera.cx) / s, (xy[:, 1] - camera.cy) / s
        return np.stack([x ** (t - j) * y**j for t in range(self.order + 1) for j in range(t + 1)], axis=1)

    def offset(self, xy: np.ndarray, camera: Camera) -> np.ndarray:
        return scale_px(camera) * (self._monomials(xy, camera) @ self.coeffs)
