"""Lost-in-space star identification (:class:`LostInSpaceIdentifier`): 4-star pattern hashing (Tetra), no prior
attitude needed.

Method
    Brown & Stubis' Tetra (J. Brown and K. Stubis, "TETRA: Star Identification with Hash Tables", AIAA/USU Conference
    on Small Satellites, 2017), in the form of its successors tetra3 (ESA) and its fork cedar-solve: a pattern
    of four stars is described by the five smaller of its six pairwise angular distances divided by the largest (edge
    ratios, free of the plate scale), and each ratio is quantised into one of ``bins`` bins; the five bin numbers form
    the pattern's key.  The database holds the keys of catalogue patterns sorted (a key's patterns by largest edge),
    so a lookup is a binary search (the role of Tetra's open-addressing hash table).

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
    is solved for the attitude (SVD solution of Wahba's problem); when it matches fewer than half the detections, so
    are its stars three at a time, and the fit matching most detections stands for it (a pattern can hold a
    neighbour of one detected star in its place: its fit then turns about the pattern, the stars near it still
    match and the neighbour's id goes to the star's detection).  The attitude is verified as in tetra3/cedar-solve:
    with ``n`` detections in all heads, ``m`` of them within ``match_radius_px`` of a catalogue star (pattern stars
    included) and ``p`` the chance that a random detection lands that close to one (local catalogue density times
    the match area), the probability of a false match is ``P(X >= m - 2)`` for ``X ~ Binomial(n, p)``; hypotheses
    below ``match_threshold`` are verified (a frame's chance of accepting a wrong attitude is then at most the number
    of attitudes it tests, three-star fits included, times ``match_threshold``, by the union bound).  Of the verified
    hypotheses of the first breadth-first step that has any, the one matching most detections wins; when one head
    has four detections or more (the common case), the quads of the first two steps (15 quads) are looked up one at
    a time instead, in plain numbers (a few quads cost less so than as arrays, and the search stops at the first
    verified one), and the first verified one wins (two verified attitudes in one step would mean a false match).
    Matching and refining the attitude then alternate, the search widened by the attitude's uncertainty (a pattern in
    one small field leaves the roll about it loose, which moves the stars of the other heads); another head's matches
    join the fit, and its detections are labelled, only when the attitude fitted on the heads already confirmed predicts
    them within their match radius or they are too many for chance over the rolls searched
    (:func:`~starenv.agents.identify.verify.unconfirmed_heads`: one chance match would pin the roll to itself).  Then
    every detection within the labelling radius of a catalogue star is labelled (a detection with two catalogue stars
    within its radius or within ``CLAIM_SIGMAS`` centroid sigmas, or a star with two detections that close, is left
    unidentified, which one made it being a guess (a scatter measured on the frame's pairs widens the claim radius:
    :func:`~starenv.agents.identify.geometry.claim_scale2`); of two detections further apart the closest is the
    star's).  The labelling radius is the match radius, widened when the scatter of the matched detections about their
    stars (measured under the refined attitude, on 8 pairs or more) puts 4 standard deviations beyond it, up to 1.5
    match radii: with 1 px of noise per axis, the 3 px default alone would leave about 1 % of the stars unlabelled
    (``exp(-4.5)``).  Verifying, refining and labelling compare the detections with the labelling stars (the database's
    first) of a cone about each head's boresight, found once for all three, by brute force (both sets are small), rather
    than through a k-d tree query a detection; for one head the cone's stars are those listed for the sky cell of its
    boresight (the sky split into cells on a cube's faces, each listing the stars within a head's reach of any of its
    points; made by :meth:`reset`).  A cell also bounds the database stars within half a field of any of its points:
    verification tries ``p`` from that bound first and counts the stars only when it fails (the false-match probability
    grows with ``p``, so what passes with the bound passes with the count: the same hypotheses are verified).

    A star closer than ``MERGE_PX`` pixels to a brighter one is taken as part of it (the sensor sees one star):
    detections are matched to the brighter only.

The tracking identifier (:class:`~starenv.agents.identify.tracking.TrackingIdentifier`, which needs a prior
attitude) is a separate module and falls back on this one when its verification fails.

Ids are HIP numbers; -1 marks a detection left unidentified.
"""

from __future__ import annotations

import bisect
import itertools
import math
import operator
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.special import bdtrc

from starenv import checks
from starenv.agents.base import StarMeasurements
from starenv.agents.blocks import wahba_svd
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
    CLAIM_SIGMAS,
    EDGE_FROM,
    EDGE_TO,
    IDENTITY,
    MERGE_PX,
    ORDER_EDGES,
    STAR_ORDERS,
    chord,
    claim_scale2,
    closest_per_star,
    mask_pairs,
    resolvable,
    same_cameras,
    same_matches,
    sole_per_star,
    with_ids,
)
from starenv.agents.identify.verify import anchor_head, predicted_scatter, unconfirmed_heads
from starenv.sim.optics import Camera, NoDistortion
from starenv.sim.sky import StarCatalog

_SAME_ATTITUDE_TRACE = 1e-6  # 3 - trace(A B^T) below this (under 1 mrad apart): the same attitude
_GROW_STEPS = 4  # match-and-refine rounds after a hypothesis is accepted
_GROW_MAX = 10.0  # widest search in those rounds, in match radii
_LABEL_SIGMAS = 4.0  # the labelling radius holds this many centroid standard deviations (as measured) ...
_LABEL_MAX = 1.5  # ... up to this many match radii
_SCATTER_PAIRS = 8  # detections within the match radius needed to measure the scatter
_GRID_CELLS = 24  # sky cells along a cube face's side: the stars about a boresight are listed per cell
_GRID_MARGIN_PX = 2.0  # margin of the cell lists beyond the heads' corners (coarsest pixels)
_BIN_STEPS = (np.arange(32)[:, None] >> np.arange(5)) & 1  # (32, 5): step s probes the bin above for the set bits of s
_PROBES = np.all(_BIN_STEPS[None] <= _BIN_STEPS[:, None], axis=2)  # (32, 32): [w, s] step s within the bits w
_BITS = 1 << np.arange(5)  # bit of each ratio in a bin step
_THREE_OF_FOUR = [[k for k in range(4) if k != left_out] for left_out in range(4)]  # a quad less each star
_SIGNS = np.array([-1.0, 1.0])[:, None, None]
_ONES = np.ones(3)
_ORDER_GRAM = (4 * STAR_ORDERS[:, EDGE_FROM] + STAR_ORDERS[:, EDGE_TO]).T.copy()  # (6, 24) Gram entry of edge, order
_EDGE_PAIRS = list(zip(EDGE_FROM.tolist(), EDGE_TO.tolist(), strict=True))
_STAR_ORDER_LISTS = STAR_ORDERS.tolist()
_ORDER_OF_EDGES = {tuple(edges): order for order, edges in enumerate(ORDER_EDGES.tolist())}  # star order of an edge map
_PLAIN_STEPS = {  # per number of stars (4-6): the quads of the first two steps, and each as an index (1, 4)
    count: [(quad, np.array([quad])) for quad in itertools.combinations(range(min(count, 5)), 4)]
    + [(quad + (5,), np.array([quad + (5,)])) for quad in itertools.combinations(range(5), 3) if count == 6]
    for count in (4, 5, 6)
}


def _breadth_first_quads(count: int) -> list[np.ndarray]:
    """4-subsets of ``range(count)`` in steps: those within the 5 first, then those adding index 5, 6, ..."""
    first = np.array(list(itertools.combinations(range(min(count, 5)), 4)), dtype=np.intp).reshape(-1, 4)
    steps = [first]
    for last in range(5, count):
        others = np.array(list(itertools.combinations(range(last), 3)), dtype=np.intp)
        steps.append(np.column_stack([others, np.full(len(others), last)]))
    return steps


def _pinhole_rays(cam: Camera) -> np.ndarray:
    """The matrix (3, 3) taking undistorted pixel positions ``[x, y, 1]`` (rows) to camera-frame rays
    ``[(x - cx) / fx, (y - cy) / fy, 1]``."""
    return np.array([[1.0 / cam.fx, 0.0, 0.0], [0.0, 1.0 / cam.fy, 0.0], [-cam.cx / cam.fx, -cam.cy / cam.fy, 1.0]])


def _cube_cell(x: float, y: float, z: float) -> int:
    """The sky cell of a unit vector: the cube face its largest component points to, split into ``_GRID_CELLS`` by
    ``_GRID_CELLS`` cells along the other two components divided by that one (a gnomonic projection)."""
    n = _GRID_CELLS
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        face, largest, u, v = (0 if x > 0.0 else 1), ax, y, z
    elif ay >= az:
        face, largest, u, v = (2 if y > 0.0 else 3), ay, x, z
    else:
        face, largest, u, v = (4 if z > 0.0 else 5), az, x, y
    i = min(int((u / largest + 1.0) * (0.5 * n)), n - 1)
    j = min(int((v / largest + 1.0) * (0.5 * n)), n - 1)
    return (face * n + i) * n + j


def _sky_grid(tree: cKDTree, reach: float, first_rows: int, half_field: float) -> tuple[list, np.ndarray, list, list]:
    """Per sky cell (:func:`_cube_cell`), the rows of the stars of ``tree`` within ``reach`` (rad, at least
    ``half_field``) of any point of the cell, ascending: (offsets of each cell's rows (cells + 1,), the rows, per cell
    how many are below ``first_rows``, per cell at most how many of those lie within ``half_field`` of one of its
    points)."""
    n = _GRID_CELLS
    ticks = np.linspace(-1.0, 1.0, n + 1)
    u, v = np.meshgrid(ticks, ticks, indexing="ij")  # cell corners (n + 1, n + 1)
    centres, radii = [], []
    for face in range(6):
        sign = 1.0 if face % 2 == 0 else -1.0
        axis = face // 2
        corners = np.insert(np.stack([u, v], axis=-1), axis, sign, axis=-1)  # (n + 1, n + 1, 3)
        corners /= np.linalg.norm(corners, axis=-1, keepdims=True)
        centre = corners[:-1, :-1] + corners[1:, :-1] + corners[:-1, 1:] + corners[1:, 1:]
        centre /= np.linalg.norm(centre, axis=-1, keepdims=True)
        cosines = np.stack([np.sum(centre * corners[a : a + n, b : b + n], axis=-1) for a in (0, 1) for b in (0, 1)])
        centres.append(centre.reshape(-1, 3))
        radii.append(np.arccos(np.clip(cosines.min(axis=0), -1.0, 1.0)).ravel())
    centres, radii = np.concatenate(centres), np.concatenate(radii)
    found = tree.query_ball_point(centres, 2.0 * np.sin(np.minimum(reach + radii, math.pi) / 2.0), return_sorted=True)
    counts = np.array([len(rows) for rows in found])
    rows = np.fromiter(itertools.chain.from_iterable(found), dtype=np.intp, count=int(counts.sum()))
    offsets = np.concatenate([[0], np.cumsum(counts)])
    below = np.concatenate([[0], np.cumsum(rows < first_rows)])
    # Within half a field of a point of the cell: within that plus the cell's radius of its centre (a little more).
    cell = np.repeat(np.arange(len(counts)), counts)
    first = (rows < first_rows).nonzero()[0]
    cos_reach = np.cos(np.minimum(half_field + radii, math.pi))[cell[first]] - 1e-9
    near = np.einsum("ij,ij->i", tree.data[rows[first]], centres[cell[first]]) >= cos_reach
    in_field = np.bincount(cell[first[near]], minlength=len(counts))
    return offsets.tolist(), rows, (below[offsets[1:]] - below[offsets[:-1]]).tolist(), in_field.tolist()


def _split_rows(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A matrix (3, 3) applied to rows ``[x, y, 1]`` as ``[x, y] @ its first two rows + its third``."""
    return matrix[:2].copy(), matrix[2].copy()


class _Heads(NamedTuple):
    """Per-head constants of a list of cameras, made once for it: the cameras, their body -> camera matrices (None:
    the identity), for an undistorted head the matrix (3, 3) taking pixel positions ``[x, y, 1]`` (rows) to
    body-frame directions, split by :func:`_split_rows` (None: a head with distortion, which goes through
    :meth:`~starenv.sim.optics.Camera.unproject`), match radii (rad), body-frame boresights and, for one head, the
    constant part of its frames (:meth:`LostInSpaceIdentifier._frame_constants`)."""

    cameras: tuple
    mountings: tuple
    pinholes: tuple
    radius: tuple
    axes: tuple
    one: _Frame | None


class _Frame(NamedTuple):
    """The detections of one identification: pooled body-frame unit vectors (n, 3), their squared match radius (n,),
    the smallest dot product with a star within that radius (``cos_radius``) and within ``_GROW_MAX`` radii
    (``cos_grow``) (these three are numbers when all detections share one radius), the largest radius; per head with
    detections its boresight ``axes`` (h, 3) and the chord of a cone about it that holds every catalogue star a
    detection can be matched to while growing a hypothesis; ``area``: the largest match disc as a fraction of the
    database field, ``reuse``: the smallest trace(A B^T) of two attitudes whose cones are interchangeable
    (:meth:`LostInSpaceIdentifier._nearby`); ``head``: each detection's head (n,), None for one head."""

    body: np.ndarray
    radius2: float | np.ndarray
    cos_radius: float | np.ndarray
    cos_grow: float | np.ndarray
    max_radius: float
    axes: np.ndarray
    chords: list
    area: float
    reuse: float
    head: np.ndarray | None


class _Nearby(NamedTuple):
    """The labelling stars in a frame's cones under ``attitude``: their rows (s,), ascending, so that the database
    stars (the first ``n_db``) come first, their inertial unit vectors (s, 3), the cones' axes (h, 3), the stars'
    HIP numbers (s,) when at hand (None: ``rows`` give them) and, from the sky cell of one cone, at most how many
    database stars lie within half a field of its axis (None: not known)."""

    attitude: np.ndarray
    rows: np.ndarray
    unit: np.ndarray
    n_db: int
    centres: np.ndarray
    hip: np.ndarray | None = None
    in_field: int | None = None


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
        self._heads: _Heads | None = None

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
        pattern stars.  The labelling stars are held with the database's match stars first, in their order, so that
        one cone search serves verifying (the database stars) and labelling (all)."""
        settings = self.settings_for(cameras, catalog)
        self.database = db = load_database(catalog, settings)
        rows = np.flatnonzero(resolvable(catalog.unit, catalog.magnitude, settings.merge_rad))
        in_db = np.flatnonzero(catalog.magnitude <= settings.mag_limit)[db.match_rows]
        rows = np.concatenate([in_db, rows[~np.isin(rows, in_db)]])
        self._label_unit, self._label_hip, self._label_db = catalog.unit[rows], catalog.hip[rows], len(in_db)
        self._label_tree = cKDTree(self._label_unit)
        reach = max(
            max(cam.half_diagonal + 2.0 * _GROW_MAX * self.match_radius_px / min(cam.fx, cam.fy) for cam in cameras)
            + _GRID_MARGIN_PX * settings.merge_rad / MERGE_PX,
            settings.fov_rad / 2.0,
        )
        self._grid, self._grid_chord = None, chord(reach)
        if len(cameras) == 1:  # a single head's cone: the stars listed per sky cell, made here, not at the first frame
            offsets, listed, below, in_field = _sky_grid(self._label_tree, reach, self._label_db, settings.fov_rad / 2)
            self._grid = offsets, listed, self._label_unit[listed], self._label_hip[listed], below, in_field
        self._bins = settings.bins
        self._digits = np.int64(self._bins) ** np.arange(5, dtype=np.int64)  # key = bin numbers @ digits
        step_keys = _BIN_STEPS @ self._digits
        self._probe_keys = np.stack([step_keys, step_keys + 1])  # per bin step: its key offset and the next one
        self._cos_half_field = math.cos(settings.fov_rad / 2.0)
        self._mean_in_field = len(db.hip) * (1.0 - self._cos_half_field) / 2.0  # database stars in a field on average
        self._digit_list = self._digits.tolist()
        self._tolerance, self._blend_rad = settings.edge_tolerance_rad, settings.blend_rad
        extent = (float(db.largest_edge.min()), float(db.largest_edge.max())) if len(db) else (math.inf, -math.inf)
        self._largest_low, self._largest_high = extent[0] - self._tolerance, extent[1] + self._tolerance
        self._heads = None

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None = None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """Label all heads' detections with HIP numbers (-1: unidentified); ``prior`` and ``images`` are not used."""
        if self.database is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        if len(stars) != len(cameras):
            raise ValueError(f"stars must hold one StarMeasurements per camera ({len(cameras)}), got {len(stars)}")
        counts = [len(s) for s in stars]
        ids = np.empty(sum(counts), dtype=np.int64)
        ids.fill(-1)
        if max(counts, default=0) >= 4:
            frame = self._frame(stars, self._heads_of(cameras), counts)
            solved = self._solve(frame, stars, counts)
            if solved is not None:  # label each detection with exactly one star within its radius (one a star)
                _, nearby, dots = solved
                scalar = isinstance(frame.radius2, float)
                within = dots >= (frame.cos_radius if scalar else frame.cos_radius[:, None])
                count = int(np.count_nonzero(within))
                if count >= _SCATTER_PAIRS:  # the radius widened to the centroid scatter measured
                    if scalar:  # mean squared residual (chord^2 = 2 - 2 dot), in match radii squared, per axis
                        variance = (1.0 - float(np.vdot(dots, within)) / count) / frame.radius2
                    else:
                        detection, star = mask_pairs(within)
                        variance = float(((1.0 - dots[detection, star]) / frame.radius2[detection]).mean())
                    widen2 = min(_LABEL_SIGMAS**2 * variance, _LABEL_MAX**2)  # (in match radii)
                    if widen2 > 1.0:
                        within = dots >= 1.0 - (0.5 * widen2) * (frame.radius2 if scalar else frame.radius2[:, None])
                detection, star = mask_pairs(within)
                detections = detection.tolist()
                if len(set(detections)) < len(detections):  # some with two or more: left out
                    alone = np.bincount(detection, minlength=len(ids))[detection] == 1
                    detection, star = detection[alone], star[alone]
                # Each star's closest detection; a star with a second detection within the claim radius (CLAIM_SIGMAS
                # centroid sigmas, or claim_scale2 times the scatter measured on those closest pairs, in match radii
                # squared per axis) labels neither, and a detection with a second star that close is not labelled.
                dot = np.empty(len(ids))
                dot.fill(-np.inf)
                dot[detection] = dots[detection, star]
                star_of = np.zeros(len(ids), dtype=np.intp)
                star_of[detection] = star
                detection, star = closest_per_star(detection, star_of, -dot)
                radius2 = frame.radius2 if scalar else frame.radius2[detection]
                claim = CLAIM_SIGMAS**2 * (self.centroid_noise_px / self.match_radius_px) ** 2  # (match radii^2)
                if len(detection) >= _SCATTER_PAIRS:  # (a sum over the count: np.mean's bits, less its overhead)
                    claim = float(np.add.reduce((1.0 - dot[detection]) / radius2)) / len(detection)
                    claim *= claim_scale2(len(detection))
                claim2 = claim * (frame.radius2 if scalar else frame.radius2[:, None])
                detection, star = sole_per_star(detection, star_of, dots >= 1.0 - 0.5 * claim2)
                ids[detection] = (self._label_hip[nearby.rows] if nearby.hip is None else nearby.hip)[star]
        if len(stars) == 1:
            return [StarMeasurements(stars[0].xy.copy(), stars[0].flux.copy(), ids)]
        return with_ids(stars, ids)

    def _heads_of(self, cameras: list[Camera]) -> _Heads:
        """The per-head constants of ``cameras`` (kept for the last list of cameras seen; cameras are frozen)."""
        heads = self._heads
        if heads is not None and same_cameras(heads.cameras, cameras):
            return heads
        mountings = [cam.mounting.as_matrix() for cam in cameras]
        self._heads = heads = _Heads(
            cameras=tuple(cameras),
            mountings=tuple(None if np.array_equal(m, IDENTITY) else m for m in mountings),
            pinholes=tuple(
                _split_rows(_pinhole_rays(cam) @ m) if type(cam.distortion) is NoDistortion else None
                for cam, m in zip(cameras, mountings, strict=True)
            ),
            radius=tuple(self.match_radius_px / min(cam.fx, cam.fy) for cam in cameras),
            axes=tuple(m[2].copy() for m in mountings),
            one=None if len(cameras) != 1 else self._frame_constants(self.match_radius_px / min(cameras[0].fx,
                                                                                                  cameras[0].fy),
                                                                      mountings[0][2].copy()),
        )
        return heads

    def _frame_constants(self, radius: float, axis: np.ndarray) -> _Frame:
        """The frame of one head of match radius ``radius`` (rad) and boresight ``axis``, less its detections (``body``)
        and cone (``chords``)."""
        half_field = self.database.settings.fov_rad / 2.0
        return _Frame(
            body=np.zeros((0, 3)),
            radius2=radius**2,
            cos_radius=1.0 - 0.5 * radius**2,
            cos_grow=1.0 - (0.5 * _GROW_MAX**2) * radius**2,
            max_radius=radius,
            axes=axis[None],
            chords=[],
            area=radius**2 / (2.0 * (1.0 - math.cos(half_field))),
            reuse=1.0 + 2.0 * math.cos(_GROW_MAX * radius),
            head=None,
        )

    def _frame(self, stars: list[StarMeasurements], heads: _Heads, counts: list[int]) -> _Frame:
        """The detections of one call with their match radii and search cones (see :class:`_Frame`)."""
        vectors, reaches = [], []  # per head, its body vectors and the largest angle of one from its boresight
        for s, cam, mounting, pinhole, axis in zip(
            stars, heads.cameras, heads.mountings, heads.pinholes, heads.axes, strict=True
        ):
            xy = np.asarray(s.xy, dtype=np.float64).reshape(-1, 2)
            if not len(xy):
                reaches.append(0.0)
                vectors.append(np.zeros((0, 3)))
            elif pinhole is None:
                v = cam.unproject(xy) if mounting is None else cam.unproject(xy) @ mounting
                reaches.append(math.acos(min(float((v @ axis).min()), 1.0)))
                vectors.append(v)
            else:  # the pinhole's rays [(x - cx) / fx, (y - cy) / fy, 1], rotated into the body frame, normalised
                v = xy.dot(pinhole[0])  # (ndarray.dot: less overhead than @ on small arrays)
                v += pinhole[1]
                length = np.sqrt((v * v).dot(_ONES))
                v /= length[:, None]
                reaches.append(math.acos(min(1.0 / float(length.max()), 1.0)))  # cos(angle) = 1 / |ray|
                vectors.append(v)
        half_field = self.database.settings.fov_rad / 2.0
        if len(vectors) == 1:  # one head: its frame constants made once
            one = heads.one
            cone = chord(max(reaches[0] + 2.0 * _GROW_MAX * one.max_radius, half_field))
            return one._replace(body=vectors[0], chords=[cone])
        body = np.concatenate(vectors)
        radii = {r for r, count in zip(heads.radius, counts, strict=True) if count}
        max_radius = max(radii)
        if len(radii) == 1:  # one radius for all: a number
            radius2 = max_radius**2
        else:
            radius2 = np.repeat(np.square(heads.radius), counts)
        axes, chords = [], []
        for count, axis, reach in zip(counts, heads.axes, reaches, strict=True):
            if count:
                axes.append(axis)
                chords.append(chord(max(reach + 2.0 * _GROW_MAX * max_radius, half_field)))
        return _Frame(
            body=body,
            radius2=radius2,
            cos_radius=1.0 - 0.5 * radius2,
            cos_grow=1.0 - (0.5 * _GROW_MAX**2) * radius2,
            max_radius=max_radius,
            axes=np.array(axes),
            chords=chords,
            area=max_radius**2 / (2.0 * (1.0 - math.cos(half_field))),
            reuse=1.0 + 2.0 * math.cos(_GROW_MAX * max_radius),
            head=np.repeat(np.arange(len(counts)), counts),
        )

    def _solve(self, frame: _Frame, stars: list[StarMeasurements], counts: list[int]) -> tuple | None:
        """(attitude (3, 3) inertial -> body, the stars about it (:class:`_Nearby`), the dot products (n, s) of the
        detections with them) from the verified hypothesis of the first breadth-first step that has any, grown and
        refined (:meth:`_grow`); None if no step has one."""
        brightest, first = [], 0
        for s, count in zip(stars, counts, strict=True):  # per head, pooled rows of its brightest detections
            if count >= 4:  # (brightest first)
                order = (-s.flux).argsort(kind="stable")[: self.max_pattern_stars]
                brightest.append(order + first if first else order)
            first += count
        steps = self._quad_steps
        if len(brightest) == 1:  # one head: the quads of the first two steps one at a time, in plain numbers
            top = brightest[0][:6]
            vectors = frame.body[top]
            angles = np.arccos(np.minimum(vectors.dot(vectors.T), 1.0)).tolist()
            for quad, index in _PLAIN_STEPS[len(top)]:
                candidates = self._quad_candidates([angles[quad[i]][quad[j]] for i, j in _EDGE_PAIRS])
                if candidates:
                    hypothesis = self._best_hypothesis(frame, vectors[index], candidates, frame.radius2)
                    if hypothesis is not None:  # (a second verified attitude in the step would be a false match)
                        return self._grow(frame, *hypothesis)
            steps = steps[2:]
        heads = []
        for rows in brightest:  # their angles
            vectors = frame.body[rows]
            heads.append((rows, np.arccos(np.minimum(vectors @ vectors.T, 1.0))))
        for step, (edge_from, edge_to), last in steps:
            quads, edges = [], []
            for rows, angles in heads:
                count = bisect.bisect_left(last, len(rows))  # the quads within this head's stars
                if count:
                    quads.append(rows[step[:count]])
                    edges.append(angles[edge_from[:count], edge_to[:count]])
            if not quads:
                return None
            if len(quads) > 1:
                quads, edges = [np.concatenate(quads)], [np.concatenate(edges)]
            quad_of, catalog_rows = self._candidates(edges[0])
            detections = quads[0][quad_of]  # (k, 4)
            radius2 = frame.radius2 if isinstance(frame.radius2, float) else frame.radius2[detections]
            hypothesis = self._best_hypothesis(frame, frame.body[detections], catalog_rows, radius2)
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
        owner, step = mask_pairs(probed & (ordered[:, :1] >= settings.blend_rad))
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
        gram = (vectors @ vectors.transpose(0, 2, 1)).reshape(-1, 16)
        catalog_edges = np.arccos(np.minimum(gram, 1.0))[:, _ORDER_GRAM]  # (k, 6, 24): edge e under order o
        miss = np.abs(catalog_edges - edges[quad_of, :, None]).max(axis=1)  # (k, 24)
        close = (miss.min(axis=1) <= tolerance).nonzero()[0]
        return quad_of[close], catalog_rows[close[:, None], STAR_ORDERS[miss[close].argmin(axis=1)]]

    def _quad_candidates(self, edges: list) -> list:
        """:meth:`_candidates` of one quad of edges ``edges`` (six numbers, rad) in plain numbers: the catalogue star
        rows (4,) of each matching pattern, in the quad's star order."""
        db = self.database
        ordered = sorted(edges)
        largest = ordered[5]
        tolerance, bins = self._tolerance, self._bins
        if ordered[0] < self._blend_rad or not self._largest_low <= largest <= self._largest_high:
            return []  # no database pattern has such edges
        scale, floor, digits, top = tolerance / largest, math.floor, self._digit_list, bins - 1
        base, steps = 0, [0]
        for k in range(5):  # each ratio's bin, and the one above when ratio + tolerance reaches it
            ratio = ordered[k] / largest
            spread = (ratio + 1.0) * scale
            low = floor((ratio - spread) * bins)
            if low < 0:
                low = 0
            base += low * digits[k]
            if low < top and floor((ratio + spread) * bins) > low:
                steps += [step + digits[k] for step in steps]
        keys = [base + step for step in steps]
        bounds = db.keys.searchsorted(keys + [key + 1 for key in keys]).tolist()
        patterns = []  # those of these keys whose largest edge matches (a key's patterns are sorted by it)
        edge_of = memoryview(db.largest_edge)  # (its items are plain numbers; made here: a memoryview does not pickle)
        reach = tolerance + 4.0 * math.ulp(largest)  # (a window over the rounding, then checked)
        for first, end in zip(bounds[: len(keys)], bounds[len(keys) :], strict=True):
            if end > first:
                first = bisect.bisect_left(edge_of, largest - reach, first, end)
                end = bisect.bisect_right(edge_of, largest + reach, first, end)
                patterns += [p for p in range(first, end) if abs(edge_of[p] - largest) <= tolerance]
        if not patterns:
            return []
        # Any match keeps each edge within the tolerance of its catalogue edge, so the sorted edges too; and edges more
        # than two tolerances apart keep their order: then the match by rank is the only one.
        rank = None
        found = []
        stars = db.patterns[patterns]
        for rows, ((ax, ay, az), (bx, by, bz), (cx, cy, cz), (dx, dy, dz)) in zip(
            stars.tolist(), db.unit[stars].tolist(), strict=True
        ):
            catalog = [  # edges 01, 02, 03, 12, 13, 23
                math.acos(min(ax * bx + ay * by + az * bz, 1.0)),
                math.acos(min(ax * cx + ay * cy + az * cz, 1.0)),
                math.acos(min(ax * dx + ay * dy + az * dz, 1.0)),
                math.acos(min(bx * cx + by * cy + bz * cz, 1.0)),
                math.acos(min(bx * dx + by * dy + bz * dz, 1.0)),
                math.acos(min(cx * dx + cy * dy + cz * dz, 1.0)),
            ]
            if max(map(abs, map(operator.sub, sorted(catalog), ordered))) > tolerance:
                continue
            if rank is None:  # (the quad's rank of each edge, and whether its edges are apart)
                rank = [0] * 6
                for position, edge in enumerate(sorted(range(6), key=edges.__getitem__)):
                    rank[edge] = position
                separated = min(map(operator.sub, ordered[1:], ordered[:5])) > 2.0 * tolerance
            if separated:  # the miss of the match by rank is that of the sorted edges
                by_rank = sorted(range(6), key=catalog.__getitem__)
                best = _ORDER_OF_EDGES.get(tuple([by_rank[position] for position in rank]), -1)
            else:  # the star order of the smallest largest edge miss, the first of equals
                miss = np.abs(np.array(catalog)[ORDER_EDGES] - edges).max(axis=1)
                best = int(miss.argmin())
                if miss[best] > tolerance:
                    best = -1
            if best >= 0:
                found.append([rows[star] for star in _STAR_ORDER_LISTS[best]])
        return found

    def _best_hypothesis(self, frame: _Frame, pattern_body: np.ndarray, catalog_rows: np.ndarray | list,
                         radius2: float | np.ndarray) -> tuple | None:
        """The verified hypothesis matching most detections among the candidates: quads of detections of body vectors
        ``pattern_body`` (k, 4, 3, or 1, 4, 3: one quad) matched by the catalogue stars ``catalog_rows`` (k, 4),
        their squared match radii ``radius2``; or None.  A hypothesis is (attitude (3, 3), the stars about it
        (:meth:`_nearby`), its matched detections and their labelling rows)."""
        if len(catalog_rows) == 0:
            return None
        catalog = self.database.unit[catalog_rows]
        if len(pattern_body) == 1 and isinstance(radius2, float):  # one quad: each candidate checked in plain numbers
            body, fits = pattern_body[0], []
            body_list = body.tolist()
            for inertial in catalog:
                attitude = wahba_svd(body, inertial)
                (a, b, c), (d, e, f), (g, h, i) = attitude.tolist()
                if all(  # every star within its match radius
                    (a * x + b * y + c * z - u) ** 2 + (d * x + e * y + f * z - v) ** 2
                    + (g * x + h * y + i * z - w) ** 2 <= radius2
                    for (x, y, z), (u, v, w) in zip(inertial.tolist(), body_list, strict=True)
                ):
                    fits.append((attitude, body, inertial))
        else:
            attitudes = wahba_svd(pattern_body, catalog)
            miss = ((catalog @ attitudes.transpose(0, 2, 1) - pattern_body) ** 2).sum(axis=2)
            fits = [(attitudes[k], pattern_body[k], catalog[k]) for k in (miss <= radius2).all(axis=1).nonzero()[0]]
        best, best_count = None, 0
        n, area, threshold = len(frame.body), frame.area, self.match_threshold
        for attitude, body, inertial in fits:
            if best is not None and np.vdot(attitude, best[0]) > 3.0 - _SAME_ATTITUDE_TRACE:
                continue  # the same solution from another pattern
            nearby = self._nearby(frame, attitude)
            _, star, dot = self._closest(frame, attitude, nearby)
            matched, rows = closest_per_star((dot >= frame.cos_radius).nonzero()[0], star, -dot)
            if 2 * len(matched) < n:  # few matches: perhaps a pattern with one wrong star (see _three_star_fit)
                attitude, nearby, matched, rows = self._three_star_fit(frame, body, inertial,
                                                                       (attitude, nearby, matched, rows))
            m = len(matched)
            if m <= best_count or m < 3:
                continue
            # Database stars in the field about each boresight, at most: the sky cell's bound first (the chance of a
            # false match grows with it, so what passes with it passes with the count), then the count.
            in_field = nearby.in_field
            if in_field is None or bdtrc(m - 3, n, min(in_field * area, 1.0)) >= threshold:
                db_unit, cos_half_field = nearby.unit[: nearby.n_db], self._cos_half_field
                if len(nearby.centres) == 1:
                    in_field = np.count_nonzero(db_unit @ nearby.centres[0] >= cos_half_field)
                else:
                    in_field = ((db_unit @ nearby.centres.T) >= cos_half_field).sum(axis=0).max()
                if bdtrc(m - 3, n, min(in_field * area, 1.0)) >= threshold:
                    continue
            best, best_count = (attitude, nearby, matched, rows), m
        return best

    def _three_star_fit(self, frame: _Frame, body: np.ndarray, inertial: np.ndarray, fit: tuple) -> tuple:
        """Of a pattern's fit ``fit`` (attitude (3, 3), the stars about it, its matched detections and their labelling
        rows) and the fits of its stars three at a time (body vectors ``body`` (4, 3) matched to the catalogue
        directions ``inertial`` (4, 3)), the one matching most detections (the first of equals).

        A database pattern can hold, in place of one of the detected stars, a neighbour of it whose edges to the
        other three differ from the right star's by less than the tolerance.  Its fit then turns about the pattern to
        share the wrong star's offset among all four: the stars near the pattern still match (and can verify it), the
        rest of the field does not, and the wrong star takes the neighbour's id.  Without it, the three right stars
        give the attitude."""
        best = fit
        for left_out in range(4):
            keep = _THREE_OF_FOUR[left_out]
            attitude = wahba_svd(body[keep], inertial[keep])
            nearby = self._nearby(frame, attitude, best[1])
            _, star, dot = self._closest(frame, attitude, nearby)
            matched, rows = closest_per_star((dot >= frame.cos_radius).nonzero()[0], star, -dot)
            if len(matched) > len(best[2]):
                best = attitude, nearby, matched, rows
        return best

    def _grow(self, frame: _Frame, attitude: np.ndarray, nearby: _Nearby, matched: np.ndarray,
              rows: np.ndarray) -> tuple:
        """(attitude (3, 3) inertial -> body, the stars about it, the dot products (n, s) of the detections with them),
        the attitude refined on all matches of a verified hypothesis ``attitude`` (``nearby``: the stars about it,
        ``matched``, ``rows``: its matches).

        A hypothesis from one head's pattern leaves the roll about that head poorly known, which shifts the stars of
        other heads by more than the match radius; so matching alternates with refining the attitude, each detection
        searched within its match radius widened by 3 sigma of its predicted direction under the attitude's
        covariance (:meth:`_widened`), until the matches stop changing.  The last matching uses the plain match
        radius.  With several heads, the matches of a head other than the anchor (:func:`anchor_head`: most matches,
        three or more) enter the first fit, and the last, only when :meth:`_unconfirmed_heads` does not hold them
        back: a far head's match under the loose roll can be a chance one, and in the fit it would pin the roll to
        itself, shrink the head's predicted scatter and keep its own stars out of the widened search.  The detections
        of a head held back at the end are not labelled.  A round whose fit keeps fewer than half the plain matches
        of the round before (widened matches that were chance ones) is undone, and growing stops.
        """
        body, unit = frame.body, self._label_unit
        anchor = None if frame.head is None else anchor_head(frame.head, matched)
        if anchor is not None:
            heads = frame.head[matched]
            if np.any(heads != anchor):  # (matches in other heads to confirm)
                doubtful = self._unconfirmed_heads(frame, anchor, matched, nearby)
                if doubtful:
                    keep = ~np.isin(heads, doubtful)
                    matched, rows = matched[keep], rows[keep]
        last, changed = None, True  # (changed: the last matching may differ from the matches fitted)
        for step in range(_GROW_STEPS + 1):  # (the last round matches in the plain radius only)
            attitude = wahba_svd(body[matched], unit[rows])
            nearby = self._nearby(frame, attitude, nearby)
            dots, star, dot = self._closest(frame, attitude, nearby)
            within = dot >= frame.cos_radius
            final = closest_per_star(within.nonzero()[0], star, -dot)
            if last is not None and 2 * len(final[0]) < len(last[3][0]):  # the widened matches broke the fit
                attitude, nearby, dots, final = last
                break
            last = attitude, nearby, dots, final
            if step == _GROW_STEPS:
                break
            grown = final
            band = ((dot >= frame.cos_grow) > within).nonzero()[0]  # only these may gain from a widened radius
            if len(band):
                widened = self._widened(frame, matched, band, dot)
                if len(widened):
                    within[widened] = True
                    grown = closest_per_star(within.nonzero()[0], star, -dot)
            if same_matches(grown, (matched, rows)):
                changed = grown is not final
                break
            matched, rows = grown
        refit = changed and not same_matches(final, (matched, rows))  # (else the attitude is fitted on them)
        dropped = [] if anchor is None else self._unconfirmed_heads(frame, anchor, final[0], nearby)
        if dropped:
            keep = ~np.isin(frame.head[final[0]], dropped)
            final, refit = (final[0][keep], final[1][keep]), True
        if refit:
            attitude = wahba_svd(body[final[0]], unit[final[1]])
            nearby = self._nearby(frame, attitude, nearby)
            dots = body.dot(attitude.dot(nearby.unit.T))
        if dropped:
            dots[np.isin(frame.head, dropped)] = -1.0  # (no star within any radius: left unlabelled)
        return attitude, nearby, dots

    def _widened(self, frame: _Frame, matched: np.ndarray, band: np.ndarray, dot: np.ndarray) -> list:
        """The detections of ``band`` (beyond their match radius, within ``_GROW_MAX`` radii of a star at dot product
        ``dot``) within their match radius widened by 3 sigma of their predicted direction under the covariance of an
        attitude fitted on the ``matched`` detections."""
        cos_radius, scalar = frame.cos_radius, isinstance(frame.cos_radius, float)
        scatter = predicted_scatter(frame.body[matched], self._weight(frame, matched), frame.body[band])
        return [
            row
            for row, near, variance in zip(band.tolist(), dot[band].tolist(), scatter, strict=True)
            if near >= (cos_radius if scalar else cos_radius[row]) - 4.5 * variance
        ]

    def _weight(self, frame: _Frame, rows: np.ndarray | None = None) -> float | np.ndarray:
        """The inverse centroid variance (rad^-2 per axis) of ``frame``'s detections ``rows`` (all: None): a number
        when all share one radius."""
        scale = (self.match_radius_px / self.centroid_noise_px) ** 2  # (match radii per centroid sigma) squared
        if isinstance(frame.radius2, float):
            return scale / frame.radius2
        return scale / (frame.radius2 if rows is None else frame.radius2[rows])

    def _unconfirmed_heads(self, frame: _Frame, anchor: int, matched: np.ndarray, nearby: _Nearby) -> list:
        """:func:`~starenv.agents.identify.verify.unconfirmed_heads` of ``matched``, ``p`` per head as in the
        verification from the database stars within half a field of its boresight or, when fewer, from the sky's
        mean (a sparse head's count is too small a sample to bound ``p`` by)."""
        heads = np.unique(frame.head)
        in_field = np.maximum(
            np.count_nonzero(nearby.unit[: nearby.n_db] @ nearby.centres.T >= self._cos_half_field, axis=0),
            self._mean_in_field,
        )
        chance = np.zeros(int(heads[-1]) + 1)
        chance[heads] = np.minimum(in_field * frame.area, 1.0)
        radius2 = np.zeros(len(chance))
        radius2[frame.head] = frame.radius2
        return unconfirmed_heads(frame.body, frame.head, matched, anchor, self._weight(frame), radius2, chance,
                                 self.match_threshold)

    def _nearby(self, frame: _Frame, attitude: np.ndarray, known: _Nearby | None = None) -> _Nearby:
        """The labelling stars in ``frame``'s cones under ``attitude``; ``known`` itself if it was made for an
        attitude within ``_GROW_MAX`` match radii of this one, as it then holds every star a detection may be matched
        to."""
        if known is not None and np.vdot(known.attitude, attitude) >= frame.reuse:
            return known  # trace(A B^T) = 1 + 2 cos(angle between A and B)
        centres = frame.axes.dot(attitude)
        if self._grid is not None and len(frame.chords) == 1 and frame.chords[0] <= self._grid_chord:
            offsets, listed, units, hips, below, in_field = self._grid  # the stars listed for the sky cell
            cell = _cube_cell(*centres[0].tolist())
            first, end = offsets[cell], offsets[cell + 1]
            return _Nearby(attitude, listed[first:end], units[first:end], below[cell], centres, hips[first:end],
                           in_field[cell])
        if len(frame.chords) == 1:
            found = self._label_tree.query_ball_point(centres[0], frame.chords[0], return_sorted=True)
            rows = np.array(found, dtype=np.intp)
        else:  # the cones may overlap
            found = self._label_tree.query_ball_point(centres, frame.chords, return_sorted=False)
            rows = np.unique(np.fromiter(itertools.chain.from_iterable(found), dtype=np.intp))
        return _Nearby(attitude, rows, self._label_unit[rows], int(rows.searchsorted(self._label_db)), centres)

    def _closest(self, frame: _Frame, attitude: np.ndarray, nearby: _Nearby) -> tuple:
        """The dot products (n, s) of the detections with ``nearby``'s stars under ``attitude``, and per detection the
        nearest database star (labelling row) and the dot product with it (-inf when there is none)."""
        dots = frame.body.dot(attitude.dot(nearby.unit.T))
        if nearby.n_db == 0:
            return dots, np.zeros(len(dots), dtype=np.intp), np.full(len(dots), -np.inf)
        best = dots[:, : nearby.n_db].argmax(axis=1)
        return dots, nearby.rows[best], dots[np.arange(len(dots)), best]
