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
within ``SHIFT_PX`` of its start across the trail and ``SHIFT_PX`` plus ``ALONG_FRACTION`` of the trail's length
along it (the matched filter places a faint trail's centre to a fraction of its length along it; the fit's pixels
reach that far beyond the trail's ends), its flux is positive with ``F / sigma_F >= min_snr`` and its mid-exposure
position lies on the frame; the other candidates are left as observed.  The candidates are fitted side by side
(one batch of Gauss-Newton steps for all); of two fits that land on one star (a trail found as two candidates) the
brighter is kept.

Output.  The observed frame with each kept trail replaced by its still star: ``g - F T(c) + F S(c)``, ``S`` the
still spot (the same model with no motion), so the residual noise stays as observed and a detector tuned to the
sensor finds a point star at ``c``.  Candidates: the matched-filter streak finder of
:func:`starenv.agents.restore.algorithms.streak_candidates`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erf

from starenv import checks
from starenv.agents.base import StepInput
from starenv.agents.restore.kernels import (
    exposure_path,
    frame_streaks,
    spot_sigma,
    star_paths,
    window,
)

PSF_REACH_SIGMA = 4.0  # the fit covers pixels within this many spot sigmas (+ SHIFT_PX) of the trail
SHIFT_PX = 2.0  # how far the fit may move a candidate from its first position before its pixels run out (px)
ALONG_FRACTION = 0.1  # along the trail it may move SHIFT_PX + this fraction of the trail's length further
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
    ``dT/dc_x``, ``dT/dc_y`` (n,).  Batched: x, y (C, n), centre (C, 2), knots (C, K + 1, 2) give (C, n) each.

    Each chord of length L is a uniform line convolved with a Gaussian: along it ``(Phi(u / s) - Phi((u - L) / s))
    / L``, across it ``phi(v / s) / s``, with ``s^2 = sigma^2 + 1/12`` (the pixel's box added to the spot: the
    renderer integrates the spot over each pixel; this is its second-moment match, within 1 % of the peak); a chord
    of length 0 is a round Gaussian."""
    single = np.ndim(x) == 1
    x, y = np.atleast_2d(x), np.atleast_2d(y)
    centre = np.asarray(centre, dtype=np.float64).reshape(-1, 2)
    knots = np.asarray(knots, dtype=np.float64).reshape(len(centre), -1, 2)
    s = math.sqrt(sigma**2 + 1.0 / 12.0)
    norm = math.sqrt(2.0 * math.pi) * s
    n_chords = knots.shape[1] - 1
    total, gx, gy = np.zeros(x.shape), np.zeros(x.shape), np.zeros(x.shape)
    for k in range(n_chords):
        d = knots[:, k + 1] - knots[:, k]
        length = np.hypot(d[:, 0], d[:, 1])
        still = length < 1e-6
        safe = np.where(still, 1.0, length)
        e = np.where(still[:, None], [1.0, 0.0], d / safe[:, None])
        dx = x - (centre[:, 0] + knots[:, k, 0])[:, None]
        dy = y - (centre[:, 1] + knots[:, k, 1])[:, None]
        ex, ey = e[:, 0, None], e[:, 1, None]
        u = dx * ex + dy * ey
        v = -dx * ey + dy * ex
        cross = np.exp(-0.5 * (v / s) ** 2) / norm
        head = np.exp(-0.5 * (u / s) ** 2)
        if still.all():
            along, d_along = head / norm, -u / s**2 * head / norm
        else:
            ln = length[:, None]
            tail = np.exp(-0.5 * ((u - ln) / s) ** 2)
            along = 0.5 * (erf(u / (math.sqrt(2.0) * s)) - erf((u - ln) / (math.sqrt(2.0) * s))) / safe[:, None]
            d_along = (head - tail) / (norm * safe[:, None])
            if still.any():
                along = np.where(still[:, None], head / norm, along)
                d_along = np.where(still[:, None], -u / s**2 * head / norm, d_along)
        g = along * cross
        du = d_along * cross  # dT/du; dT/dv = -v / s^2 T; the centre moves the pixel by -1: dT/dc = -grad T
        dv = -v / s**2 * g
        total += g
        gx -= du * ex - dv * ey
        gy -= du * ey + dv * ex
    out = total / n_chords, gx / n_chords, gy / n_chords
    return tuple(a[0] for a in out) if single else out


def _normal(t, tx, ty, flux, w):
    """Gauss-Newton's Jacobian (C, n, 4) of the model ``b + F T`` in (c_x, c_y, F, b), zero off the pixels ``w``."""
    return np.stack([flux[:, None] * tx, flux[:, None] * ty, t, np.ones(t.shape)], axis=-1) * w[..., None]


def fit_trails(values: np.ndarray, x: np.ndarray, y: np.ndarray, valid: np.ndarray, starts: np.ndarray,
               knots: np.ndarray, sigma: float, noise: float, iterations: int = 10, outlier_sigma: float = 5.0,
               min_snr: float = 0.0, max_shift_px=SHIFT_PX):
    """Least-squares fits of :func:`trail_model` plus a constant background, one per candidate, side by side: pixel
    ``values`` (C, n) DN at (x, y) (C, n) px, of which the ``valid`` ones (C, n) count, starting from ``starts``
    (C, 2) px, each along its ``knots`` (C, K + 1, 2).

    Returns ``centre (C, 2) px, flux (C,) DN, background (C,) DN, covariance (C, 4, 4) of (c_x, c_y, F, b),
    converged (C,)``; the covariance is ``noise**2 (J^T J)^-1`` at the solution.  Positive outliers (``outlier_sigma``
    noise sigmas above the first fit) are dropped and those fits repeated once.  A start whose linear flux estimate
    is below half of ``min_snr`` of its own sigma is not iterated, and a fit stops (not converged) once its flux falls
    under that floor or it moves ``SHIFT_PX`` beyond ``max_shift_px`` (scalar or (C,) px) from its start: noise
    candidates cost little time."""
    starts = np.array(starts, dtype=np.float64).reshape(-1, 2)
    c = starts.copy()
    n = len(c)
    max_shift = np.broadcast_to(np.asarray(max_shift_px, dtype=np.float64), (n,))
    use = np.asarray(valid, dtype=bool).copy()
    flux, level = np.zeros(n), np.zeros(n)
    cov = np.full((n, 4, 4), np.nan)
    converged = np.zeros(n, dtype=bool)
    live = use.sum(axis=1) >= 8
    todo = live.copy()
    t, tx, ty = trail_model(x, y, c, knots, sigma)  # the model at c, kept current through both rounds
    for rnd in range(2):
        w = use.astype(np.float64)
        # linear start for (F, b) at the current position: 2 x 2 normal equations per candidate
        s1, st, stt = w.sum(1), (w * t).sum(1), (w * t * t).sum(1)
        sd, std = (w * values).sum(1), (w * t * values).sum(1)
        det = np.where(todo, stt * s1 - st**2, 1.0)
        det = np.where(det > 0, det, 1.0)
        flux = np.where(todo, (s1 * std - st * sd) / det, flux)
        level = np.where(todo, (stt * sd - st * std) / det, level)
        if rnd == 0:
            floor = 0.5 * min_snr * noise * np.sqrt(s1 / det)  # DN: half of min_snr of the linear flux sigma
            if min_snr > 0:
                todo &= flux >= floor
                live &= todo
        r = (values - level[:, None] - flux[:, None] * t) * w
        done = ~todo
        for _ in range(iterations):
            step = ~done
            if not step.any():
                break
            j = _normal(t, tx, ty, flux, w)
            jt = j.swapaxes(1, 2)
            jtj = jt @ j
            jtj[~step] = np.eye(4)
            delta = np.linalg.solve(jtj + 1e-12 * np.eye(4), jt @ r[..., None])[..., 0]
            delta[~step] = 0.0
            rows = np.flatnonzero(step)  # the model is evaluated on the fits still moving only
            xs, ys, ws, vs, ks = x[rows], y[rows], w[rows], values[rows], knots[rows]
            d = delta[rows]
            t_new, tx_new, ty_new = trail_model(xs, ys, c[rows] + d[:, :2], ks, sigma)
            r_new = (vs - (level[rows] + d[:, 3])[:, None] - (flux[rows] + d[:, 2])[:, None] * t_new) * ws
            for halving in range(9):  # halve steps that raise a fit's sum of squares (Gauss-Newton overshoots)
                worse = np.flatnonzero((r_new**2).sum(1) > (r[rows] ** 2).sum(1))
                if len(worse) == 0:
                    break
                if halving == 8:  # no descent along the step: the fit is stuck, it stops (not converged)
                    done[rows[worse]] = True
                    d[worse] = 0.0
                    t_new[worse], tx_new[worse], ty_new[worse] = t[rows[worse]], tx[rows[worse]], ty[rows[worse]]
                    r_new[worse] = r[rows[worse]]
                    break
                d[worse] *= 0.5
                tw, txw, tyw = trail_model(xs[worse], ys[worse], c[rows[worse]] + d[worse, :2], ks[worse], sigma)
                t_new[worse], tx_new[worse], ty_new[worse] = tw, txw, tyw
                r_new[worse] = (vs[worse] - (level[rows[worse]] + d[worse, 3])[:, None]
                                - (flux[rows[worse]] + d[worse, 2])[:, None] * tw) * ws[worse]
            delta[rows] = d
            c += delta[:, :2]
            flux += delta[:, 2]
            level += delta[:, 3]
            t[rows], tx[rows], ty[rows], r[rows] = t_new, tx_new, ty_new, r_new
            settled = step & ~done & np.all(np.abs(delta[:, :2]) < MAX_STEP_PX, axis=1)
            converged |= settled
            done |= settled
            # A fit that has left its pixels or whose flux fell under the floor is not a star to keep: it stops,
            # not converged.
            done |= step & ~settled & ((np.hypot(*(c - starts).T) > max_shift + SHIFT_PX) | (flux <= floor))
        j = _normal(t, tx, ty, flux, w)
        cov = np.where(todo[:, None, None], noise**2 * np.linalg.pinv(j.swapaxes(1, 2) @ j), cov)
        if rnd == 1:
            break
        resid = values - level[:, None] - flux[:, None] * t
        outliers = use & (resid > outlier_sigma * noise) & live[:, None]
        todo = outliers.any(axis=1)
        if not todo.any():
            break
        use &= ~outliers
        converged &= ~todo
    return c, flux, level, cov, converged & live


def fit_trail(values: np.ndarray, x: np.ndarray, y: np.ndarray, start, knots: np.ndarray, sigma: float,
              noise: float, iterations: int = 10, outlier_sigma: float = 5.0, min_snr: float = 0.0):
    """:func:`fit_trails` for one candidate on all its pixels (n,): ``(centre (2,), flux, background, covariance
    (4, 4), converged)``."""
    c, flux, level, cov, ok = fit_trails(values[None], x[None], y[None], np.ones((1, len(values)), dtype=bool),
                                         np.reshape(start, (1, 2)), knots[None], sigma, noise, iterations,
                                         outlier_sigma, min_snr)
    return c[0], float(flux[0]), float(level[0]), cov[0], bool(ok[0])


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
    are left as observed), ``min_trail_px`` (candidates whose trail is shorter are left as observed: a trail of a
    few pixels is a slightly elongated spot, which the detector's own centroid already handles, and the model's
    approximate pixel integration would only add its 1 % shape error).  ``last_info``: candidates, fits kept,
    median fitted position sigma (px).
    """

    iterations = 0

    def __init__(self, psf_sigma_px: float | None = None, threshold_sigma: float = 5.0, min_area_px: int = 4,
                 min_snr: float = 5.0, outlier_sigma: float = 5.0, max_box_px: int = 1024, min_trail_px: float = 4.0):
        self.psf_sigma_px = spot_sigma(psf_sigma_px)
        self.threshold_sigma = checks.in_range("threshold_sigma", threshold_sigma, 0.0, 100.0, low_open=True)
        self.min_area_px = checks.integer("min_area_px", min_area_px, 1, 10**6)
        self.min_snr = checks.in_range("min_snr", min_snr, 0.0, 1e6)
        self.outlier_sigma = checks.in_range("outlier_sigma", outlier_sigma, 1.0, 1e6, low_open=True)
        self.max_box_px = checks.integer("max_box_px", max_box_px, 8, 1 << 16)
        self.min_trail_px = checks.in_range("min_trail_px", min_trail_px, 0.0, 1e4, unit="px")
        self.last_info: dict = {}

    def deblur(self, image: np.ndarray, head: int, step: StepInput) -> np.ndarray:
        cam = step.cameras[head]
        found = frame_streaks(image, head, step, self.psf_sigma_px, self.threshold_sigma, self.min_area_px)
        data, sigma, noise, centres, peaks = found.data, found.sigma, found.noise, found.centroids, found.peaks
        self.last_info = {"candidates": int(len(centres)), "kept": 0, "position_sigma_px": None}
        out = data.copy()
        if len(centres) == 0:
            return out
        full_scale = float(data.max()) if _is_full_scale(data) else math.inf
        t0, t1 = window(step)
        paths = star_paths(cam, step.gyro, t0, t1, centres)
        mid = paths.shape[1] // 2
        # Start at the filter's peak where the candidate's trail is about as long as the filter's (the frame
        # centre's) streak, at the component's centroid where it is longer (about the boresight the centre's streak
        # is a point and the response of an arc has a plateau).
        length = np.linalg.norm(np.diff(paths, axis=1), axis=2).sum(axis=1)
        centre_length = float(np.linalg.norm(np.diff(exposure_path(step, head), axis=0), axis=1).sum())
        centres = np.where((length <= 1.25 * centre_length + 2.0)[:, None], peaks, centres)
        reach = PSF_REACH_SIGMA * sigma + SHIFT_PX
        height, width = data.shape
        cands = []  # (index, knots, rows, cols, along (2,) unit vector, along slack px) of each with enough pixels
        for i in np.flatnonzero(length >= self.min_trail_px):
            knots = chords(paths[i] - paths[i, mid])
            # The filter locates a trail's centre well across it, to a fraction of its length along it: the pixels
            # reach ALONG_FRACTION of the length beyond each end, so a fit started off-centre along the trail finds
            # its ends.
            chord = knots[-1] - knots[0]
            along = chord / max(float(np.hypot(*chord)), 1e-9)
            slack = ALONG_FRACTION * float(length[i])
            ends = np.vstack([knots[0] - slack * along, knots, knots[-1] + slack * along])
            lo = np.floor(centres[i] + ends.min(axis=0) - reach).astype(np.int64)
            hi = np.ceil(centres[i] + ends.max(axis=0) + reach).astype(np.int64)
            if np.any(hi - lo + 1 > self.max_box_px):
                continue
            lo = np.maximum(lo, 0)
            hi = np.minimum(hi, [width - 1, height - 1])
            yy, xx = np.mgrid[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
            keep = near_path(xx.ravel().astype(np.float64), yy.ravel().astype(np.float64), centres[i] + ends, reach)
            keep &= data[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1].ravel() < full_scale
            if keep.sum() >= 8:
                cands.append((i, knots, yy.ravel()[keep], xx.ravel()[keep], along, slack))
        fits = []  # (flux, index, centre, knots, rows, cols, position sigma) of the fits kept
        for n_knots in sorted({len(cd[1]) for cd in cands}):  # one batch per chord count
            group = [cd for cd in cands if len(cd[1]) == n_knots]
            size = max(len(cd[2]) for cd in group)
            rows = np.zeros((len(group), size), dtype=np.int64)
            cols = np.zeros((len(group), size), dtype=np.int64)
            valid = np.zeros((len(group), size), dtype=bool)
            for g, (_, _, r, cl, _, _) in enumerate(group):
                rows[g, : len(r)], cols[g, : len(r)], valid[g, : len(r)] = r, cl, True
            idx = np.array([cd[0] for cd in group])
            knots = np.stack([cd[1] for cd in group])
            along = np.stack([cd[4] for cd in group])
            slack = np.array([cd[5] for cd in group])
            c, flux, _, cov, ok = fit_trails(data[rows, cols], cols.astype(np.float64), rows.astype(np.float64),
                                             valid, centres[idx], knots, sigma, noise,
                                             outlier_sigma=self.outlier_sigma, min_snr=self.min_snr,
                                             max_shift_px=SHIFT_PX + slack)
            sigma_f = np.sqrt(np.maximum(cov[:, 2, 2], 0.0))
            good = ok & (flux > 0) & (flux >= self.min_snr * sigma_f)
            shift = c - centres[idx]
            shift_along = np.einsum("ij,ij->i", shift, along)
            shift_across = np.abs(shift[:, 1] * along[:, 0] - shift[:, 0] * along[:, 1])
            good &= (shift_across <= SHIFT_PX) & (np.abs(shift_along) <= SHIFT_PX + slack)
            good &= (c[:, 0] >= 0) & (c[:, 0] <= width - 1) & (c[:, 1] >= 0) & (c[:, 1] <= height - 1)
            for g in np.flatnonzero(good):
                fits.append((flux[g], idx[g], c[g], knots[g], group[g][2], group[g][3],
                             math.sqrt(max(0.5 * (cov[g, 0, 0] + cov[g, 1, 1]), 0.0))))
        kept = []  # brightest first; a fit that lands on a brighter one's star (a trail found twice) is dropped
        for fit in sorted(fits, key=lambda f: -f[0]):
            if all(np.hypot(*(fit[2] - k[2])) > SHIFT_PX for k in kept):
                kept.append(fit)
        for flux, _, c, knots, rows, cols, _ in kept:
            x, y = cols.astype(np.float64), rows.astype(np.float64)
            trail = trail_model(x, y, c, knots, sigma)[0]
            still = trail_model(x, y, c, np.zeros((2, 2)), sigma)[0]
            out[rows, cols] += flux * (still - trail)
        sigmas = [k[6] for k in kept]
        self.last_info.update(kept=len(sigmas), position_sigma_px=float(np.median(sigmas)) if sigmas else None)
        return out


def _is_full_scale(data: np.ndarray) -> bool:
    """Whether the frame's maximum is an ADC's full-scale code ``2^n - 1`` (n = 8..16): saturated pixels."""
    top = float(data.max())
    return any(top == 2**n - 1 for n in range(8, 17))
