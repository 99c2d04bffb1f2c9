"""The bench's datasheet (datasheet.csv, the report's opening tables) and its intervals, from synthetic run files whose
bias, noise, drift, gaps and fixes are known by construction; --seeds and the bench's seeds key."""

import csv
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest

from starenv.bench.datasheet import COLUMNS
from starenv.bench.report import aggregate, write_report
from starenv.bench.runner import RunResult, run_file, write_run
from starenv.bench.spec import load_bench, parse_bench
from starenv.cli import main

RUNS, STEPS, DT = 8, 400, 0.1
FIRST_FIX, GAP = 3, range(100, 105)  # not solved before step 3; no attitude at all on steps 100-104
# per axis: bias, white-noise deviation, drift amplitude (a sine of DRIFT_PERIOD frames: two whole periods per run)
AXES = {"x": (2.0, 0.5, 0.0), "y": (-1.0, 0.3, 0.0), "roll": (5.0, 4.0, 6.0)}
DRIFT_PERIOD = 200
BODY = {"x": "x", "y": "y", "roll": "z"}

BENCH = """
name = "synthetic"
seeds = {seeds}
steps = {steps}
[[runs]]
scenario = "paper_000"
pipelines = ["tracking", "lost_in_space"]
"""


def synthetic_run(seed: int, pipeline: str) -> list[dict]:
    """One run's flat records: signed errors per axis of bias + white noise + drift for head 0 and the body (the
    same series), no attitude in GAP, solved from FIRST_FIX on; "lost_in_space" never gives an attitude."""
    rng = np.random.default_rng(100 + seed)
    k = np.arange(STEPS)
    series = {a: b + rng.normal(0.0, s, STEPS) + amp * np.sin(2 * np.pi * k / DRIFT_PERIOD)
              for a, (b, s, amp) in AXES.items()}
    records = []
    for i in range(STEPS):
        has = pipeline == "tracking" and i not in GAP
        rec = {"frame": i + 1, "time_s": DT * (i + 1), "available": float(has), "within_threshold": float(has),
               "solved": float(has and i >= FIRST_FIX), "latency_pipeline_ms": 10.0 + i % 5,
               "attitude_error_arcsec": float(math.sqrt(sum(series[a][i] ** 2 for a in AXES))) if has else None,
               "head0_cross_boresight_error_arcsec": float(np.hypot(series["x"][i], series["y"][i])) if has else None}
        for a in AXES:
            rec[f"head0_error_{a}_arcsec"] = float(series[a][i]) if has else None
            rec[f"body_error_{BODY[a]}_arcsec"] = float(series[a][i]) if has else None
        records.append(rec)
    return records


def write_synthetic(folder, runs=RUNS, steps=STEPS, make=synthetic_run):
    """Run files of the synthetic bench (tracking and lost_in_space on paper_000, ``runs`` seeds)."""
    bench = parse_bench(BENCH.format(seeds=runs, steps=steps), check=False)
    for run in bench.runs:
        write_run(run_file(folder, run), run,
                  RunResult(run.run_id, make(run.seed, run.pipeline.name), [], None, 1.0))
    return bench, [run_file(folder, r) for r in bench.runs]


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synthetic")
    bench, files = write_synthetic(folder)
    write_report(bench, files, folder)
    with open(folder / "datasheet.csv", newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        return folder, reader.fieldnames, list(reader)


def value(row, column):
    return float(row[column]) if row[column] != "" else None


def test_datasheet_columns_are_the_issues_then_the_rest(sheet):
    _, header, rows = sheet
    assert header[:21] == [
        "scenario", "sweep_key", "sweep_value", "pipeline", "head", "runs", "steps", "availability",
        "availability_ci_low", "availability_ci_high", "bias_x_arcsec", "bias_y_arcsec", "bias_roll_arcsec",
        "nea_x_arcsec", "nea_y_arcsec", "nea_roll_arcsec", "total3s_x_arcsec", "total3s_y_arcsec",
        "total3s_roll_arcsec", "acquisition_s_median", "max_tracking_rate_dps"]
    assert header == list(COLUMNS)
    # one row per (case, head or body): head 0 and the body of each pipeline
    assert [(r["pipeline"], r["head"]) for r in rows] == [
        ("tracking", "0"), ("tracking", "body"), ("lost_in_space", "0"), ("lost_in_space", "body")]


@pytest.mark.parametrize("head", ["0", "body"])
def test_datasheet_recovers_known_bias_noise_and_drift_per_axis(sheet, head):
    _, _, rows = sheet
    row = next(r for r in rows if r["pipeline"] == "tracking" and r["head"] == head)
    n = RUNS * (STEPS - len(GAP))  # steps with an attitude, pooled
    n_diff = RUNS * (STEPS - len(GAP) - 1)  # first differences within runs (one spans the gap)
    for axis, (bias, sigma, amp) in AXES.items():
        # bias: standard error sigma/sqrt(n); the drift's whole periods lose the gap's 5 samples, <= 5 amp / 395
        assert abs(value(row, f"bias_{axis}_arcsec") - bias) < 5 * sigma / math.sqrt(n) + 5 * amp / (STEPS - 5)
        # NEA: white noise's first differences (lag-1 correlation -1/2) give the deviation a standard error
        # sigma sqrt(1.5 / (2 n_diff)); the drift adds (2 pi amp / P)^2 / 4 to NEA^2
        drift_nea2 = (2 * np.pi * amp / DRIFT_PERIOD) ** 2 / 4
        nea = value(row, f"nea_{axis}_arcsec")
        assert abs(nea - math.sqrt(sigma**2 + drift_nea2)) < 5 * sigma * math.sqrt(1.5 / (2 * n_diff))
        # low frequency: var(e) - NEA^2 = amp^2 / 2, each of the two with its standard error (Gaussian forms)
        variance = sigma**2 + amp**2 / 2
        tolerance = 3 * (variance * math.sqrt(2 / n) + 2 * sigma**2 * math.sqrt(1.5 / (2 * n_diff)))
        assert abs(value(row, f"low_frequency_{axis}_arcsec") ** 2 - amp**2 / 2) < tolerance
        # total: 3 x RMS, RMS^2 = bias^2 + variance; its standard error sd(e^2)/sqrt(n), sd(e^2) of a Gaussian
        rms2 = bias**2 + variance
        sd_e2 = math.sqrt(2 * variance**2 + 4 * bias**2 * variance)
        assert abs((value(row, f"total3s_{axis}_arcsec") / 3) ** 2 - rms2) < 5 * sd_e2 / math.sqrt(n)
        assert value(row, f"total1s_{axis}_arcsec") == pytest.approx(value(row, f"total3s_{axis}_arcsec") / 3)


def test_every_figure_has_an_ordered_interval_of_the_expected_width(sheet):
    _, _, rows = sheet
    row = next(r for r in rows if r["pipeline"] == "tracking" and r["head"] == "0")
    n = RUNS * (STEPS - len(GAP))
    for term in ("bias", "nea", "low_frequency", "total1s", "total3s"):
        for axis in AXES:
            column = f"{term}_{axis}_arcsec"
            low, mid, high = (value(row, column + s) for s in ("_ci_low", "", "_ci_high"))
            assert low <= mid <= high, column
    for axis, (_, sigma, amp) in AXES.items():
        if amp:
            continue  # the drift's phase is the same in every run: no spread of run means to size against
        low, high = value(row, f"bias_{axis}_arcsec_ci_low"), value(row, f"bias_{axis}_arcsec_ci_high")
        # the bootstrap over 8 runs estimates the pooled mean's standard error sigma / sqrt(n) from 8 run means:
        # relative error ~ 1 / sqrt(2 * 7), so within 3 of those the width lies in [0.2, 1.8] x 2 * 1.96 * se
        expected = 2 * 1.96 * sigma / math.sqrt(n)
        assert 0.2 * expected < high - low < 1.8 * expected, axis
    # availability: the exact binomial interval of the pooled steps, as scipy computes it
    k, total = RUNS * (STEPS - len(GAP)), RUNS * STEPS
    exact = binomtest(k, total).proportion_ci(0.95, method="exact")
    assert value(row, "availability") == pytest.approx(k / total, rel=1e-12)
    assert value(row, "availability_ci_low") == pytest.approx(exact.low, rel=1e-9)
    assert value(row, "availability_ci_high") == pytest.approx(exact.high, rel=1e-9)


def test_acquisition_reacquisition_update_rate_and_latency(sheet):
    _, _, rows = sheet
    row = next(r for r in rows if r["pipeline"] == "tracking" and r["head"] == "0")
    assert value(row, "acquisition_s_median") == pytest.approx(FIRST_FIX * DT)  # first fix on step 3
    assert value(row, "reacquisition_s_median") == pytest.approx(len(GAP) * DT)  # lost on step 100, back on 105
    assert row["acquisition_runs"] == str(RUNS) and row["reacquisitions"] == str(RUNS)
    assert value(row, "update_rate_hz") == pytest.approx(1 / DT)
    assert value(row, "latency_ms_median") == 12.0  # 10 + (step mod 5): 10, 11, 12, 13, 14 equally often
    assert row["max_tracking_rate_dps"] == ""  # no rate sweep


def test_nothing_measured_is_empty_in_the_csv_and_a_dash_in_the_report(sheet):
    folder, _, rows = sheet
    lost = next(r for r in rows if r["pipeline"] == "lost_in_space" and r["head"] == "0")
    for column in ("bias_x_arcsec", "nea_roll_arcsec", "total3s_y_arcsec", "bias_x_arcsec_ci_low",
                   "acquisition_s_median", "reacquisition_s_median"):
        assert lost[column] == "", column
    assert value(lost, "availability") == 0.0 and value(lost, "availability_ci_low") == 0.0
    report = (folder / "report.md").read_text()
    assert report.startswith("# Benchmark report: synthetic\n\n## Datasheet")
    line = next(x for x in report.splitlines() if x.startswith("| lost_in_space | 0 |"))
    cells = line.strip("| ").split(" | ")
    assert cells[3].startswith("0 [0, ")  # availability 0 with its interval
    assert cells[4:15] == ["-"] * 11  # bias, NEA, total 3 sigma per axis, acquisition and re-acquisition
    tracking = next(x for x in report.splitlines() if x.startswith("| tracking | 0 |")).strip("| ").split(" | ")
    assert tracking[13:15] == [f"{FIRST_FIX * DT:g}", f"{len(GAP) * DT:g} (of {RUNS})"]


def test_a_pipeline_without_a_corrector_shows_no_distortion_left(tmp_path):
    def make(seed, pipeline):
        records = synthetic_run(seed, "tracking")[:20]
        for r in records:  # without a corrector the action's corrected positions are its measured ones
            r["correction_error_px_mean"] = 0.0 if pipeline == "tracking" else 0.25
            if pipeline == "lost_in_space":
                r["latency_corrector_ms"] = 1.0
        return records

    bench, files = write_synthetic(tmp_path, runs=2, steps=20, make=make)
    rows = {r["pipeline"]: r for r in aggregate(files)}
    assert "correction_error_px_mean_median" not in rows["tracking"]
    assert rows["lost_in_space"]["correction_error_px_mean_median"] == 0.25
    write_report(bench, files, tmp_path)
    table = (tmp_path / "report.md").read_text().split("## Accuracy", 1)[1].split("\n\n")[1].splitlines()
    column = table[0].strip("| ").split(" | ").index("distortion left median / p95 (px)")
    cells = {line.strip("| ").split(" | ")[2]: line.strip("| ").split(" | ")[column] for line in table[2:]}
    assert cells == {"tracking": "- / -", "lost_in_space": "0.25 / 0.25"}


def test_same_run_files_give_the_same_bytes(sheet, tmp_path):
    folder, _, _ = sheet  # written with the default jobs (the CPU count); here in one process
    bench = parse_bench(BENCH.format(seeds=RUNS, steps=STEPS), check=False)
    shutil.copytree(folder / "runs", tmp_path / "runs")
    write_report(bench, [run_file(tmp_path, r) for r in bench.runs], tmp_path, jobs=1)
    for name in ("datasheet.csv", "summary.csv"):
        assert (tmp_path / name).read_bytes() == (folder / name).read_bytes(), name


def test_summary_csv_carries_intervals_for_shares_and_errors(sheet):
    folder, _, _ = sheet
    with open(folder / "summary.csv", newline="", encoding="utf-8") as f:
        rows = {r["pipeline"]: r for r in csv.DictReader(f)}
    row = rows["tracking"]
    for column in ("within_threshold", "fixed", "attitude_error_arcsec_median", "attitude_error_arcsec_p95",
                   "head0_error_roll_arcsec_mean", "head0_error_roll_arcsec_rms", "body_error_z_arcsec_mean",
                   "head0_cross_boresight_error_arcsec_median"):
        low, mid, high = (float(row[column + s]) for s in ("_ci_low", "", "_ci_high"))
        assert low <= mid <= high, column
    sheet_row = next(r for r in sheet[2] if r["pipeline"] == "tracking" and r["head"] == "0")
    # a signed error's mean and RMS are the datasheet's bias and total 1 sigma, intervals included
    for stat, term in (("mean", "bias"), ("rms", "total1s")):
        for s in ("", "_ci_low", "_ci_high"):
            assert float(row[f"head0_error_x_arcsec_{stat}{s}"]) == pytest.approx(
                float(sheet_row[f"{term}_x_arcsec{s}"]), rel=1e-12)


RATE_BENCH = """
name = "rates"
seeds = [0, 1]
steps = 10
[[runs]]
scenario = "paper_000"
pipelines = ["tracking", "lost_in_space"]
sweep = { key = "motion.rate_dps", axis = [1, 0, 0], values = [0, 5, 10, 15] }
"""


def test_max_tracking_rate_is_the_working_limit_of_the_rate_sweep(tmp_path):
    bench = parse_bench(RATE_BENCH, check=False)
    # tracking: every step fixed up to 10 deg/s, half at 15; lost_in_space: half at 5 deg/s already
    fails_at = {"tracking": 15, "lost_in_space": 5}
    for run in bench.runs:
        records = synthetic_run(run.seed, "tracking")[:10]
        for i, r in enumerate(records):
            r["solved"] = float(run.sweep_value < fails_at[run.pipeline.name] or i % 2 == 0)
        write_run(run_file(tmp_path, run), run, RunResult(run.run_id, records, [], None, 1.0))
    write_report(bench, [run_file(tmp_path, r) for r in bench.runs], tmp_path)
    with open(tmp_path / "datasheet.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    limits = {(r["pipeline"], r["sweep_value"]): r["max_tracking_rate_dps"] for r in rows}
    assert set(limits.values()) == {"10", "0"}
    assert all(lim == ("10" if p == "tracking" else "0") for (p, _), lim in limits.items())
    assert len(rows) == 2 * 4 * 2  # pipelines x rates x (head 0, body)


def test_seeds_option_replaces_every_seeds_list():
    text = BENCH.format(seeds="[4, 9]", steps=3) + "seeds = [7]\n"  # the group's own list too
    assert {r.seed for r in parse_bench(text, check=False).runs} == {7}
    assert {r.seed for r in parse_bench(text, check=False, seeds=3).runs} == {0, 1, 2}
    assert {r.seed for r in parse_bench(BENCH.format(seeds=3, steps=3), check=False).runs} == {0, 1, 2}
    recorded = parse_bench("recordings = [1]\n" + BENCH.format(seeds=3, steps=3), check=False)
    assert {r.seed for r in recorded.runs if r.record} == {1} and recorded.recorder is not None


@pytest.mark.parametrize("args, text, named", [
    (["--seeds", "0"], BENCH.format(seeds=2, steps=3), "--seeds: expected a count N >= 1"),
    (["--seeds", "-3"], BENCH.format(seeds=2, steps=3), "--seeds: expected a count N >= 1"),
    ([], BENCH.format(seeds=0, steps=3), "seeds: expected a non-empty list of integers >= 0, or a count N >= 1"),
    ([], BENCH.format(seeds="[]", steps=3), "seeds: expected a non-empty list of integers >= 0, or a count N >= 1"),
    ([], BENCH.format(seeds=2.5, steps=3), "seeds: expected"),
    ([], "recordings = [-1]\n" + BENCH.format(seeds=2, steps=3), "recordings: expected true, false or a non-empty"),
])
def test_bad_seeds_are_one_line_errors_naming_the_key(tmp_path, capsys, args, text, named):
    path = tmp_path / "b.toml"
    path.write_text(text)
    out = tmp_path / "out"
    assert main(["bench", str(path), "--out", str(out), "--quiet", *args]) == 2
    err = capsys.readouterr().err
    assert named in err and len(err.strip().splitlines()) == 1, err
    assert not (out / "runs").exists()


def test_readme_and_bundled_bench_quote_its_run_count():
    bench = load_bench("bundled", check=False)
    runs, steps = len(bench.runs), sum(r.steps for r in bench.runs)
    root = Path(__file__).resolve().parent.parent
    first_section = (root / "README.md").read_text(encoding="utf-8").split("\n## ", 2)[1]
    grouped = f"{steps:,}".replace(",", " ")  # the README groups digits: "1 234"
    assert f"{runs} runs, {grouped} steps" in first_section
    bench_file = (root / "scenarios" / "benches" / "bundled.toml").read_text(encoding="utf-8")
    assert f"{runs} runs, {steps} steps" in bench_file
