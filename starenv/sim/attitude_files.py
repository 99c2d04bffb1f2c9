"""Attitude and gyro histories from files: a mission's attitude ephemeris as a motion, a flight gyro log replayed.

Attitude files (:func:`read_attitude`)
    * a CCSDS Attitude Ephemeris Message (CCSDS 504.0-B, AEM), KVN or XML, read through the ``ccsds-ndm`` library
      (the ``aem`` extra): AEM 1.0 in both forms, AEM 2.0 in XML (the library does not read 2.0 KVN back).  Quaternion
      segments only (``ATTITUDE_TYPE = QUATERNION``), between an inertial frame (``ICRF``, ``EME2000``, ``GCRF``:
      taken as ICRS, their sub-arcsecond frame offsets ignored) and the body frame (any other name).  A CCSDS
      quaternion is the rotation from its first frame to its second (``QC = cos(angle / 2)``), so the attitude
      (ICRS -> body, scipy's active convention) is its inverse for ``ICRF -> body`` and itself for ``body -> ICRF``.
      Times are the file's time system's, taken as 86 400 s days (a leap second inside a UTC file is not counted);
      simulation time 0 is the first segment's ``USEABLE_START_TIME`` (or its first record) plus ``start_s``.
      Segments must meet: a segment's last record at the time of the next one's first, with the same attitude.
    * a CSV with the header ``t, qx, qy, qz, qw``: simulation time (s) and the attitude ICRS -> body as a
      scalar-last quaternion (starenv's own ``[x, y, z, w]``, as ``info["truth"]["attitude"]``).

    Between samples the attitude is the geodesic (SLERP) between its neighbours, along the shorter arc (a sample's
    quaternion sign does not matter): a constant body rate over each interval (:class:`AttitudeHistory`), which the
    gyro model averages exactly (:meth:`AttitudeHistory.mean_body_rate`).  An AEM stating ``INTERPOLATION_METHOD =
    LAGRANGE`` with its ``INTERPOLATION_DEGREE`` is followed instead (:class:`LagrangeHistory`); ``HERMITE`` is
    refused by name (an attitude-only file gives it no derivatives), as is any other method.

Gyro logs (:func:`read_gyro_csv`)
    A CSV with the header ``t, wx, wy, wz``: each sample's time stamp (s, simulation time: the end of its interval)
    and the mean body rate over its interval (rad/s, body frame = gyro axes), sampled at one rate.

Every file is data: its numbers are read, nothing in it names code or another file, an XML form with a document type
declaration (entities) is refused, and sizes are bounded (:data:`MAX_FILE_BYTES`, :data:`MAX_RECORDS`).  A bad file
raises ``ValueError`` with one line naming ``file:line`` where a line is at fault: a non-number, NaN, a quaternion
whose norm is off 1 by more than :data:`UNIT_TOLERANCE`, time not increasing, a gap longer than the allowed step, a
time outside the file's span.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.files import csv_rows
from starenv.sim.gyro import GyroSamples
from starenv.sim.motion import Motion

MAX_FILE_BYTES = 2**28  # an attitude or gyro file's size: bounds parse time and memory
MAX_RECORDS = 2**23  # samples in one file
UNIT_TOLERANCE = 1e-6  # largest | |q| - 1 | of a file's quaternion (printed quaternions carry 7+ digits)
TIME_TOLERANCE_S = 1e-9  # how far past its ends a time may fall and still be taken at the end (float rounding)
INERTIAL_FRAMES = ("ICRF", "ICRF1", "ICRF2", "ICRF3", "EME2000", "GCRF", "J2000")
SLERP_METHODS = ("LINEAR", "SLERP")  # AEM interpolation methods read as SLERP (the geodesic between two samples)
MAX_LAGRANGE_DEGREE = 15  # INTERPOLATION_DEGREE of a LAGRANGE file (higher degrees ring between samples)
ATTITUDE_CSV_COLUMNS = ("t", "qx", "qy", "qz", "qw")
GYRO_CSV_COLUMNS = ("t", "wx", "wy", "wz")
GYRO_JITTER = 1e-3  # largest relative deviation of a gyro log's sample interval from its median
MAX_GYRO_RATE_RAD_S = math.radians(3600.0)  # a recorded rate's bound (the env's observation bound)


def _check_size(path: Path) -> None:
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ValueError(f"{path}: at most {MAX_FILE_BYTES} bytes expected, got {size}")


def _text(path: Path) -> str:
    _check_size(path)
    try:
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def _csv_rows(path: Path, columns: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The numbers of a CSV whose header names ``columns`` (in any order; ``#`` comments and blank lines skipped),
    as an (n, len(columns)) array in ``columns`` order, and each row's line number (1-based)."""
    rows, lines = [], []
    for line, fields in csv_rows(path, columns, max_bytes=MAX_FILE_BYTES):
        values = {}
        for name, text in fields.items():
            try:
                values[name] = float(text)
            except ValueError:
                raise ValueError(f"{path}:{line}: {name}: expected a number, got {text.strip()[:40]!r}") from None
            if not math.isfinite(values[name]):
                raise ValueError(f"{path}:{line}: {name}: expected a finite number, got {text.strip()[:40]!r}")
        rows.append([values[c] for c in columns])
        lines.append(line)
        if len(rows) > MAX_RECORDS:
            raise ValueError(f"{path}:{line}: at most {MAX_RECORDS} samples expected")
    if len(rows) < 2:
        raise ValueError(f"{path}: expected a header ({', '.join(columns)}) and at least two samples, got "
                         f"{len(rows)}")
    return np.array(rows, dtype=np.float64), np.array(lines)


def _check_times(path: Path, t: np.ndarray, lines: np.ndarray, max_step_s: float | None) -> None:
    """Time strictly increasing, and (``max_step_s``) no step longer than it, each fault naming its line."""
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0.0)
    if bad.size:
        k = bad[0] + 1
        raise ValueError(f"{path}:{lines[k]}: time {float(t[k])!r} does not increase (the previous sample, line "
                         f"{lines[k - 1]}, is at {float(t[k - 1])!r})")
    if max_step_s is not None:
        gaps = np.flatnonzero(steps > max_step_s)
        if gaps.size:
            k = gaps[0] + 1
            raise ValueError(f"{path}:{lines[k]}: a gap of {steps[k - 1]:.6g} s after the sample of line "
                             f"{lines[k - 1]} (at most max_step_s = {max_step_s:g} s between samples)")


def _check_unit(path: Path, quats: np.ndarray, lines: np.ndarray) -> None:
    norms = np.linalg.norm(quats, axis=1)
    bad = np.flatnonzero(~(np.abs(norms - 1.0) <= UNIT_TOLERANCE))
    if bad.size:
        k = bad[0]
        raise ValueError(f"{path}:{lines[k]}: a unit quaternion expected (| |q| - 1 | <= {UNIT_TOLERANCE:g}), got "
                         f"{quats[k].tolist()} of norm {norms[k]:.9g}")


@dataclass(frozen=True)
class AttitudeRecord:
    """An attitude history read from a file: sample times ``t`` (n,) s of simulation time, the attitudes ICRS ->
    body at them, and each sample's line in ``source``."""

    t: np.ndarray
    attitude: Rotation
    lines: np.ndarray
    source: str
    span: tuple[float, float] | None = None  # the times (s) it is valid over; None: its first to last sample
    lagrange_degree: int | None = None  # an AEM's INTERPOLATION_METHOD = LAGRANGE degree; None: SLERP


def read_attitude_csv(path: str | os.PathLike, max_step_s: float | None = None) -> AttitudeRecord:
    """An attitude CSV (``t, qx, qy, qz, qw``: s, ICRS -> body scalar-last) checked line by line."""
    path = Path(path)
    rows, lines = _csv_rows(path, ATTITUDE_CSV_COLUMNS)
    _check_unit(path, rows[:, 1:], lines)
    _check_times(path, rows[:, 0], lines, max_step_s)
    return AttitudeRecord(rows[:, 0], Rotation.from_quat(rows[:, 1:]), lines, str(path))


_ISO = re.compile(r"(\d{4})-(?:(\d{2})-(\d{2})|(\d{3}))T(\d{2}):(\d{2}):(\d{2}(?:\.\d*)?)Z?")


def parse_epoch(text: str) -> tuple[int, float]:
    """A CCSDS epoch ``YYYY-MM-DDThh:mm:ss[.s]`` or ``YYYY-DDDThh:mm:ss[.s]`` as (day number, seconds of the day);
    days of 86 400 s (a leap second ``:60`` is the next day's first second)."""
    match = _ISO.fullmatch(text.strip())
    if match is None:
        raise ValueError(f"expected an epoch YYYY-MM-DDThh:mm:ss or YYYY-DDDThh:mm:ss, got {text[:40]!r}")
    year, month, day, doy, hour, minute, second = match.groups()
    if doy is not None:
        days = int(np.datetime64(f"{year}-01-01", "D").astype(np.int64)) + int(doy) - 1
    else:
        try:
            days = int(np.datetime64(f"{year}-{month}-{day}", "D").astype(np.int64))
        except ValueError:
            raise ValueError(f"expected a calendar date, got {text[:40]!r}") from None
    return days, int(hour) * 3600.0 + int(minute) * 60.0 + float(second)


def format_epoch(unix_ns: int) -> str:
    """Unix time (ns) as a CCSDS epoch ``YYYY-MM-DDThh:mm:ss.sssssssss`` (to the nanosecond)."""
    seconds, ns = divmod(int(unix_ns), 10**9)
    return f"{np.datetime64(seconds, 's').astype(str)}.{ns:09d}"


def _ndm_io():
    try:
        from ccsds_ndm.ndm_io import NdmIo
    except ImportError:
        raise ModuleNotFoundError("reading or writing a CCSDS AEM needs the ccsds-ndm library: "
                                  "pip install 'starenv[aem]'") from None
    return NdmIo()


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300]


def _record_lines(text: str, epochs: list[str]) -> list[int]:
    """The line (1-based) of each record, found as the next line holding its epoch text (KVN or XML alike)."""
    lines = text.splitlines()
    found, at = [], 0
    for epoch in epochs:
        while at < len(lines) and not (lines[at].lstrip().startswith(epoch) or f"<EPOCH>{epoch}<" in lines[at]):
            at += 1
        found.append(at + 1 if at < len(lines) else 0)
        at += 1
    return found


def _value(x) -> str:
    """An enum or string metadata value as its upper-case text ('' for None)."""
    return "" if x is None else str(getattr(x, "value", x)).strip().upper()


def _check_kvn_data(path: Path, text: str) -> None:
    """Every data line of a KVN AEM (between DATA_START and DATA_STOP, comments aside) is an epoch and four
    numbers: the library would take a short line without a word, so each is checked here, naming its line."""
    inside = False
    for line, raw in enumerate(text.splitlines(), start=1):
        words = raw.split()
        if not words:
            continue
        if words[0] in ("DATA_START", "DATA_STOP"):
            inside = words[0] == "DATA_START"
        elif inside and words[0] != "COMMENT":
            try:
                ok = len(words) == 5 and all(math.isfinite(float(w)) for w in words[1:])
            except ValueError:
                ok = False
            if not ok:
                raise ValueError(f"{path}:{line}: an epoch and four finite quaternion numbers expected, got "
                                 f"{raw.strip()[:80]!r}")


def read_aem(path: str | os.PathLike, start_s: float = 0.0, max_step_s: float | None = None) -> AttitudeRecord:
    """A CCSDS AEM (KVN or XML) as an attitude history, simulation time 0 at its first usable time plus ``start_s``
    (s); see the module docstring for what is read and refused."""
    path = Path(path)
    text = _text(path)
    if re.search(r"<!(DOCTYPE|ENTITY)", text, re.IGNORECASE):
        raise ValueError(f"{path}: an XML document type declaration (entities) is not read: an AEM is data")
    kinds = {k.upper() for k in re.findall(r"^\s*ATTITUDE_TYPE\s*=\s*(\S+)", text, re.MULTILINE)}
    if not text.lstrip().startswith("<") and kinds <= {"QUATERNION"}:  # other kinds are refused by name below
        _check_kvn_data(path, text)
        if re.search(r"^\s*CCSDS_AEM_VERS\s*=\s*2", text, re.MULTILINE):
            raise ValueError(f"{path}: AEM 2.0 in KVN, which ccsds-ndm does not read back: give it as XML (or as AEM "
                             f"1.0 KVN)")
    try:
        aem = _ndm_io().from_string(text)
    except ModuleNotFoundError:
        raise
    except Exception as exc:  # noqa: BLE001  (the library raises many kinds; one line names the file)
        raise ValueError(f"{path}: not a CCSDS message ccsds-ndm reads: {type(exc).__name__}: "
                         f"{_one_line(exc)}") from None
    if type(aem).__name__ != "Aem":
        raise ValueError(f"{path}: expected a CCSDS AEM, got a {type(aem).__name__.upper()}")
    times, quats, epochs = [], [], []
    day0 = second0 = None
    lagrange_degree: int | None = None
    usable: list[float | None] = [None, None]
    previous_end = None
    segments = aem.body.segment
    for s, segment in enumerate(segments):
        meta, where = segment.metadata, f"{path}: segment {s + 1}"
        kind = _value(meta.attitude_type)
        if kind != "QUATERNION":
            raise ValueError(f"{where}: ATTITUDE_TYPE QUATERNION expected, got {kind or 'none'}")
        method = _value(meta.interpolation_method)
        if method and method not in SLERP_METHODS + ("LAGRANGE",):
            raise ValueError(f"{where}: INTERPOLATION_METHOD {method}: SLERP ({', '.join(SLERP_METHODS)}) or LAGRANGE "
                             f"interpolation is read (an attitude-only file gives Hermite no derivatives); resample "
                             f"the file or drop the keyword")
        degree = meta.interpolation_degree if method == "LAGRANGE" else None
        if method == "LAGRANGE" and not (isinstance(degree, int) and 1 <= degree <= MAX_LAGRANGE_DEGREE):
            raise ValueError(f"{where}: INTERPOLATION_DEGREE: an integer in [1, {MAX_LAGRANGE_DEGREE}] expected "
                             f"with LAGRANGE, got {degree!r}")
        if s and degree != lagrange_degree:
            raise ValueError(f"{where}: interpolation {method or 'SLERP'} {degree or ''}: every segment's expected "
                             f"to be the first one's")
        lagrange_degree = degree
        if hasattr(meta, "quaternion_type") and meta.quaternion_type is None:  # AEM 1.0: the scalar's place
            raise ValueError(f"{where}: QUATERNION_TYPE (FIRST or LAST) expected with quaternions, it is missing")
        frame_a, frame_b = _value(meta.ref_frame_a), _value(meta.ref_frame_b)
        direction = _value(getattr(meta, "attitude_dir", None)) or "A2B"
        first, second = (frame_a, frame_b) if direction == "A2B" else (frame_b, frame_a)
        if (first in INERTIAL_FRAMES) == (second in INERTIAL_FRAMES):
            raise ValueError(f"{where}: a rotation between an inertial frame ({', '.join(INERTIAL_FRAMES)}) and the "
                             f"body frame expected, got REF_FRAME_A {frame_a}, REF_FRAME_B {frame_b}")
        inverse = first in INERTIAL_FRAMES  # inertial -> body: the attitude is the quaternion's inverse
        seg_t, seg_q, seg_epochs = [], [], []
        for state in segment.data.attitude_state:
            record = getattr(state, "quaternion_state", None) or getattr(state, "quaternion_ephemeris", None)
            q = record.quaternion
            try:
                day, sec = parse_epoch(record.epoch)
            except ValueError as exc:
                row = _record_lines(text, [record.epoch])[0]
                raise ValueError(f"{path}:{row}: {exc}") from None
            if day0 is None:
                day0, second0 = day, sec
            seg_t.append((day - day0) * 86400.0 + (sec - second0))
            quat = np.array([q.q1, q.q2, q.q3, q.qc], dtype=np.float64)
            seg_q.append(quat * [-1.0, -1.0, -1.0, 1.0] if inverse else quat)
            seg_epochs.append(record.epoch)
        if not seg_t:
            raise ValueError(f"{where}: no attitude records")
        for i, key in ((0, "useable_start_time"), (1, "useable_stop_time")):
            value = getattr(meta, key, None)
            if value and (s == 0 if i == 0 else s == len(segments) - 1):
                day, sec = parse_epoch(value)
                usable[i] = (day - day0) * 86400.0 + (sec - second0)
        if previous_end is not None:
            end_t, end_q = previous_end
            row = _record_lines(text, seg_epochs[:1])[0]
            if seg_t[0] != end_t:
                raise ValueError(f"{path}:{row}: segment {s + 1} starts {seg_t[0] - end_t:.6g} s after the previous "
                                 f"one ends: a gap (segments must meet, the next starting at the previous one's end)")
            angle = (Rotation.from_quat(seg_q[0]) * Rotation.from_quat(end_q).inv()).magnitude()
            if angle > UNIT_TOLERANCE:
                raise ValueError(f"{path}:{row}: segment {s + 1} starts {math.degrees(angle):.6g} deg from where the "
                                 f"previous one ends: an attitude jump no gyro can follow")
            seg_t, seg_q, seg_epochs = seg_t[1:], seg_q[1:], seg_epochs[1:]
        previous_end = (seg_t[-1], seg_q[-1]) if seg_t else previous_end
        times += seg_t
        quats += seg_q
        epochs += seg_epochs
        if len(times) > MAX_RECORDS:
            raise ValueError(f"{path}: at most {MAX_RECORDS} attitude records expected")
    lines = np.array(_record_lines(text, epochs))
    t = np.array(times)
    quats_arr = np.array(quats, dtype=np.float64).reshape(-1, 4)
    if not np.all(np.isfinite(quats_arr)):
        k = int(np.flatnonzero(~np.all(np.isfinite(quats_arr), axis=1))[0])
        raise ValueError(f"{path}:{lines[k]}: a finite quaternion expected, got {quats_arr[k].tolist()}")
    _check_unit(path, quats_arr, lines)
    _check_times(path, t, lines, max_step_s)
    if len(t) < 2:
        raise ValueError(f"{path}: at least two attitude records expected, got {len(t)}")
    lo = t[0] if usable[0] is None else max(t[0], usable[0])
    hi = t[-1] if usable[1] is None else min(t[-1], usable[1])
    if not lo < hi:
        raise ValueError(f"{path}: USEABLE_START_TIME .. USEABLE_STOP_TIME holds no time between its records")
    origin = lo + start_s
    if lagrange_degree is not None and len(t) <= lagrange_degree:
        raise ValueError(f"{path}: LAGRANGE of degree {lagrange_degree} needs at least {lagrange_degree + 1} records, "
                         f"got {len(t)}")
    return AttitudeRecord(t - origin, Rotation.from_quat(quats_arr), lines, str(path), (lo - origin, hi - origin),
                          lagrange_degree)


def read_attitude(path: str | os.PathLike, start_s: float = 0.0, max_step_s: float | None = None) -> AttitudeRecord:
    """An attitude file: a CSV (a name ending in ``.csv``: ``t, qx, qy, qz, qw``, times shifted by ``-start_s``)
    or a CCSDS AEM (any other name)."""
    if str(path).lower().endswith(".csv"):
        record = read_attitude_csv(path, max_step_s)
        return AttitudeRecord(record.t - start_s, record.attitude, record.lines, record.source)
    return read_aem(path, start_s, max_step_s)


class AttitudeHistory(Motion):
    """The attitude of an :class:`AttitudeRecord`, SLERP between its samples (the shorter arc), defined over its
    span of times only.

    Over the interval ``[t_k, t_k+1]`` the attitude is ``A(t) = exp(-[w_k x] (t - t_k)) A_k`` with the constant
    body rate ``w_k = -rotvec(A_k+1 A_k^-1) / (t_k+1 - t_k)`` (rad/s, body frame), so ``A(t_k) = A_k`` and the rate
    integrates exactly to every sample.  ``delta(t) = A(t) A_0^-1``, ``A_0`` the attitude at t = 0 (:attr:`initial`).
    """

    def __init__(self, record: AttitudeRecord):
        self.record = record
        self.t = np.asarray(record.t, dtype=np.float64)
        if self.t.ndim != 1 or self.t.size < 2 or not np.all(np.diff(self.t) > 0.0):
            raise ValueError(f"{record.source}: at least two samples at increasing times expected")
        self._attitudes = record.attitude
        steps = (record.attitude[1:] * record.attitude[:-1].inv()).as_rotvec()
        angles = np.linalg.norm(steps, axis=1)
        ambiguous = np.flatnonzero(angles > math.pi - 1e-6)
        if ambiguous.size:
            k = ambiguous[0] + 1
            raise ValueError(f"{record.source}:{record.lines[k]}: a turn of 180 deg from the previous sample: the "
                             f"shorter arc is ambiguous (sample the file more often)")
        self._steps = steps
        self._rates = -steps / np.diff(self.t)[:, None]
        lo, hi = self.span
        self.initial = self.attitude(0.0) if lo <= 0.0 <= hi else self.attitude(lo)
        self._initial_inv = self.initial.inv()

    @property
    def span(self) -> tuple[float, float]:
        """The times (s) the history is valid over: its first and last sample's, or an AEM's usable span."""
        if self.record.span is None:
            return float(self.t[0]), float(self.t[-1])
        return float(self.record.span[0]), float(self.record.span[1])

    def _interval(self, t) -> tuple[np.ndarray, np.ndarray, bool]:
        """Each time's interval index and the time since that interval's start (s); refuses a time outside the
        span (beyond :data:`TIME_TOLERANCE_S`)."""
        ts = np.asarray(t, dtype=np.float64)
        scalar = ts.ndim == 0
        ts = np.atleast_1d(ts)
        if ts.ndim > 1 or not np.all(np.isfinite(ts)):
            raise ValueError(f"t must be a finite scalar or 1-D array of seconds, got shape {ts.shape}")
        lo, hi = self.span
        outside = (ts < lo - TIME_TOLERANCE_S) | (ts > hi + TIME_TOLERANCE_S)
        if np.any(outside):
            bad = float(ts[outside][0])
            raise ValueError(f"{self.record.source}: t = {bad:.9g} s is outside the file's times [{lo:.9g}, "
                             f"{hi:.9g}] s (simulation time)")
        ts = np.clip(ts, lo, hi)
        k = np.clip(np.searchsorted(self.t, ts, side="right") - 1, 0, self.t.size - 2)
        return k, ts - self.t[k], scalar

    def attitude(self, t) -> Rotation:
        """Inertial -> body at time(s) ``t`` (s)."""
        k, tau, scalar = self._interval(t)
        fraction = tau / (self.t[k + 1] - self.t[k])
        rot = Rotation.from_rotvec(fraction[:, None] * self._steps[k]) * self._attitudes[k]
        return rot[0] if scalar else rot

    def delta(self, t) -> Rotation:
        return self.attitude(t) * self._initial_inv

    def body_rate(self, t) -> np.ndarray:
        k, _, scalar = self._interval(t)
        rates = self._rates[k]
        return rates[0] if scalar else rates

    def mean_body_rate(self, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
        """The exact mean body rate (n, 3) rad/s over each interval ``(t0, t1]`` (s, ``t1 > t0``): the rate is
        constant between samples, so the mean is each piece's rate weighted by its share of the interval."""
        t0, t1 = np.asarray(t0, dtype=np.float64), np.asarray(t1, dtype=np.float64)
        k0, _, _ = self._interval(t0)
        k1, _, _ = self._interval(t1)
        k1 = np.where((k1 > k0) & (np.clip(t1, *self.span) == self.t[k1]), k1 - 1, k1)  # (t0, t1] ends on a sample
        mean = self._rates[k0].copy()
        for i in np.flatnonzero(k1 > k0):  # intervals that straddle samples (at most one in a few)
            edges = np.concatenate([[t0[i]], self.t[k0[i] + 1: k1[i] + 1], [t1[i]]])
            mean[i] = np.diff(edges) @ self._rates[k0[i]: k1[i] + 1] / (t1[i] - t0[i])
        return mean

    def max_rate(self, t0, t1) -> float:
        lo, hi = float(t0), float(t1)
        first = max(0, int(np.searchsorted(self.t, lo, side="right")) - 1)
        last = min(self.t.size - 2, max(first, int(np.searchsorted(self.t, hi, side="left")) - 1))
        return float(np.max(np.linalg.norm(self._rates[first: last + 1], axis=1)))


class LagrangeHistory(AttitudeHistory):
    """An AEM's ``INTERPOLATION_METHOD = LAGRANGE``: each quaternion component interpolated by the Lagrange
    polynomial of degree d through the d + 1 samples around the time (the window ``k - (d - 1) // 2`` onwards for
    the interval ``[t_k, t_k+1]``, moved inside the file at its ends), with the samples' signs made continuous, and
    the result normalised.  The body rate (rad/s, body frame) is that of the normalised polynomial,
    ``w = -2 vec(n' (x) n*)`` (Hamilton product, from ``dA/dt = -[w x] A``); the gyro model averages it by its
    quadrature rule (no exact mean: ``mean_body_rate`` is None).  :meth:`max_rate` bounds |w| from 16 points per
    sample interval plus a quarter (the polynomial's rate is smooth within a window; at a window change the attitude
    steps by the interpolation error, which no rate carries)."""

    mean_body_rate = None

    def __init__(self, record: AttitudeRecord, degree: int):
        self.degree = int(degree)  # set before the base class takes the initial attitude through attitude()
        if not 1 <= self.degree < len(record.t):
            raise ValueError(f"{record.source}: LAGRANGE degree {degree} needs more than {degree} samples")
        quats = record.attitude.as_quat()
        flips = np.cumprod(np.where(np.einsum("ij,ij->i", quats[1:], quats[:-1]) < 0.0, -1.0, 1.0))
        self._quats = quats * np.concatenate([[1.0], flips])[:, None]
        super().__init__(record)
        grid = np.concatenate([np.linspace(a, b, 16) for a, b in zip(self.t[:-1], self.t[1:], strict=True)])
        rates = np.linalg.norm(self.body_rate(np.clip(grid, *self.span)), axis=1).reshape(-1, 16)
        self._interval_bound = 1.25 * rates.max(axis=1)

    def _polynomial(self, t) -> tuple[np.ndarray, np.ndarray, bool]:
        """The normalised quaternion n (m, 4) and its time derivative (m, 4) at times ``t``."""
        k, _, scalar = self._interval(t)
        ts = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), *self.span)
        d = self.degree
        start = np.clip(k - (d - 1) // 2, 0, self.t.size - d - 1)
        nodes = self.t[start[:, None] + np.arange(d + 1)]  # (m, d + 1)
        values = self._quats[start[:, None] + np.arange(d + 1)]  # (m, d + 1, 4)
        x = ts[:, None] - nodes  # (m, d + 1)
        diff = nodes[:, :, None] - nodes[:, None, :]  # x_j - x_i
        np.einsum("mjj->mj", diff)[:] = 1.0
        basis = np.empty_like(x)
        slope = np.zeros_like(x)
        for j in range(d + 1):
            others = [i for i in range(d + 1) if i != j]
            basis[:, j] = np.prod(x[:, others] / diff[:, j, others], axis=1)
            for i in others:
                rest = [m for m in others if m != i]
                slope[:, j] += np.prod(x[:, rest] / diff[:, j, rest], axis=1) / diff[:, j, i]
        q = np.einsum("mj,mjc->mc", basis, values)
        q_dot = np.einsum("mj,mjc->mc", slope, values)
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        n = q / norm
        n_dot = (q_dot - n * np.einsum("mc,mc->m", n, q_dot)[:, None]) / norm
        return n, n_dot, scalar

    def attitude(self, t) -> Rotation:
        n, _, scalar = self._polynomial(t)
        rot = Rotation.from_quat(n)
        return rot[0] if scalar else rot

    def body_rate(self, t) -> np.ndarray:
        n, n_dot, scalar = self._polynomial(t)
        nv, nw, dv, dw = n[:, :3], n[:, 3:], n_dot[:, :3], n_dot[:, 3:]
        rates = -2.0 * (nw * dv - dw * nv + np.cross(nv, dv))
        return rates[0] if scalar else rates

    def max_rate(self, t0, t1) -> float:
        lo, hi = float(t0), float(t1)
        first = max(0, int(np.searchsorted(self.t, lo, side="right")) - 1)
        last = min(self.t.size - 2, max(first, int(np.searchsorted(self.t, hi, side="left")) - 1))
        return float(np.max(self._interval_bound[first: last + 1]))


def attitude_motion(record: AttitudeRecord) -> AttitudeHistory:
    """The motion of an attitude record: SLERP, or the Lagrange interpolation its AEM states."""
    if record.lagrange_degree is None:
        return AttitudeHistory(record)
    return LagrangeHistory(record, record.lagrange_degree)


@dataclass(frozen=True)
class GyroRecord:
    """A recorded gyro log: time stamps ``t`` (n,) s (simulation time, each its interval's end), mean body rates
    ``rate`` (n, 3) rad/s (body frame), the sample interval ``dt`` (s, the median step), each sample's line."""

    t: np.ndarray
    rate: np.ndarray
    dt: float
    lines: np.ndarray
    source: str


def read_gyro_csv(path: str | os.PathLike) -> GyroRecord:
    """A gyro log CSV (``t, wx, wy, wz``: s, rad/s body frame) at one sample rate, checked line by line: time
    increasing, every step within :data:`GYRO_JITTER` of the median (a longer one is a gap), rates finite and within
    :data:`MAX_GYRO_RATE_RAD_S`."""
    path = Path(path)
    rows, lines = _csv_rows(path, GYRO_CSV_COLUMNS)
    t = rows[:, 0]
    _check_times(path, t, lines, None)
    steps = np.diff(t)
    dt = float(np.median(steps))
    off = np.flatnonzero(np.abs(steps - dt) > GYRO_JITTER * dt)
    if off.size:
        k = off[0] + 1
        what = "a gap" if steps[k - 1] > dt else "an early sample"
        raise ValueError(f"{path}:{lines[k]}: {what}: {steps[k - 1]:.6g} s after the previous sample, the log's "
                         f"interval being {dt:.6g} s (within {GYRO_JITTER:g} of it expected)")
    fast = np.flatnonzero(np.any(np.abs(rows[:, 1:]) > MAX_GYRO_RATE_RAD_S, axis=1))
    if fast.size:
        k = fast[0]
        raise ValueError(f"{path}:{lines[k]}: rates within +-{MAX_GYRO_RATE_RAD_S:.6g} rad/s expected, got "
                         f"{rows[k, 1:].tolist()}")
    return GyroRecord(t, rows[:, 1:].copy(), dt, lines, str(path))


class GyroReplay:
    """A recorded gyro log delivered in place of the gyro model: :meth:`sample_until` hands over the recorded samples
    stamped in (last delivered, ``t_end``] (those at t <= 0 never), whatever the true motion; its bias is unknown
    (NaN).  The same interface as :class:`starenv.sim.gyro.Gyro`."""

    def __init__(self, record: GyroRecord):
        self.record = record
        self._delivered = int(np.searchsorted(record.t, 0.0, side="right"))

    @property
    def bias_rad_s(self) -> np.ndarray:
        """Unknown for a recorded log: NaN (3,)."""
        return np.full(3, np.nan)

    def sample_until(self, body_rate, t_end: float) -> GyroSamples:  # noqa: ARG002  (the model's interface)
        """The recorded samples with time stamps in (last delivered, ``t_end``] (s)."""
        stop = max(self._delivered, int(np.searchsorted(self.record.t, float(t_end), side="right")))
        picked = slice(self._delivered, stop)
        self._delivered = stop
        return GyroSamples(t=self.record.t[picked].copy(), rate=self.record.rate[picked].copy(), dt=self.record.dt)


@dataclass(frozen=True)
class AemSegment:
    """One segment to write: attitudes ICRS -> body at Unix times (ns), the spacecraft's name and a comment."""

    unix_ns: np.ndarray
    attitude: Rotation
    object_name: str
    comment: str


def aem_text(segments: list[AemSegment], form: str = "kvn", originator: str = "starenv") -> str:
    """An AEM 1.0 (CCSDS 504.0-B-1) holding ``segments``, in ``form`` ``"kvn"`` or ``"xml"``, written by the
    ``ccsds-ndm`` library: ``REF_FRAME_A = ICRF``, ``REF_FRAME_B = SC_BODY_1``, ``ATTITUDE_DIR = A2B``,
    ``QUATERNION_TYPE = LAST`` (the inverse of each attitude, its scalar made non-negative), ``TIME_SYSTEM = UTC``
    (Unix time: leap seconds not counted), every number to full double precision."""
    from ccsds_ndm.mapping import NDMFileFormats
    from ccsds_ndm.models import ndmxml2 as aem

    if form not in ("kvn", "xml"):
        raise ValueError(f"form must be 'kvn' or 'xml', got {form!r}")
    _ndm_io()  # the library's absence is one line
    body = []
    for segment in segments:
        epochs = [format_epoch(t) for t in segment.unix_ns]
        quats = segment.attitude.inv().as_quat(canonical=True)  # ICRF -> body frame rotation, QC >= 0
        meta = aem.AemMetadata(
            comment=[segment.comment], object_name=segment.object_name, object_id="NONE", ref_frame_a="ICRF",
            ref_frame_b="SC_BODY_1", attitude_dir=aem.RotDirectionType.A2_B, time_system=aem.TimeSystemType.UTC,
            start_time=epochs[0], stop_time=epochs[-1], attitude_type=aem.AttitudeTypeType.QUATERNION_1,
            quaternion_type=aem.QuaternionTypeType.LAST_1)
        states = [aem.AttitudeStateType(quaternion_state=aem.QuaternionEphemerisType(
            epoch=e, quaternion=aem.QuaternionType(q1=float(q[0]), q2=float(q[1]), q3=float(q[2]), qc=float(q[3]))))
            for e, q in zip(epochs, quats, strict=True)]
        body.append(aem.AemSegment(metadata=meta, data=aem.AemData(attitude_state=states)))
    created = format_epoch(int(segments[0].unix_ns[0])) if segments else "2000-01-01T00:00:00"
    message = aem.Aem(header=aem.NdmHeader(creation_date=created, originator=originator),
                      body=aem.AemBody(segment=body))
    return _ndm_io().to_string(message, NDMFileFormats.KVN if form == "kvn" else NDMFileFormats.XML)
