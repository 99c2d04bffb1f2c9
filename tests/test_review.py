"""The Rerun review reads at a glance: frames stretched for the eye with the raw counts kept, overlays that say what
they are, panels only for data (one unit each) and a log of what happened -- checked on a constructed run whose
every marker, drop and loss of fix is known beforehand, and on the layout itself (no browser needed)."""

from collections import defaultdict

import numpy as np
import pytest
import rerun.blueprint as rrb
from rerun.blueprint.components import ContainerKind

from starenv import metrics
from starenv.env import StarSensorEnv
from starenv.episode import StepLog
from starenv.record import rerun as review
from starenv.record.rerun import (
    CLASSES,
    DROPPED,
    IDENTIFIED,
    PREDICTION,
    PREDICTION_OFF,
    TRUTH,
    UNIDENTIFIED,
    WRONG,
    RerunRecorder,
    blueprint,
    legend_markdown,
)
from starenv.view import stretch

BACKGROUND, SIGMA, PEAK = 1000.0, 10.0, 5000.0  # counts: a synthetic frame's background, noise, star peak above it


def star_frame(shape=(128, 128), seed=0) -> tuple[np.ndarray, tuple[int, int]]:
    """A uint16 frame: Gaussian noise about a flat background and one star (Gaussian spot, sigma 1 px); its peak."""
    rng = np.random.default_rng(seed)
    frame = BACKGROUND + SIGMA * rng.standard_normal(shape)
    y, x = np.mgrid[: shape[0], : shape[1]]
    peak = (40, 70)
    frame += PEAK * np.exp(-((x - peak[1]) ** 2 + (y - peak[0]) ** 2) / 2.0)
    return np.round(frame).astype(np.uint16), peak


def test_the_stretch_maps_the_background_to_black_and_a_star_peak_to_white():
    """Black up to the background + black_sigma noise sigmas: the median pixel (the background) maps to 0; the
    star's peak is above the 99.99th percentile, so it maps to 255.  Noise stays dark: the background's 99th
    percentile, about 2.3 sigma above it, maps to asinh((2.3 - 1) / 3) / asinh((500 - 1) / 3) = 0.07 of full scale
    for a 500-sigma peak; 0.15 leaves room for the noise estimate (median absolute deviation) being off by tens of
    percent."""
    frame, (py, px) = star_frame()
    shown = stretch(frame, review.BLACK_SIGMA)
    assert shown.dtype == np.uint8
    assert shown[py, px] == 255
    background = np.ones(frame.shape, dtype=bool)
    background[py - 6: py + 7, px - 6: px + 7] = False
    assert np.median(shown[background]) == 0
    assert np.percentile(shown[background], 99) < 0.15 * 255
    plain = stretch(frame)  # black at the background itself: half the noise shows, dim
    assert np.median(plain[background]) <= 1 and np.percentile(plain[background], 99) > np.percentile(
        shown[background], 99)


TRUE_XY = np.array([[100.0, 100.0], [200.0, 100.0], [300.0, 300.0], [400.0, 400.0]])
TRUE_IDS = np.array([10, 11, 12, 13])
# detections: 10 and 11 identified right, a claim of 99 (not on the frame) and one of 12 on star 13 (star 12 is
# 141 px away, far outside the 3 px gate) wrong, one without an id
DETECTED_XY = np.array([[100.3, 100.0], [200.0, 99.6], [300.0, 300.0], [400.0, 400.0], [50.0, 450.0]])
CLAIMED = np.array([10, 11, 99, 12, -1])
EXPECTED = [IDENTIFIED, IDENTIFIED, WRONG, WRONG, UNIDENTIFIED]
PREDICTED_XY, PREDICTED_IDS = np.array([[100.0, 100.0], [20.0, 20.0]]), np.array([10, 77])  # 77: not on the frame
# the run: frame 0 fixed, frame 1 dropped (the gyro prediction carries it: no fix), frame 2 fixed again
SOURCES = ["solved", "predicted", "solved"]


def step_log(k: int, env, frame: np.ndarray) -> StepLog:
    """Step ``k`` of the constructed run of one 512 x 512 head."""
    delivered = SOURCES[k] == "solved"
    width, height = env.scenario.heads[0].camera.width, env.scenario.heads[0].camera.height
    frames = np.zeros((1, height, width), dtype=np.uint16)
    frames[0] = frame
    q = np.array([0.0, 0.0, 0.0, 1.0])
    obs = {"frames": frames, "frame_valid": np.array([delivered]),
           "gyro": {"t": np.array([0.01 * k]), "rate": np.zeros((1, 3)), "count": 1}}
    truth = {"stars": [{"xy_centroid": TRUE_XY, "catalog_id": TRUE_IDS}], "time_s": 0.1 * k + 0.025, "frame": k,
             "attitude": q, "gyro_bias": np.zeros(3)}
    n = len(CLAIMED) if delivered else 0
    action = {"attitude": q, "detections_xy": DETECTED_XY[None], "catalog_ids": CLAIMED[None],
              "detection_mask": (np.arange(len(CLAIMED)) < n)[None], "predicted_xy": PREDICTED_XY[None],
              "predicted_ids": PREDICTED_IDS[None], "prediction_mask": np.ones((1, 2), dtype=bool)}
    fixed = float(delivered)
    record = {"frame": k, "available": 1.0, "within_threshold": 1.0, "solved": fixed, "fixed": fixed,
              "attitude_error_arcsec": 2.0, "centroid_error_px_mean": 0.2 if delivered else None,
              "ids_wrong": 2.0 if delivered else 0.0, "latency_pipeline_ms": 3.0}
    return StepLog(k, obs, truth, action, {"available": True}, record, SOURCES[k], {}, pipeline=object())


@pytest.fixture(scope="module")
def constructed(tmp_path_factory):
    """The constructed run recorded live: (rows, statics, raw frame, path); rows: (entity, frame) -> column -> value."""
    path = tmp_path_factory.mktemp("review") / "constructed.rrd"
    env = StarSensorEnv("paper_000")
    frame, _ = star_frame(shape=(512, 512), seed=1)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CI", "1")  # no Rerun analytics
        recorder = RerunRecorder(path)
        recorder.start(env, 0, None)
        for k in range(len(SOURCES)):
            recorder.step(step_log(k, env, frame))
        recorder.close()
    import rerun as rr

    rows, statics = defaultdict(dict), defaultdict(dict)
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        table = chunk.to_record_batch().to_pydict()
        for i in range(chunk.num_rows):
            cell = statics[chunk.entity_path] if chunk.is_static else rows[chunk.entity_path, table["frame"][i]]
            cell.update({k: v[i] for k, v in table.items() if k not in ("rerun.controls.RowId", "frame", "sim_time")
                         and v[i] is not None})
    return rows, statics, frame, path


def rgba(color) -> int:
    return (color[0] << 24) | (color[1] << 16) | (color[2] << 8) | 255


def test_every_overlay_kind_is_logged_with_its_class_and_the_legend_names_them_all(constructed):
    rows, statics, *_ = constructed
    context = statics["/"]["AnnotationContext:context"][0]
    assert {c["class_id"]: (c["class_description"]["info"]["label"], c["class_description"]["info"]["color"])
            for c in context} == {k: (c.label, rgba(c.color)) for k, c in CLASSES.items()}
    legend = statics["/legend"]["TextDocument:text"][0]
    assert all(c.label in legend and c.colour_name in legend for c in CLASSES.values())
    assert legend == legend_markdown([p for h in (None, 0) for p in review.metric_panels(step_log_keys(), h)])
    base = "/head0/image"
    assert rows[f"{base}/truth", 0]["LineStrips2D:class_ids"] == [TRUTH]  # one class for every ring
    assert len(rows[f"{base}/truth", 0]["LineStrips2D:strips"]) == len(TRUE_IDS)
    assert rows[f"{base}/detections", 0]["Boxes2D:class_ids"] == EXPECTED
    wrong = rows[f"{base}/wrong_ids", 0]
    assert wrong["Boxes2D:labels"] == ["HIP 99?", "HIP 12?"] and wrong["Boxes2D:class_ids"] == [WRONG]
    assert wrong["Boxes2D:show_labels"] == [True]  # the only labels shown: the rest carry theirs for hover
    for entity, kind in (("truth", "LineStrips2D"), ("detections", "Boxes2D"), ("predictions", "LineStrips2D")):
        assert rows[f"{base}/{entity}", 0][f"{kind}:show_labels"] == [False]
    assert rows[f"{base}/detections", 0]["Boxes2D:labels"] == ["HIP 10", "HIP 11", "HIP 99", "HIP 12", "no id"]
    assert rows[f"{base}/predictions", 0]["LineStrips2D:class_ids"] == [PREDICTION, PREDICTION_OFF] * 4  # 4 ticks
    assert rows[f"{base}/dropped", 1]["Boxes2D:class_ids"] == [DROPPED]
    assert rows[f"{base}/dropped/label", 1]["Points2D:labels"] == ["FRAME DROPPED"]
    assert not rows[f"{base}/dropped", 0].get("Boxes2D:class_ids") and not rows[f"{base}/dropped", 2].get(
        "Boxes2D:class_ids")
    # the 3-D view: detections in the same classes; the axes labelled at their tips only
    assert rows["/attitude/stars/detections", 0]["Points3D:class_ids"] == EXPECTED
    assert rows["/attitude/axis_labels", 0]["Points3D:labels"] == ["+X", "+Y", "+Z / head 0", ""]  # bore: +Z
    assert rows["/attitude/true", 0]["Arrows3D:show_labels"] == [False]


def test_frames_are_shown_stretched_with_the_raw_counts_kept_and_cleared_when_dropped(constructed):
    rows, _, frame, _ = constructed
    shown = rows["/head0/image", 0]
    height, width = frame.shape
    assert bytes(shown["Image:buffer"][0]) == stretch(frame, review.BLACK_SIGMA).tobytes()
    assert bytes(rows["/head0/raw", 0]["Image:buffer"][0]) == frame.astype("<u2").tobytes()
    assert "Image:buffer" not in rows["/head0/image", 1] and "Image:buffer" not in rows["/head0/raw", 1]
    assert rows["/head0/image", 1]["Clear:is_recursive"] == [False]
    assert (width, height) == (512, 512)


def test_the_log_and_the_status_timeline_get_the_drop_the_loss_of_fix_and_the_reacquisition(constructed):
    rows, _, _, path = constructed
    events = log_texts(path, "/log/events")
    wrong = "head 0: 2 wrong identification(s): HIP 99, HIP 12"
    assert events[0] == ["frame 0: first fix (solved, within the threshold)", f"frame 0: {wrong}"]
    assert events[1] == ["frame 1: fix lost: attitude carried by the predictor"]
    assert events[2] == ["frame 2: fix re-acquired, 0.1 s after it was lost", f"frame 2: {wrong}"]
    assert rows["/status/frames", 1]["StateChange:state"] == ["dropped: head 0"]
    assert rows["/status/frames", 2]["StateChange:state"] == ["all delivered"]
    assert [rows["/status/fixed", k]["StateChange:state"][0] for k in range(3)] == ["yes", "no", "yes"]
    assert ("/status/available", 1) not in rows  # logged when it changes only


def log_texts(path, entity: str) -> dict[int, list[str]]:
    """Frame -> the texts logged to ``entity``, in logging order."""
    import rerun as rr

    rows = defaultdict(list)
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        if chunk.entity_path == entity and not chunk.is_static:
            table = chunk.to_record_batch().to_pydict()
            for _row, frame, text in sorted(zip(table["rerun.controls.RowId"], table["frame"],
                                                  table["TextLog:text"], strict=True)):
                rows[frame] += text
    return rows


def test_the_log_lines_of_a_drop_come_from_the_recording(constructed):
    """Every log line of the constructed run's drop step: the drop and the carried attitude (one row each)."""
    rows = log_texts(constructed[3], "/log")
    assert sorted(rows[1]) == ["frame 1: head 0 frame dropped",
                               "frame 1: no attitude solution, reporting the gyro prediction"]
    assert not rows[0] and not rows[2]


def views(node):
    """Every view of a blueprint container, depth first."""
    if isinstance(node, rrb.Container):
        return [v for child in node.contents for v in views(child)]
    return [node]


def containers(node):
    if isinstance(node, rrb.Container):
        return [node] + [c for child in node.contents for c in containers(child)]
    return []


FIRST_RECORD = {"frame": 0, "available": 1.0, "fixed": 1.0, "attitude_error_arcsec": 1.0, "body_error_x_arcsec": 0.5,
                "head0_error_x_arcsec": 0.3, "centroid_error_px_mean": 0.1, "id_rate": 1.0, "ids_correct": 20,
                "latency_pipeline_ms": 4.0}


@pytest.mark.parametrize("n_heads", [1, 2, 3, 4])
def test_panels_hold_one_unit_and_only_groups_with_data(n_heads):
    """A panel per group and unit the first record holds (flags on the status timeline instead); none for a group
    without a key (restoration without a deblurrer, a filter's without one); per-head panels under their heads; no
    empty grid cell for 1-4 heads."""
    keys = {k: v for k, v in FIRST_RECORD.items() if not k.startswith("head") or int(k[4]) < n_heads}
    bp = blueprint([(512, 512)] * n_heads, keys)
    series = [v for v in views(bp.root_container) if isinstance(v, rrb.TimeSeriesView)]
    shown = {}
    for view in series:
        if view.origin == "gyro":
            continue
        paths = [p.removeprefix("+ ") for p in view.contents]
        keys_shown = [p.rsplit("/", 1)[1] for p in paths]
        assert len({metrics.lookup(k).unit for k in keys_shown}) == 1, view.name
        assert all(review.metric_path(k) == p for k, p in zip(keys_shown, paths, strict=True))
        shown.update(dict.fromkeys(keys_shown, view.origin))
    flags = {k for k in keys if k not in metrics.INDEX_KEYS and metrics.lookup(k).unit == "0/1"}
    assert set(shown) == set(keys) - set(metrics.INDEX_KEYS) - flags
    groups = {origin.split("/")[1] for origin in shown.values()}
    assert groups == {"attitude", "per_head", "px", "share", "count", "latency"}  # no gain, no filter panel
    assert [v.origin for v in views(bp.root_container) if isinstance(v, rrb.Spatial2DView)] == [
        f"head{h}" for h in range(n_heads)]
    assert sum(isinstance(v, rrb.StateTimelineView) for v in views(bp.root_container)) == 1
    for container in containers(bp.root_container):
        if container.kind == ContainerKind.Grid:
            assert len(container.contents) % container.grid_columns == 0  # a full grid: no empty cell
    with_gain = blueprint([(512, 512)], {**keys, "restoration_psnr_gain_db": 1.0})
    assert "metrics/gain" in {v.origin for v in views(with_gain.root_container)}


def step_log_keys() -> list[str]:
    return list(step_log(0, StarSensorEnv("paper_000"), np.zeros((512, 512), np.uint16)).record)


def test_no_plot_draws_a_legend_and_each_series_colour_is_distinct_in_its_panel_and_named(constructed):
    """Legends stay off the lines: every time-series view hides its legend; within a panel every series has its own
    colour (logged with the series' style), and the legend panel names the colour of each series whose panel title
    does not (axis errors are named red / green / blue in their titles)."""
    _, statics, *_ = constructed
    keys = {**FIRST_RECORD, "head1_error_x_arcsec": 0.1}
    bp = blueprint([(512, 512)] * 2, keys, with_filter=True)
    for view in views(bp.root_container):
        if isinstance(view, rrb.TimeSeriesView):
            assert list(view.properties["PlotLegend"].visible.as_arrow_array().to_pylist()) == [False], view.name
    legend = statics["/legend"]["TextDocument:text"][0]
    for panel in review.metric_panels(step_log_keys(), None):
        logged = [statics["/" + path]["SeriesLines:colors"][0] for path in panel.paths]
        assert logged == [rgba(c) for c in panel.rgb] and len(set(logged)) == len(logged), panel.title
        for name, colour in panel.colours:
            assert f"{name} {colour}" in legend


def test_the_raw_counts_are_a_transparent_layer_above_the_stretch_so_hovering_reads_them(constructed):
    rows, *_ = constructed
    raw, shown = rows["/head0/raw", 0], rows["/head0/image", 0]
    assert raw["Image:opacity"] == [0.0] and "Image:opacity" not in shown
    assert raw["Image:draw_order"][0] > shown["Image:draw_order"][0]


def test_the_3d_view_looks_along_the_boresights():
    bp = blueprint([(512, 512)], FIRST_RECORD, eye=review._eye(np.array([0.0, 0.0, 0.0, 1.0]), np.eye(3)))
    sky = next(v for v in views(bp.root_container) if isinstance(v, rrb.Spatial3DView))
    eye = sky.properties["EyeControls3D"]
    position = np.array(eye.position.as_arrow_array().to_pylist()[0])
    target = np.array(eye.look_target.as_arrow_array().to_pylist()[0])
    mean = np.ones(3) / np.sqrt(3.0)  # the mean boresight of heads along x, y, z (identity attitude)
    look = (target - position) / np.linalg.norm(target - position)
    assert look @ mean > np.cos(np.radians(30.0))  # looking out along the mean boresight, from behind the origin
    assert position @ mean < 0
