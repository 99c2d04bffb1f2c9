"""Star identification: lost in space by 4-star pattern hashing (Tetra), and tracking from a prior attitude.

Lost in space (:class:`LostInSpaceIdentifier`)
    Brown & Stubis' Tetra (J. Brown and K. Stubis, "TETRA: Star Identification with Hash Tables", AIAA/USU Conference
    on Small Satellites, 2017), in the form of its successors tetra3 (ESA) and its fork cedar-solve: a pattern
    of four stars is described by the five smaller of its six pairwise angular distances divided by the largest (edge
    ratios, free of the plate scale), and each ratio is quantised into one of ``bins`` bins; the five bin numbers form
    the pattern's key.  The database holds the keys of catalogue patterns sorted, so a lookup is a binary search
    (the role of Tetra's open-addressing hash table).

    *Database.*  Stars are the catalogue's down to ``mag_limit``; a star with another one closer than
    ``_BLEND_PX`` pixels is never used in a pattern (the two would blend on the sensor).  Patterns come from tetra3's
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
    the closest).

Tracking (:class:`TrackingIdentifier`)
    With a prior attitude (inertial -> body), the catalogue stars near each head's boresight (a cone query) are
    rotated into the body frame and paired with the detections' body vectors within ``gate_px`` (an angle through
    each head's plate scale) by a Hungarian assignment on squared distance, so each star and each detection is used
    once; the attitude is refined from the pairs and the pairing repeated with ``refine_gate_px``.  With no prior, or
    fewer than ``min_matches`` stars paired, the fallback (lost in space by default) labels the frame.

    Both identifiers take a star closer than ``_MERGE_PX`` pixels to a brighter one as part of it (the sensor sees
    one star): detections are matched to the brighter only.

Ids are HIP numbers; -1 marks a detection left unidentified.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import math
import os
import tempfile
import warnings
import zipfile
from dataclasses import astuple, dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.special import bdtrc

from starenv import checks
from starenv.agents.base import Identifier, Stars
from starenv.optics import Camera
from starenv.sky import StarCatalog, cache_dir

METHOD_VERSION = 1  # bump when the database layout or its construction changes
_N_SIGMA = 3.0  # edge tolerance in standard deviations of an edge's angle
_BLEND_PX = 8.0  # stars closer than this (px, coarsest head) are not used in patterns
PATTERN_STARS_PER_FIELD = 20.0  # default database depth: stars on average in the narrowest head's field
_MERGE_PX = 2.0  # a star closer than this (px, coarsest head) to a brighter one is taken as part of it
_MIN_EDGE_FRACTION = 0.25  # smallest largest-edge of a pattern, as a fraction of the field
_LATTICE_SPACING_FRACTION = 0.25  # spacing of the pattern-region centres, as a fraction of the field
_SAME_ATTITUDE_TRACE = 1e-6  # 3 - trace(A B^T) below this (under 1 mrad apart): the same attitude
_GROW_STEPS = 4  # match-and-refine rounds after a hypothesis is accepted
_GROW_MAX = 10.0  # widest search in those rounds, in match radii
_MAX_BINS = 1000  # ratio bins per dimension at most (keys stay within int64)

_EDGE_FROM, _EDGE_TO = np.triu_indices(4, 1)  # the six edges of a pattern: 01, 02, 03, 12, 13, 23
_STAR_ORDERS = np.array(list(itertools.permutations(range(4))))  # (24, 4)
_TABLES = ("patterns", "keys", "largest_edge")  # the database arrays, in the order build_patterns returns them
_BIN_STEPS = np.array(list(itertools.product((0, 1), repeat=5)))  # (32, 5) lower bin or the one above, per ratio


def _chord(angle_rad: float) -> float:
    """Straight-line distance between two unit vectors ``angle_rad`` apart."""
    return 2.0 * math.sin(min(angle_rad, math.pi) / 2.0)


def _pattern_edges(vectors: np.ndarray) -> np.ndarray:
    """The six pairwise angles (rad), ordered 01, 02, 03, 12, 13, 23, of unit-vector quadruples (..., 4, 3)."""
    chord = np.linalg.norm(vectors[..., _EDGE_FROM, :] - vectors[..., _EDGE_TO, :], axis=-1)
    return 2.0 * np.arcsin(np.minimum(chord / 2.0, 1.0))


def _wahba(body: np.ndarray, inertial: np.ndarray) -> np.ndarray:
    """Attitude matrices (..., 3, 3), inertial -> body, minimising sum |b - A r|^2 over pairs (..., n, 3) (SVD)."""
    u, _, vt = np.linalg.svd(np.einsum("...ni,...nj->...ij", body, inertial))
    u[..., :, 2] *= (np.linalg.det(u) * np.linalg.det(vt))[..., None]
    return u @ vt


def _body_vectors(stars: list[Stars], cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Pooled detections of all heads (heads in order): body-frame unit vectors (n, 3) and the head of each (n,)."""
    if len(stars) != len(cameras):
        raise ValueError(f"stars must hold one Stars per camera ({len(cameras)}), got {len(stars)}")
    vectors = [cam.unproject(s.xy) @ cam.mounting.as_matrix() for s, cam in zip(stars, cameras, strict=True)]
    heads = np.repeat(np.arange(len(stars)), [len(s) for s in stars])
    return np.concatenate(vectors) if vectors else np.zeros((0, 3)), heads


def _labelled(stars: list[Stars], ids: np.ndarray) -> list[Stars]:
    """Copies of ``stars`` with catalogue ids from the pooled id array ``ids`` (heads in order)."""
    out, start = [], 0
    for s in stars:
        out.append(Stars(s.xy.copy(), s.flux.copy(), ids[start : start + len(s)].copy()))
        start += len(s)
    return out


def _fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` nearly evenly spread unit vectors (n, 3)."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    azimuth = math.pi * (3.0 - math.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)


@dataclass(frozen=True)
class DatabaseSettings:
    """What a pattern database depends on besides the catalogue: field (rad), magnitude limit, edge tolerance (rad),
    blend and merge separations (rad) and stars per region."""

    fov_rad: float
    mag_limit: float
    edge_tolerance_rad: float
    blend_rad: float
    merge_rad: float
    pattern_stars_per_region: int

    @property
    def min_edge_rad(self) -> float:
        """Smallest largest-edge of a pattern (rad)."""
        return _MIN_EDGE_FRACTION * self.fov_rad

    @property
    def bins(self) -> int:
        """Ratio bins per dimension: a bin is at least twice a ratio's tolerance, so a lookup probes <= 2 a ratio."""
        worst_ratio_tolerance = 2.0 * self.edge_tolerance_rad / self.min_edge_rad
        return int(np.clip(math.floor(1.0 / (2.0 * worst_ratio_tolerance)), 1, _MAX_BINS))


@dataclass(frozen=True, eq=False)
class PatternDatabase:
    """A Tetra pattern database: the stars (catalogue order, Hp <= mag_limit), their 4-star patterns and sorted keys.

    ``hip`` (n,), ``magnitude`` (n,) Hp and ``unit`` (n, 3) ICRS unit vectors of the stars; ``patterns`` (p, 4) rows
    into them, ``keys`` (p,) int64 sorted and ``largest_edge`` (p,) float32 the largest pairwise angle of each pattern
    (rad).  ``path`` is the cache file and ``from_cache`` says whether it was read from it rather than built.
    ``match_rows`` are the stars detections are matched to (none within the merge separation of a brighter star),
    ``tree`` their k-d tree.
    """

    settings: DatabaseSettings
    hip: np.ndarray
    magnitude: np.ndarray
    unit: np.ndarray
    patterns: np.ndarray
    keys: np.ndarray
    largest_edge: np.ndarray
    path: Path
    from_cache: bool
    match_rows: np.ndarray = field(init=False, repr=False)
    tree: cKDTree = field(init=False, repr=False)

    def __post_init__(self):
        rows = np.flatnonzero(resolvable(self.unit, self.magnitude, self.settings.merge_rad))
        object.__setattr__(self, "match_rows", rows)
        object.__setattr__(self, "tree", cKDTree(self.unit[rows]))

    def __len__(self) -> int:
        return len(self.keys)


def _bins_to_keys(digits: np.ndarray, bins: int) -> np.ndarray:
    """Keys (int64) of the five bin numbers (..., 5) of patterns, read as digits base ``bins``."""
    return digits @ (np.int64(bins) ** np.arange(5, dtype=np.int64))


def pattern_keys(ratios: np.ndarray, bins: int) -> np.ndarray:
    """Keys (int64) of edge ratios (..., 5) in [0, 1], each quantised into ``bins`` bins."""
    return _bins_to_keys(np.clip(np.floor(ratios * bins).astype(np.int64), 0, bins - 1), bins)


def resolvable(unit: np.ndarray, magnitude: np.ndarray, merge_rad: float) -> np.ndarray:
    """Mask (n,) of the stars with no brighter star (or equal one listed earlier) within ``merge_rad``: a sensor sees
    each pair closer than that as one star, the brighter."""
    pairs = cKDTree(unit).query_pairs(_chord(merge_rad), output_type="ndarray")
    a, b = pairs[:, 0], pairs[:, 1]
    fainter = np.where((magnitude[b] > magnitude[a]) | ((magnitude[b] == magnitude[a]) & (b > a)), b, a)
    keep = np.ones(len(unit), dtype=bool)
    keep[fainter] = False
    return keep


def _usable_for_patterns(unit: np.ndarray, magnitude: np.ndarray, settings: DatabaseSettings) -> np.ndarray:
    """Rows of the stars that may join a pattern (no neighbour within the blend separation), brightest first."""
    close = cKDTree(unit).query_pairs(_chord(settings.blend_rad), output_type="ndarray")
    usable = np.ones(len(unit), dtype=bool)
    usable[close.ravel()] = False
    rows = np.flatnonzero(usable)
    return rows[np.argsort(magnitude[rows], kind="stable")]


def build_patterns(unit: np.ndarray, magnitude: np.ndarray, settings: DatabaseSettings) -> tuple[np.ndarray, ...]:
    """Patterns (p, 4) int32 rows of ``unit``, their keys (p,) int64 and largest edges (p,) float32 rad, sorted by
    key; see the module docstring."""
    candidates = _usable_for_patterns(unit, magnitude, settings)
    per_region = settings.pattern_stars_per_region
    spacing = _LATTICE_SPACING_FRACTION * settings.fov_rad
    centres = _fibonacci_sphere(max(12, math.ceil(4.0 * math.pi / spacing**2)))
    near = cKDTree(centres).sparse_distance_matrix(
        cKDTree(unit[candidates]), _chord(settings.fov_rad / 2.0), output_type="ndarray"
    )
    # Group (centre, star) pairs by centre, brightest star first (candidates are sorted by brightness).
    order = np.lexsort((near["j"], near["i"]))
    centre, star = near["i"][order], near["j"][order]
    rank = np.arange(len(centre)) - np.searchsorted(centre, centre)
    kept = rank < per_region
    brightest = np.full((len(centres), per_region), -1, dtype=np.int32)
    brightest[centre[kept], rank[kept]] = candidates[star[kept]]
    quads = brightest[:, np.array(list(itertools.combinations(range(per_region), 4)))].reshape(-1, 4)
    quads = np.sort(quads[np.all(quads >= 0, axis=1)], axis=1)
    wide_quads = quads.astype(np.int64)
    high, low = wide_quads[:, 0] * len(unit) + wide_quads[:, 1], wide_quads[:, 2] * len(unit) + wide_quads[:, 3]
    order = np.lexsort((low, high))
    high, low, quads = high[order], low[order], quads[order]
    first = np.ones(len(quads), dtype=bool)
    first[1:] = (high[1:] != high[:-1]) | (low[1:] != low[:-1])
    quads = quads[first]
    edges = np.sort(_pattern_edges(unit[quads]), axis=1)
    wide = edges[:, 5] >= settings.min_edge_rad
    quads, edges = quads[wide], edges[wide]
    keys = pattern_keys(edges[:, :5] / edges[:, 5:], settings.bins)
    order = np.argsort(keys, kind="stable")
    return quads[order], keys[order], edges[order, 5].astype(np.float32)


def _database_file(settings: DatabaseSettings, hip: np.ndarray, unit: np.ndarray, epoch: float) -> tuple[Path, str]:
    """Cache file and identity string of the database for ``settings`` and these stars."""
    digest = hashlib.sha256()
    digest.update(repr((METHOD_VERSION, float(epoch), astuple(settings))).encode())
    digest.update(np.ascontiguousarray(hip, dtype=np.int64).tobytes())
    digest.update(np.ascontiguousarray(unit, dtype=np.float64).tobytes())
    identity = digest.hexdigest()
    return cache_dir() / "identify" / f"tetra-{identity[:24]}.npz", identity


def _read_database(file: Path, identity: str, n_stars: int) -> tuple[np.ndarray, ...] | None:
    """Patterns, keys and largest edges stored in ``file`` if it is readable, complete and for ``identity``; else
    None."""
    try:
        with np.load(file, allow_pickle=False) as stored:
            patterns, keys, largest_edge = (stored[name] for name in _TABLES)
            ok = (
                str(stored["identity"]) == identity
                and patterns.dtype == np.int32
                and keys.dtype == np.int64
                and largest_edge.dtype == np.float32
                and patterns.shape == (len(keys), 4)
                and largest_edge.shape == keys.shape
                and (len(keys) == 0 or (patterns.min() >= 0 and patterns.max() < n_stars))
                and bool(np.all(keys[1:] >= keys[:-1]))
            )
            return (patterns, keys, largest_edge) if ok else None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def _write_database(file: Path, identity: str, tables: tuple[np.ndarray, ...]) -> None:
    """Store the database atomically (temporary file, then ``os.replace``); a failure to write only warns."""
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(prefix=file.name + ".", suffix=".tmp", dir=file.parent)
        try:
            with os.fdopen(handle, "wb") as out:
                np.savez(out, identity=np.str_(identity), **dict(zip(_TABLES, tables, strict=True)))
            os.replace(temporary, file)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(temporary)
            raise
    except OSError as exc:
        warnings.warn(f"could not write the pattern database cache {file}: {exc}", RuntimeWarning, stacklevel=3)


def load_database(catalog: StarCatalog, settings: DatabaseSettings) -> PatternDatabase:
    """The pattern database of ``catalog``'s stars down to ``settings.mag_limit``, from disk or built (and stored).

    The cache file lives in ``starenv.sky.cache_dir() / "identify"``, named by a hash of the method version, the
    catalogue (HIP numbers, positions, epoch) and ``settings``; an unreadable or foreign file is rebuilt.
    """
    bright = catalog.magnitude <= settings.mag_limit
    hip, unit = catalog.hip[bright], catalog.unit[bright]
    file, identity = _database_file(settings, hip, unit, catalog.epoch)
    tables = _read_database(file, identity, len(hip))
    from_cache = tables is not None
    if not from_cache:
        tables = build_patterns(unit, catalog.magnitude[bright], settings)
        _write_database(file, identity, tables)
    return PatternDatabase(settings, hip, catalog.magnitude[bright], unit, *tables, path=file, from_cache=from_cache)


def _breadth_first_quads(count: int) -> list[np.ndarray]:
    """4-subsets of ``range(count)`` in steps: those within the 5 first, then those adding index 5, 6, ..."""
    first = np.array(list(itertools.combinations(range(min(count, 5)), 4)), dtype=np.intp).reshape(-1, 4)
    steps = [first]
    for last in range(5, count):
        others = np.array(list(itertools.combinations(range(last), 3)), dtype=np.intp)
        steps.append(np.column_stack([others, np.full(len(others), last)]))
    return steps


def field_mag_limit(cameras: list[Camera], magnitudes: np.ndarray, stars_per_field: float = 10.0) -> float:
    """The brightest magnitude limit, in 0.25 mag steps up to the faintest of ``magnitudes`` (a full-sky catalog),
    that puts ``stars_per_field`` stars on average in the narrowest head's field: narrow fields need fainter stars."""
    area_sr = min(cam.fov[0] * cam.fov[1] for cam in cameras)  # small-field approximation
    faintest = float(np.max(magnitudes))
    for limit in np.arange(-1.0, faintest, 0.25):
        if np.count_nonzero(magnitudes <= limit) * area_sr / (4 * np.pi) >= stars_per_field:
            return float(limit)
    return faintest


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
        self._quad_steps = _breadth_first_quads(self.max_pattern_stars)
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
            edge_tolerance_rad=_N_SIGMA * math.sqrt(2.0) * self.centroid_noise_px * pixel_rad,
            blend_rad=_BLEND_PX * pixel_rad,
            merge_rad=_MERGE_PX * pixel_rad,
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

    def identify(self, stars: list[Stars], cameras: list[Camera], prior: Rotation | None = None) -> list[Stars]:
        """Label all heads' detections with HIP numbers (-1: unidentified); ``prior`` is not used."""
        if self.database is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        body, heads = _body_vectors(stars, cameras)
        ids = np.full(len(body), -1, dtype=np.int64)
        pixel_rad = np.array([1.0 / min(cam.fx, cam.fy) for cam in cameras])
        radius, noise = self.match_radius_px * pixel_rad[heads], self.centroid_noise_px * pixel_rad[heads]
        boresights = np.stack([cam.mounting.as_matrix()[2] for cam in cameras])[np.unique(heads)]
        first_rows = np.cumsum([0] + [len(s) for s in stars[:-1]])
        brightest = [  # per head, pooled rows of its brightest detections, brightest first
            first + np.argsort(-s.flux, kind="stable")[: self.max_pattern_stars]
            for s, first in zip(stars, first_rows, strict=True)
        ]
        for step in self._quad_steps:
            quads = np.concatenate([order[step[np.all(step < len(order), axis=1)]] for order in brightest])
            if len(quads) == 0:
                break
            attitude = self._best_hypothesis(body, quads, radius, boresights)
            if attitude is not None:
                matched, rows = self._grow(body, attitude, radius, noise)
                refined = _wahba(body[matched], self.database.unit[rows])
                labelled, stars_hit = _closest_pairs(self._label_tree, body @ refined, radius)
                ids[labelled] = self._label_hip[stars_hit]
                break
        return _labelled(stars, ids)

    def _grow(
        self, body: np.ndarray, attitude: np.ndarray, radius: np.ndarray, noise: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Matches (detections, catalogue rows) of a verified hypothesis ``attitude`` (3, 3), inertial -> body.

        A hypothesis from one head's pattern leaves the roll about that head poorly known, which shifts the stars of
        other heads by more than the match radius; so matching alternates with refining the attitude, each detection
        searched within its match radius widened by 3 sigma of its predicted direction under the attitude's
        covariance (``noise``: each detection's 1-sigma direction noise, rad), up to ``_GROW_MAX`` match radii, until
        the matches stop changing.  The last matching uses the plain match radius.
        """
        matched, rows = self._matches(body, attitude, radius)
        for _ in range(_GROW_STEPS):
            attitude = _wahba(body[matched], self.database.unit[rows])
            b, weight = body[matched], noise[matched] ** -2.0
            information = weight.sum() * np.eye(3) - np.einsum("n,ni,nj->ij", weight, b, b)
            covariance = np.linalg.inv(information)  # rad^2, about body axes
            spread = np.trace(covariance) - np.einsum("ni,ij,nj->n", body, covariance, body)
            widened = np.minimum(np.sqrt(radius**2 + 9.0 * np.maximum(spread, 0.0)), _GROW_MAX * radius)
            grown, grown_rows = self._matches(body, attitude, widened)
            if np.array_equal(grown, matched) and np.array_equal(grown_rows, rows):
                break
            matched, rows = grown, grown_rows
        return self._matches(body, _wahba(body[matched], self.database.unit[rows]), radius)

    def _candidates(self, quad_vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(quad, catalogue star rows (k, 4) in the quad's star order) for the catalogue patterns matching the quads."""
        db = self.database
        settings = db.settings
        tolerance = settings.edge_tolerance_rad
        edges = _pattern_edges(quad_vectors)  # (q, 6)
        ordered = np.sort(edges, axis=1)
        largest = ordered[:, 5]
        fits = (largest <= settings.fov_rad + tolerance) & (largest >= settings.min_edge_rad - tolerance)
        fits &= ordered[:, 0] >= settings.blend_rad
        quad_index = np.flatnonzero(fits)
        ratios = ordered[fits, :5] / largest[fits, None]
        ratio_tolerance = tolerance * (1.0 + ratios) / largest[fits, None]
        bins = settings.bins
        low = np.clip(np.floor((ratios - ratio_tolerance) * bins).astype(np.int64), 0, bins - 1)
        high = np.clip(np.floor((ratios + ratio_tolerance) * bins).astype(np.int64), 0, bins - 1)
        steps_ok = np.all(_BIN_STEPS[None] <= (high - low)[:, None, :], axis=2)  # (q, 32)
        keys = _bins_to_keys(low[:, None, :] + _BIN_STEPS[None], bins)
        owner, step = np.nonzero(steps_ok)
        keys = keys[owner, step]
        first = np.searchsorted(db.keys, keys, side="left")
        count = np.searchsorted(db.keys, keys, side="right") - first
        owner = np.repeat(owner, count)
        pattern = np.repeat(first - np.cumsum(count) + count, count) + np.arange(count.sum())
        quad_of = quad_index[owner]
        same_scale = np.abs(db.largest_edge[pattern] - largest[quad_of]) <= tolerance
        quad_of, catalog_rows = quad_of[same_scale], db.patterns[pattern[same_scale]]
        catalog_ordered = np.sort(_pattern_edges(db.unit[catalog_rows]), axis=1)
        same_edges = np.all(np.abs(catalog_ordered - ordered[quad_of]) <= tolerance, axis=1)
        quad_of, catalog_rows = quad_of[same_edges], catalog_rows[same_edges]
        orders = catalog_rows[:, _STAR_ORDERS]  # (k, 24, 4)
        miss = np.max(np.abs(_pattern_edges(db.unit[orders]) - edges[quad_of, None, :]), axis=2)  # (k, 24)
        best = np.argmin(miss, axis=1)
        close = miss[np.arange(len(best)), best] <= tolerance
        return quad_of[close], orders[close, best[close]]

    def _best_hypothesis(
        self, body: np.ndarray, quads: np.ndarray, radius: np.ndarray, boresights: np.ndarray
    ) -> np.ndarray | None:
        """The verified attitude (3, 3) matching most detections among the quads' hypotheses, or None."""
        db = self.database
        quad_of, catalog_rows = self._candidates(body[quads])
        if len(quad_of) == 0:
            return None
        pattern_body = body[quads[quad_of]]  # (k, 4, 3)
        attitudes = _wahba(pattern_body, db.unit[catalog_rows])
        predicted = np.einsum("kij,knj->kni", attitudes, db.unit[catalog_rows])
        fit = np.all(np.linalg.norm(predicted - pattern_body, axis=2) <= radius[quads[quad_of]], axis=1)
        best, best_count = None, 0
        field_radius = db.settings.fov_rad / 2.0
        cap = 2.0 * math.pi * (1.0 - math.cos(field_radius))
        for attitude in attitudes[fit]:
            if best is not None and np.trace(attitude @ best.T) > 3.0 - _SAME_ATTITUDE_TRACE:
                continue  # the same solution from another pattern
            matched, _ = self._matches(body, attitude, radius)
            m = len(matched)
            if m <= best_count:
                continue
            nearby = db.tree.query_ball_point(boresights @ attitude, _chord(field_radius), return_length=True)
            p_single = float(np.max(nearby)) / cap * math.pi * float(np.max(radius)) ** 2
            if m >= 3 and bdtrc(m - 3, len(body), min(p_single, 1.0)) < self.match_threshold:
                best, best_count = attitude, m
        return best

    def _matches(self, body: np.ndarray, attitude: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Detections (rows of ``body``) within ``radius`` of a database star under ``attitude``, and those stars'
        catalogue rows; each star keeps only its closest detection."""
        matched, nearest = _closest_pairs(self.database.tree, body @ attitude, radius)
        return matched, self.database.match_rows[nearest]


def _closest_pairs(tree: cKDTree, directions: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``directions`` (inertial unit vectors) within ``radius`` (rad, per row) of a point of ``tree``, and
    those points' indices; a point paired with several rows keeps only the closest."""
    distance, nearest = tree.query(directions, distance_upper_bound=float(np.max(radius)))
    matched = np.flatnonzero(distance <= radius)
    matched = matched[np.argsort(distance[matched], kind="stable")]
    _, first = np.unique(nearest[matched], return_index=True)
    matched = np.sort(matched[first])
    return matched, nearest[matched]


class TrackingIdentifier:
    """Identification from a prior attitude by gated nearest-star pairing; lost in space when that fails.

    ``gate_px`` is the first pairing radius, ``refine_gate_px`` the radius after refining the attitude on the first
    pairs (both converted to angles with each head's plate scale); fewer than ``min_matches`` pairs (or no prior)
    hands the frame to ``fallback`` (default :class:`LostInSpaceIdentifier` with its defaults).  The stars are all
    those of the catalogue given to :meth:`reset` but the fainter of pairs closer than ``_MERGE_PX`` pixels.
    """

    def __init__(
        self,
        fallback: Identifier | None = None,
        gate_px: float = 5.0,
        refine_gate_px: float = 2.0,
        min_matches: int = 3,
    ):
        if fallback is not None and not isinstance(fallback, Identifier):
            raise ValueError(f"fallback must implement the Identifier protocol, got {type(fallback).__name__}")
        self.fallback = LostInSpaceIdentifier() if fallback is None else fallback
        self.gate_px = checks.in_range("gate_px", gate_px, 0.0, 1000.0, low_open=True, unit="px")
        self.refine_gate_px = checks.in_range(
            "refine_gate_px", refine_gate_px, 0.0, self.gate_px, low_open=True, unit="px"
        )
        self.min_matches = checks.integer("min_matches", min_matches, 3, 1000)
        self.catalog: StarCatalog | None = None

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        """Index the catalogue's resolvable stars for these heads and reset the fallback."""
        if not cameras:
            raise ValueError("cameras must hold at least one Camera")
        merge_rad = _MERGE_PX * max(1.0 / min(cam.fx, cam.fy) for cam in cameras)
        self._rows = np.flatnonzero(resolvable(catalog.unit, catalog.magnitude, merge_rad))
        self._tree = cKDTree(catalog.unit[self._rows])
        self.catalog = catalog
        self.fallback.reset(cameras, catalog)

    def identify(self, stars: list[Stars], cameras: list[Camera], prior: Rotation | None) -> list[Stars]:
        """Label all heads' detections with HIP numbers (-1: unidentified), tracking from ``prior`` if it is given."""
        if self.catalog is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        body, heads = _body_vectors(stars, cameras)
        if prior is not None and len(body) >= self.min_matches:
            pixel_rad = np.array([1.0 / min(cam.fx, cam.fy) for cam in cameras])[heads]
            attitude = prior.as_matrix()
            rows = self._in_view(cameras, attitude)
            detections, matched_rows = self._pairs(body, rows, attitude, self.gate_px * pixel_rad)
            if len(detections) >= self.min_matches:
                attitude = _wahba(body[detections], self.catalog.unit[matched_rows])
                detections, matched_rows = self._pairs(body, rows, attitude, self.refine_gate_px * pixel_rad)
                if len(detections) >= self.min_matches:
                    ids = np.full(len(body), -1, dtype=np.int64)
                    ids[detections] = self.catalog.hip[matched_rows]
                    return _labelled(stars, ids)
        return self.fallback.identify(stars, cameras, prior)

    def _in_view(self, cameras: list[Camera], attitude: np.ndarray) -> np.ndarray:
        """Catalogue rows of the resolvable stars within each head's half diagonal plus the gate of its boresight
        under ``attitude`` (3, 3), inertial -> body (a cone query per head)."""
        boresights = np.stack([cam.mounting.as_matrix()[2] @ attitude for cam in cameras])
        reach = [_chord(cam.half_diagonal + 2.0 * self.gate_px / min(cam.fx, cam.fy)) for cam in cameras]
        found = self._tree.query_ball_point(boresights, reach)
        return self._rows[np.unique(np.concatenate([np.asarray(f, dtype=np.intp) for f in found]))]

    def _pairs(
        self, body: np.ndarray, rows: np.ndarray, attitude: np.ndarray, gate_rad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Detections (rows of ``body``) and catalogue rows (from ``rows``) paired under ``attitude`` (3, 3): each
        detection within its ``gate_rad`` of a star, one to one, least total squared distance."""
        predicted = self.catalog.unit[rows] @ attitude.T  # body frame
        squared = np.maximum(2.0 - 2.0 * (body @ predicted.T), 0.0)  # squared chord, = squared angle here
        gated = squared <= gate_rad[:, None] ** 2
        near_detections, near_stars = np.flatnonzero(gated.any(axis=1)), np.flatnonzero(gated.any(axis=0))
        near = np.ix_(near_detections, near_stars)
        gated, squared = gated[near], squared[near]
        # Pairs outside the gate cost more than any set of gated pairs: the most pairs win, then the closest.
        outside = (min(gated.shape) + 1) * float(np.max(gate_rad)) ** 2
        detection, star = linear_sum_assignment(np.where(gated, squared, outside))
        inside = gated[detection, star]
        return near_detections[detection[inside]], rows[near_stars[star[inside]]]
