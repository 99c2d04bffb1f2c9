"""The Tetra pattern database of the lost-in-space identifier (see :mod:`.lost_in_space` for the method): catalogue
patterns of four stars keyed by their quantised edge ratios, built from a sky lattice and cached on disk."""

from __future__ import annotations

import hashlib
import itertools
import math
from dataclasses import astuple, dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from starenv.agents.identify.geometry import chord, pattern_edges, resolvable
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog, cache_dir, load_npz_checked, save_npz_atomic

METHOD_VERSION = 2  # bump when the database layout or its construction changes
N_SIGMA = 3.0  # edge tolerance in standard deviations of an edge's angle
BLEND_PX = 8.0  # stars closer than this (px, coarsest head) are not used in patterns
PATTERN_STARS_PER_FIELD = 20.0  # default database depth: stars on average in the narrowest head's field
_MIN_EDGE_FRACTION = 0.25  # smallest largest-edge of a pattern, as a fraction of the field
_LATTICE_SPACING_FRACTION = 0.25  # spacing of the pattern-region centres, as a fraction of the field
_MAX_BINS = 1000  # ratio bins per dimension at most (keys stay within int64)
_TABLES = ("patterns", "keys", "largest_edge")  # the database arrays, in the order build_patterns returns them


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
    (rad), ascending within a key.  ``path`` is the cache file and ``from_cache`` says whether it was read from it
    rather than built.  ``match_rows`` are the stars detections are matched to (none within the merge separation of a
    brighter star) and ``match_unit`` their unit vectors.
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
    match_unit: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        rows = np.flatnonzero(resolvable(self.unit, self.magnitude, self.settings.merge_rad))
        object.__setattr__(self, "match_rows", rows)
        object.__setattr__(self, "match_unit", self.unit[rows])

    def __len__(self) -> int:
        return len(self.keys)


def _bins_to_keys(digits: np.ndarray, bins: int) -> np.ndarray:
    """Keys (int64) of the five bin numbers (..., 5) of patterns, read as digits base ``bins``."""
    return digits @ (np.int64(bins) ** np.arange(5, dtype=np.int64))


def pattern_keys(ratios: np.ndarray, bins: int) -> np.ndarray:
    """Keys (int64) of edge ratios (..., 5) in [0, 1], each quantised into ``bins`` bins."""
    return _bins_to_keys(np.clip(np.floor(ratios * bins).astype(np.int64), 0, bins - 1), bins)


def _usable_for_patterns(unit: np.ndarray, magnitude: np.ndarray, settings: DatabaseSettings) -> np.ndarray:
    """Rows of the stars that may join a pattern (no neighbour within the blend separation), brightest first."""
    close = cKDTree(unit).query_pairs(chord(settings.blend_rad), output_type="ndarray")
    usable = np.ones(len(unit), dtype=bool)
    usable[close.ravel()] = False
    rows = np.flatnonzero(usable)
    return rows[np.argsort(magnitude[rows], kind="stable")]


def build_patterns(unit: np.ndarray, magnitude: np.ndarray, settings: DatabaseSettings) -> tuple[np.ndarray, ...]:
    """Patterns (p, 4) int32 rows of ``unit``, their keys (p,) int64 and largest edges (p,) float32 rad, sorted by
    key and then largest edge; see the module docstring."""
    candidates = _usable_for_patterns(unit, magnitude, settings)
    per_region = settings.pattern_stars_per_region
    spacing = _LATTICE_SPACING_FRACTION * settings.fov_rad
    centres = _fibonacci_sphere(max(12, math.ceil(4.0 * math.pi / spacing**2)))
    near = cKDTree(centres).sparse_distance_matrix(
        cKDTree(unit[candidates]), chord(settings.fov_rad / 2.0), output_type="ndarray"
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
    edges = np.sort(pattern_edges(unit[quads]), axis=1)
    wide = edges[:, 5] >= settings.min_edge_rad
    quads, edges = quads[wide], edges[wide]
    keys = pattern_keys(edges[:, :5] / edges[:, 5:], settings.bins)
    largest = edges[:, 5].astype(np.float32)
    order = np.lexsort((largest, keys))
    return quads[order], keys[order], largest[order]


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
    stored = load_npz_checked(file)  # None unless intact: its contents match the hash stored with them
    try:
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
            and bool(np.all((keys[1:] > keys[:-1]) | (largest_edge[1:] >= largest_edge[:-1])))
        )
    except (TypeError, KeyError, ValueError):
        return None
    return (patterns, keys, largest_edge) if ok else None


def _write_database(file: Path, identity: str, tables: tuple[np.ndarray, ...]) -> None:
    """Store the database atomically; a failure to write only warns."""
    arrays = {"identity": np.str_(identity), **dict(zip(_TABLES, tables, strict=True))}
    save_npz_atomic(file, arrays, "pattern database")


def load_database(catalog: StarCatalog, settings: DatabaseSettings) -> PatternDatabase:
    """The pattern database of ``catalog``'s stars down to ``settings.mag_limit``, from disk or built (and stored).

    The cache file lives in ``starenv.sim.sky.cache_dir() / "identify"``, named by a hash of the method version, the
    catalogue (HIP numbers, positions, epoch) and ``settings``; an unreadable, truncated, altered (its content hash
    does not match) or foreign file is rebuilt.
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


def field_mag_limit(cameras: list[Camera], magnitudes: np.ndarray, stars_per_field: float = 10.0) -> float:
    """The brightest magnitude limit, in 0.25 mag steps up to the faintest of ``magnitudes`` (a full-sky catalog),
    that puts ``stars_per_field`` stars on average in the narrowest head's field: narrow fields need fainter stars."""
    area_sr = min(cam.fov[0] * cam.fov[1] for cam in cameras)  # small-field approximation
    faintest = float(np.max(magnitudes))
    for limit in np.arange(-1.0, faintest, 0.25):
        if np.count_nonzero(magnitudes <= limit) * area_sr / (4 * np.pi) >= stars_per_field:
            return float(limit)
    return faintest
