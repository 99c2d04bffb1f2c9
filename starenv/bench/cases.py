"""A bench's run files grouped into cases, and the intervals over a case's runs that every figure of its report carries.

A case is one scenario (with the fixed overrides of its run group, ``set``), one swept key and value, one pipeline;
its runs are its seeds.  The runs are the independent samples: steps within a run are correlated (a bias, a slow
drift), so a figure's 95 % interval is a percentile bootstrap over runs (``starenv.datasheet.bootstrap_interval``)
and needs two runs or more; a share (availability, fixes) has the exact binomial interval of its pooled steps
(``starenv.datasheet.binomial_interval``), which treats the steps as independent.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from starenv import metrics
from starenv.bench.runner import read_run
from starenv.datasheet import binomial_interval, bootstrap_interval, error_split
from starenv.scoring import derive

WORKING_SHARE = 0.9  # a swept value "works" for a pipeline when this share of its steps has a fix
CI_LOW, CI_HIGH = "_ci_low", "_ci_high"  # suffixes of an interval's columns


@dataclass
class Case:
    """One case: the first run's identity and each run's step records (``derive``d), in step order; the intervals
    computed of it are kept (:meth:`interval`), so that a figure the summary and the datasheet share (a signed
    error's mean is its bias, its RMS the total 1 sigma) is bootstrapped once."""

    ident: dict
    runs: list[list[dict]]
    _series: dict = field(default_factory=dict, repr=False)
    _intervals: dict = field(default_factory=dict, repr=False)

    @property
    def records(self) -> list[dict]:
        """Every step of every run."""
        return [r for run in self.runs for r in run]

    def series(self, key: str) -> list[np.ndarray]:
        """Per run, ``key``'s value at every step (NaN where it has none); the same arrays on every call."""
        if key not in self._series:
            self._series[key] = [np.array([np.nan if r.get(key) is None else r[key] for r in run], dtype=np.float64)
                                 for run in self.runs]
        return self._series[key]

    def interval(self, key: str, statistic: str) -> tuple:
        """95 % bootstrap interval over runs of ``statistic`` (``starenv.metrics.STATISTICS``) of ``key``'s pooled
        values; (None, None) with fewer than two runs or nothing to pool."""
        if (key, statistic) not in self._intervals:
            function = metrics.STATISTICS[statistic].function
            runs = [r[np.isfinite(r)] for r in self.series(key)]

            def pooled(drawn: list[np.ndarray]) -> float:
                values = np.concatenate(drawn)
                return function(values) if len(values) else float("nan")

            low, high = bootstrap_interval(runs, _per_multiset(pooled))
            self._intervals[key, statistic] = (_finite(low), _finite(high))
        return self._intervals[key, statistic]


def set_overrides(ident: dict) -> dict:
    """A run's fixed overrides (its group's ``set``): its overrides less the swept key."""
    swept = (ident.get("sweep") or {}).get("key")
    return {k: v for k, v in ident["overrides"].items() if k != swept}


def sweep_label(sweep: dict) -> str:
    """A sweep's name in tables: its key, and the axis a magnitude is swept along (``motion.rate_dps about [1, 0,
    0]``), so that sweeps of one key along different axes stay apart."""
    axis = sweep.get("axis")
    if axis is None:
        return sweep["key"]
    return f"{sweep['key']} about [{', '.join(f'{float(a):.3g}' for a in axis)}]"


def load_cases(run_files: list[Path]) -> list[Case]:
    """The cases of ``run_files``, in first-seen order (runs in file order)."""
    cases: dict[tuple, Case] = {}
    for path in run_files:
        header, steps, _ = read_run(path)
        ident = header["identity"]
        sweep = ident["sweep"] or {}
        key = (ident["scenario"], json.dumps(set_overrides(ident), sort_keys=True),
               sweep_label(sweep) if sweep else None, json.dumps(sweep.get("value")), ident["pipeline"]["name"])
        cases.setdefault(key, Case(ident, [])).runs.append([derive(r) for r in steps])
    return list(cases.values())


def is_rate_sweep(sweep_key: str) -> bool:
    """Whether a sweep label names a rate (``...rate_dps``, along an axis or not)."""
    return bool(sweep_key) and sweep_key.split(" about ", 1)[0].endswith("rate_dps")


def working_limit(rows: list[dict], share: str = "fixed") -> float | None:
    """Largest swept value up to which (from the smallest swept value on) every value's ``share`` (``fixed``, or
    ``within_threshold`` for availability) reaches ``WORKING_SHARE``; None when the smallest already fails.
    ``rows``: one pipeline's cases of one sweep (summary rows)."""
    limit = None
    for r in sorted(rows, key=lambda r: r["sweep_value"]):
        if (r.get(share) or 0.0) < WORKING_SHARE:
            break
        limit = r["sweep_value"]
    return limit


def fmt(v) -> str:
    """A table cell: ``-`` for nothing measured (None, empty), 3 significant digits for a float."""
    if v is None or v == "":
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if np.isfinite(v) else str(v)
    return str(v)


def fmt_interval(value, low, high) -> str:
    """``value [low, high]`` (``value`` alone without an interval; ``-`` without a value)."""
    if value is None or value == "":
        return "-"
    if low is None or high is None or low == "" or high == "":
        return fmt(value)
    return f"{fmt(value)} [{fmt(low)}, {fmt(high)}]"


def row_interval(row: dict, column: str) -> tuple:
    """(value, low, high) of a column and its interval columns in a row (None where absent)."""
    return tuple(None if row.get(c) in (None, "") else row[c] for c in (column, column + CI_LOW, column + CI_HIGH))


def case_name(row: dict) -> str:
    """A case's scenario in tables: its name, with its group's fixed overrides (``set``) when it has any."""
    fixed = json.loads(row["set"]) if row.get("set") else {}
    if not fixed:
        return row["scenario"]
    return f"{row['scenario']} ({', '.join(f'{k} = {json.dumps(v)}' for k, v in fixed.items())})"


def compared(rows: list[dict]) -> dict[str, tuple[list[dict], str]]:
    """Per scenario (``case_name``), the rows its headline and datasheet compare, and which they are: the cases
    without a sweep; for a scenario with swept cases only, those at the smallest value of its first swept key."""
    out = {}
    for name in dict.fromkeys(case_name(r) for r in rows):
        cases = [r for r in rows if case_name(r) == name]
        plain = [r for r in cases if not r["sweep_key"]]
        if plain:
            out[name] = (plain, "")
            continue
        key = cases[0]["sweep_key"]
        lowest = min(r["sweep_value"] for r in cases if r["sweep_key"] == key)
        out[name] = ([r for r in cases if r["sweep_key"] == key and r["sweep_value"] == lowest],
                     f"{key} = {fmt(lowest)}")
    return out


def _per_multiset(statistic: Callable[[list[np.ndarray]], object]) -> Callable[[list[np.ndarray]], object]:
    """``statistic`` of a list of runs computed once per multiset of runs drawn (by the runs' identity): a bootstrap
    over a few runs draws the same multisets many times, and every statistic here ignores the runs' order."""
    cache: dict[tuple, object] = {}

    def once(runs: list[np.ndarray]):
        key = tuple(sorted(map(id, runs)))
        try:
            return cache[key]
        except KeyError:
            value = cache[key] = statistic(runs)
            return value

    return once


def _finite(v) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


SPLIT_TERMS = ("bias", "nea", "low_frequency", "total_1s", "total_3s")
POOLED_TERMS = {"bias": "mean", "total_1s": "rms"}  # terms that are a statistic of the pooled errors


def split_with_intervals(case: Case, key: str) -> dict[str, tuple]:
    """``error_split`` of one axis's signed errors (flat-record ``key``, the steps with a value) and each term's
    95 % bootstrap interval over runs: term -> (value, low, high), None where it cannot be estimated.  The bias and
    total 1 sigma are the pooled errors' mean and RMS (:meth:`Case.interval`, shared with ``summary.csv``); the
    total 3 sigma's interval is three times the total 1 sigma's (a percentile of three times a value is three times
    its percentile)."""
    runs = case.series(key)
    split = error_split(runs)
    per_draw = _per_multiset(error_split)  # one split per multiset drawn, shared by the terms bootstrapped here
    out = {}
    for term in SPLIT_TERMS:
        if term in POOLED_TERMS:
            low, high = case.interval(key, POOLED_TERMS[term])
        elif term == "total_3s":
            low, high = (None if v is None else 3.0 * v for v in out["total_1s"][1:])
        else:
            low, high = (_finite(v) for v in bootstrap_interval(runs, lambda drawn, t=term: per_draw(drawn)[t]))
        out[term] = (_finite(split[term]), low, high)
    return out


def share_interval(values: np.ndarray) -> tuple:
    """Exact binomial 95 % interval of the share of 1s among 0/1 ``values`` (None, None without values)."""
    low, high = binomial_interval(int(round(float(np.sum(values)))), len(values))
    return _finite(low), _finite(high)
