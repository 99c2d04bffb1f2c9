"""Aggregating a bench's run files into tables (markdown, CSV), plots (PNG) and ``report.md``.

Cases are (scenario, swept key and value, pipeline); a case pools the steps of all its seeds.  Per case, every
metric of ``starenv.metrics`` that its steps carry gets the statistics its declaration names, over the steps that
have a value (attitude errors: over available steps only), one ``summary.csv`` column each
(``starenv.metrics.column``: ``share`` as the metric's own name, e.g. ``within_threshold`` = availability, ``fixed``;
``mean``, ``median``, ``p95`` (linear interpolation) as suffixes).  The report's tables show the metrics with a
``label``: the accuracy table those of ``info["scores"]`` and the flat record, one table per other scope
(restoration, filter: only cases that carry it) and the latency per agent role, each with a legend.  A key no
metric declares is an error naming it.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np

from starenv import metrics
from starenv.bench.runner import read_run
from starenv.scoring import derive

ROLE_NAMES = {"pipeline": "whole pipeline"}  # latency_pipeline_ms: one whole policy call
UNITS = {"_dps": "deg/s", "_deg": "deg", "_arcsec": "arcsec", "_hz": "Hz", "_s": "s", "_px": "px", "_um": "um",
         "_mm": "mm", "_e": "e-", "_rthr": "deg/sqrt(h)"}


def sweep_label(sweep: dict) -> str:
    """A sweep's name in tables: its key, and the axis a magnitude is swept along (``motion.rate_dps about [1, 0,
    0]``), so that sweeps of one key along different axes stay apart."""
    axis = sweep.get("axis")
    if axis is None:
        return sweep["key"]
    return f"{sweep['key']} about [{', '.join(_fmt(float(a)) for a in axis)}]"


def key_unit(key: str) -> str:
    """The unit a scenario key carries in its name (``motion.rate_dps`` -> ``deg/s``), or ''."""
    last = key.split(" about ", 1)[0].rsplit(".", 1)[-1]
    return next((u for suffix, u in UNITS.items() if last.endswith(suffix)), "")


def _label(value) -> str:
    return "" if value is None else json.dumps(value)


def aggregate(run_files: list[Path]) -> list[dict]:
    """One row per case, in first-seen order: identity columns, then the statistics described in the module doc."""
    cases: dict[tuple, dict] = {}
    for path in run_files:
        header, steps, _ = read_run(path)
        ident = header["identity"]
        sweep = ident["sweep"] or {}
        key = (ident["scenario"], sweep_label(sweep) if sweep else None, _label(sweep.get("value")),
               ident["pipeline"]["name"])
        case = cases.setdefault(key, {"ident": ident, "runs": 0, "records": []})
        case["runs"] += 1
        case["records"].extend(derive(r) for r in steps)
    rows = []
    for (scenario, sweep_key, _, pipeline), case in cases.items():
        sweep = case["ident"]["sweep"] or {}
        row = {"scenario": scenario, "sweep_key": sweep_key or "", "sweep_value": sweep.get("value", ""),
               "pipeline": pipeline, "runs": case["runs"], "steps": len(case["records"]),
               "pipeline_agents": _choice(case["ident"]["pipeline"]),
               "pipeline_unrestored": _choice(case["ident"]["pipeline"], without="deblurrer")}
        records = case["records"]
        for key in metrics.order({k for r in records for k in r if k not in metrics.INDEX_KEYS}):
            values = np.array([r[key] for r in records if r.get(key) is not None], dtype=np.float64)
            for stat in metrics.lookup(key).statistics:
                row[metrics.column(key, stat)] = metrics.STATISTICS[stat].function(values) if len(values) else None
        rows.append(row)
    return rows


def _choice(pipeline: dict, without: str | None = None) -> str:
    """A pipeline's agents, options and catalogue limit as canonical JSON, less the role ``without``."""
    agents = {k: v for k, v in pipeline.get("agents", {}).items() if k != without}
    options = {k: v for k, v in pipeline.get("options", {}).items() if k != without}
    return json.dumps([agents, options, pipeline.get("catalog_mag_limit")], sort_keys=True)


def write_csv(rows: list[dict], path: Path) -> None:
    columns = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, columns, restval="")
        w.writeheader()
        for r in rows:
            w.writerow({k: "" if v is None else json.dumps(v) if isinstance(v, list) else v for k, v in r.items()})


def _fmt(v) -> str:
    if v is None or v == "":
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if math.isfinite(v) else str(v)
    return str(v)


CASE_HEAD = ["scenario", "sweep", "pipeline", "runs", "steps"]
ACCURACY_SCOPES = ("step", "attitude", "head_attitude", "head", "record")
# (section heading, scopes, whether every case has a row (else only the cases with a value in those scopes))
TABLES = (
    ("Accuracy", ACCURACY_SCOPES, True),
    ("Restoration (pipelines with a deblurrer)", ("restoration",), False),
    ("Filter against truth (pipelines with a fusion filter)", ("filter",), False),
    ("Latency per agent role", ("latency",), True),
)


def _case_cells(r: dict) -> list[str]:
    sweep = f"{r['sweep_key']} = {_fmt(r['sweep_value'])}" if r["sweep_key"] else "-"
    return [r["scenario"], sweep, r["pipeline"], str(r["runs"]), str(r["steps"])]


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
            cells = [" / ".join(_fmt(r.get(metrics.column(key, s))) for s in m.columns_shown)
                     for m, key, _ in columns]
            lines.append("| " + " | ".join(_case_cells(r) + cells) + " |")
        out.append(f"## {title}\n\n" + "\n".join(lines) + "\n\n" + _legend([m for m, _, _ in columns]) + "\n")
    return "\n".join(out)


DODGE_MARKERS = ("o", "s", "^", "D", "v", "P")
WORKING_SHARE = 0.9  # a swept value "works" for a pipeline when this share of its steps has a fix


def _rank(r: dict) -> tuple:
    """Sort key of a case, best first: higher availability, then lower median attitude error, then lower latency."""
    def num(v, missing):
        return missing if v is None or v == "" else float(v)
    return (-num(r.get("within_threshold"), 0.0), num(r.get("attitude_error_arcsec_median"), math.inf),
            num(r.get("latency_pipeline_ms_median"), math.inf))


def working_limit(rows: list[dict], share: str = "fixed") -> float | None:
    """Largest swept value up to which (from the smallest swept value on) every value's ``share`` (``fixed``, or
    ``within_threshold`` for availability) reaches ``WORKING_SHARE``; None when the smallest already fails.
    ``rows``: one pipeline's cases of one sweep."""
    limit = None
    for r in sorted(rows, key=lambda r: r["sweep_value"]):
        if (r.get(share) or 0.0) < WORKING_SHARE:
            break
        limit = r["sweep_value"]
    return limit


def headline(rows: list[dict]) -> str:
    """Per scenario: the best pipeline (by availability, then median error, then latency) of its cases without a
    sweep (or, for a swept-only scenario, at the smallest swept value), with its availability, median / p95
    attitude error and median pipeline latency; and per numeric sweep the working limit of each pipeline, best
    first."""
    lines = ["| scenario | best pipeline | availability | att. err. median / p95 (arcsec) | latency median (ms) "
             f"| working up to (fixed >= {WORKING_SHARE:g}) |", "|---|---|---|---|---|---|"]
    for scenario in dict.fromkeys(r["scenario"] for r in rows):
        cases = [r for r in rows if r["scenario"] == scenario]
        plain = [r for r in cases if not r["sweep_key"]]
        if not plain:
            lowest = min(r["sweep_value"] for r in cases)
            plain = [r for r in cases if r["sweep_value"] == lowest]
        best = min(plain, key=_rank)
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
        where = "" if not best["sweep_key"] else f" ({best['sweep_key']} = {_fmt(best['sweep_value'])})"
        lines.append(f"| {scenario} | {best['pipeline']}{where} | {_fmt(best.get('within_threshold'))} | "
                     f"{_fmt(best.get('attitude_error_arcsec_median'))} / {_fmt(best.get('attitude_error_arcsec_p95'))}"
                     f" | {_fmt(best.get('latency_pipeline_ms_median'))} | {'; '.join(sweeps) or '-'} |")
    return ("## Headline\n\nPer scenario, its best pipeline (highest availability, then lowest median attitude "
            "error, then lowest latency) and, per swept key, how far each pipeline keeps working: the largest swept "
            f"value up to which every value has a fix (solved, within the threshold) on >= {WORKING_SHARE:g} of "
            "its steps (none: not even the "
            "smallest).\n\n" + "\n".join(lines) + "\n")


def _restores(rows: list[dict]) -> bool:
    """Whether a pipeline's cases carry restoration scores (it has a deblurrer)."""
    return any(r.get("restoration_stars_after_median") is not None for r in rows)


def working_rates(rows: list[dict]) -> str:
    """Per rate sweep (a ``*rate_dps`` key along an axis): each pipeline's share of steps with a fix at every swept
    rate, its working rate (:func:`working_limit`), the rate it reaches by availability alone (a predictor or filter
    coasting through frames counts there) and, for a restoring pipeline, its working rate over that of the same
    pipeline without its deblurrer when the bench ran it ("x unrestored"); '' when the bench sweeps no rate."""
    out = []
    groups = dict.fromkeys((r["scenario"], r["sweep_key"]) for r in rows
                           if r["sweep_key"].split(" about ", 1)[0].endswith("rate_dps"))
    for scenario, key in groups:
        cases = [r for r in rows if (r["scenario"], r["sweep_key"]) == (scenario, key)
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
            at = {r["sweep_value"]: r.get("fixed") for r in per[p]}
            lim, coasting = limits[p], working_limit(per[p], "within_threshold")
            twin = by_agents.get(per[p][0].get("pipeline_unrestored")) if _restores(per[p]) else None
            base = limits.get(twin) if twin else None
            ratio = f"{lim / base:.2f} ({twin})" if lim is not None and base else "-"
            cells = [p, "yes" if _restores(per[p]) else "no", "none" if lim is None else _fmt(lim), ratio,
                     "none" if coasting is None else _fmt(coasting), *(_fmt(at.get(v)) for v in values)]
            lines.append("| " + " | ".join(cells) + " |")
        out.append("\n".join(lines))
    if not out:
        return ""
    return ("## Working rate\n\nShare of steps with a fix (the frame solved: >= 3 correct ids and none wrong, and "
            "the attitude within the scenario's threshold) at each swept rate (deg/s); a pipeline's working rate is "
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


def plot(rows: list[dict], run_files: list[Path], folder: Path) -> list[tuple[str, Path]]:
    """Error and ID rate vs swept value per (scenario, key), and latency per role per scenario; (title, path)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    made = []
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r["sweep_key"] and isinstance(r["sweep_value"], int | float):
            groups.setdefault((r["scenario"], r["sweep_key"]), []).append(r)
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
            for i, pipeline in enumerate(pipelines):
                # identical pipelines would hide each other: each is shifted sideways by a fraction of the sweep
                # step and drawn with its own marker, the first ones largest so that later ones sit inside them
                dodge = (i - (len(pipelines) - 1) / 2) * 0.08 * step
                marker, size = DODGE_MARKERS[i % len(DODGE_MARKERS)], 9 - 1.5 * min(i, 4)
                pts = sorted((r["sweep_value"], *(r.get(c) for c in cols)) for r in group if r["pipeline"] == pipeline)
                x = [p[0] + dodge for p in pts]
                line = ax.plot(x, [np.nan if p[1] is None else p[1] for p in pts], marker=marker, markersize=size,
                               linestyle="-", alpha=0.85, label=f"{pipeline}" + (" median" if len(cols) > 1 else ""))[0]
                if len(cols) > 1:
                    ax.plot(x, [np.nan if p[2] is None else p[2] for p in pts], marker=marker, markersize=size * 0.7,
                            linestyle="--", fillstyle="none", alpha=0.85, color=line.get_color(),
                            label=f"{pipeline} p95")
            if len(pipelines) > 1:
                xlabel_note = f"  [pipelines offset by {0.08 * step:.3g} for visibility]"
            else:
                xlabel_note = ""
            if logy:
                ax.set_yscale("log")
            else:
                ax.set_ylim(-0.02, 1.02)
            ax.set_xlabel(xlabel + xlabel_note)
            ax.set_ylabel(ylabel)
            title = f"{scenario}: {ylabel.split(' (')[0]} vs {key.rsplit('.', 1)[-1]}"
            if what in ("availability", "fixed"):
                ax.axhline(WORKING_SHARE, color="k", linewidth=0.8, linestyle=":")
            ax.grid(True, which="both", alpha=0.3)
            made.append((title, _save(fig, ax, title, folder / f"{_slug(scenario, key, what)}.png")))
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


def write_report(bench, run_files: list[Path], out: Path) -> Path:
    """Tables (``summary.md``, ``summary.csv``), plots (``plots/*.png``) and ``report.md`` linking them."""
    out = Path(out)
    rows = aggregate(run_files)
    tables = markdown_tables(rows)
    top = headline(rows)
    rates = working_rates(rows)
    (out / "summary.md").write_text(f"# {bench.name}: summary\n\n{top}\n{rates}\n{tables}", encoding="utf-8")
    write_csv(rows, out / "summary.csv")
    plots = plot(rows, run_files, out / "plots")
    lines = [f"# Benchmark report: {bench.name}", ""]
    if bench.description:
        lines += [bench.description, ""]
    lines += [top, rates] if rates else [top]
    lines += [
        f"Bench file: `{bench.source}`.  {len(run_files)} runs, {sum(r['steps'] for r in rows)} scored steps.  "
        "Per-step scores: [`runs/`](runs/) (one JSON-lines file per run, its identity in the first line).  "
        "Tables: [summary.md](summary.md), [summary.csv](summary.csv) (every statistic of every metric).",
        "",
        "Each table's legend defines its columns (every metric, with its unit: `python -m starenv.metrics`).  "
        "Attitude errors are over available steps.  Latencies are wall-clock on the machine that ran the step (the "
        "only values that differ between repeated runs).",
        "",
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
