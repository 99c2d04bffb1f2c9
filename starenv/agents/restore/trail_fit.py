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
brighter is kept.  Each kept fit's residual is then searched for a second, parallel trail (a pair the candidate
finder took for one trail), which is fitted and kept like a first fit (:meth:`TrailFitDeblurrer._second_stars`):
left as observed, it would sit beside the restored star for the detector to merge with it, pulling the merged
centroid off the star by a part of their separation.
The first star of such a pair is then fitted again with the second's light taken off, and the second again without
the first's (one step of fitting the two together).

Chains.  The finder gives one candidate per connected component of the filter's response, so of several trails on
one line that overlap end to end (paper_000 at 75 deg/s about X: HIP 26241, the four Trapezium stars and HIP 26237
in one 100 px chain) only one is fitted.  Each fit's residual is also matched against its own trail moved a
quarter, a half and three quarters of its length along it; where that finds a trail of ``SECOND_SIGMA``, the frame
less every kept trail is searched again around the fit, and the new candidates fitted the same way, up to
``MAX_ROUNDS`` rounds (the brightest of a chain first, then the next).  Left as observed, a piece of such a chain's
trail is a detection no star explains, which the identifier may take for a catalogue star near it.

Output.  The observed frame with each kept trail replaced by its still star: ``g - F T(c) + F S(c)``, ``S`` the
still spot (the same model with no motion), so the residual noise stays as observed and a detector tuned to the
sensor finds a point star at ``c``.  Candidates: the matched-filter streak finder of
:func:`starenv.agents.blocks.streak_candidates`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import erf

from starenv import checks
from starenv.agents.base import StepInput
from starenv.agents.restore.kernels import (
    ExposureMotion,
    frame_streaks,
    spot_sigma,
    window,
)

PSF_REACH_SIGMA = 4.0  # the fit covers pixels within this many spot sigmas (+ SHIFT_PX) of the trail
SHIFT_PX = 2.0  # how far the fit may move a candidate from its first position before its pixels run out (px)
ALONG_FRACTION = 0.1  # along the trail it may move SHIFT_PX + this fraction of the trail's length further
MAX_STEP_PX = 0.01  # Gauss-Newton stops when the position moves less than this (px)
# A trail is drawn as chords no farther than this from its gyro path (px): a fraction of the fitted centres' sigma,
# so the chords' departure from the path stays under the fit's noise while a long trail needs few chords.
CHORD_TOLERANCE_PX = 0.1
MAX_CHORDS = 32
MODEL_CHUNK_PX = 1 << 14  # trail_model evaluates this many pixels at a time (float32: in cache)
NEAR_CHUNK_PX = 1 << 16  # near_paths screens this many pixels at once (float32: in cache)
ERF_SATURATION = 6.0  # |a| beyond which erf(a) rounds to +-1 (from 5.93 in float64, sooner in float32)
# exp() arguments are held above this: its underflow (and products of two underflows) take numpy's slow path, many
# times slower; exp(-30) = 1e-13 of the peak, below float32's resolution of any sum
GAUSS_FLOOR = -30.0
SECOND_SIGMA = 5.0  # a parallel trail in a fit's residual this significant (noise sigmas) is a second star
SECOND_SCREEN = 1.0  # residuals whose excess sum of squares is below this many of its sigmas are not searched
MAX_ROUNDS = 4  # fits on the frame, then on it less the kept trails (a chain of overlapping trails, brightest first)
ALONG_OFFSETS = (-0.75, -0.5, -0.25, 0.25, 0.5, 0.75)  # a fit's residual is searched this far along (trail lengths)
SCAN_BOW_PX = 0.25  # the residual scan takes a trail as straight when it bows this little
NEW_START_PX = 0.5  # a later round's candidate starting this near an earlier one's start is not fitted again


def _gauss(z: np.ndarray) -> np.ndarray:
    """``exp(-z^2 / 2)``, its argument held above ``GAUSS_FLOOR``."""
    return np.exp(np.maximum(-0.5 * z**2, GAUSS_FLOOR))


def _erf(a: np.ndarray) -> np.ndarray:
    """``scipy.special.erf(a)``, bit for bit, evaluated only where it is not +-1 (most of a trail's pixels lie far
    from its chords' ends, where it is, and skip the erf call there)."""
    out = np.sign(a)
    near = np.flatnonzero(np.abs(a) < ERF_SATURATION)
    out.ravel()[near] = erf(a.ravel()[near])
    return out


def chords(offsets: np.ndarray) -> np.ndarray | list[np.ndarray]:
    """The trail's knots (K + 1, 2) px relative to mid-exposure: its positions at the exposure's start, at K - 1
    equally spaced instants and at its end, so that constant-speed chords between them stay within
    ``CHORD_TOLERANCE_PX`` of the path.  ``offsets`` (m, 2): the path at the m midpoint instants ``(j + 1/2) / m``
    of the exposure (:func:`starenv.agents.restore.kernels.star_paths`); the ends are extrapolated half a sample.
    ``offsets`` (C, m, 2): C trails at once, a list of their knots."""
    o = np.asarray(offsets, dtype=np.float64)
    batch = o.ndim == 3
    o = o.reshape(-1, o.shape[-2], 2) if batch else o.reshape(1, -1, 2)
    m = o.shape[1]
    if m == 1:
        knots = np.repeat(o, 2, axis=1)
        return list(knots) if batch else knots[0]
    t = np.concatenate([[0.0], (np.arange(m) + 0.5) / m, [1.0]])
    ext = np.concatenate([o[:, :1] - 0.5 * (o[:, 1:2] - o[:, :1]), o, o[:, -1:] + 0.5 * (o[:, -1:] - o[:, -2:-1])],
                         axis=1)
    out: list[np.ndarray] = [np.zeros((0, 2))] * len(o)
    todo = np.arange(len(o))
    k = 1
    while len(todo):
        knots_t = np.linspace(0.0, 1.0, k + 1)
        knots = _interp(knots_t, t, ext[todo])
        ok = np.abs(_interp(t, knots_t, knots) - ext[todo]).max(axis=(1, 2)) <= CHORD_TOLERANCE_PX
        ok |= k >= MAX_CHORDS
        for j, kn in zip(todo[ok], knots[ok], strict=True):
            out[j] = kn
        todo = todo[~ok]
        k *= 2
    return out if batch else out[0]


def _interp(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``np.interp(x, xp, .)`` of each of the curves ``fp`` (C, len(xp), 2) at once: (C, len(x), 2)."""
    j = np.clip(np.searchsorted(xp, x, side="right") - 1, 0, len(xp) - 2)
    w = ((x - xp[j]) / (xp[j + 1] - xp[j]))[None, :, None]
    return fp[:, j] + w * (fp[:, j + 1] - fp[:, j])


def trail_model(x: np.ndarray, y: np.ndarray, centre, knots: np.ndarray, sigma: float,
                dtype=np.float32, derivatives: bool = True):
    """Unit-flux trail at the pixels (x, y) (n,) px of a star at mid-exposure ``centre`` (x, y) px moving at constant
    speed along each chord of ``centre + knots`` (:func:`chords`), equal time on each, and its derivatives
    ``dT/dc_x``, ``dT/dc_y`` (n,).  Batched: x, y (C, n), centre (C, 2), knots (C, K + 1, 2) give (C, n) each.

    Each chord of length L is a uniform line convolved with a Gaussian: along it ``(Phi(u / s) - Phi((u - L) / s))
    / L``, across it ``phi(v / s) / s``, with ``s^2 = sigma^2 + 1/12`` (the pixel's box added to the spot: the
    renderer integrates the spot over each pixel; this is its second-moment match, within 1 % of the peak); a chord
    of length 0 is a round Gaussian.  Positions relative to the chords are taken in float64, the profiles in
    ``dtype`` (float32: 1e-6 of the peak, far below the model's own 1 %, and cheaper than float64), which the three
    arrays returned have; ``derivatives=False``: the trail alone, the derivatives None."""
    single = np.ndim(x) == 1
    x, y = np.atleast_2d(x), np.atleast_2d(y)
    centre = np.asarray(centre, dtype=np.float64).reshape(-1, 2)
    knots = np.asarray(knots, dtype=np.float64).reshape(len(centre), -1, 2)
    if x.size > MODEL_CHUNK_PX and len(x) > 1:  # a few trails at a time: the temporaries stay in cache
        rows = max(1, MODEL_CHUNK_PX // x.shape[1])
        parts = [trail_model(x[a : a + rows], y[a : a + rows], centre[a : a + rows], knots[a : a + rows], sigma, dtype,
                             derivatives) for a in range(0, len(x), rows)]
        return tuple(None if p[0] is None else np.concatenate(p) for p in zip(*parts, strict=True))
    s = math.sqrt(sigma**2 + 1.0 / 12.0)
    norm = math.sqrt(2.0 * math.pi) * s
    n_chords = knots.shape[1] - 1
    ftype = np.dtype(dtype).type  # the profiles' precision
    xr = (x - centre[:, 0, None]).astype(ftype)  # pixels relative to the centre: within the trail's reach
    yr = (y - centre[:, 1, None]).astype(ftype)
    total, gx, gy = (np.zeros(x.shape, dtype=ftype) for _ in range(3))
    for k in range(n_chords):
        u, v, e, length, still, safe = _chord_coordinates(xr, yr, knots[:, k], knots[:, k + 1], s)
        ex, ey = e[:, 0, None].astype(ftype), e[:, 1, None].astype(ftype)
        cross = _gauss(v)
        head = _gauss(u) if derivatives or still.any() else None
        if still.all():
            along, d_along = head, -u * head
        else:
            ln = (length / s).astype(ftype)[:, None]
            along = _along_profile(u, ln) * (0.5 * norm / safe).astype(ftype)[:, None]
            d_along = (head - _gauss(u - ln)) * (s / safe).astype(ftype)[:, None] if derivatives else None
            if still.any():
                along = np.where(still[:, None], head, along)
                d_along = np.where(still[:, None], -u * head, d_along) if derivatives else None
        # In units of s, T = along cross / norm^2, dT/du = d_along cross / (s norm^2) and dT/dv = -v T / s; the
        # centre moves the pixel by -1: dT/dc = -grad T.
        g = along * cross
        total += g
        if derivatives:
            du = d_along * cross
            dv = v * g
            gx -= du * ex + dv * ey
            gy += dv * ex - du * ey
    scale = 1.0 / (n_chords * norm**2)
    out = total * ftype(scale), gx * ftype(scale / s), gy * ftype(scale / s)
    if not derivatives:
        out = out[0], None, None
    return tuple(None if a is None else a[0] for a in out) if single else out


def _chord_coordinates(xr: np.ndarray, yr: np.ndarray, start: np.ndarray, end: np.ndarray, s: float):
    """Pixels at (xr, yr) (C, n) px from each trail's centre, in units of ``s`` px along (u) and across (v) its chord
    from ``start`` to ``end`` (C, 2) px (relative to the centre), u from the chord's start, in the pixels' dtype;
    with the chord's unit vector e (C, 2), length (C,) px, whether it is a point (C,) and its length or 1 there."""
    ftype = xr.dtype.type
    d = end - start
    length = np.hypot(d[:, 0], d[:, 1])
    still = length < 1e-6
    safe = np.where(still, 1.0, length)
    e = np.where(still[:, None], [1.0, 0.0], d / safe[:, None])
    es = (e / s).astype(ftype)
    u0 = ((start[:, 0] * e[:, 0] + start[:, 1] * e[:, 1]) / s).astype(ftype)[:, None]
    v0 = ((start[:, 1] * e[:, 0] - start[:, 0] * e[:, 1]) / s).astype(ftype)[:, None]
    u = xr * es[:, 0, None] + yr * es[:, 1, None] - u0
    v = yr * es[:, 0, None] - xr * es[:, 1, None] - v0
    return u, v, e, length, still, safe


def _along_profile(u: np.ndarray, ln: np.ndarray) -> np.ndarray:
    """``erf(u / sqrt 2) - erf((u - ln) / sqrt 2)``: a uniform line of length ``ln`` blurred by a unit Gaussian,
    at ``u`` from its start (all in units of the blur), up to its normalisation."""
    half = u.dtype.type(math.sqrt(0.5))
    return _erf(u * half) - _erf((u - ln) * half)


def matched_shifts(x: np.ndarray, y: np.ndarray, centre: np.ndarray, knots: np.ndarray, sigma: float,
                   residual: np.ndarray, weight: np.ndarray, noise: float, across_px,
                   along_lengths) -> tuple[np.ndarray, np.ndarray]:
    """Significance (noise sigmas) of another trail like each fit's own in its ``residual`` (C, n) DN at its pixels
    (x, y) (C, n), which count with ``weight`` (C, n) 0 or 1, moved by each of ``across_px`` px across the trail,
    and by each of ``along_lengths`` trail lengths along it: arrays (len(across_px), C) and (len(along_lengths), C)
    of ``sum(r T') / (noise |T'|)``, ``T'`` the moved :func:`trail_model` times the weights.  A trail of one chord
    is the product of its profiles along and across it, so moved across only the cross profile is evaluated again,
    and moved along only the along one.  A trail of several chords is taken as its end-to-end chord where no knot is
    more than ``SCAN_BOW_PX`` from it (the statistic changes by a fraction of a percent), else evaluated whole at
    each shift."""
    centre = np.asarray(centre, dtype=np.float64)
    chord = knots[:, -1] - knots[:, 0]
    length = np.hypot(chord[:, 0], chord[:, 1])
    e = chord / np.maximum(length, 1e-9)[:, None]
    across = np.stack([-e[:, 1], e[:, 0]], axis=1)

    def significance(t):
        t = t * weight
        return (residual * t).sum(1) / (noise * np.sqrt(np.maximum((t * t).sum(1), 1e-30)))

    knot_off = knots - knots[:, :1]
    bow = np.abs(knot_off[..., 1] * e[:, None, 0] - knot_off[..., 0] * e[:, None, 1]).max(axis=1)
    if np.any(bow > SCAN_BOW_PX):
        def moved(shift):
            return significance(trail_model(x, y, centre + shift, knots, sigma, derivatives=False)[0])
        return (np.array([moved(v * across) for v in across_px]).reshape(-1, len(centre)),
                np.array([moved(f * length[:, None] * e) for f in along_lengths]).reshape(-1, len(centre)))
    s = math.sqrt(sigma**2 + 1.0 / 12.0)
    xr = (x - centre[:, 0, None]).astype(np.float32)
    yr = (y - centre[:, 1, None]).astype(np.float32)
    u, v, _, chord_length, still, _ = _chord_coordinates(xr, yr, knots[:, 0], knots[:, -1], s)
    ln = (chord_length / s).astype(np.float32)[:, None]

    def along_at(shift):  # shift (C,) px along the chord
        w = u - (shift / s).astype(np.float32)[:, None]
        return np.where(still[:, None], _gauss(w), _along_profile(w, ln))

    head, cross = along_at(np.zeros(len(centre))), _gauss(v)
    moved_across = [significance(head * _gauss(v - np.float32(a / s))) for a in across_px]
    moved_along = [significance(along_at(f * chord_length) * cross) for f in along_lengths]
    return np.array(moved_across).reshape(-1, len(centre)), np.array(moved_along).reshape(-1, len(centre))


def _normal_equations(t, tx, ty, flux, w, r=None):
    """Gauss-Newton's ``J^T J`` (C, 4, 4) and, given residuals ``r`` (C, n), ``J^T r`` (C, 4), float64, of the model
    ``b + F T`` in (c_x, c_y, F, b) on the pixels ``w`` (C, n): ``J = [F dT/dc_x, F dT/dc_y, T, 1]``, summed in the
    model's precision (:func:`trail_model`) without its factor F, which is applied to the sums."""
    k = np.empty((len(t), 4, t.shape[1]), dtype=t.dtype)
    k[:, 3] = w
    for i, a in enumerate((tx, ty, t)):
        np.multiply(a, k[:, 3], out=k[:, i])
    scale = np.stack([flux, flux, np.ones(len(flux)), np.ones(len(flux))], axis=1)
    jtj = (k @ k.swapaxes(1, 2)) * scale[:, :, None] * scale[:, None, :]
    return jtj, None if r is None else (k @ r[:, :, None].astype(t.dtype))[..., 0] * scale


def fit_trails(values: np.ndarray, x: np.ndarray, y: np.ndarray, valid: np.ndarray, starts: np.ndarray,
               knots: np.ndarray, sigma: float, noise: float, iterations: int = 20, outlier_sigma: float = 5.0,
               min_snr: float = 0.0, max_shift_px=SHIFT_PX, with_model: bool = False):
    """Least-squares fits of :func:`trail_model` plus a constant background, one per candidate, side by side: pixel
    ``values`` (C, n) DN at (x, y) (C, n) px, of which the ``valid`` ones (C, n) count, starting from ``starts``
    (C, 2) px, each along its ``knots`` (C, K + 1, 2).

    Returns ``centre (C, 2) px, flux (C,) DN, background (C,) DN, covariance (C, 4, 4) of (c_x, c_y, F, b),
    converged (C,)``; the covariance is ``noise**2 (J^T J)^-1`` at the solution.  Positive outliers (``outlier_sigma``
    noise sigmas above the first fit) are dropped and those fits repeated once.  A start whose linear flux estimate
    is below half of ``min_snr`` of its own sigma is not iterated, and a fit stops (not converged) once its flux falls
    under that floor or it moves ``SHIFT_PX`` beyond ``max_shift_px`` (scalar or (C,) px) from its start: noise
    candidates cost little time.  ``with_model``: the unit trail (C, n) float32 at each fit's last position is
    returned too, after the rest."""
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
            rows = np.flatnonzero(step)  # the fits still moving, the only ones stepped and evaluated
            xs, ys, ws, vs, ks = x[rows], y[rows], w[rows], values[rows], knots[rows]
            jtj, jtr = _normal_equations(t[rows], tx[rows], ty[rows], flux[rows], ws, r[rows])
            d = np.linalg.solve(jtj + 1e-12 * np.eye(4), jtr[..., None])[..., 0]
            delta = np.zeros((n, 4))
            t_new, tx_new, ty_new = trail_model(xs, ys, c[rows] + d[:, :2], ks, sigma)
            r_new = (vs - (level[rows] + d[:, 3])[:, None] - (flux[rows] + d[:, 2])[:, None] * t_new) * ws
            before = (r[rows] ** 2).sum(1)
            for halving in range(9):  # halve steps that raise a fit's sum of squares (Gauss-Newton overshoots);
                # a step that moves the position by less than MAX_STEP_PX is taken as it is: it has converged, and
                # the change in the sum of squares is below the float32 model's resolution
                worse = np.flatnonzero(((r_new**2).sum(1) > before) & np.any(np.abs(d[:, :2]) >= MAX_STEP_PX, axis=1))
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
        cov = np.where(todo[:, None, None], noise**2 * np.linalg.pinv(_normal_equations(t, tx, ty, flux, w)[0]), cov)
        if rnd == 1:
            break
        resid = values - level[:, None] - flux[:, None] * t
        outliers = use & (resid > outlier_sigma * noise) & live[:, None]
        todo = outliers.any(axis=1)
        if not todo.any():
            break
        use &= ~outliers
        converged &= ~todo
    out = c, flux, level, cov, converged & live
    return out + (t,) if with_model else out


def fit_trail(values: np.ndarray, x: np.ndarray, y: np.ndarray, start, knots: np.ndarray, sigma: float,
              noise: float, iterations: int = 10, outlier_sigma: float = 5.0, min_snr: float = 0.0):
    """:func:`fit_trails` for one candidate on all its pixels (n,): ``(centre (2,), flux, background, covariance
    (4, 4), converged)``."""
    c, flux, level, cov, ok = fit_trails(values[None], x[None], y[None], np.ones((1, len(values)), dtype=bool),
                                         np.reshape(start, (1, 2)), knots[None], sigma, noise, iterations,
                                         outlier_sigma, min_snr)
    return c[0], float(flux[0]), float(level[0]), cov[0], bool(ok[0])


def near_paths(lo: np.ndarray, hi: np.ndarray, paths: np.ndarray, reach: float) -> list[np.ndarray]:
    """The pixels within ``reach`` px of each polyline ``paths`` (C, P, 2) px inside its box ``lo``..``hi`` (C, 2)
    (inclusive x, y): one (n, 2) int array of (row, col) per polyline, in raster order.

    Distances are measured (float32, in box coordinates: 1e-5 px) only on the pixels of the strip about each
    polyline's chord that holds every point within ``reach`` of it (the chord's line +- ``reach`` + the polyline's
    largest distance from it); boxes of similar area are taken together, ``NEAR_CHUNK_PX`` pixels at a time."""
    local = (paths - lo[:, None, :]).astype(np.float32)  # box coordinates
    chord = local[:, -1] - local[:, 0]
    size = np.hypot(chord[:, 0], chord[:, 1])
    e = np.where(size[:, None] > 0, chord / np.where(size > 0, size, 1.0)[:, None], np.float32([1.0, 0.0]))
    normal = np.stack([-e[:, 1], e[:, 0]], axis=1)
    strip = reach + np.abs(((local - local[:, :1]) * normal[:, None]).sum(axis=2)).max(axis=1)
    start, d = local[:, :-1], np.diff(local, axis=1)  # (C, P - 1, 2) segments
    ll = (d**2).sum(axis=2)
    inv = np.where(ll > 0, 1.0 / np.where(ll > 0, ll, 1.0), 0.0).astype(np.float32)  # a point segment: its start
    area = np.prod(hi - lo + 1, axis=1)
    out: list[np.ndarray] = [np.zeros((0, 2), dtype=np.int64)] * len(lo)
    order = np.argsort(area, kind="stable")
    first = 0
    while first < len(order):
        stop = first + 1
        while stop < len(order) and (stop + 1 - first) * area[order[stop]] <= NEAR_CHUNK_PX:
            stop += 1
        part, first = order[first:stop], stop
        w, h = (hi[part] - lo[part] + 1).max(axis=0)
        x = np.arange(w, dtype=np.float32)[None, None, :]
        y = np.arange(h, dtype=np.float32)[None, :, None]
        ox, oy, nx, ny = (v[part, None, None] for v in (local[:, 0, 0], local[:, 0, 1], *normal.T))
        band = np.abs((x - ox) * nx + (y - oy) * ny) <= strip[part, None, None]
        band &= (x <= (hi - lo)[part, 0, None, None]) & (y <= (hi - lo)[part, 1, None, None])
        g, r, c = np.nonzero(band)
        px, py = c.astype(np.float32), r.astype(np.float32)
        best = np.full(len(g), np.inf, dtype=np.float32)
        who = part[g]
        for k in range(d.shape[1]):
            ax, ay, dx, dy = start[who, k, 0], start[who, k, 1], d[who, k, 0], d[who, k, 1]
            along = np.clip(((px - ax) * dx + (py - ay) * dy) * inv[who, k], 0.0, 1.0)
            np.minimum(best, np.hypot(px - ax - along * dx, py - ay - along * dy), out=best)
        near = best <= reach
        g, rows, cols = g[near], r[near] + lo[who[near], 1], c[near] + lo[who[near], 0]
        pieces = np.split(np.stack([rows, cols], axis=1), np.cumsum(np.bincount(g, minlength=len(part)))[:-1])
        for j, piece in zip(part, pieces, strict=True):
            out[j] = piece
    return out


class TrailFitDeblurrer:
    """Each candidate streak fitted with its own gyro-predicted trail (least squares on the raw pixels) and replaced
    by the still star at the fitted mid-exposure position; see the module docstring.

    Options: ``psf_sigma_px`` (None: the camera's spot sigma), ``threshold_sigma`` and ``min_area_px`` of the
    candidate finder, ``min_snr`` (least ``F / sigma_F`` of a kept fit), ``outlier_sigma`` (pixels this many noise
    sigmas above the first fit are left out), ``max_box_px`` (candidates whose trail box is larger on either side
    are left as observed), ``min_trail_px`` (candidates whose trail is shorter are left as observed: a trail of a
    few pixels is a slightly elongated spot, which the detector's own centroid already handles, and the model's
    approximate pixel integration would only add its 1 % shape error).  ``last_info``: candidates, fits kept, of
    them second stars found in the residuals, rounds of fitting, median fitted position sigma (px).
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
        found = frame_streaks(image, head, step, self.psf_sigma_px, self.threshold_sigma, self.min_area_px,
                              drop_points=True)
        data, sigma, noise = found.data, found.sigma, found.noise
        self.last_info = {"candidates": int(len(found.centroids)), "kept": 0, "second": 0, "rounds": 0,
                          "position_sigma_px": None}
        # found.data is the float64 copy of an integer frame: the output is written on it, unless it is the
        # caller's own array.
        out = data.copy() if np.may_share_memory(data, image) else data
        if len(found.centroids) == 0:
            return out
        full_scale = _full_scale(data)
        motion = ExposureMotion(cam, step.gyro, *window(step))
        centre_length = float(np.linalg.norm(np.diff(found.streak_path, axis=0), axis=1).sum())
        reach_px = PSF_REACH_SIGMA * sigma + SHIFT_PX
        kept, seconds, tried = [], 0, np.zeros((0, 2))
        lights = []  # (rows, cols, F T) of each round's kept fits on their pixels
        values, centres, peaks = data, found.centroids, found.peaks
        for round_ in range(MAX_ROUNDS):
            self.last_info["rounds"] = round_ + 1
            new, starts = self._first_fits(values, data, centres, peaks, motion, centre_length, sigma, noise,
                                           full_scale, [k.centre for k in kept], tried)
            tried = np.vstack([tried, starts])
            if not new:
                break
            second, busy = self._second_stars(new, values, sigma, noise, full_scale, [k.centre for k in kept])
            kept += new + second
            seconds += len(second)
            lights.append(_light(new + second, sigma, still=False))
            if round_ == MAX_ROUNDS - 1 or not busy:
                break
            # The next round searches the frame with the new trails taken off, around the fits whose residual
            # showed another trail along their own (a chain of overlapping trails fitted as one candidate: the
            # brightest first); a candidate found where one was tried before (a component the subtraction did not
            # touch) is not fitted again.
            values = values.copy() if values is data else values
            rows, cols, light = lights[-1]
            np.subtract.at(values, (rows, cols), light)
            reach = found.reach_px  # the response changes this far from a changed pixel
            centres, peaks = [], []
            for lo, hi in _merged_boxes([(np.array([f.cols.min(), f.rows.min()]) - reach,
                                          np.array([f.cols.max(), f.rows.max()]) + reach) for f in busy]):
                c, p, _ = found.search(values, lo, hi)
                centres.append(c)
                peaks.append(p)
            centres, peaks = np.concatenate(centres), np.concatenate(peaks)
            # what is left within a fit's reach of a kept star is its own residue (a neighbour that close is a
            # blend, searched for across the trail by the second-star search)
            near = cKDTree(np.array([k.centre for k in kept])).query(peaks, distance_upper_bound=reach_px)[0]
            centres, peaks = centres[near == np.inf], peaks[near == np.inf]
            if len(centres) == 0:
                break
        if kept:  # F (S - T) of each kept fit on its pixels, added in the fits' order, one pixel after another
            rows, cols, trail = (np.concatenate(a) for a in zip(*lights, strict=True))
            still = _light(kept, sigma, still=True)[2]
            np.add.at(out, (rows, cols), still - trail)
        sigmas = [k.position_sigma for k in kept]
        self.last_info.update(kept=len(sigmas), second=seconds,
                              position_sigma_px=float(np.median(sigmas)) if sigmas else None)
        return out

    def _first_fits(self, values: np.ndarray, data: np.ndarray, centres: np.ndarray, peaks: np.ndarray,
                    motion: ExposureMotion, centre_length: float, sigma: float, noise: float, full_scale: float,
                    taken: list[np.ndarray], tried: np.ndarray) -> tuple[list[_Fit], np.ndarray]:
        """The fits kept of candidates at ``centres`` / ``peaks`` (k, 2) px on the frame ``values`` (DN: the frame
        ``data``, or it with trails taken off), each along its own trail over the exposure's ``motion``, brightest
        first, none within ``SHIFT_PX`` of a brighter one or of a ``taken`` centre; and the starts (j, 2) px of the
        candidates fitted: those not starting within ``NEW_START_PX`` of a start ``tried`` (j, 2) before (a
        component the trails taken off did not change would be fitted the same way again)."""
        paths = motion.paths(centres)
        mid = paths.shape[1] // 2
        length = np.linalg.norm(np.diff(paths, axis=1), axis=2).sum(axis=1)
        # Start at the filter's peak where the candidate's trail is about as long as the filter's (the frame
        # centre's) streak, at the component's centroid where it is longer (about the boresight the centre's streak
        # is a point and the response of an arc has a plateau).
        centres = np.where((length <= 1.25 * centre_length + 2.0)[:, None], peaks, centres)
        if len(tried):
            fresh = cKDTree(tried).query(centres, distance_upper_bound=NEW_START_PX)[0] == np.inf
            paths, length, centres = paths[fresh], length[fresh], centres[fresh]
        reach = PSF_REACH_SIGMA * sigma + SHIFT_PX
        height, width = data.shape
        # The filter locates a trail's centre well across it, to a fraction of its length along it: the pixels
        # reach ALONG_FRACTION of the length beyond each end, so a fit started off-centre along the trail finds its
        # ends.
        trails = []  # (index, knots, along (2,) unit vector, along slack px, polyline, lo, hi) of each in its box
        long = np.flatnonzero(length >= self.min_trail_px)
        for i, knots in zip(long, chords(paths[long] - paths[long, mid : mid + 1]), strict=True):
            chord = knots[-1] - knots[0]
            along = chord / max(float(np.hypot(*chord)), 1e-9)
            slack = ALONG_FRACTION * float(length[i])
            ends = np.vstack([knots[0] - slack * along, knots, knots[-1] + slack * along])
            lo = np.floor(centres[i] + ends.min(axis=0) - reach).astype(np.int64)
            hi = np.ceil(centres[i] + ends.max(axis=0) + reach).astype(np.int64)
            if np.all(hi - lo + 1 <= self.max_box_px):
                trails.append((i, knots, along, slack, centres[i] + ends, np.maximum(lo, 0),
                               np.minimum(hi, [width - 1, height - 1])))
        cands = []  # (index, knots, rows, cols, along, slack) of each with enough pixels
        for n_ends in sorted({len(tr[4]) for tr in trails}):  # near_paths per polyline length
            group = [tr for tr in trails if len(tr[4]) == n_ends]
            pixels = near_paths(np.array([tr[5] for tr in group]), np.array([tr[6] for tr in group]),
                                np.array([tr[4] for tr in group]), reach)
            for (i, knots, along, slack, *_), rc in zip(group, pixels, strict=True):
                if full_scale < math.inf:
                    rc = rc[data[rc[:, 0], rc[:, 1]] < full_scale]
                if len(rc) >= 8:
                    cands.append((i, knots, rc[:, 0], rc[:, 1], along, slack))
        cands.sort(key=lambda cd: cd[0])
        fits = []
        for n_knots in sorted({len(cd[1]) for cd in cands}):  # one batch per chord count
            group = [cd for cd in cands if len(cd[1]) == n_knots]
            rows, cols, valid = _padded([cd[2] for cd in group], [cd[3] for cd in group])
            idx = np.array([cd[0] for cd in group])
            fitted = self._fit_batch(values[rows, cols], rows, cols, valid, [(cd[2], cd[3]) for cd in group],
                                     centres[idx], np.stack([cd[1] for cd in group]),
                                     np.stack([cd[4] for cd in group]), np.array([cd[5] for cd in group]),
                                     data.shape, sigma, noise)
            fits += [f for f in fitted if f is not None]
        # Brightest first; a fit that lands on a brighter one's star or a taken one (a trail found twice) is dropped.
        fits.sort(key=lambda f: -f.flux)
        at = np.array([f.centre for f in fits]).reshape(-1, 2)
        close = np.hypot(*(at[:, None] - at[None]).transpose(2, 0, 1)) <= SHIFT_PX
        free = np.ones(len(fits), dtype=bool)
        if taken:
            free = np.hypot(*(at[:, None] - np.array(taken)[None]).transpose(2, 0, 1)).min(axis=1) > SHIFT_PX
        keep = np.zeros(len(fits), dtype=bool)
        for a in range(len(fits)):
            keep[a] = free[a] and not (close[a, :a] & keep[:a]).any()
        return [fit for fit, k in zip(fits, keep, strict=True) if k], centres

    def _fit_batch(self, values: np.ndarray, rows: np.ndarray, cols: np.ndarray, valid: np.ndarray,
                   pixels: list[tuple[np.ndarray, np.ndarray]], starts: np.ndarray, knots: np.ndarray,
                   along: np.ndarray, slack: np.ndarray, shape: tuple[int, int], sigma: float,
                   noise: float) -> list[_Fit | None]:
        """Fits of one batch (one chord count) side by side: pixel ``values`` (C, n) DN at the padded ``rows``,
        ``cols`` of which the ``valid`` ones count, from ``starts`` (C, 2) px along ``knots``; each accepted one
        (:func:`_accepted`, ``along`` and ``slack`` per fit) as a :class:`_Fit` on its own ``pixels`` (rows, cols),
        None for the others."""
        c, flux, level, cov, ok, t = fit_trails(values, cols.astype(np.float32), rows.astype(np.float32), valid,
                                                starts, knots, sigma, noise, outlier_sigma=self.outlier_sigma,
                                                min_snr=self.min_snr, max_shift_px=SHIFT_PX + slack, with_model=True)
        good = _accepted(c, flux, cov, ok, starts, along, slack, shape, self.min_snr)
        return [_Fit(flux[g], c[g], knots[g], *pixels[g], math.sqrt(max(0.5 * (cov[g, 0, 0] + cov[g, 1, 1]), 0.0)),
                     level[g], along[g], t[g, : len(pixels[g][0])]) if good[g] else None for g in range(len(c))]

    def _second_stars(self, fits: list[_Fit], data: np.ndarray, sigma: float, noise: float,
                      full_scale: float, taken: list[np.ndarray]) -> tuple[list[_Fit], list[_Fit]]:
        """Stars found in the fits' residuals and fitted: the second star of a pair the candidate finder took for one
        trail (so only one was fitted, and the other, left as observed, would sit beside the restored star for the
        detector to merge with it).

        Each fit's residual (its pixels less its trail) is searched for a parallel trail offset across it by 2 px to
        the fit's reach, by the matched filter of the same trail: a significance of ``SECOND_SIGMA`` noise sigmas or
        more starts a fit there, on the fit's pixels moved by the offset with the first star's fitted light taken
        off, free to move along the trail as a first fit is (the model's ~1 % shape error leaves no such residual
        even on a trail of 1e7 DN: ``tests/test_trail_fit.py``).  It is kept on a first fit's acceptance, and when
        it lands no nearer than ``SHIFT_PX`` to a kept star (``fits``, those found, or a ``taken`` centre of an
        earlier round).  Only residuals whose sum of squares exceeds the noise's by ``SECOND_SCREEN`` of its spread
        are searched (a second trail of significance ``z`` adds about ``z^2``).  The fits whose residual, matched
        against their own trail moved ``ALONG_OFFSETS`` of its length along it, shows a trail of ``SECOND_SIGMA``
        are returned too: where a chain of trails on one line may hide more stars.  The first star of each pair
        found is fitted again without its second's light and replaced in ``fits``, then the second without the new
        first's."""
        height, width = data.shape
        reach = math.floor(PSF_REACH_SIGMA * sigma + SHIFT_PX)
        offsets = np.arange(2.0, reach + 1.0)
        offsets = np.concatenate([-offsets[::-1], offsets])
        starts = []  # (fit index, offset px) of each second star to fit
        busy = []  # the fits whose residual shows another trail along their own
        for n_knots in sorted({len(f.knots) for f in fits}):
            group = [i for i, f in enumerate(fits) if len(f.knots) == n_knots]
            rows, cols, valid = _padded([fits[i].rows for i in group], [fits[i].cols for i in group])
            x, y = cols.astype(np.float64), rows.astype(np.float64)
            c = np.array([fits[i].centre for i in group])
            knots = np.stack([fits[i].knots for i in group])
            flux = np.array([fits[i].flux for i in group])
            level = np.array([fits[i].background for i in group])
            w = valid.astype(np.float64)
            t = _padded_values([fits[i].model for i in group], x.shape[1])
            r = (data[rows, cols] - level[:, None] - flux[:, None] * t) * w
            n = w.sum(1)
            excess = ((r * r).sum(1) / noise**2 - n) / np.sqrt(2.0 * np.maximum(n, 1.0))
            screened = np.flatnonzero(excess >= SECOND_SCREEN)
            if len(screened) == 0:
                continue
            group = [group[g] for g in screened]
            x, y, c, knots, w, r = (a[screened] for a in (x, y, c, knots, w, r))
            # Across: a parallel trail beside it.  Along: a trail on the same line overlapping one end (a chain the
            # candidate finder took for one trail).
            z_across, z_along = matched_shifts(x, y, c, knots, sigma, r, w, noise, offsets, ALONG_OFFSETS)
            best = offsets[np.argmax(z_across, axis=0)]
            for g in np.flatnonzero(z_across.max(axis=0) >= SECOND_SIGMA):
                starts.append((group[g], best[g]))
            z = z_along.max(axis=0, initial=-np.inf)
            busy += [fits[group[g]] for g in np.flatnonzero(z >= SECOND_SIGMA)]
        found = []
        for n_knots in sorted({len(fits[i].knots) for i, _ in starts}):
            group = [(i, v) for i, v in starts if len(fits[i].knots) == n_knots]
            moved = []
            for i, v in group:
                f = fits[i]
                shift = np.rint(v * f.across).astype(np.int64)
                on = ((f.cols + shift[0] >= 0) & (f.cols + shift[0] < width)
                      & (f.rows + shift[1] >= 0) & (f.rows + shift[1] < height))
                r, q = f.rows[on] + shift[1], f.cols[on] + shift[0]
                below = data[r, q] < full_scale  # saturated pixels carry no flux information
                moved.append((r[below], q[below]))
            rows, cols, valid = _padded([m[0] for m in moved], [m[1] for m in moved])
            first = [fits[i] for i, _ in group]
            knots = np.stack([f.knots for f in first])
            light = np.stack([f.flux for f in first])[:, None] * trail_model(
                cols.astype(np.float64), rows.astype(np.float64), np.array([f.centre for f in first]), knots, sigma,
                derivatives=False)[0]
            along = np.array([f.along for f in first])
            start = np.array([f.centre + v * f.across for f, (_, v) in zip(first, group, strict=True)])
            slack = ALONG_FRACTION * np.linalg.norm(np.diff(knots, axis=1), axis=2).sum(axis=1)
            fitted = self._fit_batch(np.where(valid, data[rows, cols] - light, 0.0), rows, cols, valid, moved, start,
                                     knots, along, slack, data.shape, sigma, noise)
            for (i, _), fit in zip(group, fitted, strict=True):
                near = taken + [f.centre for f in fits] + [f.centre for f, _ in found]
                if fit is not None and min(float(np.hypot(*(fit.centre - p))) for p in near) > SHIFT_PX:
                    found.append((fit, i))
        if found:  # each first star again without its second's light, then each second without the new first's
            firsts = self._refit([fits[i] for _, i in found], [f for f, _ in found], data, sigma, noise)
            for (_, i), first in zip(found, firsts, strict=True):
                fits[i] = first
            found = [(f, i) for f, i in zip(self._refit([f for f, _ in found], firsts, data, sigma, noise),
                                            [i for _, i in found], strict=True)]
        return [f for f, _ in found], busy

    def _refit(self, fits: list[_Fit], partners: list[_Fit], data: np.ndarray, sigma: float,
               noise: float) -> list[_Fit]:
        """Each fit made again on its own pixels of ``data`` with its partner's modelled light taken off, started
        where it is (one of two blended trails, first fitted with the other's light in its pixels); a fit not
        accepted again is kept as it was."""
        out = list(fits)
        for n_knots in sorted({len(f.knots) for f in fits}):
            group = [j for j, f in enumerate(fits) if len(f.knots) == n_knots]
            rows, cols, valid = _padded([fits[j].rows for j in group], [fits[j].cols for j in group])
            mates = [partners[j] for j in group]
            light = np.array([f.flux for f in mates])[:, None] * trail_model(
                cols.astype(np.float64), rows.astype(np.float64), np.array([f.centre for f in mates]),
                np.stack([f.knots for f in mates]), sigma, derivatives=False)[0]
            knots = np.stack([fits[j].knots for j in group])
            slack = ALONG_FRACTION * np.linalg.norm(np.diff(knots, axis=1), axis=2).sum(axis=1)
            fitted = self._fit_batch(np.where(valid, data[rows, cols] - light, 0.0), rows, cols, valid,
                                     [(fits[j].rows, fits[j].cols) for j in group],
                                     np.array([fits[j].centre for j in group]), knots,
                                     np.array([fits[j].along for j in group]), slack, data.shape, sigma, noise)
            for j, fit in zip(group, fitted, strict=True):
                if fit is not None:
                    out[j] = fit
        return out


@dataclass
class _Fit:
    """A trail fit: flux (DN), mid-exposure centre (2,) px, chord knots relative to it (K + 1, 2) px, the pixels
    it was fitted on (rows, cols), its position sigma (px), background (DN), unit vector along the trail and unit
    trail (:func:`trail_model`) on its pixels."""

    flux: float
    centre: np.ndarray
    knots: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    position_sigma: float
    background: float
    along: np.ndarray
    model: np.ndarray

    @property
    def across(self) -> np.ndarray:
        """Unit vector (2,) across the trail: ``along`` turned by +90 deg."""
        return np.array([-self.along[1], self.along[0]])


def _accepted(centre: np.ndarray, flux: np.ndarray, cov: np.ndarray, converged: np.ndarray, start: np.ndarray,
              along: np.ndarray, slack: np.ndarray, shape: tuple[int, int], min_snr: float) -> np.ndarray:
    """Which fits (C,) are kept: converged, positive flux of at least ``min_snr`` of its sigma, within ``SHIFT_PX``
    of the start across the trail and ``SHIFT_PX`` + ``slack`` (C,) px along it (``along``: unit vectors (C, 2)),
    the centre on a frame of ``shape``."""
    height, width = shape
    shift = centre - start
    shift_along = np.einsum("ij,ij->i", shift, along)
    shift_across = np.abs(shift[:, 1] * along[:, 0] - shift[:, 0] * along[:, 1])
    good = converged & (flux > 0) & (flux >= min_snr * np.sqrt(np.maximum(cov[:, 2, 2], 0.0)))
    good &= (shift_across <= SHIFT_PX) & (np.abs(shift_along) <= SHIFT_PX + slack)
    return good & (centre[:, 0] >= 0) & (centre[:, 0] <= width - 1) & (centre[:, 1] >= 0) & (centre[:, 1] <= height - 1)


def _merged_boxes(boxes: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Boxes (lo, hi) (x, y px, inclusive) merged until none overlap: each overlapping pair replaced by the box
    holding both."""
    merged = []
    for lo, hi in boxes:
        lo, hi = lo.copy(), hi.copy()
        joined = True
        while joined:
            joined = False
            for k, (a, b) in enumerate(merged):
                if np.all(lo <= b) and np.all(a <= hi):
                    lo, hi = np.minimum(lo, a), np.maximum(hi, b)
                    del merged[k]
                    joined = True
                    break
        merged.append((lo, hi))
    return merged


def _light(fits: list[_Fit], sigma: float, still: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each fit's modelled light on its own pixels, ``F T`` (``still``: ``F S``, its star with no motion), as
    rows, columns and DN (n,), the fits one after another in their order."""
    light = [f.flux * f.model for f in fits]
    if still:
        for n_knots in sorted({len(f.knots) for f in fits}):  # one batch per chord count
            group = [i for i, f in enumerate(fits) if len(f.knots) == n_knots]
            rows, cols, _ = _padded([fits[i].rows for i in group], [fits[i].cols for i in group])
            model = trail_model(cols.astype(np.float64), rows.astype(np.float64),
                                np.array([fits[i].centre for i in group]), np.zeros((len(group), 2, 2)), sigma,
                                derivatives=False)[0]
            for g, i in enumerate(group):
                light[i] = fits[i].flux * model[g, : len(fits[i].rows)]
    return (np.concatenate([f.rows for f in fits]), np.concatenate([f.cols for f in fits]), np.concatenate(light))


def _padded_values(values: list[np.ndarray], size: int) -> np.ndarray:
    """Per-pixel values of several fits side by side (C, size), zero-padded as :func:`_padded` pads their pixels."""
    out = np.zeros((len(values), size), dtype=values[0].dtype)
    for g, v in enumerate(values):
        out[g, : len(v)] = v
    return out


def _padded(rows: list[np.ndarray], cols: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel lists of several fits side by side: rows, columns (C, n) int, zero-padded to the longest, and which
    are real (C, n)."""
    size = max(len(r) for r in rows)
    out_rows = np.zeros((len(rows), size), dtype=np.int64)
    out_cols = np.zeros((len(rows), size), dtype=np.int64)
    valid = np.zeros((len(rows), size), dtype=bool)
    for g, (r, cl) in enumerate(zip(rows, cols, strict=True)):
        out_rows[g, : len(r)], out_cols[g, : len(r)], valid[g, : len(r)] = r, cl, True
    return out_rows, out_cols, valid


def _full_scale(data: np.ndarray) -> float:
    """The frame's maximum (DN) where it is an ADC's full-scale code ``2^n - 1`` (n = 8..16): saturated pixels;
    else inf."""
    top = float(data.max())
    return top if any(top == 2**n - 1 for n in range(8, 17)) else math.inf
