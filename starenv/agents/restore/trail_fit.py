"""Trail fitting: each streak fitted with its own gyro-predicted trail by least squares on the raw pixels, then
replaced by the still star at the fitted mid-exposure position (:class:`TrailFitDeblurrer`).  No deconvolution.

Model.  A star at mid-exposure position ``c`` (px) moves along ``c + r_j`` (j = 1..m, the path offsets from the
gyro, :func:`starenv.agents.restore.kernels.star_paths`, space-variant: each candidate gets the path of a star at its
own position).  Its expected image on the pixel grid (pixel ``k`` covers ``[k - 1/2, k + 1/2]``) is

    mu(x, y) = b + F / m * sum_j g(x - c_x - r_jx) g(y - c_y - r_jy),
    g(u) = Phi((u + 1/2) / sigma) - Phi((u - 1/2) / sigma),

the renderer's pixel-integrated Gaussian (:func:`starenv.sim.render.band_fractions`) with the camera's spot sigma.
The sum over samples is a matrix product ``G_y^T G_x`` (separable per sample), and so are its derivatives in ``c``.
``(c, F, b)`` are found by Gauss-Newton on the sum of squared residuals over the trail's box: the maximum-likelihood
estimate for white Gaussian pixel noise, which is what faint smeared stars see (their shot noise is below the read,
dark and sky noise; a bright star's extra shot noise only costs it some efficiency).  The information the fit uses
along the trail comes from its two ends, across it from the whole length: the estimate reaches the Cramer-Rao
bound of this model, where a centre of gravity of thresholded pixels loses the faint ends first.

Robustness.  Pixels at the ADC's full-scale code are left out of the fit (a saturated trail's core carries no
flux information); after the first fit, pixels more than ``outlier_sigma`` noise sigmas above the model (a hot
pixel, a cosmic ray, a neighbour's trail) are left out and the fit is repeated.  A fit is kept when it converges
inside its box, its flux is positive with ``F / sigma_F >= min_snr`` and its mid-exposure position lies on the
frame; the other candidates are left as observed.  Candidates are fitted brightest first, each on the frame less
the trails already kept, so overlapping trails do not pull each other.

Output.  The observed frame with each kept trail replaced by its still star: ``g - F T(c) + F S(c)``, ``S`` the
still spot (the same ``g`` at ``r_j = 0``), so the residual noise stays as observed and a detector tuned to the
sensor finds a point star at ``c``.  Candidates: the matched-filter streak finder of
:func:`starenv.agents.restore.algorithms.streak_candidates`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erf

from starenv import checks
from starenv.agents.base import StepInput
from starenv.agents.restore.algorithms import checked_image, robust_background, streak_candidates
from starenv.agents.restore.kernels import frame_kernel, sigma_for, spot_sigma, star_paths, window

PSF_REACH_SIGMA = 4.0  # the fit box extends this many spot sigmas beyond the trail's ends
MAX_STEP_PX = 1e-3  # Gauss-Newton stops when the position moves less than this (px)


def _bands(coords: np.ndarray, centres: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-integrated unit Gaussians (m, n) of sigma ``sigma`` px centred at ``centres`` (m,) over the pixels at
    ``coords`` (n,), and their derivatives with respect to the centre."""
    s = math.sqrt(2.0) * sigma
    hi = coords[None, :] + 0.5 - centres[:, None]
    lo = hi - 1.0
    g = 0.5 * (erf(hi / s) - erf(lo / s))
    dens = 1.0 / (math.sqrt(2.0 * math.pi) * sigma)
    dg = dens * (np.exp(-0.5 * (lo / sigma) ** 2) - np.exp(-0.5 * (hi / sigma) ** 2))
    return g, dg


def trail_model(xs: np.ndarray, ys: np.ndarray, centre, offsets: np.ndarray, sigma: float):
    """Unit-flux trail ``T`` (len(ys), len(xs)) of a star at mid-exposure ``centre`` (x, y) px moving through
    ``centre + offsets`` (m, 2) px (equal time weights), and its derivatives ``dT/dc_x``, ``dT/dc_y``."""
    gx, dgx = _bands(xs, centre[0] + offsets[:, 0], sigma)
    gy, dgy = _bands(ys, centre[1] + offsets[:, 1], sigma)
    m = len(offsets)
    return gy.T @ gx / m, gy.T @ dgx / m, dgy.T @ gx / m


def fit_trail(patch: np.ndarray, xs: np.ndarray, ys: np.ndarray, start, offsets: np.ndarray, sigma: float,
              noise: float, usable: np.ndarray, iterations: int = 12, outlier_sigma: float = 5.0):
    """Least-squares fit of :func:`trail_model` plus a constant background to ``patch`` (DN) on its pixels at
    columns ``xs`` and rows ``ys``, over the ``usable`` pixels.

    Returns ``(centre (2,) px, flux DN, background DN, covariance (4, 4) of (c_x, c_y, F, b), converged)``; the
    covariance is ``noise**2 (J^T J)^-1`` at the solution.  Positive outliers (``outlier_sigma`` noise sigmas above
    the first fit) are dropped and the fit repeated once."""
    c = np.asarray(start, dtype=np.float64).copy()
    d = patch.ravel()
    use = usable.ravel().copy()
    flux, level, cov, converged = 0.0, float(np.median(d[use])) if use.any() else 0.0, None, False
    for rnd in range(2):
        flux = None
        for _ in range(iterations):
            t, tx, ty = trail_model(xs, ys, c, offsets, sigma)
            if flux is None:  # linear start for (F, b) at the current position
                a = np.stack([t.ravel()[use], np.ones(use.sum())], axis=1)
                flux, level = np.linalg.lstsq(a, d[use], rcond=None)[0]
            j = np.stack([flux * tx.ravel(), flux * ty.ravel(), t.ravel(), np.ones(t.size)], axis=1)[use]
            r = d[use] - level - flux * t.ravel()[use]
            jtj = j.T @ j
            try:
                delta = np.linalg.solve(jtj, j.T @ r)
            except np.linalg.LinAlgError:
                return c, 0.0, level, None, False
            c += delta[:2]
            flux += delta[2]
            level += delta[3]
            converged = bool(np.all(np.abs(delta[:2]) < MAX_STEP_PX))
            if converged:
                break
        t, tx, ty = trail_model(xs, ys, c, offsets, sigma)
        j = np.stack([flux * tx.ravel(), flux * ty.ravel(), t.ravel(), np.ones(t.size)], axis=1)[use]
        cov = noise**2 * np.linalg.pinv(j.T @ j)
        if rnd == 1:
            break
        resid = d - level - flux * t.ravel()
        outliers = use & (resid > outlier_sigma * noise)
        if not outliers.any():
            break
        use &= ~outliers
    return c, float(flux), float(level), cov, converged


class TrailFitDeblurrer:
    """Each candidate streak fitted with its own gyro-predicted trail (least squares on the raw pixels) and replaced
    by the still star at the fitted mid-exposure position; see the module docstring.

    Options: ``psf_sigma_px`` (None: the camera's spot sigma), ``threshold_sigma`` and ``min_area_px`` of the
    candidate finder, ``min_snr`` (least ``F / sigma_F`` of a kept fit), ``outlier_sigma`` (pixels this many noise
    sigmas above the first fit are left out), ``max_box_px`` (candidates whose trail box is larger on either side
    are left as observed).  ``last_info``: candidates, fits kept, median fitted position sigma (px).
    """

    iterations = 0

    def __init__(self, psf_sigma_px: float | None = None, threshold_sigma: float = 5.0, min_area_px: int = 4,
                 min_snr: float = 5.0, outlier_sigma: float = 5.0, max_box_px: int = 1024):
        self.psf_sigma_px = spot_sigma(psf_sigma_px)
        self.threshold_sigma = checks.in_range("threshold_sigma", threshold_sigma, 0.0, 100.0, low_open=True)
        self.min_area_px = checks.integer("min_area_px", min_area_px, 1, 10**6)
        self.min_snr = checks.in_range("min_snr", min_snr, 0.0, 1e6)
        self.outlier_sigma = checks.in_range("outlier_sigma", outlier_sigma, 1.0, 1e6, low_open=True)
        self.max_box_px = checks.integer("max_box_px", max_box_px, 8, 1 << 16)
        self.last_info: dict = {}

    def deblur(self, image: np.ndarray, head: int, step: StepInput) -> np.ndarray:
        cam = step.cameras[head]
        data = checked_image(image, cam)
        sigma = sigma_for(self.psf_sigma_px, cam)
        level, noise = robust_background(data)
        streak, _ = frame_kernel(step, head, sigma)
        centres, strength = streak_candidates(data, level, noise, streak, self.threshold_sigma, self.min_area_px)
        self.last_info = {"candidates": int(len(centres)), "kept": 0, "position_sigma_px": None}
        out = data.copy()
        if len(centres) == 0:
            return out
        full_scale = float(data.max()) if _is_full_scale(data) else math.inf
        t0, t1 = window(step)
        paths = star_paths(cam, step.gyro, t0, t1, centres)
        offsets = paths - paths[:, len(paths[0]) // 2 : len(paths[0]) // 2 + 1]  # from the mid-exposure sample
        work = data.copy()  # the frame less the trails kept so far
        reach = PSF_REACH_SIGMA * sigma + 2.0
        sigmas = []
        height, width = data.shape
        for i in np.argsort(-strength):
            lo = np.floor(centres[i] + offsets[i].min(axis=0) - reach).astype(np.int64)
            hi = np.ceil(centres[i] + offsets[i].max(axis=0) + reach).astype(np.int64)
            if np.any(hi - lo + 1 > self.max_box_px):
                continue
            lo = np.maximum(lo, 0)
            hi = np.minimum(hi, [width - 1, height - 1])
            xs = np.arange(lo[0], hi[0] + 1, dtype=np.float64)
            ys = np.arange(lo[1], hi[1] + 1, dtype=np.float64)
            patch = work[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
            usable = data[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1] < full_scale
            c, flux, bg, cov, ok = fit_trail(patch, xs, ys, centres[i], offsets[i], sigma, noise, usable,
                                             outlier_sigma=self.outlier_sigma)
            if not ok or cov is None or flux <= 0.0 or flux < self.min_snr * math.sqrt(max(cov[2, 2], 0.0)):
                continue
            if not (lo[0] <= c[0] <= hi[0] and lo[1] <= c[1] <= hi[1] and 0 <= c[0] <= width - 1
                    and 0 <= c[1] <= height - 1):
                continue
            trail, _, _ = trail_model(xs, ys, c, offsets[i], sigma)
            still, _, _ = trail_model(xs, ys, c, np.zeros((1, 2)), sigma)
            work[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1] -= flux * trail
            out[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1] += flux * (still - trail)
            sigmas.append(math.sqrt(max(0.5 * (cov[0, 0] + cov[1, 1]), 0.0)))
        self.last_info.update(kept=len(sigmas), position_sigma_px=float(np.median(sigmas)) if sigmas else None)
        return out


def _is_full_scale(data: np.ndarray) -> bool:
    """Whether the frame's maximum is an ADC's full-scale code ``2^n - 1`` (n = 8..16): saturated pixels."""
    top = float(data.max())
    return any(top == 2**n - 1 for n in range(8, 17))
