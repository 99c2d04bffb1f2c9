"""Star identification: lost in space by 4-star pattern hashing (Tetra), and tracking from a prior attitude.

Lost in space (:class:`LostInSpaceIdentifier`)
    Brown & Stubis' Tetra (J. Brown and K. Stubis, "TETRA: Star Identification with Hash Tables", AIAA/USU Conference
    on Small Satellites, 2017), in the form of its successors tetra3 (ESA) and its fork cedar-solve: a pattern
    of four stars is described by the five smaller of its six pairwise angular distances divided by the largest (edge
    ratios, free of the plate scale), and each ratio is quantised into one of ``bins`` bins; the five bin numbers form
    the pattern's key.  The database holds the keys of catalogue patterns sorted, so a lookup is a binary search
    (the role of Tetra's open-addressing hash table).

    *Database.*  Stars are the catalogue's down to ``mag_limit``; a star with another one closer than
    ``BLEND_PX`` pixels is never used in a pattern (the two would blend on the sensor).  Patterns come from tetra3's
    lattice fields: a Fibonacci lattice of centres covers the sky (spacing a quarter of the field), and the
    ``pattern_stars_per_region`` brightest usable stars within half the field of each centre give every 4-star
    combination of them; duplicates are merged.  The field is the largest head's shorter side (``fov_rad``), so a
    pattern fits in a circle the head sees whole.  Patterns whose largest edge is below a quarter of the field are left
    out: their ratios are too sensitive to centroid noise.  The database is cached on disk (see :func:`load_database`).

    *Matching.*  All heads are pooled: each detection becomes a body-frame unit vector
    ``camera.mounting.inv().apply(camera.unproject(xy))``.  4-star patterns are taken within each head (a pattern must
    fit in one field) from its brightest detections, breadth-first: all patterns of the 5 brightest, then those adding
    the 6th, ... up to ``max_pattern_stars``, every head at the same pace.  The edge tolerance is ``3 sqrt(2)`` times
    the centroid noise (``centroid_noise_px``) at the coarsest plate scale; it fixes each ratio's tolerance and so the
    bins probed (at most two a ratio, 32 keys a pattern).  A catalogue pattern found there must also match the largest
    edge and then all six edges in angle (the scale is known) under one of the 24 star orders.  Each such hypothesis
    is solved for the attitude (SVD solution of Wahba's problem) and verified as in tetra3/cedar-solve: with ``n``
    detections in all heads, ``m`` of them within ``match_radius_px`` of a catalogue star (pattern stars included)
    and ``p`` the chance that a random detection lands that close to one (local catalogue density times the match
    area), the probability of a false match is ``P(X >= m - 2)`` for ``X ~ Binomial(n, p)``; hypotheses below
    ``match_threshold`` are verified.  Of the verified hypotheses of the first breadth-first step that has any, the
    one matching most detections wins.  Matching and refining the attitude then alternate, the search widened by the
    attitude's uncertainty (a pattern in one small field leaves the roll about it loose, which moves the stars of the
    other heads), and every detection within the match radius of a catalogue star is labelled (one detection a star,
    the closest; a detection with two catalogue stars within its radius is left unidentified: which one made it is a
    guess).  Verifying and refining compare the detections with the database stars of a cone about each head's
    boresight, by brute force (both sets are small), rather than through the k-d tree of the whole sky.

Tracking (:class:`TrackingIdentifier`, :mod:`starenv.agents.identify.tracking`)
    With a prior attitude: detections paired with the catalogue stars within a gate of their predicted positions by
    the agreement of pairwise angles, solved, re-paired tightly and verified; this identifier is its fallback.

    Both identifiers take a star closer than ``MERGE_PX`` pixels to a brighter one as part of it (the sensor sees
    one star): detections are matched to the brighter only.

Ids are HIP numbers; -1 marks a detection left unidentified.
"""

from __future__ import annotations

import bisect
import itertools
import math
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.special import bdtrc

from starenv import checks
from starenv.agents.base import StarMeasurements
from starenv.agents.identify.database import (
    BLEND_PX,
    N_SIGMA,
    PATTERN_STARS_PER_FIELD,
    DatabaseSettings,
    PatternDatabase,
    field_mag_limit,
    load_database,
)
from starenv.agents.identify.geometry import (
    EDGE_FROM,
    EDGE_TO,
    IDENTITY,
    MERGE_PX,
    ORDER_EDGES,
    STAR_ORDERS,
    body_vectors,
    chord,
    closest_per_star,
    resolvable,
    same_matches,
    with_ids,
)
from starenv.agents.solve import wahba_svd
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog

_SAME_ATTITUDE_TRACE = 1e-6  # 3 - trace(A B^T) below this (under 1 mrad apart): the same attitude
_GROW_STEPS = 4  # match-and-refine rounds after a hypothesis is accepted
_GROW_MAX = 10.0  # widest search in those rounds, in match radii
_BIN_STEPS = (np.arange(32)[:, None] >> np.arange(5)) & 1  # (32, 5): step s probes the bin above for the set bits of s
_PROBES = np.all(_BIN_STEPS[None] <= _BIN_STEPS[:, None], axis=2)  # (32, 32): [w, s] step s within the bits w
_BITS = 1 << np.arange(5)  # bit of each ratio in a bin step
_SIGNS = np.array([-1.0, 1.0])[:, None, None]


def _breadth_first_quads(count: int) -> list[np.ndarray]:
    """4-subsets of ``range(count)`` in steps: those within the 5 first, then those adding index 5, 6, ..."""
    first = np.array(list(itertools.combinations(range(min(count, 5)), 4)), dtype=np.intp).reshape(-1, 4)
    steps = [first]
    for last in range(5, count):
        others = np.array(list(itertools.combinations(range(last), 3)), dtype=np.intp)
        steps.append(np.column_stack([others, np.full(len(others), last)]))
    return steps


class _Frame(NamedTuple):
    """The detections of one identification: pooled body-frame unit vectors (n, 3), their match radius (rad), its
    square and largest value, and per head with detections its boresight ``axes`` (h, 3) and the chord of a cone
    about it that holds every database star a detection can be matched to while growing a hypothesis."""

    body: np.ndarray
    radius: np.ndarray
    radius2: np.ndarray
    max_radius: float
    axes: np.ndarray
    chords: np.ndarray


class LostInSpaceIdentifier:
    """Identification without a prior attitude by Tetra 4-star pattern hashing (see the module docstring).

    ``mag_limit`` (Hp) bounds the database stars (None: :func:`field_mag_limit` of the catalogue given to
    :meth:`reset` for ``PATTERN_STARS_PER_FIELD`` stars per field); ``pattern_stars_per_region`` is the number of
    brightest stars per field-sized region that form patterns; ``centroid_noise_px`` (1-sigma, per axis) sets the
    pattern tolerance; ``match_radius_px`` is the verification and labelling radius; ``match_threshold`` the largest
    accepted probability of a false match; patterns are drawn from the ``max_pattern_stars`` brightest detections of
    each head. The first :meth:`reset` for a set of heads and a catalogue builds the database (about a second) and
    caches it on disk; later ones, in any process, load it in milliseconds.
    """

    def __init__(
        self,
        mag_limit: float | None = None,
        pattern_stars_per_region: int = 10,
        centroid_noise_px: float = 0.5,
        match_radius_px: float = 3.0,
        match_threshold: float = 1e-5,
        max_pattern_stars: int = 12,
    ):
        self.mag_limit = None if mag_limit is None else checks.in_range("mag_limit", mag_limit, -2.0, 14.0, unit="mag")
        self.pattern_stars_per_region = checks.integer("pattern_stars_per_region", pattern_stars_per_region, 4, 12)
        self.centroid_noise_px = checks.in_range("centroid_noise_px", centroid_noise_px, 0.0, 10.0, low_open=True)
        self.match_radius_px = checks.in_range("match_radius_px", match_radius_px, 0.0, 100.0, low_open=True)
        self.match_threshold = checks.in_range("match_threshold", match_threshold, 0.0, 1.0, low_open=True)
        self.max_pattern_stars = checks.integer("max_pattern_stars", max_pattern_stars, 4, 30)
        self._quad_steps = [  # per step: its quads, their edges as star pairs, the largest star of each
            (step, (step[:, EDGE_FROM], step[:, EDGE_TO]), step.max(axis=1).tolist())
            for step in _breadth_first_quads(self.max_pattern_stars)
        ]
        self.database: PatternDatabase | None = None

    def settings_for(self, cameras: list[Camera], catalog: StarCatalog) -> DatabaseSettings:
        """Database settings for these heads: the largest head's shorter field side, its coarsest plate scale; the
        magnitude limit is ``mag_limit`` or, when None, :func:`field_mag_limit` of the catalogue handed over."""
        if not cameras:
            raise ValueError("cameras must hold at least one Camera")
        pixel_rad = max(1.0 / min(cam.fx, cam.fy) for cam in cameras)
        return DatabaseSettings(
            fov_rad=max(min(cam.fov) for cam in cameras),
            mag_limit=field_mag_limit(cameras, catalog.magnitude, PATTERN_STARS_PER_FIELD)
            if self.mag_limit is None
            else self.mag_limit,
            edge_tolerance_rad=N_SIGMA * math.sqrt(2.0) * self.centroid_noise_px * pixel_rad,
            blend_rad=BLEND_PX * pixel_rad,
            merge_rad=MERGE_PX * pixel_rad,
            pattern_stars_per_region=self.pattern_stars_per_region,
        )

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        """Load (or build and cache) the pattern database for these heads and catalogue, and index the whole
        catalogue's resolvable stars: a verified attitude labels detections from all of it, not only the (brighter)
        pattern stars."""
        settings = self.settings_for(cameras, catalog)
        self.database = load_database(catalog, settings)
        rows = np.flatnonzero(resolvable(catalog.unit, catalog.magnitude, settings.merge_rad))
        self._label_tree, self._label_hip = cKDTree(catalog.unit[rows]), catalog.hip[rows]
        self._bins = settings.bins
        self._digits = np.int64(self._bins) ** np.arange(5, dtype=np.int64)  # key = bin numbers @ digits
        step_keys = _BIN_STEPS @ self._digits
        self._probe_keys = np.stack([step_keys, step_keys + 1])  # per bin step: its key offset and the next one

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None = None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """Label all heads' detections with HIP numbers (-1: unidentified); ``prior`` and ``images`` are not used."""
        if self.database is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        body, heads = body_vectors(stars, cameras)
        ids = np.full(len(body), -1, dtype=np.int64)
        if any(len(s) >= 4 for s in stars):
            frame = self._frame(body, heads, stars, cameras)
            attitude = self._solve(frame, stars)
            if attitude is not None:
                distance, nearest = self._label_tree.query(body @ attitude, k=2, distance_upper_bound=frame.max_radius)
                alone = ((distance[:, 0] <= frame.radius) & (distance[:, 1] > frame.radius)).nonzero()[0]
                labelled, stars_hit = closest_per_star(alone, nearest[:, 0], distance[:, 0])
                ids[labelled] = self._label_hip[stars_hit]
        return with_ids(stars, ids)

    def _frame(self, body: np.ndarray, heads: np.ndarray, stars: list[StarMeasurements],
               cameras: list[Camera]) -> _Frame:
        """The detections of one call with their match radii and search cones (see :class:`_Frame`)."""
        pixel_rad = np.array([1.0 / min(cam.fx, cam.fy) for cam in cameras])[heads]
        radius = self.match_radius_px * pixel_rad
        max_radius = float(radius.max())
        axes, chords, first = [], [], 0
        for s, cam in zip(stars, cameras, strict=True):
            if len(s):
                axis = cam.mounting.as_matrix()[2]
                reach = math.acos(min(float((body[first : first + len(s)] @ axis).min()), 1.0))
                axes.append(axis)
                chords.append(chord(max(reach + 2.0 * _GROW_MAX * max_radius, self.database.settings.fov_rad / 2.0)))
            first += len(s)
        return _Frame(body, radius, radius**2, max_radius, np.array(axes), np.array(chords))

    def _solve(self, frame: _Frame, stars: list[StarMeasurements]) -> np.ndarray | None:
        """The attitude (3, 3), inertial -> body, from the verified hypothesis of the first breadth-first step that
        has any, grown and refined (:meth:`_grow`); None if no step has one."""
        heads, first = [], 0
        for s in stars:  # per head, pooled rows of its brightest detections (brightest first) and their angles
            rows = first + np.argsort(-s.flux, kind="stable")[: self.max_pattern_stars]
            vectors = frame.body[rows]
            heads.append((rows, np.arccos(np.minimum(vectors @ vectors.T, 1.0))))
            first += len(s)
        for step, (edge_from, edge_to), last in self._quad_steps:
            quads, edges = [], []
            for rows, angles in heads:
                count = bisect.bisect_left(last, len(rows))  # the quads within this head's stars
                quads.append(rows[step[:count]])
                edges.append(angles[edge_from[:count], edge_to[:count]])
            quads, edges = np.concatenate(quads), np.concatenate(edges)
            if len(quads) == 0:
                return None
            hypothesis = self._best_hypothesis(frame, quads, edges)
            if hypothesis is not None:
                return self._grow(frame, *hypothesis)
        return None

    def _candidates(self, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(quad, catalogue star rows (k, 4) in the quad's star order) for the catalogue patterns matching quads of
        edges ``edges`` (q, 6)."""
        db = self.database
        settings, bins = db.settings, self._bins
        tolerance = settings.edge_tolerance_rad
        ordered = np.sort(edges, axis=1)
        largest = ordered[:, 5:]
        ratios = ordered[:, :5] / largest
        bounds = np.floor((ratios + _SIGNS * ((ratios + 1.0) * (tolerance / largest))) * bins)  # bins of ratio -+ tol
        low = np.maximum(bounds[0], 0.0)
        probed = _PROBES[(np.minimum(bounds[1], bins - 1.0) > low) @ _BITS]  # (q, 32) bin steps probed
        owner, step = (probed & (ordered[:, :1] >= settings.blend_rad)).nonzero()
        first, end = db.keys.searchsorted((low.astype(np.int64) @ self._digits)[owner] + self._probe_keys[:, step])
        count = end - first
        total = count.sum()
        if total == 0:
            return owner[:0], db.patterns[:0]
        pattern = (first - count.cumsum() + count).repeat(count) + np.arange(total)
        quad_of = owner.repeat(count)
        # The largest edge matches (which also keeps the quads to the database's range of largest edges) ...
        same_scale = (np.abs(db.largest_edge[pattern] - largest[quad_of, 0]) <= tolerance).nonzero()[0]
        quad_of, catalog_rows = quad_of[same_scale], db.patterns[pattern[same_scale]]
        # ... and then all six edges, under one of the 24 star orders.
        vectors = db.unit[catalog_rows]
        catalog_edges = np.arccos(np.minimum((vectors @ vectors.transpose(0, 2, 1))[:, EDGE_FROM, EDGE_TO], 1.0))
        miss = np.abs(catalog_edges[:, ORDER_EDGES] - edges[quad_of, None, :]).max(axis=2)  # (k, 24)
        close = (miss.min(axis=1) <= tolerance).nonzero()[0]
        return quad_of[close], catalog_rows[close[:, None], STAR_ORDERS[miss[close].argmin(axis=1)]]

    def _best_hypothesis(self, frame: _Frame, quads: np.ndarray, edges: np.ndarray) -> tuple | None:
        """The verified hypothesis matching most detections among those of the quads (pooled rows (q, 4)) of edges
        ``edges`` (q, 6), or None; a hypothesis is (attitude (3, 3), the database stars about it (:meth:`_nearby`),
        its matched detections and their match rows)."""
        db = self.database
        quad_of, catalog_rows = self._candidates(edges)
        if len(quad_of) == 0:
            return None
        detections = quads[quad_of]  # (k, 4)
        pattern_body, catalog = frame.body[detections], db.unit[catalog_rows]
        attitudes = wahba_svd(pattern_body, catalog)
        miss = ((catalog @ attitudes.transpose(0, 2, 1) - pattern_body) ** 2).sum(axis=2)
        half_field = db.settings.fov_rad / 2.0
        area = math.pi * frame.max_radius**2 / (2.0 * math.pi * (1.0 - math.cos(half_field)))
        best, best_count = None, 0
        for attitude in attitudes[(miss <= frame.radius2[detections]).all(axis=1)]:
            if best is not None and np.vdot(attitude, best[0]) > 3.0 - _SAME_ATTITUDE_TRACE:
                continue  # the same solution from another pattern
            nearby = self._nearby(frame, attitude)
            star, squared = self._closest(frame, attitude, nearby)
            matched, rows = closest_per_star((squared <= frame.radius2).nonzero()[0], star, squared)
            m = len(matched)
            if m <= best_count:
                continue
            in_field = ((nearby[2] @ (frame.axes @ attitude).T) >= math.cos(half_field)).sum(axis=0).max()
            if m >= 3 and bdtrc(m - 3, len(frame.body), min(in_field * area, 1.0)) < self.match_threshold:
                best, best_count = (attitude, nearby, matched, rows), m
        return best

    def _grow(
        self, frame: _Frame, attitude: np.ndarray, nearby: tuple, matched: np.ndarray, rows: np.ndarray
    ) -> np.ndarray:
        """The attitude (3, 3), inertial -> body, refined on all matches of a verified hypothesis ``attitude``
        (``nearby``: the database stars about it, ``matched``, ``rows``: its matches).

        A hypothesis from one head's pattern leaves the roll about that head poorly known, which shifts the stars of
        other heads by more than the match radius; so matching alternates with refining the attitude, each detection
        searched within its match radius widened by 3 sigma of its predicted direction under the attitude's
        covariance (:meth:`_widened2`), until the matches stop changing.  The last matching uses the plain match
        radius.
        """
        body, unit = frame.body, self.database.match_unit
        for _ in range(_GROW_STEPS):
            attitude = wahba_svd(body[matched], unit[rows])
            nearby = self._nearby(frame, attitude, nearby)
            star, squared = self._closest(frame, attitude, nearby)
            within = squared <= frame.radius2
            final = closest_per_star(within.nonzero()[0], star, squared)
            grown = final
            if ((squared <= _GROW_MAX**2 * frame.radius2) > within).any():  # else no widened radius matters
                grown = closest_per_star((squared <= self._widened2(frame, matched)).nonzero()[0], star, squared)
            if same_matches(grown, (matched, rows)):
                break
            matched, rows = grown
        else:
            attitude = wahba_svd(body[matched], unit[rows])
            star, squared = self._closest(frame, attitude, self._nearby(frame, attitude, nearby))
            final = closest_per_star((squared <= frame.radius2).nonzero()[0], star, squared)
        return attitude if same_matches(final, (matched, rows)) else wahba_svd(body[final[0]], unit[final[1]])

    def _widened2(self, frame: _Frame, matched: np.ndarray) -> np.ndarray:
        """Squared search radii (n,): each detection's match radius widened by 3 sigma of its predicted direction
        under the covariance of an attitude fitted on the ``matched`` detections, up to ``_GROW_MAX`` match radii."""
        b = frame.body[matched]
        weight = (self.match_radius_px / self.centroid_noise_px) ** 2 / frame.radius2[matched]  # noise ** -2
        covariance = np.linalg.inv(weight.sum() * IDENTITY - (b.T * weight) @ b)  # rad^2, about body axes
        spread = covariance.trace() - ((frame.body @ covariance) * frame.body).sum(axis=1)
        return np.minimum(frame.radius2 + 9.0 * np.maximum(spread, 0.0), _GROW_MAX**2 * frame.radius2)

    def _nearby(self, frame: _Frame, attitude: np.ndarray, known: tuple | None = None) -> tuple:
        """(attitude, match rows, inertial unit vectors (s, 3)) of the database stars in ``frame``'s cones under
        ``attitude``; ``known`` itself if it was made for an attitude within ``_GROW_MAX`` match radii of this one,
        as it then holds every star a detection may be matched to."""
        if known is not None and np.vdot(known[0], attitude) >= 1.0 + 2.0 * math.cos(_GROW_MAX * frame.max_radius):
            return known  # trace(A B^T) = 1 + 2 cos(angle between A and B)
        found = self.database.tree.query_ball_point(frame.axes @ attitude, frame.chords, return_sorted=False)
        if len(found) == 1:
            rows = np.array(found[0], dtype=np.intp)
        else:  # the cones may overlap
            rows = np.unique(np.fromiter(itertools.chain.from_iterable(found), dtype=np.intp))
        return attitude, rows, self.database.match_unit[rows]

    def _closest(self, frame: _Frame, attitude: np.ndarray, nearby: tuple) -> tuple[np.ndarray, np.ndarray]:
        """Per detection, the nearest database star of ``nearby`` under ``attitude`` (match row) and the squared
        distance to it (inf when there is none)."""
        _, rows, unit = nearby
        if len(rows) == 0:
            return np.zeros(len(frame.body), dtype=np.intp), np.full(len(frame.body), np.inf)
        squared = 2.0 - 2.0 * (frame.body @ (attitude @ unit.T))  # (n, s) squared distances of unit vectors
        return rows[squared.argmin(axis=1)], squared.min(axis=1)
