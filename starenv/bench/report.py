"""Aggregating a bench's run files into tables (markdown, CSV), plots (PNG) and ``report.md``.

Cases are (scenario with its group's fixed overrides, swept key and value, pipeline:
``starenv.bench.cases``); a case pools the steps of all its seeds.  Per case, every
metric of ``starenv.metrics`` that its steps carry gets the statistics its declaration names, over the steps that
have a value (attitude errors: over available steps only), one ``summary.csv`` column each
(``starenv.metrics.column``: ``share`` as the metric's own name, e.g. ``within_threshold`` = availability, ``fixed``;
``mean``, ``rms``, ``median``, ``p95`` (linear interpolation) as suffixes), each share and each statistic of an
attitude error (arcsec) with its 95 % interval over runs in two more columns (``..._ci_low``, ``..._ci_high``:
exact binomial on the pooled steps for a share, bootstrap over runs otherwise; empty with one run).  A metric a
pipeline role measures is left empty (``-``) for a pipeline without that role (``MEASURED_BY``: the distortion left
after correction needs a corrector).  ``datasheet.csv`` and the report's opening tables:
``starenv.bench.datasheet``.  The report's tables show the metrics with a
``label``: the accuracy table those of ``info["scores"]`` and the flat record, one table per other scope
(restoration, filter: only cases that carry it) and the latency per agent role, each with a legend.  A key no
metric declares is an error naming it.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import multiprocessing
import os
import re
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from starenv import metrics
from starenv.bench import datasheet
from starenv.bench.cases import (
    CI_HIGH,
    CI_LOW,
    WORKING_SHARE,
    Case,
    case_name,
    compared,
    fmt_interval,
    is_rate_sweep,
    load_cases,
    row_interval,
    set_overrides,
    share_interval,
    sweep_label,
    working_limit,
)
from starenv.bench.cases import fmt as _fmt
from starenv.bench.runner import read_run

ROLE_NAMES = {"pipeline": "whole pipeline"}  # latency_pipeline_ms: one whole policy call
UNITS = {"_dps": "deg/s", "_deg": "deg", "_arcsec": "arcsec", "_hz": "Hz", "_s": "s", "_px": "px", "_um": "um",
         "_mm": "mm", "_e": "e-", "_rthr": "deg/sqrt(h)"}


def key_unit(key: str) -> str:
    """The unit a scenario key carries in its name (``motion.rate_dps`` -> ``deg/s``), or ''."""
    last = key.split(" about ", 1)[0].rsplit(".", 1)[-1]
    return next((u for suffix, u in UNITS.items() if last.endswith(suffix)), "")


MEASURED_BY = {"correction_": "corrector"}  # metric-name prefix -> the pipeline role without which it means nothing
INTERVAL_UNITS = (metrics.ARCSEC,)  # the statistics of these metrics carry a bootstrap interval (shares: binomial)


def case_identity(case: Case) -> dict:
    """A case's identity columns (``set``: its group's fixed overrides as JSON, empty when none)."""
    ident = case.ident
    sweep = ident["sweep"] or {}
    fixed = set_overrides(ident)
    return {"scenario": ident["scenario"], "set": json.dumps(fixed, sort_keys=True) if fixed else "",
            "sweep_key": sweep_label(sweep) if sweep else "", "sweep_value": sweep.get("value", ""),
            "pipeline": ident["pipeline"]["name"], "runs": len(case.runs), "steps": len(case.records)}


def _measured(key: str, records: list[dict]) -> bool:
    """Whether the role a metric needs (``MEASURED_BY``) ran in these steps (it has a latency there)."""
    role = next((r for prefix, r in MEASURED_BY.items() if key.startswith(prefix)), None)
    return role is None or any(r.get(f"latency_{role}_ms") is not None for r in records)


def summary_row(case: Case) -> dict:
    """A case's ``summary.csv`` row: identity columns, then the statistics and intervals described in the module
    doc."""
    row = {**case_identity(case), "pipeline_agents": _choice(case.ident["pipeline"]),
           "pipeline_unrestored": _choice(case.ident["pipeline"], without="deblurrer")}
    records = case.records
    keys = {k for r in records for k in r if k not in metrics.INDEX_KEYS}
    for key in metrics.order(k for k in keys if _measured(k, records)):
        metric = metrics.lookup(key)
        values = np.array([r[key] for r in records if r.get(key) is not None], dtype=np.float64)
        for stat in metric.statistics:
            column = metrics.column(key, stat)
            row[column] = metrics.STATISTICS[stat].function(values) if len(values) else None
            if stat == "share":
                row[column + CI_LOW], row[column + CI_HIGH] = share_interval(values)
            elif metric.unit in INTERVAL_UNITS:
                row[column + CI_LOW], row[column + CI_HIGH] = case.interval(key, stat)
    return row


def aggregate(run_files: list[Path], cases: list[Case] | None = None) -> list[dict]:
    """One row per case (:func:`summary_row`), in first-seen order (``cases``: the run files already loaded,
    ``starenv.bench.cases.load_cases``)."""
    return [summary_row(case) for case in (load_cases(run_files) if cases is None else cases)]


def _choice(pipeline: dict, without: str | None = None) -> str:
    """A pipeline's agents, options and catalogue limit as canonical JSON, less the role ``without``."""
    agents = {k: v for k, v in pipeline.get("agents", {}).items() if k != without}
    options = {k: v for k, v in pipeline.get("options", {}).items() if k != without}
    return json.dumps([agents, options, pipeline.get("catalog_mag_limit")], sort_keys=True)


def write_csv(rows: list[dict], path: Path, columns: tuple[str, ...] | None = None) -> None:
    """Rows as CSV (``columns``: their order; default every key in first-seen order): None as an empty cell, a
    list as JSON."""
    columns = list(dict.fromkeys(k for r in rows for k in r)) if columns is None else list(columns)
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, columns, restval="")
        w.writeheader()
        for r in rows:
            w.writerow({k: "" if v is None else json.dumps(v) if isinstance(v, list) else v for k, v in r.items()})


CASE_HEAD = ["scenario", "sweep", "pipeline", "runs", "steps"]
ACCURACY_SCOPES = ("step", "attitude", "body_attitude", "head_attitude", "head", "record")
# (section heading, scopes, whether every case has a row (else only the cases with a value in those scopes))
TABLES = (
    ("Accuracy", ACCURACY_SCOPES, True),
    ("Restoration (pipelines with a deblurrer)", ("restoration",), False),
    ("Filter against truth (pipelines with a fusion filter)", ("filter",), False),
    ("Latency per agent role", ("latency",), True),
)


def _case_cells(r: dict) -> list[str]:
    sweep = f"{r['sweep_key']} = {_fmt(r['sweep_value'])}" if r["sweep_key"] else "-"
    return [case_name(r), sweep, r["pipeline"], str(r["runs"]), str(r["steps"])]


def _instances(rows: list[dict], metric: metrics.Metric) -> list[tuple[str, dict[str, str]]]:
    """The record keys of ``metric`` the rows carry statistics of, with the values of its name's placeholders (a
    name without placeholders: its one key, carried or not)."""
    if "{" not in metric.name:
        return [(metric.name, {})]
    keys = {}
    for r in rows:
        for col in r:
            parsed = metrics.parse_column(col)
            found = parsed and metrics.find(parsed[0])
            if found and found[0] is metric:
                keys[parsed[0]] = found[1]
    return sorted(keys.items())


def _heading(metric: metrics.Metric, params: dict[str, str]) -> str:
    """A table column's heading: label (placeholders filled in), statistics shown, unit."""
    names = {k: ROLE_NAMES.get(v, v) if k == "role" else v for k, v in params.items()}
    text = metric.label.format(**names)
    if metric.columns_shown != ("share",):
        text += " " + " / ".join(metric.columns_shown)
    return text + ("" if metric.unit in metrics.UNITLESS else f" ({metric.unit})")


PLACEHOLDER = re.compile(r"\{(\w+)\}")


def _legend(shown: list[metrics.Metric]) -> str:
    """One line per metric of a table: its label (a placeholder as ``<name>``) and meaning."""
    return "\n".join("- " + PLACEHOLDER.sub(r"<\1>", m.label) + f": {m.description}" for m in dict.fromkeys(shown))


def markdown_tables(rows: list[dict]) -> str:
    """The tables of :data:`TABLES`, each with the labelled metrics of its scopes (one column per record key and
    the statistics it shows) and a legend, as markdown."""
    out = []
    for title, scopes, every_case in TABLES:
        labelled = [m for m in metrics.METRICS if m.scope in scopes and m.label]
        columns = [(m, key, params) for m in labelled for key, params in _instances(rows, m)]
        keep = [r for r in rows if every_case or any(
            r.get(metrics.column(key, s)) is not None for m, key, _ in columns for s in m.statistics)]
        if not keep or not columns:
            continue
        heads = [_heading(m, params) for m, _, params in columns]
        lines = ["| " + " | ".join(CASE_HEAD + heads) + " |", "|" + "---|" * (len(CASE_HEAD) + len(heads))]
        for r in keep:
            cells = [" / ".join(fmt_interval(*row_interval(r, metrics.column(key, s))) for s in m.columns_shown)
                     for m, key, _ in columns]
            lines.append("| " + " | ".join(_case_cells(r) + cells) + " |")
        out.append(f"## {title}\n\n" + "\n".join(lines) + "\n\n" + _legend([m for m, _, _ in columns]) + "\n")
    return "\n".join(out)


DODGE_MARKERS = ("o", "s", "^", "D", "v", "P")


def _figure(r: dict, column: str) -> tuple:
    """(value, low, high) of a column as floats (None where absent)."""
    return tuple(None if v is None else float(v) for v in row_interval(r, column))


def _rank(r: dict) -> tuple:
    """Sort key of a case by point estimates, best first: higher availability, then lower median attitude error."""
    avail, err = _figure(r, "within_threshold")[0], _figure(r, "attitude_error_arcsec_median")[0]
    return (-(avail if avail is not None else 0.0), err if err is not None else math.inf)


def _apart(a: tuple, b: tuple) -> bool:
    """Whether two (value, low, high) figures are told apart: both have an interval and the intervals do not
    overlap."""
    if None in a or None in b:
        return False
    return a[2] < b[1] or b[2] < a[1]


def distinguishable(a: dict, b: dict) -> bool:
    """Whether two cases are told apart: their availability intervals are disjoint, or their median attitude
    error intervals are."""
    return any(_apart(_figure(a, c), _figure(b, c)) for c in ("within_threshold", "attitude_error_arcsec_median"))


def best_cases(cases: list[dict]) -> list[dict]:
    """The best case by :func:`_rank`, then every other case not :func:`distinguishable` from it (a tie)."""
    ranked = sorted(cases, key=_rank)
    return [ranked[0], *(r for r in ranked[1:] if not distinguishable(ranked[0], r))]


def headline(rows: list[dict]) -> str:
    """Per scenario: the best pipeline of the cases it compares (``starenv.bench.cases.compared``), or the
    pipelines tied with it (:func:`best_cases`), with availability, median / p95 attitude error (95 % intervals)
    and median pipeline latency (shown, never used to rank); and per numeric sweep the working limit of each
    pipeline, best first."""
    lines = ["| scenario | best pipeline | availability | att. err. median / p95 (arcsec) | latency median (ms) "
             f"| working up to (fixed >= {WORKING_SHARE:g}) |", "|---|---|---|---|---|---|"]
    for name, (chosen, where) in compared(rows).items():
        cases = [r for r in rows if case_name(r) == name]
        best = best_cases(chosen)
        sweeps = []
        for key in dict.fromkeys(r["sweep_key"] for r in cases if r["sweep_key"]):
            swept = [r for r in cases if r["sweep_key"] == key and isinstance(r["sweep_value"], int | float)]
            limits = {p: working_limit([r for r in swept if r["pipeline"] == p])
                      for p in dict.fromkeys(r["pipeline"] for r in swept)}
            order = sorted(limits, key=lambda p: (math.inf if limits[p] is None else -limits[p], p))
            unit = key_unit(key)
            sweeps.append(f"{key}: " + ", ".join(
                f"{p} {'none' if limits[p] is None else _fmt(limits[p]) + (' ' + unit if unit else '')}"
                for p in order))
        top = best[0]
        who = top["pipeline"] if len(best) == 1 else "tie: " + ", ".join(r["pipeline"] for r in best)
        at = f" (at {where})" if where else ""
        errors = " / ".join(fmt_interval(*row_interval(top, f"attitude_error_arcsec_{s}")) for s in ("median", "p95"))
        lines.append(f"| {name} | {who}{at} | {fmt_interval(*row_interval(top, 'within_threshold'))} | {errors} | "
                     f"{_fmt(top.get('latency_pipeline_ms_median'))} | {'; '.join(sweeps) or '-'} |")
    return ("## Headline\n\nPer scenario, its best pipeline: the highest availability, then the lowest median "
            "attitude error, by point estimate.  A pipeline whose 95 % intervals overlap the best's on both "
            "figures cannot be told apart from it: the cell says **tie** and lists them, best first (the figures "
            "are the first one's); a figure without an interval (one run) tells nothing apart.  Latency is shown, "
            "never used to rank.  Scenarios are ranked on their cases without a sweep; a scenario whose cases are "
            "all swept is ranked at the smallest value of its first swept key, named in the cell.  Intervals: "
            "exact binomial over the pooled steps for availability, percentile bootstrap over runs (seeds) for "
            "errors.  Per swept key, how far each pipeline keeps working: the largest swept value up to which "
            f"every value has a fix (solved, within the threshold) on >= {WORKING_SHARE:g} of its steps (none: not "
            "even the smallest).\n\n" + "\n".join(lines) + "\n")


def _restores(rows: list[dict]) -> bool:
    """Whether a pipeline's cases carry restoration scores (it has a deblurrer)."""
    return any(r.get("restoration_stars_after_median") is not None for r in rows)


def working_rates(rows: list[dict]) -> str:
    """Per rate sweep (a ``*rate_dps`` key along an axis): each pipeline's share of steps with a fix at every swept
    rate, its working rate (:func:`working_limit`), the rate it reaches by availability alone (a predictor or filter
    coasting through frames counts there) and, for a restoring pipeline, its working rate over that of the same
    pipeline without its deblurrer when the bench ran it ("x unrestored"); '' when the bench sweeps no rate."""
    out = []
    groups = dict.fromkeys((case_name(r), r["sweep_key"]) for r in rows if is_rate_sweep(r["sweep_key"]))
    for scenario, key in groups:
        cases = [r for r in rows if (case_name(r), r["sweep_key"]) == (scenario, key)
                 and isinstance(r["sweep_value"], int | float)]
        values = sorted({r["sweep_value"] for r in cases})
        per = {p: [r for r in cases if r["pipeline"] == p] for p in dict.fromkeys(r["pipeline"] for r in cases)}
        limits = {p: working_limit(c) for p, c in per.items()}
        by_agents = {c[0].get("pipeline_agents"): p for p, c in per.items() if not _restores(c)}
        steps = sorted({r["steps"] for r in cases})
        head = ["pipeline", "restores", "working rate", "x unrestored", "by availability", *(_fmt(v) for v in values)]
        lines = [f"### {scenario}: {key} ({', '.join(map(str, steps))} steps per rate)", "",
                 "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for p in sorted(per, key=lambda p: (-(limits[p] if limits[p] is not None else -1.0), p)):
            at = {r["sweep_value"]: fmt_interval(*row_interval(r, "fixed")) for r in per[p]}
            lim, coasting = limits[p], working_limit(per[p], "within_threshold")
            twin = by_agents.get(per[p][0].get("pipeline_unrestored")) if _restores(per[p]) else None
            base = limits.get(twin) if twin else None
            ratio = f"{lim / base:.2f} ({twin})" if lim is not None and base else "-"
            cells = [p, "yes" if _restores(per[p]) else "no", "none" if lim is None else _fmt(lim), ratio,
                     "none" if coasting is None else _fmt(coasting), *(at.get(v, "-") for v in values)]
            lines.append("| " + " | ".join(cells) + " |")
        out.append("\n".join(lines))
    if not out:
        return ""
    return ("## Working rate\n\nShare of steps with a fix (the frame solved: >= 3 correct ids and none wrong, and "
            "the attitude within the scenario's threshold) at each swept rate (deg/s), with its exact binomial 95 % "
            "interval over the pooled steps; a pipeline's working rate is "
            f"the largest swept rate that, with every smaller one, has a fix on >= {WORKING_SHARE:g} of its steps.  "
            "\"by availability\": the same limit on the share of steps with an attitude within the threshold, "
            "whatever gave it -- a predictor or filter carries its attitude on the gyro through frames it cannot "
            "use, so over short runs it can stay available at rates where the frames no longer give a fix.  "
            "\"x unrestored\": a restoring pipeline's working rate over that of the same pipeline without its "
            "deblurrer (named).  Availability, fixes and ID rate against rate: the plots.\n\n"
            + "\n\n".join(out) + "\n")


def _slug(*parts: str) -> str:
    """A file-name part per part (runs of other characters become one ``_``), joined by ``-``."""
    return "-".join(re.sub(r"[^A-Za-z0-9_-]+", "_", p).strip("_") for p in parts if p)


def _case_slug(row: dict) -> str:
    """A scenario's file-name part: its name, and for a group's fixed overrides (``set``) a short hash of them
    (their text can be longer than a file name may be)."""
    if not row.get("set"):
        return row["scenario"]
    return f"{row['scenario']}-set{hashlib.sha256(row['set'].encode()).hexdigest()[:8]}"


def plot(rows: list[dict], run_files: list[Path], folder: Path, cases: list[Case] | None = None,
         sheet: list[dict] | None = None, jobs: int | None = None) -> list[tuple[str, Path]]:
    """Error, ID rate, availability and fixes vs swept value per (scenario, key), with their 95 % intervals (bands,
    error bars); latency per role per scenario; with ``cases`` (and their summary ``rows``, same order) and their
    datasheet rows ``sheet``, the datasheet figures and the per-axis error series and spectra
    (:func:`_plot_datasheet`, :func:`_plot_spectra` on ``jobs`` processes); (title, path)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    made = []
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r["sweep_key"] and isinstance(r["sweep_value"], int | float):
            groups.setdefault((case_name(r), r["sweep_key"]), []).append(r)
    slugs = {case_name(r): _case_slug(r) for r in rows}
    for (scenario, key), group in groups.items():
        unit = key_unit(key)
        xlabel = f"{key} ({unit})" if unit else key
        for what, cols, ylabel, logy in (
            ("error", ("attitude_error_arcsec_median", "attitude_error_arcsec_p95"), "attitude error (arcsec)", True),
            ("id-rate", ("id_rate_mean",), "ID rate (correct ids / detectable stars)", False),
            ("availability", ("within_threshold",), "availability (share of steps within the threshold)", False),
            ("fixed", ("fixed",), "fixes (share of steps solved and within the threshold)", False),
        ):
            fig, ax = plt.subplots(figsize=(7, 4.5))
            pipelines = list(dict.fromkeys(r["pipeline"] for r in group))
            values = sorted({r["sweep_value"] for r in group})
            step = min(np.diff(values)) if len(values) > 1 else 1.0
            banded = False
            for i, pipeline in enumerate(pipelines):
                # identical pipelines would hide each other: each is shifted sideways by a fraction of the sweep
                # step and drawn with its own marker, the first ones largest so that later ones sit inside them
                dodge = (i - (len(pipelines) - 1) / 2) * 0.08 * step
                marker, size = DODGE_MARKERS[i % len(DODGE_MARKERS)], 9 - 1.5 * min(i, 4)
                mine = sorted((r for r in group if r["pipeline"] == pipeline), key=lambda r: r["sweep_value"])
                x = np.array([r["sweep_value"] + dodge for r in mine], dtype=float)
                color = None
                for j, col in enumerate(cols):
                    fig_values = np.array([[np.nan if v is None else v for v in _figure(r, col)] for r in mine])
                    style = {"linestyle": "-", "markersize": size} if j == 0 else {
                        "linestyle": "--", "markersize": size * 0.7, "fillstyle": "none"}
                    label = pipeline + ("" if len(cols) == 1 else " " + col.rsplit("_", 1)[-1])
                    color = ax.plot(x, fig_values[:, 0], marker=marker, alpha=0.85, color=color, label=label,
                                    **style)[0].get_color()
                    if logy:  # the 95 % interval over runs as a band (none with one run)
                        banded |= bool(np.isfinite(fig_values[:, 1:]).any())
                        ax.fill_between(x, fig_values[:, 1], fig_values[:, 2], color=color, alpha=0.12, linewidth=0)
                    elif np.isfinite(fig_values[:, 1:]).any():  # a share's exact binomial interval as error bars
                        ax.errorbar(x, fig_values[:, 0], yerr=np.abs(fig_values[:, 1:].T - fig_values[:, 0]),
                                    fmt="none", ecolor=color, alpha=0.6, capsize=2)
            if len(pipelines) > 1:
                xlabel_note = f"  [pipelines offset by {0.08 * step:.3g} for visibility]"
            else:
                xlabel_note = ""
            if logy and not banded:
                ylabel_shown = ylabel + ", one run: no interval"
            else:
                ylabel_shown = ylabel + (", 95 % band over runs" if logy else "")
            if logy:
                ax.set_yscale("log")
            else:
                ax.set_ylim(-0.02, 1.02)
            ax.set_xlabel(xlabel + xlabel_note)
            ax.set_ylabel(ylabel_shown)
            title = f"{scenario}: {ylabel.split(' (')[0]} vs {key.rsplit('.', 1)[-1]}"
            if what in ("availability", "fixed"):
                ax.axhline(WORKING_SHARE, color="k", linewidth=0.8, linestyle=":")
            ax.grid(True, which="both", alpha=0.3)
            made.append((title, _save(fig, ax, title, folder / f"{_slug(slugs[scenario], key, what)}.png")))
    by_scenario: dict[str, dict[str, dict[str, list[float]]]] = {}
    for f in run_files:
        header, steps, _ = read_run(f)
        per = by_scenario.setdefault(header["identity"]["scenario"], {})
        lat = per.setdefault(header["identity"]["pipeline"]["name"], {})
        for rec in steps:
            for k, v in rec.items():
                found = metrics.find(k)
                if found is not None and found[0].scope == "latency" and v is not None:
                    lat.setdefault(found[1]["role"], []).append(v)
    made += _plot_distortion(run_files, folder, plt)
    if cases is not None and sheet is not None:
        made += _plot_datasheet(rows, sheet, folder, plt)
        made += _plot_spectra(cases, rows, sheet, folder, jobs)
    for scenario, per in by_scenario.items():
        roles = sorted({role for lat in per.values() for role in lat})
        if not roles:
            continue
        fig, ax = plt.subplots(figsize=(max(6.0, 1.4 * len(roles) * max(1, len(per)) ** 0.5), 4.5))
        width = 0.8 / len(per)
        for i, (pipeline, lat) in enumerate(per.items()):
            pos = [j + (i - (len(per) - 1) / 2) * width for j, role in enumerate(roles) if lat.get(role)]
            data = [lat[role] for role in roles if lat.get(role)]
            bp = ax.boxplot(data, positions=pos, widths=width * 0.9, patch_artist=True, showfliers=True,
                            flierprops={"markersize": 2})
            color = f"C{i}"
            for box in bp["boxes"]:
                box.set_facecolor(color)
                box.set_alpha(0.6)
            ax.plot([], [], "s", color=color, label=pipeline)
        ax.set_xticks(range(len(roles)), [ROLE_NAMES.get(role, role) for role in roles])
        ax.set_yscale("log")
        ax.set_xlabel("agent role")
        ax.set_ylabel("latency per step (ms)")
        title = f"{scenario}: agent latency per role (wall clock, all steps)"
        ax.grid(True, axis="y", which="both", alpha=0.3)
        made.append((title, _save(fig, ax, title, folder / f"{_slug(scenario, 'latency')}.png")))
    return made


SHEET_TERMS = (("bias", "bias"), ("nea", "NEA"), ("total3s", "total 3 sigma"))


def _sheet_matches(sheet_row: dict, row: dict) -> bool:
    """Whether a datasheet row belongs to the case of a summary row."""
    return all(sheet_row[k] == row[k] for k in ("scenario", "set", "sweep_key", "sweep_value", "pipeline"))


def _axis_label(frame, axis: str) -> str:
    frame_name = "body" if frame == datasheet.BODY else f"h{frame}"
    return f"{frame_name} {'z' if frame == datasheet.BODY and axis == 'roll' else axis}"


def _plot_datasheet(rows: list[dict], sheet: list[dict], folder: Path, plt) -> list[tuple[str, Path]]:
    """Per scenario, the datasheet's bias, NEA and total 3 sigma per head (and body) and axis, one marker per pipeline
    of the cases its headline compares, with the 95 % interval over runs as error bars."""
    made = []
    for name, (chosen, _) in compared(rows).items():
        per = {}
        for r in chosen:
            mine = [s for s in sheet if _sheet_matches(s, r)]
            per[r["pipeline"]] = [s for s in mine if s["head"] in datasheet.shown_frames([x["head"] for x in mine])]
        ticks = list(dict.fromkeys((s["head"], a) for ss in per.values() for s in ss for a in datasheet.AXES))
        if not ticks:
            continue
        fig, axes = plt.subplots(len(SHEET_TERMS), 1, figsize=(max(7.0, 0.6 * len(ticks) * len(per) ** 0.5), 9),
                                 sharex=True)
        for ax, (term, label) in zip(axes, SHEET_TERMS, strict=True):
            for i, (pipeline, ss) in enumerate(per.items()):
                by_tick = {(s["head"], a): _figure(s, f"{term}_{a}_arcsec") for s in ss for a in datasheet.AXES}
                x = np.arange(len(ticks)) + (i - (len(per) - 1) / 2) * 0.8 / max(len(per), 1)
                fig_values = np.array([[np.nan if v is None else v for v in by_tick.get(t, (None,) * 3)]
                                       for t in ticks])
                yerr = np.abs(fig_values[:, 1:].T - fig_values[:, 0])
                ax.errorbar(x, fig_values[:, 0], yerr=np.where(np.isfinite(yerr), yerr, 0.0), fmt=DODGE_MARKERS[
                    i % len(DODGE_MARKERS)], color=f"C{i}", capsize=3, label=pipeline)
            if term == "bias":
                ax.axhline(0.0, color="k", linewidth=0.8)
            ax.set_ylabel(f"{label} (arcsec)")
            ax.grid(True, axis="y", alpha=0.3)
        axes[-1].set_xticks(range(len(ticks)), [_axis_label(*t) for t in ticks])
        axes[-1].set_xlabel("head and axis (camera +X, +Y, roll about the boresight; body +X, +Y, +Z)")
        title = f"{name}: bias, NEA and total 3 sigma per axis (95 % intervals over runs)"
        made.append((title, _save(fig, axes[0], title, folder / f"{_slug(_case_slug(chosen[0]), 'datasheet')}.png")))
    return made


def _longest_finite(values: np.ndarray) -> np.ndarray:
    """The longest run of consecutive finite values."""
    best, start = (0, 0), None
    for k, ok in enumerate([*np.isfinite(values), False]):
        if ok and start is None:
            start = k
        elif not ok and start is not None:
            best, start = max(best, (k - start, start)), None
    return values[best[1]: best[1] + best[0]]


MIN_SPECTRUM_SAMPLES = 8  # shorter stretches of consecutive estimates give no spectrum
MAX_SEGMENT = 64  # Welch segment length (samples) at most: longer series average more segments


def _plot_spectra(cases: list[Case], rows: list[dict], sheet: list[dict], folder: Path,
                  jobs: int | None = None) -> list[tuple[str, Path]]:
    """Per compared case (``starenv.bench.cases.compared``), one figure per pipeline (:func:`_spectrum_figure`), drawn
    on ``jobs`` forked processes (:func:`forked_map`)."""
    compared_rows = {id(r) for chosen, _ in compared(rows).values() for r in chosen}
    tasks = [(case, row, [s for s in sheet if _sheet_matches(s, row)], folder)
             for case, row in zip(cases, rows, strict=True) if id(row) in compared_rows]
    return [made for made in forked_map(_spectrum_figure, tasks, jobs) if made is not None]


def _spectrum_figure(task: tuple) -> tuple[str, Path] | None:
    """One case's figure: per head the signed error series per axis of every run against time, and their power
    spectral density (Welch, averaged over runs, mean removed: the bias is the first panel's offset, the NEA the flat
    floor drawn as a dotted line, the low-frequency part the rise above it at low frequencies); (title, path), or
    None without frame times.  ``task``: (case, its summary row, its datasheet rows, folder)."""
    import matplotlib.pyplot as plt
    from scipy.signal import welch

    case, row, sheet_rows, folder = task
    shown = [f for f in datasheet.frames(case) if f != datasheet.BODY] or [datasheet.BODY]  # per head
    times = case.series("time_s")
    if not all(len(t) and np.isfinite(t).all() for t in times):
        return None
    height = 3.2 * len(shown)  # fixed margins (inches): no tight_layout pass, which costs a second drawing
    fig, axes = plt.subplots(len(shown), 2, figsize=(11, height), squeeze=False)
    fig.subplots_adjust(left=0.08, right=0.98, wspace=0.24, top=1 - 0.35 / height, bottom=0.55 / height,
                        hspace=0.9 / 3.2)
    for (ax_t, ax_f), frame in zip(axes, shown, strict=True):
        sheet_row = next((s for s in sheet_rows if s["head"] == frame), {})
        for j, (axis, key) in enumerate(datasheet.axis_keys(frame).items()):
            color, label = f"C{j}", _axis_label(frame, axis)
            series = case.series(key)
            for k, (t, e) in enumerate(zip(times, series, strict=True)):
                ax_t.plot(t - t[0], e, color=color, linewidth=0.8, alpha=0.5, label=label if k == 0 else None)
            stretches = [_longest_finite(e) for e in series]
            n = min((len(e) for e in stretches), default=0)
            if n < MIN_SPECTRUM_SAMPLES:
                continue
            fs = 1.0 / float(np.median(np.concatenate([np.diff(t) for t in times])))
            segment = min(n, MAX_SEGMENT)
            spectra = [welch(e, fs=fs, nperseg=segment, detrend="constant") for e in stretches]
            freq, density = spectra[0][0], np.mean([d for _, d in spectra], axis=0)
            ax_f.semilogy(freq[1:], density[1:], color=color, label=label)
            nea = sheet_row.get(f"nea_{axis}_arcsec")
            if nea is not None:  # white noise of deviation NEA: one-sided density 2 NEA^2 / fs
                ax_f.axhline(2.0 * nea**2 / fs, color=color, linestyle=":", linewidth=1.0)
        ax_t.set_xlabel("time since the run's first scored frame (s)")
        ax_t.set_ylabel("signed error (arcsec)")
        ax_t.grid(True, alpha=0.3)
        ax_t.legend(fontsize=8)
        ax_f.set_xlabel("frequency (Hz)")
        ax_f.set_ylabel("PSD (arcsec^2/Hz)")
        ax_f.grid(True, alpha=0.3)
    name = case_name(row) + (f", {row['sweep_key']} = {_fmt(row['sweep_value'])}" if row["sweep_key"] else "")
    title = f"{name}, {row['pipeline']}: error per axis and its spectrum ({len(case.runs)} runs)"
    axes[0][0].set_title(title, fontsize=9, loc="left")
    path = folder / f"{_slug(_case_slug(row), row['pipeline'], 'spectrum')}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return title, path


def _plot_distortion(run_files: list[Path], folder: Path, plt) -> list[tuple[str, Path]]:
    """Per scenario whose camera carries uncalibrated distortion (over 0.05 px on the identified stars): prediction
    error and distortion left after correction per step, one line per pipeline and seed."""
    series: dict[str, list[tuple[str, list[dict]]]] = {}
    for f in run_files:
        header, steps, _ = read_run(f)
        ident = header["identity"]
        if ident["sweep"] is None and any((r.get("distortion_px_mean") or 0.0) > 0.05 for r in steps):
            label = f"{ident['pipeline']['name']} s{ident['seed']}"
            series.setdefault(ident["scenario"], []).append((label, steps))
    made = []
    for scenario, runs in series.items():
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for i, (label, steps) in enumerate(sorted(runs)):
            for key, style, what in (("prediction_error_px_mean", "-", "prediction"),
                                     ("correction_error_px_mean", ":", "distortion left")):
                pts = [(r["frame"], r[key]) for r in steps if r.get(key) is not None]
                if pts:
                    ax.plot(*zip(*pts, strict=True), style, color=f"C{i}", label=f"{label} {what}")
        ax.set_yscale("log")
        ax.set_xlabel("frame")
        ax.set_ylabel("error on identified stars (px)")
        ax.grid(True, which="both", alpha=0.3)
        title = f"{scenario}: prediction error and distortion left per step"
        made.append((title, _save(fig, ax, title, folder / f"{_slug(scenario, 'distortion')}.png")))
    return made


def _save(fig, ax, title: str, path: Path) -> Path:
    """Title, legend and PNG of one figure, then close it."""
    import matplotlib.pyplot as plt

    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _case_tables(case: Case) -> tuple[dict, list[dict]]:
    """A case's summary row and its datasheet rows (their maximum rate still empty)."""
    row = summary_row(case)
    return row, datasheet.case_rows(case, row)


_FORKED: tuple = ()  # (function, items) that forked workers inherit (set just before the pool starts them)


def _forked_call(index: int):
    function, items = _FORKED
    return function(items[index])


def forked_map(function, items: list, jobs: int | None = None) -> list:
    """``[function(item) for item in items]`` on ``jobs`` forked processes (default: the CPU count; one process
    where the platform cannot fork).  Forked, not spawned (``starenv.parallel``): the workers inherit ``function``
    and ``items`` (loaded cases) instead of receiving them pickled; only the results travel."""
    global _FORKED
    jobs = min((os.cpu_count() or 1) if jobs is None else jobs, len(items))
    if jobs <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        return [function(item) for item in items]
    _FORKED = (function, items)
    try:
        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("fork")) as pool:
            return list(pool.map(_forked_call, range(len(items))))
    finally:
        _FORKED = ()


def tabulate(run_files: list[Path], jobs: int | None = None) -> tuple[list[Case], list[dict], list[dict]]:
    """The cases of ``run_files``, their summary rows (:func:`summary_row`) and datasheet rows
    (``starenv.bench.datasheet``): every figure of the report, before any table or plot is written.

    ``jobs`` processes share the cases (:func:`forked_map`; each case's figures are its own, so the result does not
    depend on ``jobs``): the bootstraps over runs are the report's costliest computation."""
    cases = load_cases(run_files)
    tables = forked_map(_case_tables, cases, jobs)
    rows = [row for row, _ in tables]
    return cases, rows, datasheet.with_rate_limits([s for _, sheet in tables for s in sheet], rows)


def write_report(bench, run_files: list[Path], out: Path, jobs: int | None = None) -> Path:
    """Tables (``summary.md``, ``summary.csv``, ``datasheet.csv``), plots (``plots/*.png``) and ``report.md``
    linking them (``jobs``: processes for the figures, :func:`tabulate`)."""
    out = Path(out)
    cases, rows, sheet = tabulate(run_files, jobs)
    tables = markdown_tables(rows)
    opening = datasheet.markdown(sheet, rows)
    split = datasheet.split_markdown(sheet, rows)
    top = headline(rows)
    rates = working_rates(rows)
    (out / "summary.md").write_text(f"# {bench.name}: summary\n\n{opening}\n{top}\n{rates}\n{split}\n{tables}",
                                    encoding="utf-8")
    write_csv(rows, out / "summary.csv")
    write_csv(sheet, out / "datasheet.csv", datasheet.COLUMNS)
    plots = plot(rows, run_files, out / "plots", cases, sheet, jobs)
    lines = [f"# Benchmark report: {bench.name}", ""]
    if bench.description:
        lines += [bench.description, ""]
    lines += [opening, top, rates] if rates else [opening, top]
    seeds = sorted({len(c.runs) for c in cases})
    lines += [
        f"Bench file: `{bench.source}`.  {len(run_files)} runs, {sum(r['steps'] for r in rows)} scored steps, "
        f"{'-'.join(map(str, (seeds[0], seeds[-1]) if len(seeds) > 1 else seeds))} run(s) per case "
        "(`starenv bench --seeds N` runs N per case).  "
        "Per-step scores: [`runs/`](runs/) (one JSON-lines file per run, its identity in the first line).  "
        "Tables: [summary.md](summary.md), [summary.csv](summary.csv) (every statistic of every metric, with "
        "the 95 % intervals in `*_ci_low` / `*_ci_high`), [datasheet.csv](datasheet.csv) (the datasheet of "
        "every case).",
        "",
        "Each table's legend defines its columns (every metric, with its unit: `python -m starenv.metrics`).  "
        "Attitude errors are over available steps.  `v [low, high]`: the 95 % interval over runs (exact binomial "
        "over the pooled steps for a share, percentile bootstrap over runs otherwise; none with one run).  `-`: "
        "nothing measured (e.g. the distortion left by a pipeline without a corrector).  Latencies are wall-clock "
        "on the machine that ran the step (the only values that differ between repeated runs).",
        "",
        split,
    ]
    recorded = sorted((out / "recordings").glob("*.mcap")) if bench.recorder else []
    if recorded:
        lines += [f"Recordings: [`recordings/`](recordings/), {len(recorded)} MCAP files (Foxglove, or "
                  "`starenv view FILE.mcap` for a Rerun review).", ""]
    lines += [
        tables,
        "## Plots",
        "",
    ]
    if not any("vs" in t for t, _ in plots):
        lines += ["No swept parameter in this bench: no error / ID-rate curves.", ""]
    for title, path in plots:
        rel = path.relative_to(out).as_posix()
        lines += [f"### {title}", "", f"![{title}]({rel})", ""]
    report = out / "report.md"
    report.write_text("\n".join(lines), encoding="utf-8")
    return report
