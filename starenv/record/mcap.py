"""MCAP recordings of episodes in Foxglove's well-known protobuf schemas, readable by Foxglove and Rerun.

Channels (log times and header stamps: integer ns, the frame's mid-exposure simulation time placed on the scenario's
epoch, never wall clock.  Simulation time 0 is the scenario's ``epoch`` read as a Julian epoch, J2000.0 (2000-01-01
12:00:00) + (epoch - 2000) x 365.25 days, written as Unix time with the TT-UTC offset (~69 s) and leap seconds
ignored: ``epoch = 2026.0`` puts frame 0 at 2026-01-01T00:00:00 + its mid-exposure.  The offset is the ``starenv.run``
metadata's ``time_origin_unix_ns``; the ``/scores`` and ``/gyro`` payloads keep simulation seconds):

* ``/head{h}/image``: ``foxglove.RawImage``, ``mono16`` little-endian, the frame as the sensor delivered it (none on a
  dropped frame);
* ``/head{h}/calibration``: ``foxglove.CameraCalibration``, frame ``head{h}``: the calibrated (sensor-known) pinhole
  intrinsics with the principal point + 0.5 px (Foxglove's pixel origin, below), ``plumb_bob`` coefficients
  ``[k1, k2, p1, p2, k3]`` for a Brown-Conrady head, no coefficients for other distortion models (paper 000's per-axis
  radial and paper 003's Legendre field have no Foxglove equivalent: their images are shown undistorted-as-pinhole);
* ``/head{h}/mounting``: ``foxglove.FrameTransform`` parent ``body``, child ``head{h}``: the calibrated mounting
  (camera axes: +Z boresight, +X along columns, +Y along rows, Foxglove's optical-frame convention), i.e. the inverse
  of the body -> camera rotation.  Calibration and mounting are written with every step so that seeking finds them;
* ``/head{h}/truth``, ``/head{h}/detections``, ``/head{h}/predictions``: ``foxglove.ImageAnnotations``: the true
  stars' trail centroids, the pipeline's detections and its predicted positions as points, with a ``HIP n`` label on
  every point that carries a catalog id (true stars, identified detections, predictions).  Foxglove's image
  coordinates put (0, 0) at the top-left *corner* of the top-left pixel, so points are starenv's positions + 0.5 px;
* ``/attitude/true``, ``/attitude/estimate``: ``foxglove.FrameTransform`` parent ``icrs``, child ``body`` /
  ``body_estimate``.  A FrameTransform gives the child frame's orientation in the parent frame (it maps child
  coordinates to parent coordinates), i.e. the inverse of starenv's attitude (ICRS -> body): the rotation written is
  the conjugate of ``truth["attitude"]`` / ``action["attitude"]``;
* ``/scores``: ``starenv.StepScores`` (``starenv.record.messages``); ``/gyro``: ``starenv.GyroSamples``;
* ``/filter``: ``starenv.FilterState``, only for a pipeline whose predictor is a fusion filter, on every step it has a
  state: its attitude, gyro bias estimate, the true bias and the 1-sigma of both (arcsec, deg/h, body axes);
* ``/log``: ``foxglove.Log``: dropped frames, steps without a solution, and the error that ended a run.

Metadata records: ``starenv.scenario`` (the scenario as TOML, overrides applied), ``starenv.run`` (seed, heads,
pipeline agents, starenv version) and, at the end, ``starenv.outcome`` (steps recorded, status, error and the
``starenv run`` command that reproduces the recording).

Crash safety: the file is written as ``FILE.mcap.partial`` (chunks reach the file as they fill) and renamed to
``FILE.mcap`` when the recorder closes, also after an error (the error is logged to ``/log`` first), so an existing
finished recording is replaced in one step, never half-overwritten.  A killed process leaves the ``.partial`` file,
readable up to its last complete chunk: :func:`read_partial` counts its messages, :func:`recover` (``starenv recover
FILE.mcap.partial``) writes a finished MCAP of its complete steps, and ``starenv view`` reviews it directly.
"""

from __future__ import annotations

import json
import os
import queue
import shlex
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.well_known import MessageEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.schema import register_schema

import starenv
from starenv.record import messages
from starenv.record.step import ERROR, FilterState, HeadData, Stars2D, StepData, from_step_log, time_ns
from starenv.sim.optics import BrownConrady

MAGIC = b"\x89MCAP0\r\n"
PIXEL_ORIGIN = 0.5  # Foxglove/Rerun image coordinates = starenv pixel coordinates + 0.5
LAYERS = {"truth": (0.2, 0.9, 0.2), "detections": (1.0, 0.3, 0.2), "predictions": (0.2, 0.7, 1.0)}  # RGB
COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


J2000_UNIX_S = 946_728_000  # 2000-01-01T12:00:00 as Unix time (s)
JULIAN_YEAR_S = 365.25 * 86_400


def time_origin_ns(epoch: float) -> int:
    """Unix time (ns) of simulation time 0: the scenario's ``epoch`` (Julian year), as the module docstring says."""
    return int(round((J2000_UNIX_S + (float(epoch) - 2000.0) * JULIAN_YEAR_S) * 1e9))


def _stamp(msg, t_ns: int) -> None:
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(int(t_ns), 1_000_000_000)


def _image(image: np.ndarray, h: int, t_ns: int) -> RawImage:
    height, width = image.shape
    msg = RawImage(frame_id=f"head{h}", width=width, height=height, encoding="mono16", step=2 * width,
                   data=image.astype("<u2", copy=False).tobytes())
    _stamp(msg, t_ns)
    return msg


def _annotations(stars: Stars2D, rgb: tuple[float, float, float], t_ns: int) -> ImageAnnotations:
    msg = ImageAnnotations()
    pts = msg.points.add(type=PointsAnnotation.POINTS, thickness=4.0)
    _stamp(pts, t_ns)
    pts.outline_color.r, pts.outline_color.g, pts.outline_color.b, pts.outline_color.a = *rgb, 1.0
    for (x, y), hip in zip(stars.xy + PIXEL_ORIGIN, stars.ids, strict=True):
        pts.points.add(x=float(x), y=float(y))
        if hip >= 0:
            text = msg.texts.add(text=f"HIP {int(hip)}", font_size=12.0)
            _stamp(text, t_ns)
            text.position.x, text.position.y = float(x), float(y)
            text.text_color.r, text.text_color.g, text.text_color.b, text.text_color.a = *rgb, 1.0
            text.background_color.a = 0.0
    return msg


def _stars(msg: ImageAnnotations) -> Stars2D:
    """Points and their ``HIP n`` labels back from :func:`_annotations` (labels sit exactly on their points)."""
    xy = np.array([(p.x, p.y) for a in msg.points for p in a.points], dtype=np.float64).reshape(-1, 2)
    labels = {(t.position.x, t.position.y): int(t.text.removeprefix("HIP ")) for t in msg.texts}
    ids = np.array([labels.get((x, y), -1) for x, y in xy], dtype=np.int64)
    return Stars2D(xy - PIXEL_ORIGIN, ids)


def camera_messages(cameras, t_ns: int) -> list[tuple[str, object]]:
    """Each head's ``foxglove.CameraCalibration`` and body -> head ``FrameTransform`` (see the module docstring)."""
    out: list[tuple[str, object]] = []
    for h, cam in enumerate(cameras):
        cx, cy = cam.cx + PIXEL_ORIGIN, cam.cy + PIXEL_ORIGIN
        cal = CameraCalibration(frame_id=f"head{h}", width=cam.width, height=cam.height,
                                K=[cam.fx, 0.0, cx, 0.0, cam.fy, cy, 0.0, 0.0, 1.0],
                                R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                                P=[cam.fx, 0.0, cx, 0.0, 0.0, cam.fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
        d = cam.distortion
        if isinstance(d, BrownConrady):
            cal.distortion_model, cal.D[:] = "plumb_bob", [d.k1, d.k2, d.p1, d.p2, d.k3]
        _stamp(cal, t_ns)
        out.append((f"/head{h}/calibration", cal))
        tf = FrameTransform(parent_frame_id="body", child_frame_id=f"head{h}")
        _stamp(tf, t_ns)
        x, y, z, w = cam.mounting.inv().as_quat()  # head axes in body coordinates
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = float(x), float(y), float(z), float(w)
        out.append((f"/head{h}/mounting", tf))
    return out


def _transform(q: np.ndarray, child: str, t_ns: int) -> FrameTransform:
    msg = FrameTransform(parent_frame_id="icrs", child_frame_id=child)
    _stamp(msg, t_ns)
    msg.rotation.x, msg.rotation.y, msg.rotation.z = (-float(v) for v in q[:3])  # conjugate: body -> icrs
    msg.rotation.w = float(q[3])
    return msg


def _log(level: int, text: str, t_ns: int) -> Log:
    msg = Log(level=level, message=text, name="starenv")
    _stamp(msg, t_ns)
    return msg


def encode_step(data: StepData, origin_ns: int = 0) -> list[tuple[str, object]]:
    """The (topic, protobuf message) pairs of one step, in a fixed order, stamped ``origin_ns + data.time_ns``."""
    t = origin_ns + data.time_ns
    out: list[tuple[str, object]] = []
    for h, head in enumerate(data.heads):
        if head.image is not None:
            out.append((f"/head{h}/image", _image(head.image, h, t)))
        for layer, rgb in LAYERS.items():
            out.append((f"/head{h}/{layer}", _annotations(getattr(head, layer), rgb, t)))
    out.append(("/attitude/true", _transform(data.attitude_true, "body", t)))
    if data.attitude_estimate is not None:
        out.append(("/attitude/estimate", _transform(data.attitude_estimate, "body_estimate", t)))
    if data.filter is not None:
        state = messages.classes()["FilterState"](frame=data.frame, time_s=data.time_ns * 1e-9)
        for name, attr in messages.FILTER_FIELDS.items():
            getattr(state, name).extend(np.asarray(getattr(data.filter, attr), dtype=np.float64).tolist())
        out.append(("/filter", state))
    scores = messages.encode_scores(data.frame, data.time_ns * 1e-9, data.source, data.scores, data.record)
    out.append(("/scores", scores))
    gyro = messages.classes()["GyroSamples"](frame=data.frame, t_s=data.gyro_t.tolist(),
                                             rate_x_rad_s=data.gyro_rate[:, 0].tolist(),
                                             rate_y_rad_s=data.gyro_rate[:, 1].tolist(),
                                             rate_z_rad_s=data.gyro_rate[:, 2].tolist())
    out.append(("/gyro", gyro))
    out.extend(("/log", _log(level, text, t)) for level, text in data.logs)
    return out


def reproduce_command(toml_name: str, seed: int, steps: int, agents: dict[str, str | None] | None) -> str:
    """The ``starenv run`` command line that repeats a recorded run from its scenario saved as ``toml_name``."""
    words = ["starenv", "run", toml_name, "--seed", str(seed), "--steps", str(steps)]
    if agents is None:
        words += ["--pipeline", "none"]
    else:
        for role, spec in agents.items():
            words += ["--agent", f"{role}={spec or 'none'}"]
    return shlex.join(words)


class McapRecorder:
    """Observer (``starenv.episode.Observer``) that writes an episode to ``path`` (``*.mcap``).

    ``chunk_size``: uncompressed bytes per chunk (a chunk is compressed and written once it is full);
    ``compression``: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.  Steps are encoded, compressed and written by a
    writer thread (zstd releases the GIL, so compression overlaps the next step's simulation and pipeline), in order;
    at most ``QUEUE`` steps wait, and ``close`` waits for all of them.  An error in the writer thread is raised by the
    next ``step`` or by ``close``.
    """

    QUEUE = 4

    def __init__(self, path: str | os.PathLike, *, chunk_size: int = 1 << 20, compression: str = "zstd"):
        self.path = Path(path)
        if self.path.suffix != ".mcap":
            raise ValueError(f"McapRecorder path: expected a file name ending in .mcap, got {str(path)!r}")
        if compression not in COMPRESSION:
            raise ValueError(f"McapRecorder compression: expected one of {sorted(COMPRESSION)}, got {compression!r}")
        if not isinstance(chunk_size, int) or chunk_size < 1:
            raise ValueError(f"McapRecorder chunk_size: expected a positive number of bytes, got {chunk_size!r}")
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.chunk_size, self.compression = chunk_size, compression
        self._file = None
        self._writer = None
        self._thread = None
        self._failed: BaseException | None = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}

    def start(self, env, seed: int, pipeline) -> None:
        base = env.unwrapped
        sc = base.scenario
        self._sizes = [(h.camera.height, h.camera.width) for h in sc.heads]
        self._cameras = base.cameras
        self._origin_ns = time_origin_ns(sc.epoch)
        self._period_ns = time_ns(sc.frame_period_s)
        self._seed = int(seed)
        self._agents = None if pipeline is None else pipeline.describe()
        self._steps = 0
        self._last_ns = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.partial, "wb")  # closed in close()
        self._writer = Writer(self._file, chunk_size=self.chunk_size, compression=COMPRESSION[self.compression])
        self._writer.start(profile="", library=f"{LIBRARY_IDENTIFIER} starenv/{starenv.__version__}")
        self._channels, self._schemas = {}, {}
        self._writer.add_metadata("starenv.scenario", {"name": sc.name, "toml": sc.to_toml()})
        self._writer.add_metadata("starenv.run", {
            "seed": str(self._seed), "heads": str(len(sc.heads)), "starenv_version": starenv.__version__,
            "epoch": repr(float(sc.epoch)), "time_origin_unix_ns": str(self._origin_ns),
            "pipeline": json.dumps(self._agents),
            "pipeline_class": "none" if pipeline is None else f"{type(pipeline).__module__}:{type(pipeline).__name__}",
        })
        self._queue: queue.Queue = queue.Queue(maxsize=self.QUEUE)
        self._thread = threading.Thread(target=self._drain, name="mcap-writer", daemon=True)
        self._thread.start()

    def step(self, log) -> None:
        if self._failed is not None:
            raise RuntimeError(f"writing {self.partial} failed") from self._failed
        self._queue.put(from_step_log(log, self._sizes))

    def _drain(self) -> None:
        while (data := self._queue.get()) is not None:
            if self._failed is None:
                try:
                    self.write(data)
                except BaseException as exc:  # handed to the episode thread by step() / close()
                    self._failed = exc

    def write(self, data: StepData) -> None:
        """Write one step (log time: the time origin + ``data.time_ns``)."""
        t = self._origin_ns + data.time_ns
        for topic, msg in encode_step(data, self._origin_ns) + camera_messages(self._cameras, t):
            self._write(topic, msg, t)
        self._file.flush()  # every chunk completed by this step goes to the file now
        self._steps += 1
        self._last_ns = data.time_ns

    def _write(self, topic: str, msg, t_ns: int) -> None:
        """One protobuf message, serialised deterministically (map fields in key order)."""
        channel = self._channels.get(topic)
        if channel is None:
            name = type(msg).DESCRIPTOR.full_name
            if name not in self._schemas:
                self._schemas[name] = register_schema(self._writer, type(msg))
            schema = self._schemas[name]
            channel = self._channels[topic] = self._writer.register_channel(topic, MessageEncoding.Protobuf, schema)
        self._writer.add_message(channel, log_time=t_ns, data=msg.SerializeToString(deterministic=True),
                                 publish_time=t_ns)

    def close(self, error: BaseException | None = None) -> None:
        if self._writer is None:
            return
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None
        if self._failed is not None:  # the file cannot be finished: keep what reached it as .partial
            self._file.close()
            self._writer = None
            if error is None:  # else the episode's own exception is already on its way
                raise RuntimeError(f"writing {self.partial} failed; what was written is kept there") from self._failed
            return
        status = "complete"
        if error is not None:
            status = "error"
            t = 0 if self._last_ns is None else self._last_ns + self._period_ns  # the step that failed
            text = f"frame {self._steps}: run stopped by {type(error).__name__}: {error}"
            self._write("/log", _log(ERROR, text, self._origin_ns + t), self._origin_ns + t)
        self._writer.add_metadata("starenv.outcome", {
            "status": status, "steps": str(self._steps),
            "error": "" if error is None else f"{type(error).__name__}: {error}",
            "reproduce": reproduce_command("scenario.toml", self._seed, self._steps, self._agents),
            "scenario_toml": "the 'toml' entry of the starenv.scenario metadata record",
        })
        self._writer.finish()
        self._file.close()
        self._writer = None
        os.replace(self.partial, self.path)


def check_mcap(path: str | os.PathLike) -> Path:
    """``path`` if it is an existing file that starts like an MCAP file, else ``ValueError`` saying what is wrong."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"recording {str(path)!r}: no such file")
    with open(p, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise ValueError(f"recording {str(path)!r}: not an MCAP file (it does not start with the MCAP magic)")
    return p


def is_finished(path: str | os.PathLike) -> bool:
    """Whether the MCAP file ``path`` was finished (it ends with the closing magic after its footer)."""
    p = check_mcap(path)
    with open(p, "rb") as f:
        f.seek(max(0, p.stat().st_size - len(MAGIC)))
        return p.stat().st_size >= 2 * len(MAGIC) and f.read() == MAGIC


def check_finished(path: str | os.PathLike) -> Path:
    """``path`` if it is a finished MCAP file, else ``ValueError`` saying how to read what it holds."""
    if not is_finished(path):
        raise ValueError(f"recording {str(path)!r}: unfinished (the run that wrote it stopped before closing it): "
                         f"review it with 'starenv view', or make it whole with 'starenv recover'")
    return Path(path)


def read_metadata(path: str | os.PathLike) -> dict[str, dict[str, str]]:
    """The metadata records of a finished recording: name -> key/value strings."""
    with open(check_finished(path), "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}


def topics(path: str | os.PathLike) -> set[str]:
    """The topics of a finished recording's channels (from its summary)."""
    with open(check_finished(path), "rb") as f:
        return {c.topic for c in make_reader(f).get_summary().channels.values()}


def _step_from(group: list[tuple[str, object]], t_ns: int, n_heads: int, next_frame: int) -> StepData:
    by_topic: dict[str, object] = {}
    logs = []
    for topic, msg in group:
        if topic == "/log":
            logs.append((int(msg.level), msg.message))
        else:
            by_topic[topic] = msg
    scores_msg = by_topic.get("/scores")
    scores, record = messages.decode_scores(scores_msg) if scores_msg is not None else ({}, {})
    heads = []
    for h in range(n_heads):
        img = by_topic.get(f"/head{h}/image")
        image = None
        if img is not None:
            image = np.frombuffer(img.data, dtype="<u2").reshape(img.height, img.step // 2)[:, : img.width]
        layers = {k: _stars(by_topic[f"/head{h}/{k}"]) if f"/head{h}/{k}" in by_topic else Stars2D.empty()
                  for k in LAYERS}
        heads.append(HeadData(image, **layers))

    def quat(topic: str) -> np.ndarray | None:
        m = by_topic.get(topic)
        return None if m is None else np.array([-m.rotation.x, -m.rotation.y, -m.rotation.z, m.rotation.w])

    state = by_topic.get("/filter")
    if state is not None:
        state = FilterState(**{attr: np.array(getattr(state, name)) for name, attr in messages.FILTER_FIELDS.items()})
    gyro = by_topic.get("/gyro")
    gyro_t = np.array(gyro.t_s) if gyro is not None else np.zeros(0)
    rate = (np.column_stack([gyro.rate_x_rad_s, gyro.rate_y_rad_s, gyro.rate_z_rad_s]) if gyro is not None
            else np.zeros((0, 3))).reshape(-1, 3)
    return StepData(
        frame=int(scores_msg.frame) if scores_msg is not None else next_frame, time_ns=t_ns, heads=heads,
        attitude_true=quat("/attitude/true"), attitude_estimate=quat("/attitude/estimate"),
        source=scores_msg.source if scores_msg is not None else "none", scores=scores, record=record,
        gyro_t=gyro_t, gyro_rate=rate, logs=logs, filter=state,
    )


def read_steps(path: str | os.PathLike) -> Iterator[StepData]:
    """The steps of a finished recording, in time order (messages without scores, e.g. the error that stopped a run,
    come back as a step of their own, numbered after the last scored one)."""
    path = check_finished(path)
    run = read_metadata(path)["starenv.run"]
    n_heads, origin = int(run["heads"]), int(run.get("time_origin_unix_ns", 0))  # older files: 0
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        group: list[tuple[str, object]] = []
        t_group, frame = None, -1
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            if t_group is not None and message.log_time != t_group:
                step = _step_from(group, t_group - origin, n_heads, frame + 1)
                frame = step.frame
                yield step
                group = []
            t_group = message.log_time
            group.append((channel.topic, decoded))
        if group:
            yield _step_from(group, t_group - origin, n_heads, frame + 1)


def _complete_records(path: str | os.PathLike) -> tuple[dict, dict, list, list]:
    """Schemas (id -> record), channels (id -> record), metadata records and messages (in file order) of a possibly
    unfinished file, read as a stream up to the first incomplete or damaged record; a chunk is used whole or not at
    all (its CRC is checked before any of its messages is kept)."""
    from mcap.records import Channel, Chunk, Message, Metadata, Schema
    from mcap.stream_reader import breakup_chunk

    schemas, channels, metadata, messages_ = {}, {}, [], []

    def take(record) -> None:
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Metadata):
            metadata.append(record)
        elif isinstance(record, Message):
            messages_.append(record)

    with open(check_mcap(path), "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False, emit_chunks=True).records:
                if isinstance(record, Chunk):
                    inner = list(breakup_chunk(record, validate_crc=True))  # raises before anything is kept
                    for r in inner:
                        take(r)
                else:
                    take(record)
        except Exception:  # truncation, a CRC or decompression error: what came before is kept
            pass
    return schemas, channels, metadata, messages_


def read_partial(path: str | os.PathLike) -> dict[str, int]:
    """Messages per topic in a possibly unfinished file (e.g. the ``.partial`` of a killed run), read as a stream up
    to the first incomplete record; chunk CRCs are checked."""
    _, channels, _, msgs = _complete_records(path)
    counts: dict[str, int] = {}
    for m in msgs:
        topic = channels[m.channel_id].topic
        counts[topic] = counts.get(topic, 0) + 1
    return counts


def recover(partial: str | os.PathLike, out: str | os.PathLike) -> int:
    """Write ``out``, a finished MCAP holding every complete step of the unfinished recording ``partial`` (up to its
    last complete chunk; a step counts when its ``/gyro`` message, the last of a step, reached the file), with the
    recording's metadata and a ``starenv.outcome`` of status ``recovered``.  Returns the number of steps kept."""
    schemas, channels, metadata, msgs = _complete_records(partial)
    names = {m.name: dict(m.metadata) for m in metadata}
    if "starenv.run" not in names:
        raise ValueError(f"recording {str(partial)!r}: nothing recoverable (no starenv.run metadata reached the file)")
    gyro = {cid for cid, c in channels.items() if c.topic == "/gyro"}
    done = {m.log_time for m in msgs if m.channel_id in gyro}
    kept = [m for m in msgs if m.log_time in done and m.channel_id in channels]
    out = Path(out)
    tmp = out.with_name(out.name + ".tmp")
    with open(tmp, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile="", library=f"{LIBRARY_IDENTIFIER} starenv/{starenv.__version__}")
        for m in metadata:
            if m.name != "starenv.outcome":
                writer.add_metadata(m.name, dict(m.metadata))
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in schemas.items()}
        channel_ids = {cid: writer.register_channel(c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0),
                                                    dict(c.metadata)) for cid, c in channels.items()}
        for m in kept:
            writer.add_message(channel_ids[m.channel_id], log_time=m.log_time, data=m.data,
                               publish_time=m.publish_time, sequence=m.sequence)
        run = names["starenv.run"]
        agents = json.loads(run.get("pipeline", "null"))
        writer.add_metadata("starenv.outcome", {
            "status": "recovered", "steps": str(len(done)),
            "error": f"the run stopped before its recording was finished; {len(done)} complete steps recovered",
            "reproduce": reproduce_command("scenario.toml", int(run["seed"]), len(done), agents),
            "scenario_toml": "the 'toml' entry of the starenv.scenario metadata record",
        })
        writer.finish()
    os.replace(tmp, out)
    return len(done)
