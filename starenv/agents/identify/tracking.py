"""Tracking identification (:class:`TrackingIdentifier`): detections paired with the catalogue stars near a prior
attitude by the consistency of their pairwise angles, solved, re-paired tightly and verified; lost in space when the
verification fails.

Why pairwise angles.  A prior off by a small angle ``e`` about any axis moves each predicted star by ``e |axis x
star| <= e``, but by different amounts and directions across the field when part of the error is roll; once ``e`` is
more than the distance between neighbouring stars, the predicted star nearest a detection is often the wrong one,
and pairs made that way are self-consistent enough to be solved and accepted.  The angle between two detections is
the angle between their stars whatever the attitude: a prior error does not change it.

Steps (detections of all heads pooled as body-frame unit vectors):

1. Candidates: every (detection, catalogue star) within ``gate_px`` of the star's position predicted by the prior.
   The gate's reach is ``gate_px`` times the plate scale: a prior off by less than that (minus a few centroid sigmas)
   keeps each detection's star among its candidates.
2. Agreement: candidates (i, a) and (j, b) of two detections and two stars agree when the chords ``|b_i - b_j|`` and
   ``|r_a - r_b|`` differ by at most ``3 sqrt(2) sigma`` (``sigma = centroid_noise_px`` per axis, as an angle at the
   coarser plate scale of the two heads; the difference of two centroid errors along the pair has sigma ``sqrt(2)
   sigma``; a chord and its angle differ by under 0.5 % below 20 deg).  A candidate's votes are the detections
   holding a candidate that agrees with it (geometric voting, Kolomenkin et al., IEEE TAES 44(2), 2008, restricted
   to the gate).
3. Each detection keeps its most-voted candidate, and so does each star (ties: the nearest its prediction); the
   core is those kept candidates that agree with at least half as many of the others as the best one does.  A wrong
   candidate agrees with a right one by chance (its chord is off by up to the gate: a chance of about tolerance /
   gate per pair), so it has few.
4. The attitude is solved from the core (SVD solution of Wahba's problem), every detection re-paired with the star
   within ``refine_gate_px`` (none when two or more are or lie within ``CLAIM_SIGMAS`` centroid sigmas, and none
   for a star with two detections that close: an ambiguous detection is left unidentified), and solve and re-pair
   repeated until the pairs stop changing (at most ``_REPAIRS`` times).  With several heads, the pairs of a head
   that the others' pairs do not predict and that could be chance over the roll they leave loose are then dropped
   (:func:`~starenv.agents.identify.verify.unconfirmed_heads`).
5. Verification (:mod:`starenv.agents.identify.verify`): with ``n`` detections and ``m`` paired, ``p`` = the chance
   that a detection lands within ``refine_gate_px`` of a catalogue star under a wrong attitude (the density of the
   catalogue stars in each head's cone, the largest of the heads'), ``g = 2`` (two agreeing pairs fix an attitude,
   and pair by construction) and ``H`` the number of agreeing candidate pairs of step 2 (the hypotheses the search
   could have ended on), the result is accepted when ``m >= min_matches`` and ``H P(X >= m - 2) <= max_false``,
   ``X ~ Binomial(n - 2, p)``.
6. When the core gives no verified result (it can hold chance agreements: on a frame of many trail pieces, pieces
   from the same part of parallel trails agree in their chords), the prior itself is the hypothesis: each detection
   paired with the star predicted within ``refine_gate_px``, and those pairs verified as in step 5 with ``H = 1``
   and ``g = 1`` (no pair is made by construction; the one counted is a margin for the prior's own error, so that
   three detections planted on predicted stars are refused), then solved and re-paired as in step 4, and the
   settled pairs verified again the same way (settling may drop pairs).  Otherwise (and with no prior) the fallback
   labels the frame.

Steps 5 and 6 each test at half of ``max_false`` (``2 H`` and 2 hypotheses), so that the frame's two attempts
together accept a wrong attitude with a probability below ``max_false``.

What that allows.  Paper 002's 12 deg head (42 arcsec/px) with the catalogue to Hp 6.5 has ~1.1e3 stars/sr on
average (~44 in a field), so a 3 px radius gives ``p ~ 7e-4``: a frame of 30 detections with agreeing candidate
pairs ``H ~ 500`` is accepted by step 5 from ``m = 6`` pairs (bound ``2 H P`` 4.9e-6), not with 5 (1.1e-3); a frame
of 4 detections needs all 4 and ``H <= 10``.  Step 6 accepts the same frame from 4 pairs under the prior (2.5e-6),
never from 3 (3.9e-4).  ``max_false = 1e-5`` bounds the chance of accepting a wrong attitude per frame by 1e-5.

A star closer than ``MERGE_PX`` pixels to a brighter one is taken as part of it (the sensor sees one star).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from starenv import checks
from starenv.agents.base import Identifier, StarMeasurements
from starenv.agents.blocks import run_starts, wahba_svd
from starenv.agents.identify.geometry import (
    CLAIM_SIGMAS,
    MERGE_PX,
    body_vectors,
    claim_scale2,
    closest_per_star,
    mask_pairs,
    resolvable,
    same_cameras,
    same_matches,
    sole_per_star,
    with_ids,
)
from starenv.agents.identify.lost_in_space import LostInSpaceIdentifier
from starenv.agents.identify.verify import (
    anchor_head,
    chance_match,
    false_match_probability,
    unconfirmed_heads,
)
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog

_SIGMAS = 3.0  # agreement tolerance of two chords, in sigmas of their difference
_REPAIRS = 3  # most solve-and-re-pair rounds after the core's solution
_SCATTER_PAIRS = 8  # pairs needed to measure the centroid scatter (else ``centroid_noise_px`` is taken)


class TrackingIdentifier:
    """Identification from a prior attitude by pairwise-angle agreement within a gate, then a tight re-pairing and a
    verification (see the module docstring); lost in space when that fails.

    ``gate_px``: the candidates' gate about the predicted stars (its reach bounds the prior error tracked);
    ``refine_gate_px``: the pairing radius after solving; ``centroid_noise_px``: 1-sigma centroid noise per axis
    (sets the agreement tolerance); ``max_false``: the largest accepted bound on the probability of a wrong attitude;
    ``min_matches``: fewest pairs accepted.  All px become angles by each head's plate scale.  Failing (or with no
    prior) hands the frame to ``fallback`` (default :class:`LostInSpaceIdentifier` with its defaults).
    """

    def __init__(
        self,
        fallback: Identifier | None = None,
        gate_px: float = 50.0,
        refine_gate_px: float = 3.0,
        centroid_noise_px: float = 1.0,
        max_false: float = 1e-5,
        min_matches: int = 3,
    ):
        if fallback is not None and not isinstance(fallback, Identifier):
            raise ValueError(f"fallback must implement the Identifier protocol, got {type(fallback).__name__}")
        self.fallback = LostInSpaceIdentifier() if fallback is None else fallback
        self.gate_px = checks.in_range("gate_px", gate_px, 0.0, 1000.0, low_open=True, unit="px")
        self.refine_gate_px = checks.in_range(
            "refine_gate_px", refine_gate_px, 0.0, self.gate_px, low_open=True, unit="px"
        )
        self.centroid_noise_px = checks.in_range(
            "centroid_noise_px", centroid_noise_px, 0.0, 10.0, low_open=True, unit="px"
        )
        self.max_false = checks.in_range("max_false", max_false, 0.0, 1.0, low_open=True)
        self.min_matches = checks.integer("min_matches", min_matches, 3, 1000)
        self.catalog: StarCatalog | None = None
        self._last_views: _Views | None = None

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        """Index the catalogue's resolvable stars for these heads and reset the fallback."""
        if not cameras:
            raise ValueError("cameras must hold at least one Camera")
        merge_rad = MERGE_PX * max(1.0 / min(cam.fx, cam.fy) for cam in cameras)
        rows = np.flatnonzero(resolvable(catalog.unit, catalog.magnitude, merge_rad))
        self._unit, self._hip = catalog.unit[rows], catalog.hip[rows]
        self._tree = cKDTree(self._unit)
        self.catalog = catalog
        self._last_views = None
        self.fallback.reset(cameras, catalog)

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """Label all heads' detections with HIP numbers (-1: unidentified), tracking from ``prior`` if it is given;
        ``images`` goes to the fallback."""
        if self.catalog is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        body, heads = body_vectors(stars, cameras)
        if prior is not None and len(body) >= self.min_matches:
            ids = self._track(body, heads, cameras, prior.as_matrix())
            if ids is not None:
                return with_ids(stars, ids)
        return self.fallback.identify(stars, cameras, prior, images)

    def _track(
        self, body: np.ndarray, heads: np.ndarray, cameras: list[Camera], prior: np.ndarray
    ) -> np.ndarray | None:
        """Pooled ids (-1 none) of the detections ``body`` (n, 3) of heads ``heads`` tracked from ``prior`` (3, 3,
        inertial -> body), or None when the verification rejects them."""
        n = len(body)
        views = self._views(cameras)
        pixel = views.pixel  # rad/px per head
        pix = pixel[heads]
        stars, density = self._in_view(views, prior)
        unit = self._unit[stars]
        radius2 = (self.refine_gate_px * pix) ** 2
        radii = radius2, pix**2, self.centroid_noise_px**2
        p = float(np.max(chance_match(density[heads], np.sqrt(radius2))))
        # Two attempts, each verified at half of max_false: together they accept a wrong attitude with a probability
        # below max_false.
        confirm = (heads, pix, density) if len(cameras) > 1 else None
        voted = self._vote(body, pixel, pix, unit, prior)
        if voted is not None:
            pairs = self._settle(body, unit, self._pair(body, unit, wahba_svd(*voted[0]), radii), radii, confirm)
            if pairs is not None and self._verified(n, len(pairs[0]), p, 2, 2 * voted[1]):
                return self._ids(n, stars, pairs)
        # 6. The prior's own pairing, verified before any solution is fitted to it, with one pair counted as given:
        # a margin for the prior's own error, so that three detections planted on predicted stars are refused.
        # The settled pairs are tested again: settling may drop pairs, and the bound stated is for what is returned.
        pairs = self._pair(body, unit, prior, radii)
        if self._verified(n, len(pairs[0]), p, 1, 2):
            pairs = self._settle(body, unit, pairs, radii, confirm)
            if pairs is not None and self._verified(n, len(pairs[0]), p, 1, 2):
                return self._ids(n, stars, pairs)
        return None

    def _vote(self, body: np.ndarray, pixel: np.ndarray, pix: np.ndarray, unit: np.ndarray,
              prior: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], int] | None:
        """Steps 1-3: the core's (body, inertial) unit vectors and the number of agreeing candidate pairs (the
        hypotheses), or None when too few candidates agree; ``pixel`` is each head's plate scale, ``pix`` each
        detection's (rad/px)."""
        # 1. Candidates within the gate of the predicted stars (det ascending: each detection's candidates in a run).
        squared = 2.0 - 2.0 * (body @ prior @ unit.T)
        det, star = mask_pairs(squared <= (self.gate_px * pix)[:, None] ** 2)
        if len(det) < self.min_matches:
            return None
        offset = squared[det, star]
        # 2. Agreement of candidate pairs' chords, and votes.
        tolerance = (_SIGMAS * math.sqrt(2.0) * self.centroid_noise_px) * (
            pixel[0] if len(pixel) == 1 else np.maximum.outer(pix[det], pix[det])
        )
        detections = body[det]
        detection_chord = np.sqrt(np.maximum(2.0 - 2.0 * (detections @ detections.T), 0.0))
        candidates = unit[star]
        star_chord = np.sqrt(np.maximum(2.0 - 2.0 * (candidates @ candidates.T), 0.0))
        agree = np.abs(detection_chord - star_chord) <= tolerance
        agree &= (det[:, None] != det) & (star[:, None] != star)
        votes = _votes(agree, det)
        # 3. One candidate a detection and a star, most votes first (then nearest its prediction); the core agrees
        # with at least half as many kept ones as the best.
        kept = _first_of_each(det, np.lexsort((offset, -votes, det)))
        kept = kept[_first_of_each(star[kept], np.lexsort((offset[kept], -votes[kept], star[kept])))]
        support = agree[kept][:, kept].sum(axis=1)
        core = kept[support >= max(2.0, support.max() / 2.0)]
        if len(core) < self.min_matches:
            return None
        return (body[det[core]], unit[star[core]]), max(np.count_nonzero(agree) // 2, 1)

    def _settle(self, body: np.ndarray, unit: np.ndarray, pairs: tuple[np.ndarray, np.ndarray],
                radii: tuple, confirm: tuple | None) -> tuple[np.ndarray, np.ndarray] | None:
        """Step 4 from a first pairing: solve and re-pair (:meth:`_pair`'s ``radii``) until the pairs settle, less
        the pairs of heads :func:`~starenv.agents.identify.verify.unconfirmed_heads` holds back when ``confirm``
        (several heads: the detections' heads, plate scales (rad/px) and each head's star density (per sr)) is
        given; None when fewer than ``min_matches`` pair."""
        for _ in range(_REPAIRS):
            if len(pairs[0]) < self.min_matches:
                return None
            attitude = wahba_svd(body[pairs[0]], unit[pairs[1]])
            repaired = self._pair(body, unit, attitude, radii)
            if same_matches(repaired, pairs):
                break
            pairs = repaired
        if confirm is not None and len(pairs[0]):
            heads, pix, density = confirm
            anchor = anchor_head(heads, pairs[0])
            if anchor is not None:
                radius2 = np.zeros(len(density))
                radius2[heads] = radii[0]
                dropped = unconfirmed_heads(body, heads, pairs[0], anchor,
                                            1.0 / (self.centroid_noise_px * pix) ** 2, radius2,
                                            chance_match(density, np.sqrt(radius2)), self.max_false)
                if dropped:
                    keep = ~np.isin(heads[pairs[0]], dropped)
                    pairs = pairs[0][keep], pairs[1][keep]
        return pairs if len(pairs[0]) >= self.min_matches else None

    def _verified(self, n: int, m: int, p: float, given: int, hypotheses: int) -> bool:
        """Step 5: ``m`` of ``n`` detections paired, ``given`` of them by construction, is no chance pairing of any
        of ``hypotheses`` attitudes."""
        return m >= self.min_matches and false_match_probability(n, m, p, given, hypotheses) <= self.max_false

    def _ids(self, n: int, stars: np.ndarray, pairs: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        ids = np.full(n, -1, dtype=np.int64)
        ids[pairs[0]] = self._hip[stars[pairs[1]]]
        return ids

    def _views(self, cameras: list[Camera]) -> _Views:
        """The per-head constants of ``cameras`` (kept for the last list of cameras seen; cameras are frozen)."""
        views = self._last_views
        if views is None or not same_cameras(views.cameras, cameras):
            pixel = np.array([1.0 / min(cam.fx, cam.fy) for cam in cameras])
            reach = np.array([
                min(cam.half_diagonal + self.gate_px * scale, math.pi)
                for cam, scale in zip(cameras, pixel.tolist(), strict=True)
            ])
            self._last_views = views = _Views(
                cameras=tuple(cameras),
                pixel=pixel,
                axes=np.stack([cam.mounting.as_matrix()[2] for cam in cameras]),
                chords=2.0 * np.sin(reach / 2.0),
                solid_angle=2.0 * math.pi * (1.0 - np.cos(reach)),
            )
        return views

    def _in_view(self, views: _Views, attitude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows (of the resolvable stars) within each head's half diagonal plus the gate of its boresight under
        ``attitude`` (3, 3), inertial -> body, and per head the density of those stars in its cone (per sr)."""
        if len(views.cameras) == 1:
            found = self._tree.query_ball_point(views.axes[0] @ attitude, views.chords[0], return_sorted=True)
            return np.asarray(found, dtype=np.intp), np.array([len(found)]) / views.solid_angle
        found = self._tree.query_ball_point(views.axes @ attitude, views.chords)
        density = np.array([len(f) for f in found]) / views.solid_angle
        return np.unique(np.concatenate([np.asarray(f, dtype=np.intp) for f in found])), density

    @staticmethod
    def _pair(body: np.ndarray, unit: np.ndarray, attitude: np.ndarray, radii: tuple) -> tuple:
        """(detections, rows of ``unit``) paired under ``attitude``: each detection with the one star within its
        squared radius ``radii[0]`` (rad^2, per detection), and only when no other detection lies within
        ``CLAIM_SIGMAS`` centroid sigmas of that star (``radii[2]``, px^2 per axis, with ``radii[1]`` the squared plate
        scale, rad^2/px^2; or ``claim_scale2`` times the scatter of each star's closest detection when there are
        ``_SCATTER_PAIRS``);
        of detections further apart the closest.  A detection with two stars or more within its radius or within
        ``CLAIM_SIGMAS`` centroid sigmas stays unpaired, and so do two detections by one star: which one made it is a
        guess (a pair a few px apart whose fainter star went undetected or is merged into the brighter in the
        catalogue, two stars whose noisy centroids swapped, or a star whose noise took its detection past the radius
        while its neighbour's lies within)."""
        radius2, pixel2, variance = radii
        squared = 2.0 - 2.0 * (body @ attitude @ unit.T)
        within = squared <= radius2[:, None]
        nearest = squared.argmin(axis=1)
        alone = np.flatnonzero(within.sum(axis=1) == 1)
        closest = squared[np.arange(len(body)), nearest]
        first = closest_per_star(alone, nearest, closest)[0]  # (each star's closest detection)
        claim2 = CLAIM_SIGMAS**2 * variance
        if len(first) >= _SCATTER_PAIRS:  # the centroid variance per axis (px^2) measured on those pairs
            claim2 = 0.5 * (float((closest[first] / pixel2[first]).sum()) / len(first)) * claim_scale2(len(first))
        return sole_per_star(first, nearest, squared <= (claim2 * pixel2)[:, None])


class _Views(NamedTuple):
    """Per-head constants of a list of cameras: the cameras, their plate scales (rad/px), body-frame boresights
    (h, 3), and the chords (rad) and solid angles (sr) of the cones about them that hold the stars tracked."""

    cameras: tuple
    pixel: np.ndarray
    axes: np.ndarray
    chords: np.ndarray
    solid_angle: np.ndarray


def _votes(agree: np.ndarray, det: np.ndarray) -> np.ndarray:
    """Per candidate, the detections holding a candidate that agrees with it: ``agree`` (c, c) of candidates whose
    detections ``det`` (c,) ascend (each detection's candidates in a run)."""
    starts = np.flatnonzero(run_starts(det))
    if len(starts) == len(det):  # one candidate a detection: a vote a candidate
        return agree.sum(axis=1)
    return np.logical_or.reduceat(agree, starts, axis=1).sum(axis=1)


def _first_of_each(group: np.ndarray, order: np.ndarray) -> np.ndarray:
    """The first entry of ``order`` (a sort by ``group``, then preference) in each group of ``group``."""
    return order[run_starts(group[order])]
