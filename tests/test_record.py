"""Recordings: the MCAP file holds exactly what the episode logged (Foxglove schemas, CRC-checked chunks, metadata that
reproduces the run), survives crashes, and Rerun reads it -- through its own MCAP importer and through ours."""

import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from starenv import cli
from starenv import scenario as scenario_mod
from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.record import messages
from starenv.record.mcap import McapRecorder, read_metadata, read_partial, read_steps
from starenv.record.rerun import RerunRecorder, mcap_to_rrd, metric_path

ROOT = Path(__file__).resolve().parents[1]
OVERRIDES = {"drops.probability": 0.3}  # paper_004 with frequent drops, so drop handling is recorded too
STEPS = 5
SEED = 2
RERUN = shutil.which("rerun")
# paper_004's epoch, 2026.0 (a Julian year), as Unix ns: J2000.0 + 26 x 365.25 days = 2026-01-01T00:00:00
ORIGIN_NS = int(datetime(2026, 1, 1, tzinfo=UTC).timestamp()) * 10**9
needs_rerun_cli = pytest.mark.skipif(RERUN is None, reason="the rerun CLI (rerun-sdk) is not installed")


@pytest.fixture(autouse=True)
def no_rerun_analytics(monkeypatch):
    monkeypatch.setenv("CI", "1")  # Rerun's analytics pipeline does not start while CI is set


class Collect:
    """Keeps every StepLog (and the env's cameras) for comparison with the recording."""

    def start(self, env, seed, pipeline):
        self.logs = []

    def step(self, log):
        self.logs.append(log)

    def close(self, error=None):
        pass


def record(path: Path, pipeline=True, steps=STEPS, extra=()):
    env = StarSensorEnv("paper_004", OVERRIDES)
    pipe = Pipeline.for_scenario(env.scenario) if pipeline else None
    seen = Collect()
    run_episode(env, pipe, seed=SEED, steps=steps, observers=[McapRecorder(path), seen, *extra])
    return seen.logs


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("record")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CI", "1")
        logs = record(tmp / "run.mcap", extra=[RerunRecorder(tmp / "live.rrd")])
    return tmp, logs


def rrd_rows(path: Path) -> Counter:
    """Temporal rows per entity (static ones, a series' style or the legend, left out)."""
    import rerun as rr

    rows = Counter()
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        if not chunk.is_static:
            rows[chunk.entity_path] += chunk.num_rows
    return rows


def image_rows(path: Path) -> Counter:
    """Rows per entity that hold an image (not a clear)."""
    import rerun as rr

    rows = Counter()
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "Image:buffer" in batch.schema.names:
            rows[chunk.entity_path] += batch.num_rows - batch.column("Image:buffer").null_count
    return rows


def rerun_cli(*args, **kw):
    return subprocess.run([RERUN, *map(str, args)], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "CI": "1"}, **kw)


def test_mcap_reads_back_with_expected_counts_and_valid_crcs(run):
    tmp, logs = run
    path = tmp / "run.mcap"
    assert not (tmp / "run.mcap.partial").exists()
    valid = np.array([log.obs["frame_valid"] for log in logs], dtype=bool)  # (steps, heads)
    assert (~valid).any(), "the drop override should drop some frames in this seeded run"
    available = sum(bool(log.scores["available"]) for log in logs)
    no_solution = sum(log.source != "solved" for log in logs)
    expected = {"/attitude/true": STEPS, "/attitude/estimate": available, "/scores": STEPS, "/gyro": STEPS}
    for h in range(valid.shape[1]):
        expected[f"/head{h}/image"] = int(valid[:, h].sum())
        for layer in ("truth", "detections", "predictions"):
            expected[f"/head{h}/{layer}"] = STEPS
        expected[f"/head{h}/calibration"] = expected[f"/head{h}/mounting"] = STEPS
    expected["/log"] = int((~valid).sum()) + no_solution
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
        assert counts == expected
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        seen = Counter(ch.topic for _, ch, _ in reader.iter_messages())  # decompresses every chunk, checks its CRC
        assert dict(seen) == expected
        times = [m.log_time for _, _, m in reader.iter_messages(log_time_order=False)]
    assert times == sorted(times)
    # log times are the frames' mid-exposure simulation times (10 Hz, exposure 0.05 s -> k * 0.1 s + 0.025 s) on the
    # scenario's epoch
    assert sorted(set(times)) == [ORIGIN_NS + int(round((k * 0.1 + 0.025) * 1e9)) for k in range(STEPS)]


def test_a_corrupted_chunk_fails_the_crc_check(run, tmp_path):
    path = tmp_path / "bad.mcap"
    data = bytearray((run[0] / "run.mcap").read_bytes())
    with open(run[0] / "run.mcap", "rb") as f:
        first = make_reader(f).get_summary().chunk_indexes[0]
    data[first.chunk_start_offset + first.chunk_length // 2] ^= 0xFF  # inside the compressed records
    path.write_bytes(bytes(data))
    with open(path, "rb") as f, pytest.raises(Exception):  # noqa: B017  (CRC mismatch or zstd corruption error)
        for _ in make_reader(f, validate_crcs=True).iter_messages():
            pass


def test_decoded_messages_equal_what_was_logged(run):
    tmp, logs = run
    decoded = {}
    with open(tmp / "run.mcap", "rb") as f:
        for _, channel, message, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append((message.log_time, msg))
    env = StarSensorEnv("paper_004", OVERRIDES)
    for h, head in enumerate(env.scenario.heads):
        images = [m for _, m in decoded[f"/head{h}/image"]]
        frames = [log.obs["frames"][h] for log in logs if log.obs["frame_valid"][h]]
        assert len(images) == len(frames)
        for img, frame in zip(images, frames, strict=True):
            assert (img.encoding, img.width, img.height, img.step) == ("mono16", 512, 512, 1024)
            assert img.data == frame[: head.camera.height, : head.camera.width].astype("<u2").tobytes()
    body_x = np.array([1.0, 0.0, 0.0])
    for (_, tf), log in zip(decoded["/attitude/true"], logs, strict=True):
        q = [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]
        assert (tf.parent_frame_id, tf.child_frame_id) == ("icrs", "body")
        # the transform maps body coordinates into ICRS: it undoes the attitude (ICRS -> body)
        truth = Rotation.from_quat(log.truth["attitude"])
        np.testing.assert_allclose(Rotation.from_quat(q).apply(truth.apply(body_x)), body_x, atol=1e-12)
    estimates = [log for log in logs if log.scores["available"]]
    for (_, tf), log in zip(decoded["/attitude/estimate"], estimates, strict=True):
        q = np.array([-tf.rotation.x, -tf.rotation.y, -tf.rotation.z, tf.rotation.w])
        np.testing.assert_array_equal(q, log.action["attitude"] / np.linalg.norm(log.action["attitude"]))
    for (_, msg), log in zip(decoded["/scores"], logs, strict=True):
        scores, record = messages.decode_scores(msg)
        assert record == log.record
        assert scores["attitude"] == log.scores["attitude"] and scores["heads"] == log.scores["heads"]
        assert msg.source == log.source
    for (_, msg), log in zip(decoded["/gyro"], logs, strict=True):
        n = int(log.obs["gyro"]["count"])
        assert n > 0 and list(msg.t_s) == log.obs["gyro"]["t"][:n].tolist()
        np.testing.assert_array_equal(np.column_stack([msg.rate_x_rad_s, msg.rate_y_rad_s, msg.rate_z_rad_s]),
                                      log.obs["gyro"]["rate"][:n])
    # overlays: Foxglove's pixel origin is the top-left pixel's corner, starenv's its centre
    for (_, ann), log in zip(decoded["/head0/detections"], logs, strict=True):
        mask = log.action["detection_mask"][0].astype(bool)
        xy = np.array([(p.x, p.y) for p in ann.points[0].points]).reshape(-1, 2)
        np.testing.assert_allclose(xy, log.action["detections_xy"][0][mask] + 0.5, atol=1e-12)
        ids = log.action["catalog_ids"][0][mask]
        assert [t.text for t in ann.texts] == [f"HIP {i}" for i in ids if i >= 0]
    for (_, ann), log in zip(decoded["/head1/truth"], logs, strict=True):
        assert [t.text for t in ann.texts] == [f"HIP {i}" for i in log.truth["stars"][1]["catalog_id"]]
    drops = [m.message for _, m in decoded["/log"] if "dropped" in m.message]
    assert len(drops) == sum(int((~log.obs["frame_valid"].astype(bool)).sum()) for log in logs)


def test_read_steps_returns_the_logged_steps(run):
    tmp, logs = run
    steps = list(read_steps(tmp / "run.mcap"))
    assert [s.frame for s in steps] == [log.index for log in logs]
    for s, log in zip(steps, logs, strict=True):
        for h, head in enumerate(s.heads):
            if log.obs["frame_valid"][h]:
                np.testing.assert_array_equal(head.image, log.obs["frames"][h])
            else:
                assert head.image is None
            truth = log.truth["stars"][h]
            np.testing.assert_array_equal(head.truth.ids, truth["catalog_id"])
            np.testing.assert_allclose(head.truth.xy, truth["xy_centroid"], atol=1e-12)
        np.testing.assert_array_equal(s.attitude_true, log.truth["attitude"])  # conjugated twice: exact


def test_metadata_reproduces_the_run(run):
    tmp, logs = run
    meta = read_metadata(tmp / "run.mcap")
    toml = meta["starenv.scenario"]["toml"]
    original = scenario_mod.load("paper_004", OVERRIDES)
    reloaded = scenario_mod.load(tomllib.loads(toml))
    assert reloaded.to_toml() == original.to_toml() == toml
    assert meta["starenv.run"]["seed"] == str(SEED) and meta["starenv.outcome"]["status"] == "complete"
    assert meta["starenv.outcome"]["steps"] == str(STEPS)
    command = meta["starenv.outcome"]["reproduce"]
    assert f"--seed {SEED} --steps {STEPS}" in command and "--agent detector=starenv.agents.detect:" in command
    # the embedded scenario with the recorded seed renders the same first frame
    env = StarSensorEnv(tomllib.loads(toml))
    obs, _ = env.reset(seed=int(meta["starenv.run"]["seed"]))
    first = next(read_steps(tmp / "run.mcap"))
    for h, head in enumerate(first.heads):
        if head.image is not None:
            np.testing.assert_array_equal(head.image, obs["frames"][h])


def test_the_recorded_command_reproduces_the_recording(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    first = tmp_path / "first.mcap"
    assert cli.main(["run", "paper_004", "--pipeline", "none", "--steps", "3", "--seed", "5",
                     "--set", "drops.probability=0.3", "--record", str(first)]) == 0
    meta = read_metadata(first)
    (tmp_path / "scenario.toml").write_text(meta["starenv.scenario"]["toml"])
    words = shlex.split(meta["starenv.outcome"]["reproduce"])
    assert words[:2] == ["starenv", "run"]
    assert cli.main([*words[1:], "--record", "again.mcap"]) == 0
    assert (tmp_path / "again.mcap").read_bytes() == first.read_bytes()


@needs_rerun_cli
def test_rerun_mcap_check_passes(run):
    out = rerun_cli("mcap", "check", run[0] / "run.mcap")
    assert out.returncode == 0, out.stderr
    rows = [line.split() for line in out.stdout.splitlines() if line.strip().startswith(("ok", "warn", "error"))]
    assert len(rows) == 23 and all(r[0] == "ok" for r in rows), out.stdout  # 6 topics per head + 5 others


@needs_rerun_cli
def test_rerun_imports_the_images_from_the_mcap(run, tmp_path):
    """Rerun's own MCAP importer (its foxglove decoder) turns /head{h}/image into 16-bit mono images, unchanged."""
    import rerun as rr

    tmp, logs = run
    out = rerun_cli("mcap", "convert", tmp / "run.mcap", "-o", tmp_path / "conv.rrd")
    assert out.returncode == 0, out.stderr
    images = {}
    for chunk in rr.chunk.RrdReader(tmp_path / "conv.rrd").stream().to_chunks():
        batch = chunk.to_record_batch()
        if chunk.entity_path.endswith("/image") and "Image:buffer" in batch.schema.names:
            for t, buf, fmt in zip(batch.column("message_log_time").cast("int64").to_pylist(),
                                   batch.column("Image:buffer"), batch.column("Image:format").to_pylist(),
                                   strict=True):
                assert (fmt[0]["width"], fmt[0]["height"]) == (512, 512)
                images[chunk.entity_path, t] = np.asarray(buf.values[0].values).tobytes()
    expected = {(f"/head{h}/image", ORIGIN_NS + int(round(log.truth["time_s"] * 1e9))):
                log.obs["frames"][h].astype("<u2").tobytes()
                for log in logs for h in range(3) if log.obs["frame_valid"][h]}
    assert images.keys() == expected.keys()
    assert all(images[k] == expected[k] for k in expected)


def test_view_builds_the_review_recording(run, tmp_path, monkeypatch, capsys):
    tmp, logs = run
    shutil.copy(tmp / "run.mcap", tmp_path / "copy.mcap")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert cli.main(["view", str(tmp_path / "copy.mcap")]) == 0  # no display: the .rrd goes next to the MCAP
    assert f"wrote {tmp_path / 'copy.rrd'}" in capsys.readouterr().out
    rrd = tmp_path / "review.rrd"
    assert cli.main(["view", str(tmp / "run.mcap"), "--rrd", str(rrd)]) == 0
    assert rrd_content(rrd) == rrd_content(tmp_path / "copy.rrd")
    rows = rrd_rows(rrd)
    images = image_rows(rrd)
    for h in range(3):
        delivered = sum(int(log.obs["frame_valid"][h]) for log in logs)
        assert images[f"/head{h}/image"] == images[f"/head{h}/raw"] == delivered < STEPS
        assert rows[f"/head{h}/image"] == rows[f"/head{h}/raw"] == STEPS  # a dropped frame clears both
        for layer in ("truth", "detections", "predictions"):
            assert rows[f"/head{h}/image/{layer}"] == STEPS
    for key, group in (("attitude_error_arcsec", "attitude"), ("body_error_z_arcsec", "attitude"),
                       ("head1_error_x_arcsec", "per_head"), ("centroid_error_px_mean", "px"),
                       ("id_rate", "share"), ("fixed", "share"), ("ids_correct", "count"),
                       ("prediction_error_px_mean", "px"), ("latency_pipeline_ms", "latency")):
        assert metric_path(key).startswith(f"metrics/{group}/")
        assert rows["/" + metric_path(key)] == sum(log.record.get(key) is not None for log in logs), key
    n_logs = sum(int((~log.obs["frame_valid"].astype(bool)).sum()) + (log.source != "solved") for log in logs)
    assert rows["/log"] == n_logs
    import rerun as rr

    reader = rr.chunk.RrdReader(rrd)
    assert len(reader.blueprints()) == 1
    chunks = reader.stream().to_chunks()
    assert all("log_time" not in c.timeline_names for c in chunks)
    assert all(set(c.timeline_names) == {"frame", "sim_time"} for c in chunks if not c.is_static)


def rrd_content(path: Path) -> dict:
    """(entity, frame, sim_time) -> component -> value of every temporal row, whatever chunks hold it."""
    import rerun as rr

    rows = {}
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        if chunk.is_static:
            continue
        table = chunk.to_record_batch().to_pydict()
        components = [k for k in table if k not in ("rerun.controls.RowId", "frame", "sim_time")]
        for i, (frame, t) in enumerate(zip(table["frame"], table["sim_time"], strict=True)):
            cell = rows.setdefault((chunk.entity_path, frame, t), {})
            for k in components:
                cell.setdefault(k, []).append(table[k][i])
    return rows


def test_live_rerun_recorder_and_mcap_review_log_the_same_data(run, tmp_path):
    """The live recorder batches rows into other chunks than the MCAP review does, so compare rows, not chunks."""
    tmp, _ = run
    review = rrd_content(mcap_to_rrd(tmp / "run.mcap", tmp_path / "review.rrd"))
    live = rrd_content(tmp / "live.rrd")
    assert review.keys() == live.keys() and len(review) > 100
    assert review == live


def test_unknown_metrics_are_kept():
    typed = dict(messages.layout())
    scores = {"frame": 7, "available": True, "within_threshold": False,
              "attitude": {"total_arcsec": 1.5, "heads": [dict.fromkeys(dict(typed["head_attitude"]), 0.25)]},
              "heads": [{**dict.fromkeys(dict(typed["head"])), "ids_correct": 4, "ids_wrong": 0, "solved": True,
                         "predictions_scored": 0, "restoration_psnr_gain_db": 3.5}]}
    record = {"attitude_error_arcsec": 1.5, "restoration_stars_after": 12.0, "id_rate": None}
    msg = messages.classes()["StepScores"].FromString(
        messages.encode_scores(7, 0.7, "solved", scores, record).SerializeToString())
    back, rec = messages.decode_scores(msg)
    assert rec == record and back == scores


@settings(max_examples=50, deadline=None)
@given(st.dictionaries(st.text(min_size=1, max_size=12),
                       st.none() | st.floats(allow_nan=False) | st.integers(-2**52, 2**52), max_size=8))
def test_any_flat_record_round_trips(record):
    scores = {"frame": 0, "available": False, "within_threshold": False, "attitude": None, "heads": []}
    _, back = messages.decode_scores(messages.encode_scores(0, 0.0, "none", scores, record))
    assert back == record


def test_two_seeded_runs_give_identical_recordings(tmp_path):
    """Without a pipeline the recordings are byte-identical; with one, only the agents' wall-clock latencies
    differ (decoded below)."""
    record(tmp_path / "a.mcap", pipeline=False, steps=3)
    record(tmp_path / "b.mcap", pipeline=False, steps=3)
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()
    record(tmp_path / "c.mcap", steps=3)
    record(tmp_path / "d.mcap", steps=3)
    for c, d in zip(read_steps(tmp_path / "c.mcap"), read_steps(tmp_path / "d.mcap"), strict=True):
        differ = {k for k in c.record if c.record[k] != d.record[k]}
        assert all(k.startswith("latency_") for k in differ)
        assert [h.image is None or np.array_equal(h.image, g.image) for h, g in zip(c.heads, d.heads, strict=True)]
        np.testing.assert_array_equal(c.attitude_estimate, d.attitude_estimate)


@needs_rerun_cli
def test_two_reviews_of_a_recording_hold_the_same_data(run, tmp_path):
    """Rerun stamps chunk and row ids from the clock, gives the blueprint a random id and flushes its chunks from a
    background thread on a wall-clock tick, so the .rrd bytes and the order of chunks differ; the recording id and the
    data (entities, timelines, rows) are identical, as ``rerun rrd compare --unordered`` confirms -- and the same
    comparison tells a recording of the same run without a pipeline apart."""
    import rerun as rr

    a = mcap_to_rrd(run[0] / "run.mcap", tmp_path / "a.rrd")
    b = mcap_to_rrd(run[0] / "run.mcap", tmp_path / "b.rrd")
    ids = {rr.chunk.RrdReader(p).recordings()[0].recording_id for p in (a, b)}
    assert len(ids) == 1
    out = rerun_cli("rrd", "compare", "--unordered", a, b)
    assert out.returncode == 0, out.stdout + out.stderr
    record(tmp_path / "bare.mcap", pipeline=False)
    bare = mcap_to_rrd(tmp_path / "bare.mcap", tmp_path / "bare.rrd")
    assert rerun_cli("rrd", "compare", "--unordered", a, bare).returncode != 0


def test_killed_run_leaves_a_readable_partial_file_and_the_old_recording_intact(run, tmp_path):
    path = tmp_path / "crash.mcap"
    shutil.copy(run[0] / "run.mcap", path)
    before = path.read_bytes()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "starenv.cli", "run", "paper_004", "--pipeline", "none",
                             "--steps", "90", "--record", str(path)], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    partial = Path(str(path) + ".partial")
    deadline = time.monotonic() + 120
    try:  # wait for a few 1 MiB chunks (less once compressed) to reach the file
        while not (partial.exists() and partial.stat().st_size > 1_500_000):
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "the recording did not grow"
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert path.read_bytes() == before  # the finished recording was not touched
    counts = read_partial(partial)
    assert counts["/head0/image"] >= 2 and counts["/scores"] >= 2
    with pytest.raises(Exception):  # noqa: B017  (an unfinished file has no footer/summary)
        with open(partial, "rb") as f:
            list(make_reader(f).iter_messages())


class FailingPipeline:
    """The built-in pipeline, except that its call for frame ``fail_at`` raises (an agent failure)."""

    def __init__(self, scenario, fail_at):
        self.inner, self.fail_at, self.calls = Pipeline.for_scenario(scenario), fail_at, 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __call__(self, obs):
        if self.calls == self.fail_at:
            raise RuntimeError("detector exploded")
        self.calls += 1
        return self.inner(obs)


def test_an_exception_mid_run_leaves_a_closed_recording_with_the_failure_logged(tmp_path):
    env = StarSensorEnv("paper_004")
    path, rrd = tmp_path / "fail.mcap", tmp_path / "fail.rrd"
    with pytest.raises(RuntimeError, match="detector exploded"):
        run_episode(env, FailingPipeline(env.scenario, 3), seed=1, steps=6,
                    observers=[McapRecorder(path), RerunRecorder(rrd)])
    assert path.exists() and not Path(str(path) + ".partial").exists()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        logs = [(m.log_time, d) for _, _, m, d in reader.iter_decoded_messages(topics=["/log"])]
    assert logs[-1][1].level == 4 and "RuntimeError: detector exploded" in logs[-1][1].message
    assert logs[-1][0] == ORIGIN_NS + int(round((3 * 0.1 + 0.025) * 1e9))  # stamped with the frame that failed
    steps = list(read_steps(path))
    assert [s.frame for s in steps] == [0, 1, 2, 3] and steps[-1].logs[-1][1].startswith("frame 3: run stopped")
    meta = read_metadata(path)["starenv.outcome"]
    assert meta["status"] == "error" and meta["steps"] == "3" and "detector exploded" in meta["error"]
    assert rrd_rows(rrd)["/log"] >= 1


def test_a_writer_failure_reaches_the_episode(tmp_path, monkeypatch):
    import starenv.record.mcap as mcap_mod

    def broken(data, origin_ns=0):
        raise OSError("disk full")

    monkeypatch.setattr(mcap_mod, "encode_step", broken)
    env = StarSensorEnv("paper_004")
    path = tmp_path / "broken.mcap"
    with pytest.raises(RuntimeError, match="writing .*broken.mcap.partial failed") as info:
        run_episode(env, None, seed=1, steps=8, observers=[McapRecorder(path)])
    assert isinstance(info.value.__cause__, OSError)
    assert not path.exists() and Path(str(path) + ".partial").exists()


def test_bad_input_gets_a_clear_error(tmp_path, capsys):
    with pytest.raises(ValueError, match="ending in .mcap"):
        McapRecorder(tmp_path / "x.txt")
    with pytest.raises(ValueError, match="compression"):
        McapRecorder(tmp_path / "x.mcap", compression="gzip")
    with pytest.raises(ValueError, match="ending in .rrd"):
        RerunRecorder(tmp_path / "x.mcap")
    assert cli.main(["view", str(tmp_path / "missing.mcap")]) == 2
    assert "no such file" in capsys.readouterr().err
    (tmp_path / "text.mcap").write_text("hello")
    assert cli.main(["view", str(tmp_path / "text.mcap")]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


def test_foxglove_cameras_place_every_true_star(run):
    """Chaining the recorded transforms icrs <- body <- head{h} and the recorded CameraCalibration takes each true
    star's catalog direction to its recorded truth point (paper_004: three heads, no distortion, exact calibration),
    read with the plain mcap reader and the protobuf decoder only."""
    tmp, logs = run
    env = StarSensorEnv("paper_004", OVERRIDES)
    catalog = env.sensor.catalog
    by_time: dict[int, dict[str, object]] = {}
    with open(tmp / "run.mcap", "rb") as f:
        for _, channel, message, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            by_time.setdefault(message.log_time, {})[channel.topic] = msg
    assert len(by_time) == STEPS
    row = {int(h): i for i, h in enumerate(catalog.hip)}
    for (t, msgs), log in zip(sorted(by_time.items()), logs, strict=True):
        assert t == ORIGIN_NS + int(round(log.truth["time_s"] * 1e9))
        body = msgs["/attitude/true"]
        r_icrs_body = Rotation.from_quat([body.rotation.x, body.rotation.y, body.rotation.z, body.rotation.w])
        for h, head in enumerate(env.scenario.heads):
            cal, tf = msgs[f"/head{h}/calibration"], msgs[f"/head{h}/mounting"]
            assert (cal.frame_id, tf.parent_frame_id, tf.child_frame_id) == (f"head{h}", "body", f"head{h}")
            assert (cal.width, cal.height, cal.distortion_model, list(cal.D)) == (512, 512, "", [])
            assert cal.timestamp.seconds * 10**9 + cal.timestamp.nanos == t
            r_body_head = Rotation.from_quat([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w])
            k = np.array(cal.K).reshape(3, 3)
            stars = log.truth["stars"][h]
            units = catalog.unit[[row[int(i)] for i in stars["catalog_id"]]]
            v = (r_icrs_body * r_body_head).inv().apply(units)  # head frame
            uv = (k @ v.T).T
            xy_foxglove = uv[:, :2] / uv[:, 2:]
            assert len(xy_foxglove) > 0
            # the truth point is the trail centroid; at mid-exposure the star sits at xy_mid (+0.5 px origin)
            np.testing.assert_allclose(xy_foxglove, np.asarray(stars["xy_mid"]) + 0.5, atol=1e-6)
            assert head.calibrated.fx == k[0, 0]


def test_rerun_review_holds_the_attitude_view_and_gyro_series(run):
    """The live .rrd's 3-D arrows are the true body axes and head boresights written in ICRS (an independent
    composition: attitude^-1 applied to the body axes and to mounting^-1 z), its true stars sit on their catalog
    directions, and every gyro sample is a point of
    the gyro series at its own simulation time, in deg/s."""
    import rerun as rr

    tmp, logs = run
    env = StarSensorEnv("paper_004", OVERRIDES)
    arrows, gyro, sky = [], {}, []
    for chunk in rr.chunk.RrdReader(tmp / "live.rrd").stream().to_chunks():
        batch = chunk.to_record_batch()
        if chunk.entity_path == "/attitude/true":
            arrows += [np.array(v.as_py()) for v in batch.column("Arrows3D:vectors")]
        elif chunk.entity_path == "/attitude/stars/truth":
            sky += [(np.array(v.as_py()).reshape(-1, 3), labels.as_py()) for v, labels in
                    zip(batch.column("Points3D:positions"), batch.column("Points3D:labels"), strict=True)]
        elif chunk.entity_path.startswith("/gyro/rate_dps/") and not chunk.is_static:  # static: the series' style
            axis = chunk.entity_path[-1]
            for t, v in zip(batch.column("sim_time").cast("int64").to_pylist(), batch.column("Scalars:scalars"),
                            strict=True):
                gyro[axis, t] = v.as_py()[0]
    assert len(arrows) == STEPS
    for vectors, log in zip(arrows, logs, strict=True):
        to_icrs = Rotation.from_quat(log.truth["attitude"]).inv()
        bores = [to_icrs.apply(h.calibrated.mounting.inv().apply([0, 0, 1])) for h in env.scenario.heads]
        np.testing.assert_allclose(vectors, np.vstack([to_icrs.apply(np.eye(3)), bores]), atol=1e-6)
    # the true stars on the sky: their catalog directions, to within the trail centroid's offset from the
    # mid-exposure position (a slow drift: well under 1 px = 42 arcsec = 2e-4 rad)
    catalog = env.sensor.catalog
    row = {int(h): i for i, h in enumerate(catalog.hip)}
    assert len(sky) == STEPS
    for (points, labels), log in zip(sky, logs, strict=True):
        hips = [int(lab.removeprefix("HIP ")) for lab in labels]
        assert hips == [int(i) for h in range(3) for i in log.truth["stars"][h]["catalog_id"]] and hips
        np.testing.assert_allclose(points, catalog.unit[[row[i] for i in hips]], atol=2e-4)
    samples = [(t, r) for log in logs for t, r in zip(log.obs["gyro"]["t"][: int(log.obs["gyro"]["count"])],
                                                      log.obs["gyro"]["rate"], strict=False)]
    assert len(gyro) == 3 * len(samples)
    for t, rate in samples:
        t_ns = int(round(t * 1e9))
        np.testing.assert_allclose([gyro[a, t_ns] for a in "xyz"], np.degrees(rate), rtol=1e-12)


class Posterior:
    """Keeps, per step, the fusion filter's own posterior (asked of the filter, not of the step log) and the true
    gyro bias and attitude."""

    def start(self, env, seed, pipeline):
        self.filter, self.states, self.events = pipeline.agents["predictor"], [], []

    def step(self, log):
        self.events.append(list(self.filter.events))
        self.states.append((*self.filter.posterior(), log.truth["gyro_bias"], log.truth["attitude"],
                            log.record["attitude_error_arcsec"]))

    def close(self, error=None):
        pass


@pytest.fixture(scope="module")
def filtered(tmp_path_factory):
    """paper_000 at 1 deg/s with the MEKF as predictor, recorded to MCAP and live to Rerun."""
    tmp = tmp_path_factory.mktemp("filtered")
    env = StarSensorEnv("paper_000", {"motion.rate_dps": [1.0, 0.0, 0.0]})
    pipe = Pipeline.for_scenario(env.scenario, {"predictor": "starenv.agents.fuse:MekfPredictor"})
    seen = Posterior()
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CI", "1")
        run_episode(env, pipe, seed=0, steps=STEPS,
                    observers=[McapRecorder(tmp / "run.mcap"), RerunRecorder(tmp / "live.rrd"), seen])
    return tmp, seen.states, seen.events


DEG_HR, ARCSEC_PER_RAD = np.degrees(1.0) * 3600.0, np.degrees(1.0) * 3600.0  # rad/s -> deg/h, rad -> arcsec


def test_the_filter_state_is_recorded_as_the_filter_reported_it(filtered, run):
    """The /filter channel holds, per step, the filter's own attitude, bias (deg/h), the true bias and the square
    roots of its covariance's diagonal (arcsec, deg/h); a pipeline without a filter writes no /filter channel."""
    tmp, states, _ = filtered
    with open(tmp / "run.mcap", "rb") as f:
        decoded = [(ch, msg) for _, ch, _, msg in make_reader(f, decoder_factories=[DecoderFactory()])
                   .iter_decoded_messages(topics=["/filter"])]
    assert len(decoded) == STEPS == len(states)
    assert {ch.topic for ch, _ in decoded} == {"/filter"}
    for (_, msg), (attitude, bias, cov, true_bias, *_) in zip(decoded, states, strict=True):
        np.testing.assert_array_equal(msg.attitude_xyzw, attitude.as_quat())
        np.testing.assert_allclose(msg.bias_deg_hr, bias * DEG_HR, rtol=1e-14)
        np.testing.assert_allclose(msg.bias_true_deg_hr, true_bias * DEG_HR, rtol=1e-14)
        np.testing.assert_allclose(msg.attitude_sigma_arcsec, np.sqrt(np.diag(cov)[:3]) * ARCSEC_PER_RAD, rtol=1e-14)
        np.testing.assert_allclose(msg.bias_sigma_deg_hr, np.sqrt(np.diag(cov)[3:]) * DEG_HR, rtol=1e-14)
    assert decoded[-1][1].bias_sigma_deg_hr[0] < decoded[0][1].bias_sigma_deg_hr[0]  # it learns
    steps = list(read_steps(tmp / "run.mcap"))
    for s, (attitude, *_) in zip(steps, states, strict=True):
        np.testing.assert_array_equal(s.filter.attitude, attitude.as_quat())
    with open(run[0] / "run.mcap", "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert "/filter" not in topics and all(s.filter is None for s in read_steps(run[0] / "run.mcap"))


def test_the_filters_events_are_in_the_recordings_log(filtered):
    """Every event the filter reported on a step (its start, gate rejections, restarts) is a /log line of that step,
    in order, read back from the MCAP file; the first step's is the filter's start."""
    tmp, _, events = filtered
    steps = list(read_steps(tmp / "run.mcap"))
    assert len(steps) == len(events)
    for k, (step, reported) in enumerate(zip(steps, events, strict=True)):
        logged = [(level, text) for level, text in step.logs if text.startswith(f"frame {k}: filter")]
        assert logged == [(level, f"frame {k}: {text}") for level, text in reported]
    assert events[0][0][1].startswith("filter started from the frame's solution")


def test_the_rerun_review_plots_the_filter_against_truth(filtered, tmp_path):
    """Live and from the MCAP, per body axis: the attitude error (rotation vector of A_est A_true^T, arcsec) and the
    bias error (deg/h) beside the filter's +-3 sigma, and the bias estimate beside the truth; the review of a
    recording without a filter has no filter series."""
    import rerun as rr

    tmp, states, _ = filtered
    review = rrd_content(mcap_to_rrd(tmp / "run.mcap", tmp_path / "review.rrd"))
    assert review == rrd_content(tmp / "live.rrd")
    series = {}
    for chunk in rr.chunk.RrdReader(tmp / "live.rrd").stream().to_chunks():
        if chunk.entity_path.startswith("/filter/") and not chunk.is_static:  # static: the series' style
            batch = chunk.to_record_batch()
            for frame, v in zip(batch.column("frame").to_pylist(), batch.column("Scalars:scalars"), strict=True):
                series[chunk.entity_path, frame] = v.as_py()[0]
    assert len(series) == STEPS * 3 * 8
    for k, (attitude, bias, cov, true_bias, true_attitude, scored) in enumerate(states):
        error = (attitude * Rotation.from_quat(true_attitude).inv()).as_rotvec() * ARCSEC_PER_RAD
        sigma = np.sqrt(np.diag(cov))
        plotted = [series[f"/filter/attitude_error_arcsec/{axis}/error", k] for axis in "xyz"]
        np.testing.assert_allclose(np.linalg.norm(plotted), scored, rtol=1e-6)  # the scorer's error angle
        for i, axis in enumerate("xyz"):
            np.testing.assert_allclose(series[f"/filter/attitude_error_arcsec/{axis}/error", k], error[i], atol=1e-9)
            np.testing.assert_allclose(series[f"/filter/attitude_error_arcsec/{axis}/plus_3sigma", k],
                                       3 * sigma[i] * ARCSEC_PER_RAD, rtol=1e-12)
            np.testing.assert_allclose(series[f"/filter/bias_error_deg_hr/{axis}/minus_3sigma", k],
                                       -3 * sigma[3 + i] * DEG_HR, rtol=1e-12)
            np.testing.assert_allclose(series[f"/filter/bias_error_deg_hr/{axis}/error", k],
                                       (bias[i] - true_bias[i]) * DEG_HR, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(series[f"/filter/bias_deg_hr/{axis}/true", k], true_bias[i] * DEG_HR,
                                       rtol=1e-12)
    assert not any(entity.startswith("/filter") for entity, *_ in review_without_filter(tmp_path))


def review_without_filter(tmp_path):
    path = tmp_path / "classical.mcap"
    record(path, steps=2)
    return rrd_content(mcap_to_rrd(path, tmp_path / "classical.rrd"))
