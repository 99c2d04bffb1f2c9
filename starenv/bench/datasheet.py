"""The bench's datasheet: per case and head (or the body frame) the figures a star-tracker datasheet quotes, with their
95 % intervals over runs, written as ``datasheet.csv`` and as the tables that open ``report.md``.

Every figure comes from an estimator of ``starenv.datasheet`` (``docs/datasheet.md`` maps each to the terms of
ECSS-E-ST-60-20C).  One row per (scenario and its group's ``set``, sweep value, pipeline, head or ``body``); the first
columns are :data:`COLUMNS`' first 21, in that order, then the rest of :data:`COLUMNS`:

* ``availability``: share of the case's steps within the threshold (``within_threshold``), exact binomial interval;
  ``available``: share with an attitude at all (the sensor's own validity flag);
* per axis ``x``, ``y``, ``roll`` (a head: its camera's +X, +Y, +Z, signed ``head{h}_error_*_arcsec``; ``body``: the
  body frame's +X, +Y, +Z, ``body_error_*_arcsec``, in the same three columns): ``bias``, ``nea`` (first
  differences within runs), ``low_frequency``, ``total1s``, ``total3s`` (``starenv.datasheet.error_split`` over
  the steps with an attitude), each with a bootstrap interval over runs (empty with one run);
* ``acquisition_s_median``: median over runs of the time from the first scored frame to the first fix (``fixed``:
  solved and within the threshold; 0 when the first frame has one), ``acquisition_runs``: the runs that had one;
  ``reacquisition_s_median`` / ``reacquisitions``: from each loss of the fix to the next
  (``starenv.datasheet.acquisition_times``);
* ``max_tracking_rate_dps``: on the rows of a rate sweep, the pipeline's working limit over that sweep
  (``starenv.bench.cases.working_limit``: the largest swept rate up to which every rate has a fix on >= 90 % of
  its steps); empty elsewhere;
* ``update_rate_hz``: one over the median interval between scored frames (``time_s``); ``latency_ms_median``: the
  median wall time of the whole pipeline per step (``latency_pipeline_ms``).

Empty cells: nothing measured (no attitude on that axis, one run for an interval, no fix, not a rate sweep).
"""

from __future__ import annotations

import json
import re

import numpy as np

from starenv.bench.cases import (
    CI_HIGH,
    CI_LOW,
    WORKING_SHARE,
    Case,
    case_name,
    compared,
    fmt,
    fmt_interval,
    is_rate_sweep,
    row_interval,
    split_with_intervals,
    working_limit,
)
from starenv.datasheet import acquisition_times

AXES = ("x", "y", "roll")
TERM_COLUMNS = {"bias": "bias", "nea": "nea", "low_frequency": "low_frequency", "total_1s": "total1s",
                "total_3s": "total3s"}  # starenv.datasheet.error_split term -> column prefix
HEAD_KEY = re.compile(r"head(\d+)_error_x_arcsec\Z")
BODY = "body"


def _figure(term: str, axis: str) -> str:
    return f"{TERM_COLUMNS[term]}_{axis}_arcsec"


def _with_interval(column: str) -> list[str]:
    return [column, column + CI_LOW, column + CI_HIGH]


LISTED = ("bias", "nea", "total_3s")  # the terms among the first 21 columns (their intervals come after them)
COLUMNS = (
    "scenario", "sweep_key", "sweep_value", "pipeline", "head", "runs", "steps",
    "availability", "availability_ci_low", "availability_ci_high",
    *(_figure(t, a) for t in LISTED for a in AXES),
    "acquisition_s_median", "max_tracking_rate_dps",
    "set", "available", "available_ci_low", "available_ci_high",
    *(c for t in TERM_COLUMNS for a in AXES
      for c in (_with_interval(_figure(t, a))[1:] if t in LISTED else _with_interval(_figure(t, a)))),
    "acquisition_runs", "reacquisition_s_median", "reacquisitions", "update_rate_hz", "latency_ms_median",
)


def axis_keys(frame: int | str) -> dict[str, str]:
    """The flat-record keys of a frame's signed errors per datasheet axis (``frame``: a head index or ``body``)."""
    if frame == BODY:
        return {"x": "body_error_x_arcsec", "y": "body_error_y_arcsec", "roll": "body_error_z_arcsec"}
    return {a: f"head{frame}_error_{a}_arcsec" for a in AXES}


def frames(case: Case) -> list[int | str]:
    """The heads whose signed errors the case's steps carry, in order, then ``body``."""
    heads = {int(m.group(1)) for r in case.records for k in r if (m := HEAD_KEY.match(k))}
    return [*sorted(heads), BODY]


def shown_frames(heads_and_body: list) -> list:
    """The frames a report shows of a case's :func:`frames`: one head alone (its body row repeats it through a fixed
    mounting), several heads and the body."""
    return heads_and_body[:1] if len(heads_and_body) == 2 else heads_and_body


def _shown(sheet: list[dict], name: str, keys: set) -> list[dict]:
    """The datasheet rows of scenario ``name`` whose case is in ``keys``, less the body row of a one-head case."""
    rows = [s for s in sheet if case_name(s) == name and _key(s) in keys]
    per_case: dict[tuple, list] = {}
    for s in rows:
        per_case.setdefault(_key(s), []).append(s)
    return [s for ss in per_case.values() for s in ss if s["head"] in shown_frames([x["head"] for x in ss])]


def _key(row: dict) -> tuple:
    return row["sweep_key"], json.dumps(row["sweep_value"]), row["pipeline"]


TIME_DECIMALS = 9  # times (s) rounded to the nanosecond: differences of frame times carry float noise below it


def _median(values) -> float | None:
    return round(float(np.median(values)), TIME_DECIMALS) if len(values) else None


SHARED = {"availability": "within_threshold", "available": "available"}  # datasheet column: summary.csv column


def _case_figures(case: Case, row: dict) -> dict:
    """The figures of a case that every one of its rows shares (``row``: its summary row, whose shares, intervals
    and latency median they repeat)."""
    out = {"latency_ms_median": row.get("latency_pipeline_ms_median")}
    for column, share in SHARED.items():
        out[column], out[column + CI_LOW], out[column + CI_HIGH] = row_interval(row, share)
    firsts, again, intervals = [], [], []
    for fixed, t in zip(case.series("fixed"), case.series("time_s"), strict=True):
        if len(t) and np.all(np.isfinite(t)):
            times = acquisition_times(np.nan_to_num(fixed) == 1.0, t)
            firsts += times["first"]
            again += times["reacquisition"]
            intervals.append(np.diff(t))
    steps = np.concatenate(intervals) if intervals else np.zeros(0)
    return {
        **out, "acquisition_s_median": _median(firsts), "acquisition_runs": len(firsts),
        "reacquisition_s_median": _median(again), "reacquisitions": len(again),
        "update_rate_hz": 1.0 / _median(steps) if len(steps) and _median(steps) > 0 else None,
    }


def rate_limits(rows: list[dict]) -> dict[tuple, float | None]:
    """Per rate sweep and pipeline (``(case_name, sweep_key, pipeline)``), its working limit over the swept rates
    (summary rows: ``fixed`` per case)."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if is_rate_sweep(r["sweep_key"]) and isinstance(r["sweep_value"], int | float):
            groups.setdefault((case_name(r), r["sweep_key"], r["pipeline"]), []).append(r)
    return {key: working_limit(group) for key, group in groups.items()}


def case_rows(case: Case, row: dict) -> list[dict]:
    """A case's rows (``row``: its summary row): one per head, then the body frame; the columns of :data:`COLUMNS`
    (None: nothing measured), the maximum tracking rate left to :func:`with_rate_limits`."""
    shared = _case_figures(case, row)
    out = []
    for frame in frames(case):
        sheet = {c: None for c in COLUMNS}
        sheet.update({k: row[k] for k in ("scenario", "set", "sweep_key", "sweep_value", "pipeline", "runs",
                                          "steps")})
        sheet.update(shared)
        sheet["head"] = frame
        for axis, key in axis_keys(frame).items():
            for term, (value, low, high) in split_with_intervals(case, key).items():
                column = _figure(term, axis)
                sheet[column], sheet[column + CI_LOW], sheet[column + CI_HIGH] = value, low, high
        out.append(sheet)
    return out


def with_rate_limits(sheet: list[dict], rows: list[dict]) -> list[dict]:
    """The datasheet rows with ``max_tracking_rate_dps`` filled in on the rows of a rate sweep (:func:`rate_limits`
    of every case's summary row)."""
    limits = rate_limits(rows)
    for s in sheet:
        s["max_tracking_rate_dps"] = limits.get((case_name(s), s["sweep_key"], s["pipeline"]))
    return sheet


def datasheet_rows(cases: list[Case], rows: list[dict]) -> list[dict]:
    """Every case's rows (``cases`` with their summary ``rows``, same order), the maximum rates filled in."""
    return with_rate_limits([s for case, row in zip(cases, rows, strict=True) for s in case_rows(case, row)], rows)


def _cell(row: dict, column: str) -> str:
    return fmt_interval(row.get(column), row.get(column + CI_LOW), row.get(column + CI_HIGH))


def _reacquisition(row: dict) -> str:
    """Median re-acquisition time and the number of losses it is over (``-``: the fix was never lost)."""
    if not row["reacquisitions"]:
        return "-"
    return f"{fmt(row['reacquisition_s_median'])} (of {row['reacquisitions']})"


def _max_rate(row: dict, limits: dict[tuple, float | None]) -> str:
    """The working limits of the rate sweeps of a row's scenario for its pipeline (``-``: none swept)."""
    found = [(key, lim) for (name, key, p), lim in limits.items() if name == case_name(row) and p == row["pipeline"]]
    if not found:
        return "-"
    if len(found) == 1:
        return "none" if found[0][1] is None else fmt(found[0][1])
    return "; ".join(f"{'none' if lim is None else fmt(lim)} ({key})" for key, lim in found)


HEAD = ["pipeline", "head", "runs", "availability", *(f"{t} {a}" for t in ("bias", "NEA", "3σ") for a in AXES),
        "acquisition (s)", "re-acquisition (s)", "max rate (deg/s)", "update (Hz)", "latency (ms)"]


def markdown(sheet: list[dict], rows: list[dict]) -> str:
    """The report's opening tables: per scenario, the datasheet rows of the cases its headline compares."""
    limits = rate_limits(rows)
    out = []
    for name, (chosen, where) in compared(rows).items():
        lines = ["| " + " | ".join(HEAD) + " |", "|" + "---|" * len(HEAD)]
        for s in _shown(sheet, name, {_key(r) for r in chosen}):
            cells = [s["pipeline"], str(s["head"]), str(s["runs"]), _cell(s, "availability"),
                     *(_cell(s, _figure(t, a)) for t in LISTED for a in AXES),
                     fmt(s["acquisition_s_median"]), _reacquisition(s), _max_rate(s, limits), fmt(s["update_rate_hz"]),
                     fmt(s["latency_ms_median"])]
            lines.append("| " + " | ".join(cells) + " |")
        note = f" (at {where}: every case of this scenario is swept)" if where else ""
        out.append(f"### {name}{note}\n\n" + "\n".join(lines))
    return ("## Datasheet\n\nPer scenario and pipeline, per head (its camera's +X, +Y and the boresight +Z, roll) "
            "and, with several heads, for the body frame (`body`: body +X, +Y, +Z in the x, y, roll columns), the "
            "figures of a star-tracker datasheet in arcsec: bias (mean), NEA (noise-equivalent angle: the deviation "
            "of first differences over sqrt(2)) and total 3 sigma (three times the RMS), over the steps with an "
            "attitude; availability (share of steps within the scenario's threshold); acquisition (median over runs "
            "of the time to the first fix); re-acquisition (median time from a loss of the fix to the next, of how "
            "many losses); max rate (the largest swept rate up to which every rate has a fix on "
            f">= {WORKING_SHARE:.0%} of its steps, from this scenario's rate sweeps); update rate; latency (median "
            "wall time of the whole pipeline per step, this machine).  `v [low, high]`: the 95 % interval over runs "
            "(bootstrap over runs; exact binomial for availability); no interval: one run.  `-`: nothing measured.  "
            "Every case, with the low-frequency part, total 1 sigma and re-acquisition: [datasheet.csv]"
            "(datasheet.csv); the estimators and how they map to ECSS-E-ST-60-20C: `docs/datasheet.md`.\n\n"
            + "\n\n".join(out) + "\n")


def split_markdown(sheet: list[dict], rows: list[dict]) -> str:
    """Per scenario, the full error split per axis of the compared cases (bias, NEA, low-frequency, total 1 and 3
    sigma, each with its interval)."""
    out = []
    head = ["pipeline", "head", "axis", "bias", "NEA", "low-frequency", "total 1σ", "total 3σ"]
    for name, (chosen, _) in compared(rows).items():
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for s in _shown(sheet, name, {_key(r) for r in chosen}):
            for axis in AXES:
                label = "z" if s["head"] == BODY and axis == "roll" else axis  # the body's third axis is its +Z
                cells = [s["pipeline"], str(s["head"]), label, *(_cell(s, _figure(t, axis)) for t in TERM_COLUMNS)]
                lines.append("| " + " | ".join(cells) + " |")
        out.append(f"### {name}\n\n" + "\n".join(lines))
    return ("## Error split per axis (ECSS-E-ST-60-20C)\n\nThe same cases as the datasheet: per axis the bias, the "
            "NEA (temporal noise, from first differences within runs), the low-frequency part (what the run's "
            "deviation holds beyond the NEA: slow drift, field-of-view errors), the total 1 sigma (RMS, bias "
            "included) and 3 sigma, arcsec, with their 95 % intervals over runs.  The per-axis error series and "
            "their power spectra, from which the split is read, are plotted below.\n\n" + "\n\n".join(out) + "\n")
