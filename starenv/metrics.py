"""The metric schema: each per-step metric declared once, in :data:`METRICS`, and every list of metrics derived from it.

A :class:`Metric` is a metric's name in the flat per-step record, its unit, meaning, Rerun panel (``group``), the
statistics that summarise it over steps, the scope it is computed in and the function that computes it there.  From
:data:`METRICS`:

* ``starenv.scoring`` computes each metric (its ``compute``) into ``info["scores"]`` and the flat record
  (``flatten``, which refuses a score no metric declares rather than drop it);
* ``starenv.env``'s docstring and the README list ``info["scores"]`` (:func:`info_table`), ``starenv.episode``'s
  docstring the flat record (:func:`record_table`); ``python -m starenv.metrics`` prints both;
* recordings: the typed fields of ``starenv.StepScores`` (``starenv.record.messages``, numbered in declaration order
  within their scope: add a metric after the last of its scope, so that older files keep their meaning) and the
  Rerun panels ``metrics/{group}`` (``starenv.record.rerun``);
* the bench: ``summary.csv``'s columns (one per metric and statistic, :func:`column`) and the report's tables and
  their legend (metrics with a ``label``; ``starenv.bench.report``).

Scopes (:data:`SCOPES`) say what ``compute`` receives and where the value is kept; a per-head scope's values are
pooled over the heads into the record by the metric's ``pool`` (``each``: one record key per head, the name holding
``{head}``).  A latency's name holds ``{role}``: one record key per agent role.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from starenv.sim.conventions import ARCSEC_PER_RAD

SOLVED_MIN_CORRECT = 3  # a frame is solved with this many correct ids and none wrong
# keys of a flat record that index it rather than measure: the scored frame's index and mid-exposure simulation time
# (s), and a run file's step
INDEX_KEYS = ("frame", "time_s", "step")


@dataclass(frozen=True)
class Scope:
    """Where a metric is computed: what its ``compute`` receives (Markdown), and where its value is kept (``place``
    in ``info["scores"]``; empty: the flat record only)."""

    place: str
    receives: str
    per_head: bool = False


SCOPES = {
    "step": Scope("scores", "`starenv.scoring.StepFrame`: the estimate, the attitude scores, the threshold"),
    "attitude": Scope("scores.attitude", "the error rotation vector of `R_est R_true^T` (rad, body frame); "
                      "available steps only"),
    "body_attitude": Scope("scores.attitude.body", "the error rotation vector (arcsec, body frame)"),
    "head_attitude": Scope("scores.attitude.heads[h]", "the error rotation vector in head h's camera frame (arcsec)",
                           per_head=True),
    "head": Scope("scores.heads[h]", "`starenv.scoring.HeadFrame`: head h's truth and the action's star lists",
                  per_head=True),
    "restoration": Scope("", "`starenv.scoring.RestoredFrame`: a restored head's frames (pipelines with a "
                         "deblurrer)", per_head=True),
    "filter": Scope("", "`starenv.scoring.FilterFrame`: a fusion filter's bias and covariance against truth "
                    "(pipelines with a filter)"),
    "latency": Scope("", "the wall time of one agent role's calls in the step (s)"),
    "record": Scope("", "the step's flat record of the other scopes' metrics"),
}


@dataclass(frozen=True)
class Statistic:
    """A summary over steps: its ``summary.csv`` column suffix, meaning and function of the values (float64 (n,),
    n >= 1)."""

    suffix: str
    meaning: str
    function: Callable[[np.ndarray], float]


STATISTICS = {
    "share": Statistic("", "share of steps where it holds (0-1)", lambda v: float(v.mean())),
    "mean": Statistic("_mean", "mean", lambda v: float(v.mean())),
    "rms": Statistic("_rms", "root mean square (of a signed error: bias included, the total 1 sigma of "
                     "`starenv.datasheet`)", lambda v: float(np.sqrt(np.mean(v * v)))),
    "median": Statistic("_median", "median", lambda v: float(np.median(v))),
    "p95": Statistic("_p95", "95th percentile (linear interpolation)", lambda v: float(np.percentile(v, 95))),
}


@dataclass(frozen=True)
class Pool:
    """How a per-head scope's values (those not None, at least one) become the record's value."""

    meaning: str
    function: Callable[[list], float] | None


POOLS = {
    "mean": Pool("mean over the heads with a value", lambda v: float(np.mean(v))),
    "sum": Pool("sum over the heads", lambda v: float(sum(v))),
    "max": Pool("largest over the heads", lambda v: float(max(v))),
    "any": Pool("1 when any head's holds", lambda v: float(any(v))),
    "each": Pool("one key per head", None),
}


@dataclass(frozen=True)
class Group:
    """A Rerun time-series panel (``metrics/{group}``), laid out only when a run's record holds one of its keys: one
    per head for per-head metrics, one per unit (``{unit}`` in the title names it), flags (``0/1``) on the status
    timeline instead (``starenv.record.rerun``)."""

    title: str


GROUPS = {
    "attitude": Group("attitude error (arcsec): angle grey; about body x y z red green blue, signed"),
    "per_head": Group("error (arcsec) about camera x y roll: red green blue, signed; across the boresight: grey"),
    "share": Group("shares (0-1)"),
    "px": Group("position errors (px)"),
    "count": Group("counts"),
    "gain": Group("restoration gain (dB)"),
    "filter": Group("filter against truth ({unit})"),
    "latency": Group("latency per agent role (ms)"),
}
UNITLESS = ("0-1", "0/1", "count", "")  # units a report heading leaves out
DTYPES = (float, int, bool)
MEDIAN_P95 = ("median", "p95")


@dataclass(frozen=True)
class Metric:
    """One per-step metric.  ``name``: its flat-record key (``{head}`` / ``{role}``: one key per head / agent role);
    ``unit``; ``description``; ``group``: its Rerun panel (:data:`GROUPS`); ``statistics`` over steps
    (:data:`STATISTICS`); ``scope`` (:data:`SCOPES`) and ``compute``: the scope's input -> value (None: no value this
    step); ``field``: its key in ``info["scores"]`` or the scope's per-head dict, where that differs from ``name``;
    ``pool``: how a per-head scope's values become the record's (:data:`POOLS`); ``dtype``: its type in
    ``info["scores"]`` and in recordings; ``label``: its column heading in the bench report (empty: ``summary.csv``
    only), showing the statistics ``shown`` (default: all); ``wall_clock``: a measurement of the machine, not a
    function of the seed."""

    name: str
    unit: str
    description: str
    group: str
    statistics: tuple[str, ...]
    scope: str
    compute: Callable[[Any], Any]
    field: str = ""
    pool: str = "mean"
    dtype: type = float
    label: str = ""
    shown: tuple[str, ...] = ()
    wall_clock: bool = False

    def __post_init__(self):
        bad = [f"{what} {value!r}" for what, value, known in (
            ("group", self.group, GROUPS), ("scope", self.scope, SCOPES), ("pool", self.pool, POOLS),
            *(("statistic", s, STATISTICS) for s in (*self.statistics, *self.shown))) if value not in known]
        if self.dtype not in DTYPES:
            bad.append(f"dtype {self.dtype!r}")
        per_head = self.scope in SCOPES and SCOPES[self.scope].per_head
        if ("{head}" in self.name) != (self.pool == "each") or self.pool != "mean" and not per_head:
            bad.append(f"pool {self.pool!r} (a per-head scope's 'each' needs '{{head}}' in the name, and only there)")
        if not self.statistics or not set(self.shown) <= set(self.statistics):
            bad.append(f"statistics {self.statistics} / shown {self.shown}")
        if bad:
            raise ValueError(f"metric {self.name!r}: unknown or inconsistent " + ", ".join(bad))

    @property
    def key(self) -> str:
        """Its key in ``info["scores"]`` (or the scope's per-head dict)."""
        return self.field or self.name

    @property
    def columns_shown(self) -> tuple[str, ...]:
        """The statistics the report's table shows."""
        return self.shown or self.statistics


def _mean(values: np.ndarray | None) -> float | None:
    return None if values is None or not len(values) else float(values.mean())


def _max(values: np.ndarray | None) -> float | None:
    return None if values is None or not len(values) else float(values.max())


def _norm_mean(xy: np.ndarray | None) -> float | None:
    return None if xy is None else float(np.linalg.norm(xy, axis=1).mean())


SHARE, PX, ARCSEC = ("share",), "px", "arcsec"
SIGNED = ("mean", "rms")  # a signed error's bias and total 1 sigma

# Descriptions are Markdown (the tables are).  Declaration order is the order of the typed fields in recordings (per
# scope) and of the report's columns.
METRICS: tuple[Metric, ...] = (
    Metric("available", "0/1", "an attitude was given (`attitude_valid = 1`)", "share", SHARE, "step",
           lambda s: s.estimate is not None, dtype=bool),
    Metric("within_threshold", "0/1", "available, with the error under the scenario's "
           "`availability_threshold_arcsec`: one number bounds the total angle; a table `{cross_boresight, roll}` "
           "bounds every head's cross-boresight error and the size of its roll error", "share", SHARE, "step",
           lambda s: s.estimate is not None and s.within, dtype=bool, label="availability"),
    Metric("fixed", "0/1", "the frame's own stars solved it (`solved`) and the attitude is within the threshold; "
           "availability also counts an attitude a predictor or filter carried through", "share", SHARE, "record",
           lambda r: None if r.get("within_threshold") is None or r.get("solved") is None
           else float(r["within_threshold"] == 1.0 and r["solved"] == 1.0), label="fixed"),
    Metric("attitude_error_arcsec", ARCSEC, "angle of `R_est R_true^T`", "attitude", MEDIAN_P95, "attitude",
           lambda e: float(np.linalg.norm(e) * ARCSEC_PER_RAD), field="total_arcsec", label="att. err."),
    Metric("body_error_x_arcsec", ARCSEC, "error about body +X, signed: the error rotation vector's component "
           "(signs: `starenv.scoring`)", "attitude", SIGNED, "body_attitude", lambda e: float(e[0]), field="x_arcsec"),
    Metric("body_error_y_arcsec", ARCSEC, "error about body +Y, signed", "attitude", SIGNED, "body_attitude",
           lambda e: float(e[1]), field="y_arcsec"),
    Metric("body_error_z_arcsec", ARCSEC, "error about body +Z, signed", "attitude", SIGNED, "body_attitude",
           lambda e: float(e[2]), field="z_arcsec"),
    Metric("head{head}_error_x_arcsec", ARCSEC, "error about the head's camera +X, signed (cross-boresight)",
           "per_head", SIGNED, "head_attitude", lambda e: float(e[0]), field="x_arcsec", pool="each"),
    Metric("head{head}_error_y_arcsec", ARCSEC, "error about the head's camera +Y, signed (cross-boresight)",
           "per_head", SIGNED, "head_attitude", lambda e: float(e[1]), field="y_arcsec", pool="each"),
    Metric("head{head}_error_roll_arcsec", ARCSEC, "error about the head's boresight (camera +Z), signed", "per_head",
           SIGNED, "head_attitude", lambda e: float(e[2]), field="roll_arcsec", pool="each", label="roll h{head}",
           shown=("rms",)),
    Metric("head{head}_cross_boresight_error_arcsec", ARCSEC, "error across the head's boresight, `hypot` of x and y",
           "per_head", MEDIAN_P95, "head_attitude", lambda e: float(np.hypot(e[0], e[1])),
           field="cross_boresight_arcsec", pool="each", label="cross-bore. h{head}"),
    Metric("centroid_error_px_mean", PX, "mean distance of the detections matched one-to-one to true trail "
           "centroids within the 3 px gate", "px", MEDIAN_P95, "head", lambda f: _mean(f.matched and f.matched.px),
           label="centroid"),
    Metric("centroid_error_px_max", PX, "largest such distance", "px", MEDIAN_P95, "head",
           lambda f: _max(f.matched and f.matched.px), pool="max"),
    Metric("detection_recall", "0-1", "detectable stars matched / detectable stars", "share", MEDIAN_P95, "head",
           lambda f: None if f.matched is None or not f.n_detectable
           else float(f.truth.detectable[f.matched.stars].sum() / f.n_detectable)),
    Metric("detection_precision", "0-1", "matched detections / detections", "share", MEDIAN_P95, "head",
           lambda f: None if f.matched is None or not len(f.detected_xy)
           else float(len(f.matched.detections) / len(f.detected_xy))),
    Metric("id_rate", "0-1", "correct ids / detectable stars (a claimed id is correct when its star's trail passes "
           "within the gate of its detection)", "share", ("mean", "median", "p95"), "head",
           lambda f: None if f.claims is None or not f.n_detectable else min(1.0, f.ids_correct / f.n_detectable),
           label="ID rate", shown=("mean",)),
    Metric("false_id_rate", "0-1", "wrong ids / claimed ids", "share", ("mean", "median", "p95"), "head",
           lambda f: None if f.claims is None or not f.claims.claimed.any()
           else f.ids_wrong / int(f.claims.claimed.sum()), label="false ID", shown=("mean",)),
    Metric("ids_correct", "count", "correct ids", "count", MEDIAN_P95, "head", lambda f: f.ids_correct, pool="sum",
           dtype=int),
    Metric("ids_wrong", "count", "wrong ids", "count", MEDIAN_P95, "head", lambda f: f.ids_wrong, pool="sum",
           dtype=int),
    Metric("solved", "0/1", f"the frame is solved: >= {SOLVED_MIN_CORRECT} correct ids and none wrong",
           "share", SHARE, "head", lambda f: f.ids_correct >= SOLVED_MIN_CORRECT and f.ids_wrong == 0, pool="any",
           dtype=bool, label="solved"),
    Metric("prediction_error_px_mean", PX, "mean distance of predicted from true mid-exposure positions (dropped "
           "frames too)", "px", MEDIAN_P95, "head", lambda f: _mean(f.prediction_px), label="prediction"),
    Metric("prediction_error_px_max", PX, "largest such distance", "px", MEDIAN_P95,
           "head", lambda f: _max(f.prediction_px)),
    Metric("predictions_scored", "count", "predictions of stars on the frame", "count", MEDIAN_P95, "head",
           lambda f: 0 if f.prediction_px is None else len(f.prediction_px), pool="sum", dtype=int),
    Metric("correction_error_px_mean", PX, "distortion left after correction (with the action's `corrected_xy`) "
           "on the correctly identified stars: the corrector's offset against the true one, mean length", "px",
           MEDIAN_P95, "head",
           lambda f: _norm_mean(f.correction and f.correction.error_px), label="distortion left"),
    Metric("correction_error_x_px", PX, "the same, mean size along x", "px", MEDIAN_P95, "head",
           lambda f: None if f.correction is None else float(np.abs(f.correction.error_px).mean(axis=0)[0])),
    Metric("correction_error_y_px", PX, "the same, mean size along y", "px", MEDIAN_P95, "head",
           lambda f: None if f.correction is None else float(np.abs(f.correction.error_px).mean(axis=0)[1])),
    Metric("distortion_px_mean", PX, "the true offset's mean length on those stars (what no corrector leaves)",
           "px", MEDIAN_P95, "head", lambda f: _norm_mean(f.correction and f.correction.true_offset_px)),
    Metric("restoration_centroid_error_blurred_px", PX, "mean distance of the detections on the blurred frame "
           "matched to true mid-exposure positions", "px", MEDIAN_P95, "restoration",
           lambda r: _mean(r.matched_px["blurred"]), field="centroid_error_blurred_px", label="centroid blurred"),
    Metric("restoration_centroid_error_px", PX, "the same on the restored frame", "px", MEDIAN_P95, "restoration",
           lambda r: _mean(r.matched_px["restored"]), field="centroid_error_px", label="centroid restored"),
    Metric("restoration_stars_before", "count", "detections matched to a true star on the blurred frame", "count",
           MEDIAN_P95, "restoration", lambda r: len(r.matched_px["blurred"]), field="stars_before", pool="sum",
           dtype=int, label="stars blurred"),
    Metric("restoration_stars_after", "count", "the same on the restored frame", "count", MEDIAN_P95, "restoration",
           lambda r: len(r.matched_px["restored"]), field="stars_after", pool="sum", dtype=int,
           label="stars restored"),
    Metric("restoration_psnr_gain_db", "dB", "PSNR of the restored minus that of the blurred frame, against the "
           "still noise-free frame", "gain", MEDIAN_P95, "restoration", lambda r: r.psnr_gain_db,
           field="psnr_gain_db", label="PSNR gain"),
    Metric("restoration_iterations", "count", "iterations the deblurrer used", "count", MEDIAN_P95, "restoration",
           lambda r: None if not r.info or r.info.get("iterations") is None else int(r.info["iterations"]),
           field="iterations", dtype=int, label="iterations"),
    Metric("gyro_bias_error_deg_hr", "deg/h", "length of the filter's gyro bias estimate minus the true bias",
           "filter", MEDIAN_P95, "filter",
           lambda f: None if f.bias_error is None else float(np.degrees(np.linalg.norm(f.bias_error)) * 3600.0),
           label="bias error"),
    Metric("attitude_nees", "", "the attitude error's squared Mahalanobis distance under the filter's covariance "
           "(chi-square, 3 degrees of freedom, for a consistent filter)", "filter", ("mean", "median", "p95"),
           "filter", lambda f: None if f.attitude_error is None or f.covariance is None
           else float(f.attitude_error @ np.linalg.solve(f.covariance[:3, :3], f.attitude_error)), label="NEES"),
    Metric("latency_{role}_ms", "ms", "wall time of the role's agent calls (`pipeline`: the whole policy call)",
           "latency", MEDIAN_P95, "latency", lambda seconds: seconds * 1e3, label="{role}", wall_clock=True),
)


def declared(scope: str | None = None) -> tuple[Metric, ...]:
    """The declared metrics (of one scope), in declaration order."""
    return tuple(m for m in METRICS if scope is None or m.scope == scope)


@cache
def _pattern(name: str) -> re.Pattern:
    parts = re.split(r"\{(\w+)\}", name)
    text = "".join(re.escape(p) if i % 2 == 0 else rf"(?P<{p}>{'[0-9]+' if p == 'head' else '.+'})"
                   for i, p in enumerate(parts))
    return re.compile(text + r"\Z")


def find(key: str) -> tuple[Metric, dict[str, str]] | None:
    """The metric a flat-record key belongs to and the values of its name's placeholders; None if none does."""
    for m in METRICS:
        found = _pattern(m.name).match(key)
        if found:
            return m, found.groupdict()
    return None


def lookup(key: str) -> Metric:
    """The metric of a flat-record key; ``KeyError`` naming it when no metric declares it."""
    found = find(key)
    if found is None:
        raise KeyError(f"{key!r}: no metric in starenv.metrics.METRICS declares it")
    return found[0]


def group_of(key: str) -> str:
    """The Rerun panel of a flat-record key (``other`` for a key no metric declares, e.g. from an older file)."""
    found = find(key)
    return "other" if found is None else found[0].group


def is_wall_clock(key: str) -> bool:
    """Whether a flat-record key holds a measurement of the machine (differs between repeated runs)."""
    found = find(key)
    return found is not None and found[0].wall_clock


def column(key: str, statistic: str) -> str:
    """The ``summary.csv`` column of a flat-record key's statistic."""
    return key + STATISTICS[statistic].suffix


def parse_column(name: str) -> tuple[str, str] | None:
    """(flat-record key, statistic) of a ``summary.csv`` column, None for other columns."""
    for stat in sorted(STATISTICS, key=lambda s: -len(STATISTICS[s].suffix)):
        suffix = STATISTICS[stat].suffix
        if name.endswith(suffix):
            key = name[: len(name) - len(suffix)]
            found = find(key)
            if found is not None and stat in found[0].statistics:
                return key, stat
    return None


def order(keys) -> list[str]:
    """Flat-record keys in declaration order (keys of one metric by name; undeclared keys last)."""
    rank = {id(m): i for i, m in enumerate(METRICS)}

    def sort_key(key: str):
        found = find(key)
        return (len(METRICS) if found is None else rank[id(found[0])], key)

    return sorted(keys, key=sort_key)


def _unit(m: Metric) -> str:
    return m.unit or "-"


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


INFO_SCOPES = ("step", "attitude", "body_attitude", "head_attitude", "head")


def info_table() -> str:
    """Markdown table of every score in ``info["scores"]``: key, unit, meaning."""
    lines = [_row(["`info` key", "unit", "meaning"]), "|---|---|---|"]
    for scope in INFO_SCOPES:
        for m in declared(scope):
            lines.append(_row([f"`{SCOPES[scope].place}.{m.key}`", _unit(m), m.description]))
    return "\n".join(lines)


def _source(m: Metric) -> str:
    scope = SCOPES[m.scope]
    if scope.place:
        where = f"`{scope.place}.{m.key}`"
    else:
        where = {"restoration": f"each restored head's `{m.key}`", "filter": "the filter against truth",
                 "latency": "the role's calls", "record": "the step's record"}[m.scope]
    return f"{where}, {POOLS[m.pool].meaning}" if scope.per_head else where


def record_table() -> str:
    """Markdown table of every flat-record metric: key, unit, where it comes from, its ``summary.csv`` columns, its
    Rerun panel, meaning."""
    lines = [_row(["record key", "unit", "from", "summary.csv columns", "panel", "meaning"]), "|---" * 6 + "|"]
    for m in METRICS:
        columns = ", ".join(f"`{column(m.name, s)}`" for s in m.statistics)
        lines.append(_row([f"`{m.name}`", _unit(m), _source(m), columns, m.group, m.description]))
    return "\n".join(lines)


def scope_table() -> str:
    """Markdown table of the scopes: what a metric's ``compute`` receives in each, and where its value is kept."""
    lines = [_row(["scope", "compute receives", "kept in `info`", "one value per head"]), "|---" * 4 + "|"]
    for name, scope in SCOPES.items():
        lines.append(_row([f"`{name}`", scope.receives, f"`{scope.place}`" if scope.place else "-",
                           "yes" if scope.per_head else "no"]))
    return "\n".join(lines)


def main() -> None:
    """Print the tables (``python -m starenv.metrics``): ``info["scores"]``, the flat record, the scopes."""
    print(info_table(), record_table(), scope_table(), sep="\n\n")


if __name__ == "__main__":
    main()
