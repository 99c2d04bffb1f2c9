"""The metric schema: a metric declared once reaches every output, and flatten carries or refuses, never drops."""

import csv
from pathlib import Path

import numpy as np
import pytest

import starenv.env
import starenv.episode
from starenv import metrics
from starenv.bench.report import write_report
from starenv.bench.runner import read_run, run_bench
from starenv.bench.spec import parse_bench
from starenv.env import StarSensorEnv
from starenv.record import messages
from starenv.record.mcap import read_steps
from starenv.record.rerun import metric_panels, metric_path
from starenv.scoring import flatten

ROOT = Path(__file__).resolve().parent.parent
BENCH = """
name = "one_metric"
seeds = [0]
steps = 3
recordings = true
[[runs]]
scenario = "paper_004"
pipelines = ["scenario"]
"""
STARS_ON_FRAME = metrics.Metric(
    "stars_on_frame", "count", "true stars on the head's frame", "count", ("median", "p95"), "head",
    lambda frame: len(frame.truth.catalog_id), pool="sum", dtype=int, label="stars on frame")


def blank_scores(n_heads: int, available: bool = True) -> dict:
    """An ``info["scores"]`` holding every declared key (None, or False for flags, 0 for counts)."""
    empty = {float: None, int: 0, bool: False}

    def values(scope):
        return {m.key: empty[m.dtype] if m.dtype is not float else 1.0 for m in metrics.declared(scope)}

    heads = [values("head_attitude") for _ in range(n_heads)]
    att = {**values("attitude"), "body": values("body_attitude"), "heads": heads} if available else {}
    return {"frame": 0, **values("step"), "available": available, "attitude": att,
            "heads": [values("head") for _ in range(n_heads)]}


def test_a_metric_declared_once_reaches_every_output(tmp_path, monkeypatch):
    """One declaration (a head-scope count, summed over heads) appears in info["scores"], the flat record, the run
    file, the MCAP recording as a typed field (the next free number of HeadScores), the Rerun review under its
    panel, summary.csv, the report's accuracy table and legend, and the generated docs tables; its values are the
    truth's star counts, read back from the recording's own truth layer."""
    monkeypatch.setattr(metrics, "METRICS", (*metrics.METRICS, STARS_ON_FRAME))
    bench = parse_bench(BENCH)
    files = run_bench(bench, tmp_path, jobs=1, progress=False, log=lambda *a, **k: None)
    _, steps, _ = read_run(files[0])
    recording = next((tmp_path / "recordings").glob("*.mcap"))
    data = list(read_steps(recording))
    assert len(data) == len(steps) == 3
    field = messages.classes()["HeadScores"].DESCRIPTOR.fields_by_name["stars_on_frame"]
    assert (field.number, field.type) == (17, messages.INT64)  # after the 16 typed head scores of today
    for step, record in zip(data, steps, strict=True):
        counts = [len(h.truth.ids) for h in step.heads]
        assert [h["stars_on_frame"] for h in step.scores["heads"]] == counts and min(counts) > 0
        assert record["stars_on_frame"] == step.record["stars_on_frame"] == float(sum(counts))
    write_report(bench, files, tmp_path)
    with open(tmp_path / "summary.csv", encoding="utf-8") as f:
        row = next(csv.DictReader(f))
    values = [r["stars_on_frame"] for r in steps]
    assert float(row["stars_on_frame_median"]) == np.median(values)
    assert float(row["stars_on_frame_p95"]) == pytest.approx(np.percentile(values, 95))
    report = (tmp_path / "report.md").read_text(encoding="utf-8")
    accuracy = report[report.index("## Accuracy"):report.index("## Latency")]
    assert "| stars on frame median / p95 |" in accuracy
    assert "- stars on frame: true stars on the head's frame" in accuracy
    assert metric_path("stars_on_frame") == "metrics/count/stars_on_frame"
    assert "metrics/count" in [panel.origin for panel in metric_panels()]
    import rerun as rr

    from starenv.record.rerun import mcap_to_rrd

    monkeypatch.setenv("CI", "1")  # no Rerun analytics
    rrd = mcap_to_rrd(recording, tmp_path / "review.rrd")
    entities = {c.entity_path for c in rr.chunk.RrdReader(rrd).stream().to_chunks()}
    assert "/metrics/count/stars_on_frame" in entities
    assert "| `scores.heads[h].stars_on_frame` | count | true stars on the head's frame |" in metrics.info_table()
    assert "| `stars_on_frame` | count | `scores.heads[h].stars_on_frame`, sum over the heads |" in (
        metrics.record_table())


def test_flatten_refuses_a_score_no_metric_declares_and_one_that_is_missing():
    env = StarSensorEnv("paper_004")
    env.reset(seed=0)
    scores = env.step(None)[4]["scores"]
    flatten(scores)  # as the env made it: accepted
    scores["heads"][1]["brightness"] = 1.0
    with pytest.raises(ValueError, match=r"scores.heads\[1\] holds \['brightness'\]"):
        flatten(scores)
    del scores["heads"][1]["brightness"]
    del scores["heads"][0]["id_rate"]
    with pytest.raises(ValueError, match=r"scores.heads\[0\] lacks .*'id_rate'"):
        flatten(scores)
    with pytest.raises(ValueError, match=r"restoration\[0\] holds \['sharpness'\]"):
        flatten(blank_scores(1), restoration=[{"sharpness": 2.0}])


def test_flatten_carries_every_declared_metric():
    """Every metric of info["scores"] and of the record scope gets its record key (one per head for ``each``), and
    each agent role's latency its own; nothing else is added but the frame index (and the frame's time, from scores
    that carry it: the env's)."""
    n_heads = 3
    record = flatten(blank_scores(n_heads), {"detector": 0.002, "pipeline": 0.005})
    expected = {"frame", "latency_detector_ms", "latency_pipeline_ms"}
    for m in metrics.METRICS:
        if m.scope in ("step", "attitude", "body_attitude", "head_attitude", "head", "record"):
            expected |= {m.name.format(head=h) for h in range(n_heads)}
    assert set(record) == expected
    assert record["latency_pipeline_ms"] == 5.0 and record["head2_error_x_arcsec"] == 1.0
    assert flatten({**blank_scores(n_heads), "time_s": 0.25}, {"detector": 0.002})["time_s"] == 0.25


@pytest.mark.parametrize("solved, within, fixed", [(True, True, 1.0), (False, True, 0.0), (True, False, 0.0)])
def test_fixed_needs_a_solved_frame_within_the_threshold(solved, within, fixed):
    scores = blank_scores(2)
    scores["heads"][1]["solved"], scores["within_threshold"] = solved, within
    assert flatten(scores)["fixed"] == fixed


def test_recorded_field_numbers_stay_those_of_older_files():
    """Typed fields are numbered in declaration order: reordering the schema would change what older files mean."""
    c = messages.classes()
    numbers = {name: [(f.name, f.number) for f in c[name].DESCRIPTOR.fields] for name in c}
    assert numbers["HeadScores"] == [
        ("centroid_error_px_mean", 1), ("centroid_error_px_max", 2), ("detection_recall", 3),
        ("detection_precision", 4), ("id_rate", 5), ("false_id_rate", 6), ("ids_correct", 7), ("ids_wrong", 8),
        ("solved", 9), ("prediction_error_px_mean", 10), ("prediction_error_px_max", 11), ("predictions_scored", 12),
        ("correction_error_px_mean", 13), ("correction_error_x_px", 14), ("correction_error_y_px", 15),
        ("distortion_px_mean", 16), ("extra", 100)]
    assert numbers["HeadAttitudeError"] == [("x_arcsec", 1), ("y_arcsec", 2), ("roll_arcsec", 3),
                                            ("cross_boresight_arcsec", 4)]
    assert numbers["BodyAttitudeError"] == [("x_arcsec", 1), ("y_arcsec", 2), ("z_arcsec", 3)]
    assert numbers["AttitudeError"] == [("total_arcsec", 1), ("heads", 2), ("body", 3)]
    assert numbers["StepScores"] == [("frame", 1), ("time_s", 2), ("source", 3), ("available", 4),
                                     ("within_threshold", 5), ("attitude", 6), ("heads", 7), ("record", 8),
                                     ("record_without_value", 9)]


def test_docs_hold_the_generated_tables():
    """The README's info table, the env's and the episode's docstrings are the schema's (``python -m
    starenv.metrics`` prints the tables to paste)."""
    assert metrics.info_table() in (ROOT / "README.md").read_text(encoding="utf-8")
    assert metrics.info_table() in starenv.env.__doc__
    assert metrics.record_table() in starenv.episode.__doc__


def test_every_record_key_finds_its_metric_and_summary_column():
    assert metrics.lookup("latency_solver_ms").wall_clock and metrics.find("head12_error_y_arcsec")[1] == {
        "head": "12"}
    assert metrics.parse_column("prediction_error_px_mean_median") == ("prediction_error_px_mean", "median")
    assert metrics.parse_column("within_threshold") == ("within_threshold", "share")
    assert metrics.parse_column("id_rate_mean") == ("id_rate", "mean")
    assert metrics.parse_column("head1_error_roll_arcsec_rms") == ("head1_error_roll_arcsec", "rms")
    assert metrics.parse_column("time_s") is None and "time_s" in metrics.INDEX_KEYS
    assert metrics.parse_column("scenario") is None and metrics.find("headx_error_y_arcsec") is None
    with pytest.raises(KeyError, match="'sharpness': no metric"):
        metrics.lookup("sharpness")


@pytest.mark.parametrize("change", [{"group": "nowhere"}, {"pool": "sum"}, {"statistics": ("mode",)},
                                    {"name": "stars_{head}", "pool": "mean"}, {"shown": ("mean",)}])
def test_an_inconsistent_declaration_is_refused(change):
    fields = {"name": "x", "unit": "", "description": "", "group": "count", "statistics": ("median",),
              "scope": "step", "compute": len, **change}
    with pytest.raises(ValueError, match="metric"):
        metrics.Metric(**fields)
