"""Trail fitting: each streak fitted with its own gyro-predicted trail by least squares on the raw pixels, then
replaced by the still star at the fitted mid-exposure position (:class:`TrailFitDeblurrer`).  No deconvolution.

Model.  A star at mid-exposure position ``c`` (px) moves along ``c + r(t)`` during the exposure, ``r`` from the
gyro (:func:`starenv.agents.restore.kernels.star_paths`, space-variant: each candidate gets the path of a star at its
own position), drawn as constant-speed chords that stay within ``CHORD_TOLERANCE_PX`` of it (one chord for a
straight trail).  A chord of length ``L`` is a uniform line convolved with the spot; with ``u`` along it from its
start and ``v`` across it, its unit-flux image is

    T(u, v) = [Phi(u / s) - Phi((u - L) / s)] / L * phi(v / s) / s,    s^2 = sigma^2 + 1/12,

``sigma`` the camera's spot and ``1/12`` px^2 the pixel's box (the renderer integrates the spot over each pixel:
this matches its second moment, to within 1 % of the peak).  The frame near the trail is modelled as
``b + F T(x - c)``; ``(c, F, b)`` are found by Gauss-Newton on the sum of squared residuals over the pixels within
``PSF_REACH_SIGMA`` spot sigmas (+ ``SHIFT_PX``) of the trail: the maximum-likelihood estimate for white Gaussian
pixel noise, which is what faint smeared stars see (their shot noise is below the read, dark and sky noise; a bright
star's extra shot noise only costs it some efficiency).  The fit's information along the trail comes from its two
ends, across it from the whole length: it reaches the Cramer-Rao bound of this model, where a centre of gravity of
thresholded pixels loses the faint ends first.

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

PSF_REACH_SIGMA = 4.0  # the fit covers pixels within this many spot sigmas (+ SHIFT_PX) of the trail
SHIFT_PX = 2.0  # how far the fit may move a candidate from its first position before its pixels run out (px)
MAX_STEP_PX = 0.01  # Gauss-Newton stops when the position moves less than this (px)
CHORD_TOLERANCE_PX = 0.05  # a trail is drawn as chords no farther than this from its gyro path
MAX_CHORDS = 32


def chords(offsets: np.ndarray) -> np.ndarray:
    """The trail's knots (K + 1, 2) px relative to mid-exposure: its positions at the exposure's start, at K - 1
    equally spaced instants and at its end, so that constant-speed chords between them stay within
    ``CHORD_TOLERANCE_PX`` of the path.  ``offsets`` (m, 2): the path at the m midpoint instants ``(j + 1/2) / m``
    of the exposure (:func:`starenv.agents.restore.kernels.star_paths`); the ends are extrapolated half a sample."""
    o = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
    m = len(o)
    if m == 1:
        return np.repeat(o, 2, axis=0)
    t = np.concatenate([[0.0], (np.arange(m) + 0.5) / m, [1.0]])
    ext = np.concatenate([o[:1] - 0.5 * (o[1] - o[0]), o, o[-1:] + 0.5 * (o[-1] - o[-2])])
    k = 1
    while True:
        knots_t = np.linspace(0.0, 1.0, k + 1)
        knots = np.stack([np.interp(knots_t, t, ext[:, 0]), np.interp(knots_t, t, ext[:, 1])], axis=1)
        on_chords = np.stack([np.interp(t, knots_t, knots[:, 0]), np.interp(t, knots_t, knots[:, 1])], axis=1)
        if k >= MAX_CHORDS or np.abs(on_chords - ext).max() <= CHORD_TOLERANCE_PX:
            return knots
        k *= 2


def trail_model(x: np.ndarray, y: np.ndarray, centre, knots: np.ndarray, sigma: float):
    """Unit-flux trail at the pixels (x, y) (n,) px of a star at mid-exposure ``centre`` (x, y) px moving at constant
    speed along each chord of ``centre + knots`` (:func:`chords`), equal time on each, and its derivatives
    ``dT/dc_x``, ``dT/dc_y`` (n,).

    Each chord of length L is a uniform line convolved with a Gaussian: along it ``(Phi(u / s) - Phi((u - L) / s))
    / L``, across it ``phi(v / s) / s``, with ``s^2 = sigma^2 + 1/12`` (the pixel's box added to the spot: the
    renderer integrates the spot over each pixel; this is its second-moment match, within 1 % of the peak)."""
    s = math.sqrt(sigma**2 + 1.0 / 12.0)
    k = len(knots) - 1
    total = np.zeros(len(x))
    gx = np.zeros(len(x))
    gy = np.zeros(len(x))
    for a, b in zip(knots[:-1], knots[1:], strict=True):
        ax, ay = centre[0] + a[0], centre[1] + a[1]
        d = b - a
        length = math.hypot(d[0], d[1])
        dx, dy = x - ax, y - ay
        if length < 1e-6:  # a still star: a round Gaussian
            g = np.exp(-0.5 * (dx**2 + dy**2) / s**2) / (2.0 * math.pi * s**2)
            total += g
            gx += g * dx / s**2
            gy += g * dy / s**2
            continue
        e = d / length
        u = dx * e[0] + dy * e[1]
        v = -dx * e[1] + dy * e[0]
        cross = np.exp(-0.5 * (v / s) ** 2) / (math.sqrt(2.0 * math.pi) * s)
        along = 0.5 * (erf(u / (math.sqrt(2.0) * s)) - erf((u - length) / (math.sqrt(2.0) * s))) / length
        d_along = (np.exp(-0.5 * (u / s) ** 2) - np.exp(-0.5 * ((u - length) / s) ** 2)) / (
            math.sqrt(2.0 * math.pi) * s * length)
        g = along * cross
        du = d_along * cross  # dT/du; dT/dv = -v / s^2 T; the centre moves the pixel by -1: dT/dc = -grad T
        dv = -v / s**2 * g
        total += g
        gx -= du * e[0] - dv * e[1]
        gy -= du * e[1] + dv * e[0]
    return total / k, gx / k, gy / k


def fit_trail(values: np.ndarray, x: np.ndarray, y: np.ndarray, start, knots: np.ndarray, sigma: float,
              noise: float, iterations: int = 10, outlier_sigma: float = 5.0, min_snr: float = 0.0):
    """Least-squares fit of :func:`trail_model` plus a constant background to pixel ``values`` (DN) at (x, y) (n,).

    Returns ``(centre (2,) px, flux DN, background DN, covariance (4, 4) of (c_x, c_y, F, b), converged)``; the
    covariance is ``noise**2 (J^T J)^-1`` at the solution.  Positive outliers (``outlier_sigma`` noise sigmas above
    the first fit) are dropped and the fit repeated once.  A start whose linear flux estimate is below half of
    ``min_snr`` of its own sigma is not iterated (returned not converged): faint noise candidates cost no time."""
    c = np.asarray(start, dtype=np.float64).copy()
    use = np.ones(len(values), dtype=bool)
    flux, level, cov, converged = 0.0, 0.0, None, False
    for rnd in range(2):
        d, xu, yu = values[use], x[use], y[use]
        t, tx, ty = trail_model(xu, yu, c, knots, sigma)
        a = np.stack([t, np.ones(len(t))], axis=1)
        (flux, level), *_ = np.linalg.lstsq(a, d, rcond=None)  # linear start for (F, b) at the current position
        if rnd == 0 and min_snr > 0:
            ata = a.T @ a
            if flux < 0.5 * min_snr * noise * math.sqrt(ata[1, 1] / max(np.linalg.det(ata), 1e-300)):
                return c, float(flux), float(level), None, False
        converged = False
        r = d - level - flux * t
        for _ in range(iterations):
            j = np.stack([flux * tx, flux * ty, t, np.ones(len(t))], axis=1)
            try:
                delta = np.linalg.solve(j.T @ j, j.T @ r)
            except np.linalg.LinAlgError:
                return c, 0.0, float(level), None, False
            for _ in range(8):  # halve a step that raises the sum of squares (Gauss-Newton overshoots far out)
                t_new, tx_new, ty_new = trail_model(xu, yu, c + delta[:2], knots, sigma)
                r_new = d - (level + delta[3]) - (flux + delta[2]) * t_new
                if r_new @ r_new <= r @ r:
                    break
                delta = 0.5 * delta
            c += delta[:2]
            flux += delta[2]
            level += delta[3]
            t, tx, ty, r = t_new, tx_new, ty_new, r_new
            if np.all(np.abs(delta[:2]) < MAX_STEP_PX):
                converged = True
                break
        j = np.stack([flux * tx, flux * ty, t, np.ones(len(t))], axis=1)
        cov = noise**2 * np.linalg.pinv(j.T @ j)
        if rnd == 1:
            break
        resid = values - level - flux * trail_model(x, y, c, knots, sigma)[0]
        outliers = use & (resid > outlier_sigma * noise)
        if not outliers.any():
            break
        use &= ~outliers
    return c, float(flux), float(level), cov, converged


def near_path(x: np.ndarray, y: np.ndarray, path: np.ndarray, reach: float) -> np.ndarray:
    """Whether each pixel (x, y) (n,) lies within ``reach`` px of the polyline ``path`` (K + 1, 2) px."""
    best = np.full(len(x), np.inf)
    for a, b in zip(path[:-1], path[1:], strict=True):
        d = b - a
        ll = float(d @ d)
        h = np.zeros(len(x)) if ll == 0 else np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / ll, 0.0, 1.0)
        best = np.minimum(best, np.hypot(x - a[0] - h * d[0], y - a[1] - h * d[1]))
    return best <= reach


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
        centres, strength = streak_candidates(data, level, noise, streak, self.threshold_sigma, self.min_area_px,
                                              at="peak")
        self.last_info = {"candidates": int(len(centres)), "kept": 0, "position_sigma_px": None}
        out = data.copy()
        if len(centres) == 0:
            return out
        full_scale = float(data.max()) if _is_full_scale(data) else math.inf
        t0, t1 = window(step)
        paths = star_paths(cam, step.gyro, t0, t1, centres)
        mid = paths.shape[1] // 2
        work = data.copy()  # the frame less the trails kept so far
        reach = PSF_REACH_SIGMA * sigma + SHIFT_PX
        sigmas = []
        height, width = data.shape
        for i in np.argsort(-strength):
            knots = chords(paths[i] - paths[i, mid])
            lo = np.floor(centres[i] + knots.min(axis=0) - reach).astype(np.int64)
            hi = np.ceil(centres[i] + knots.max(axis=0) + reach).astype(np.int64)
            if np.any(hi - lo + 1 > self.max_box_px):
                continue
            lo = np.maximum(lo, 0)
            hi = np.minimum(hi, [width - 1, height - 1])
            yy, xx = np.mgrid[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
            keep = near_path(xx.ravel().astype(np.float64), yy.ravel().astype(np.float64), centres[i] + knots, reach)
            keep &= data[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1].ravel() < full_scale
            rows, cols = yy.ravel()[keep], xx.ravel()[keep]
            if len(rows) < 8:
                continue
            x, y = cols.astype(np.float64), rows.astype(np.float64)
            c, flux, _, cov, ok = fit_trail(work[rows, cols], x, y, centres[i], knots, sigma, noise,
                                            outlier_sigma=self.outlier_sigma, min_snr=self.min_snr)
            if not ok or cov is None or flux <= 0.0 or flux < self.min_snr * math.sqrt(max(cov[2, 2], 0.0)):
                continue
            if np.hypot(*(c - centres[i])) > SHIFT_PX or not (0 <= c[0] <= width - 1 and 0 <= c[1] <= height - 1):
                continue
            trail = trail_model(x, y, c, knots, sigma)[0]
            still = trail_model(x, y, c, np.zeros((2, 2)), sigma)[0]
            work[rows, cols] -= flux * trail
            out[rows, cols] += flux * (still - trail)
            sigmas.append(math.sqrt(max(0.5 * (cov[0, 0] + cov[1, 1]), 0.0)))
        self.last_info.update(kept=len(sigmas), position_sigma_px=float(np.median(sigmas)) if sigmas else None)
        return out


def _is_full_scale(data: np.ndarray) -> bool:
    """Whether the frame's maximum is an ADC's full-scale code ``2^n - 1`` (n = 8..16): saturated pixels."""
    top = float(data.max())
    return any(top == 2**n - 1 for n in range(8, 17))
