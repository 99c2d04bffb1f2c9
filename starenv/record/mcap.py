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
finished recording is replaced in one step, never half-overwritten.  The ``.partial`` is created under a unique name
(exclusively) and then moved onto ``FILE.mcap.partial``: a file or symbolic link already there is replaced, never
written through.  A killed process leaves the ``.partial`` file, readable up to its last complete chunk:
:func:`read_partial` counts its messages, :func:`recover` (``starenv recover FILE.mcap.partial``) writes a finished
MCAP of its complete steps, and ``starenv view`` reviews it directly.

Reading treats the file as untrusted (:func:`read_steps`, :func:`read_metadata`, :func:`recover`): every record is at
most ``MAX_RECORD_BYTES`` and no length field makes the reader allocate beyond the file's size, a chunk's declared
size is at most ``MAX_CHUNK_BYTES`` and it is decompressed no further, chunk CRCs (and the data section's CRC, which
the writer records) are checked, chunks hold only schemas, channels and messages, every topic is a starenv topic of
its own schema, messages are in time order, the metadata is validated (:func:`run_info`: at most ``MAX_HEADS``
heads); anything else is a :class:`RecordingError` (a ValueError) naming the file.
"""

from __future__ import annotations

import io
import json
import os
import queue
import re
import shlex
import tempfile
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
from mcap.stream_reader import StreamReader
from mcap.well_known import MessageEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.schema import register_schema

import starenv
from starenv.files import atomic_file
from starenv.record import messages
from starenv.record.step import ERROR, FilterState, HeadData, Stars2D, StepData, from_step_log, time_ns
from starenv.sim.optics import BrownConrady

MAGIC = b"\x89MCAP0\r\n"
PIXEL_ORIGIN = 0.5  # Foxglove/Rerun image coordinates = starenv pixel coordinates + 0.5
LAYERS = {"truth": (0.2, 0.9, 0.2), "detections": (1.0, 0.3, 0.2), "predictions": (0.2, 0.7, 1.0)}  # RGB
COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
MAX_HEADS = 256  # heads a recording may hold (the reader loops over them every step)
MAX_CHUNK_SIZE = 2**26  # McapRecorder's largest chunk_size (bytes)
# A chunk closes once it holds chunk_size bytes, so it holds at most MAX_CHUNK_SIZE plus one message: at most a
# frame of starenv.scenario.MAX_FRAME_PIXELS (2^25) 16-bit pixels, 2^26 bytes, plus its fields.
MAX_CHUNK_BYTES = MAX_CHUNK_SIZE + 2**26 + 2**20
MAX_RECORD_BYTES = MAX_CHUNK_BYTES + 2**20  # a record as stored: a chunk, compression may add a little


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
        if not isinstance(chunk_size, int) or not 1 <= chunk_size <= MAX_CHUNK_SIZE:
            raise ValueError(f"McapRecorder chunk_size: expected a number of bytes in [1, {MAX_CHUNK_SIZE}], got "
                             f"{chunk_size!r}")
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
        if len(sc.heads) > MAX_HEADS:
            raise ValueError(f"McapRecorder: {len(sc.heads)} heads, a recording holds at most {MAX_HEADS}")
        if self.path.is_symlink():
            raise FileExistsError(f"{self.path}: a symbolic link; refusing to replace it with the recording")
        self._sizes = [(h.camera.height, h.camera.width) for h in sc.heads]
        self._cameras = base.cameras
        self._origin_ns = time_origin_ns(sc.epoch)
        self._period_ns = time_ns(sc.frame_period_s)
        self._seed = int(seed)
        self._agents = None if pipeline is None else pipeline.describe()
        self._steps = 0
        self._last_ns = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.partial.name}.", suffix=".tmp", dir=self.path.parent)
        try:
            os.replace(tmp, self.partial)  # replaces a stale file or link there; never opens through it
        except OSError:
            os.close(fd)
            Path(tmp).unlink(missing_ok=True)
            raise
        self._file = os.fdopen(fd, "wb")  # closed in close()
        self._writer = Writer(self._file, chunk_size=self.chunk_size, compression=COMPRESSION[self.compression],
                              enable_data_crcs=True)
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
        mine = os.fstat(self._file.fileno())
        self._file.close()
        self._writer = None
        try:
            there = os.stat(self.partial, follow_symlinks=False)
        except FileNotFoundError:
            there = None
        if there is None or (there.st_dev, there.st_ino) != (mine.st_dev, mine.st_ino):
            raise RuntimeError(f"{self.partial} was moved or replaced by another writer while this run recorded; "
                               f"the recording is lost")
        os.replace(self.partial, self.path)


class RecordingError(ValueError):
    """A recording that cannot be read as one: damaged, out of bounds, not one starenv wrote, or unfinished where a
    finished one is needed.  The message names the file."""


def _fail(path, why: str) -> RecordingError:
    return RecordingError(f"recording {str(path)!r}: {why}")


def check_mcap(path: str | os.PathLike) -> Path:
    """``path`` if it is an existing file that starts like an MCAP file, else ``ValueError`` saying what is wrong."""
    p = Path(path)
    if not p.is_file():
        raise _fail(path, "no such file")
    with open(p, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise _fail(path, "not an MCAP file (it does not start with the MCAP magic)")
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
        raise _fail(path, "unfinished (the run that wrote it stopped before closing it): review it with "
                          "'starenv view', or make it whole with 'starenv recover'")
    return Path(path)


class _Bounded:
    """A binary file whose ``read(n)`` never asks for more than what is left: a length field read from the file
    cannot make the reader allocate beyond the file's size."""

    def __init__(self, f, size: int):
        self.f, self.left = f, size

    def read(self, n: int = -1) -> bytes:
        data = self.f.read(self.left if n < 0 else min(n, self.left))
        self.left -= len(data)
        return data


def _decompress(chunk) -> bytes:
    """A chunk's records, decompressed without ever holding more than its declared size (at most
    ``MAX_CHUNK_BYTES``), checked against its size and CRC."""
    import zlib

    size = chunk.uncompressed_size
    if size > MAX_CHUNK_BYTES:
        raise ValueError(f"a chunk declares {size} bytes, more than {MAX_CHUNK_BYTES}")
    if chunk.uncompressed_crc == 0:
        raise ValueError("a chunk without a CRC (starenv's writer gives every chunk one)")
    if chunk.compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(chunk.data)).read(size + 1)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"a chunk compressed with {chunk.compression[:20]!r}")
    if len(data) != size:
        raise ValueError(f"a chunk holds {'more' if len(data) > size else 'fewer'} bytes than its declared {size}")
    if zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("a chunk's CRC does not match its content")
    return data


def _chunk_records(chunk) -> list:
    """The schema, channel and message records of a chunk (nothing else belongs in a starenv chunk)."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema

    data = _decompress(chunk)
    stream = ReadDataStream(io.BytesIO(data))
    out = []
    while stream.count < len(data):
        opcode, length = stream.read1(), stream.read8()
        start = stream.count
        if length > len(data) - start:
            raise ValueError("a record inside a chunk is longer than the chunk")
        if opcode == Opcode.MESSAGE and length >= 22:
            out.append(Message.read(stream, length))
        elif opcode == Opcode.CHANNEL:
            out.append(Channel.read(stream))
        elif opcode == Opcode.SCHEMA:
            out.append(Schema.read(stream))
        else:
            raise ValueError(f"a record of opcode {opcode:#x} inside a chunk")
        if stream.count != start + length:
            raise ValueError("a record inside a chunk is not as long as it says")
    return out


def _records(path: str | os.PathLike, *, partial: bool, chunks: bool = True) -> Iterator:
    """The records of a recording in file order, chunks opened (``chunks``; else skipped) and checked
    (:func:`_decompress`); every record at most ``MAX_RECORD_BYTES``, the data section's CRC checked when the file
    has one.  ``partial``: the file of a killed run, read up to its first incomplete or damaged record, silently
    (a chunk is used whole or not at all); otherwise damage is a :class:`RecordingError`."""
    from mcap.records import Chunk

    p = check_mcap(path)
    size = p.stat().st_size
    with open(p, "rb") as f:
        reader = StreamReader(_Bounded(f, size), emit_chunks=True, validate_crcs=True,
                              record_size_limit=min(MAX_RECORD_BYTES, size))
        records = reader.records
        while True:
            try:
                record = next(records)
                inner = (_chunk_records(record) if chunks else []) if isinstance(record, Chunk) else [record]
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001  (the parser raises many types on damaged bytes)
                if partial:
                    return
                raise _fail(path, f"damaged ({type(exc).__name__}: {str(exc)[:200]})") from exc
            yield from inner


# topic -> the schema its messages must have (``{h}``: a head index below the recording's head count)
TOPIC_SCHEMAS = {"/head{h}/image": "foxglove.RawImage", "/head{h}/calibration": "foxglove.CameraCalibration",
                 "/head{h}/mounting": "foxglove.FrameTransform", "/attitude/true": "foxglove.FrameTransform",
                 "/attitude/estimate": "foxglove.FrameTransform", "/scores": "starenv.StepScores",
                 "/gyro": "starenv.GyroSamples", "/filter": "starenv.FilterState", "/log": "foxglove.Log",
                 **{f"/head{{h}}/{layer}": "foxglove.ImageAnnotations" for layer in LAYERS}}
AGENT_SPEC = re.compile(r"[A-Za-z_][\w.]{0,199}:[A-Za-z_]\w{0,99}")


def _expected_schema(topic: str, heads: int) -> str | None:
    """The schema name ``topic`` must have in a recording of ``heads`` heads (None: not a starenv topic)."""
    m = re.fullmatch(r"/head(0|[1-9]\d{0,3})(/\w+)", topic)
    if m is not None:
        return TOPIC_SCHEMAS.get("/head{h}" + m.group(2)) if int(m.group(1)) < heads else None
    return TOPIC_SCHEMAS.get(topic)


class _Channels:
    """The schemas and channels met in a recording so far, each channel checked (a starenv topic, its schema, a
    protobuf decoder built from the schema the file carries) before any of its messages is used."""

    def __init__(self, path, heads: int):
        self.path, self.heads = path, heads
        self.schemas, self.channels, self.decoders = {}, {}, {}
        self._factory = DecoderFactory()

    def take(self, record) -> bool:
        """Keep a schema or channel record; False for any other record."""
        from mcap.records import Channel, Schema

        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            expected = _expected_schema(record.topic, self.heads)
            schema = self.schemas.get(record.schema_id)
            if expected is None:
                raise _fail(self.path, f"unexpected topic {record.topic[:60]!r} ({self.heads} heads)")
            if schema is None or schema.name != expected or record.message_encoding != MessageEncoding.Protobuf:
                raise _fail(self.path, f"topic {record.topic}: expected protobuf messages of schema {expected}")
            try:
                decoder = self._factory.decoder_for(record.message_encoding, schema)
            except Exception as exc:  # noqa: BLE001  (protobuf raises many types on a damaged descriptor set)
                raise _fail(self.path, f"schema {schema.name}: damaged ({type(exc).__name__})") from exc
            if decoder is None:
                raise _fail(self.path, f"schema {schema.name}: not a protobuf schema")
            self.channels[record.id], self.decoders[record.id] = record, decoder
        else:
            return False
        return True

    def decode(self, message):
        """(topic, decoded message) of a message record; a damaged message is a RecordingError."""
        channel = self.channels.get(message.channel_id)
        if channel is None:
            raise _fail(self.path, f"a message on channel {message.channel_id}, which no channel record defines")
        try:
            return channel.topic, self.decoders[message.channel_id](message.data)
        except Exception as exc:  # noqa: BLE001  (protobuf's DecodeError and friends)
            raise _fail(self.path, f"{channel.topic}: a message that does not decode ({type(exc).__name__})") from exc


def _integer(meta: dict, record: str, key: str, low: int, high: int, path, default=None) -> int:
    value = meta.get(record, {}).get(key)
    if value is None and default is not None:
        return default
    if not (isinstance(value, str) and re.fullmatch(r"-?\d{1,20}", value) and low <= int(value) <= high):
        raise _fail(path, f"metadata {record}.{key}: expected an integer in [{low}, {high}], got "
                          f"{value if value is None else repr(value[:40])}")
    return int(value)


def run_info(meta: dict[str, dict[str, str]], path) -> dict:
    """The validated contents of a recording's metadata (as :func:`read_metadata` returns it): ``name``, ``toml``,
    ``seed``, ``heads`` (at most ``MAX_HEADS``), ``origin_ns``, ``agents`` (role -> ``module:Class`` or None; None for
    no pipeline) and, from ``starenv.outcome`` when present, ``steps``, ``status`` and ``error``.  Missing or malformed
    entries are a :class:`RecordingError` naming the record and key.  Text (name, status, error) is the file's: make
    it printable before showing it on a terminal."""
    from starenv.scenario import AGENT_ROLES

    scenario = meta.get("starenv.scenario")
    if "starenv.run" not in meta or scenario is None:
        raise _fail(path, "not a recording starenv wrote (no starenv.run and starenv.scenario metadata)")
    for key in ("name", "toml"):
        if not isinstance(scenario.get(key), str):
            raise _fail(path, f"metadata starenv.scenario.{key}: missing")
    info = {"name": scenario["name"], "toml": scenario["toml"],
            "seed": _integer(meta, "starenv.run", "seed", 0, 2**63 - 1, path),
            "heads": _integer(meta, "starenv.run", "heads", 1, MAX_HEADS, path),
            "origin_ns": _integer(meta, "starenv.run", "time_origin_unix_ns", -2**62, 2**62, path, default=0)}
    try:
        agents = json.loads(meta["starenv.run"].get("pipeline", "null"))
    except (ValueError, RecursionError) as exc:
        raise _fail(path, "metadata starenv.run.pipeline: not JSON") from exc
    if agents is not None and not (
            isinstance(agents, dict) and set(agents) <= set(AGENT_ROLES)
            and all(a is None or (isinstance(a, str) and AGENT_SPEC.fullmatch(a)) for a in agents.values())):
        raise _fail(path, f"metadata starenv.run.pipeline: expected null or roles ({', '.join(AGENT_ROLES)}) mapped "
                          f"to 'module:Class' or null")
    info["agents"] = agents
    outcome = meta.get("starenv.outcome")
    if outcome is not None:
        info["steps"] = _integer(meta, "starenv.outcome", "steps", 0, 2**62, path)
        info["status"], info["error"] = str(outcome.get("status", "?")), str(outcome.get("error", ""))
    return info


def read_metadata(path: str | os.PathLike) -> dict[str, dict[str, str]]:
    """The metadata records of a finished recording: name -> key/value strings (the starenv records validated by
    :func:`run_info`).  Chunks are not opened; the data section's CRC is checked when the file has one."""
    from mcap.records import Metadata

    path = check_finished(path)
    meta = {m.name: dict(m.metadata) for m in _records(path, partial=False, chunks=False) if isinstance(m, Metadata)}
    run_info(meta, path)
    return meta


def topics(path: str | os.PathLike) -> set[str]:
    """The topics of a finished recording's channels (each checked as :func:`read_steps` checks it)."""
    channels = _Channels(path, run_info(read_metadata(path), path)["heads"])
    for record in _records(check_finished(path), partial=False):
        channels.take(record)
    return {c.topic for c in channels.channels.values()}


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
            if img.encoding != "mono16" or img.step != 2 * img.width or len(img.data) != img.step * img.height:
                raise ValueError(f"/head{h}/image: expected mono16 rows of 2 x width bytes, got {img.encoding[:20]!r}, "
                                 f"{img.width} x {img.height}, step {img.step}, {len(img.data)} bytes")
            image = np.frombuffer(img.data, dtype="<u2").reshape(img.height, img.width)
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
    come back as a step of their own, numbered after the last scored one).  Every chunk, channel and message is
    checked as it is read; a damaged one is a :class:`RecordingError` naming the file."""
    from mcap.records import Message

    path = check_finished(path)
    info = run_info(read_metadata(path), path)
    n_heads, origin = info["heads"], info["origin_ns"]
    channels = _Channels(path, n_heads)

    def step(group, t_ns, frame):
        try:
            return _step_from(group, t_ns - origin, n_heads, frame + 1)
        except Exception as exc:  # noqa: BLE001  (a decoded message whose fields do not hold a step)
            raise _fail(path, f"the step at log time {t_ns} ns does not hold a step ({type(exc).__name__}: "
                              f"{str(exc)[:200]!r})") from exc

    group: list[tuple[str, object]] = []
    t_group, frame = None, -1
    for record in _records(path, partial=False):
        if channels.take(record) or not isinstance(record, Message):
            continue
        if t_group is not None and record.log_time != t_group:
            if record.log_time < t_group:
                raise _fail(path, "messages out of time order (starenv writes them in time order)")
            data = step(group, t_group, frame)
            frame = data.frame
            yield data
            group = []
        t_group = record.log_time
        group.append(channels.decode(record))
    if group:
        yield step(group, t_group, frame)


def _complete_records(path: str | os.PathLike) -> tuple[dict, dict, list, list]:
    """Schemas (id -> record), channels (id -> record), metadata records and messages (in file order) of a possibly
    unfinished file, read as a stream up to the first incomplete or damaged record; a chunk is used whole or not at
    all (its size and CRC are checked before any of its messages is kept)."""
    from mcap.records import Channel, Message, Metadata, Schema

    schemas, channels, metadata, messages_ = {}, {}, [], []
    for record in _records(path, partial=True):
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Metadata):
            metadata.append(record)
        elif isinstance(record, Message):
            messages_.append(record)
    return schemas, channels, metadata, messages_


def read_partial(path: str | os.PathLike) -> dict[str, int]:
    """Messages per topic in a possibly unfinished file (e.g. the ``.partial`` of a killed run), read as a stream up
    to the first incomplete or damaged record; chunk sizes and CRCs are checked."""
    _, channels, _, msgs = _complete_records(path)
    counts: dict[str, int] = {}
    for m in msgs:
        if m.channel_id in channels:
            topic = channels[m.channel_id].topic
            counts[topic] = counts.get(topic, 0) + 1
    return counts


def recover(partial: str | os.PathLike, out: str | os.PathLike, *, replace: bool = False) -> int:
    """Write ``out``, a finished MCAP holding every complete step of the unfinished recording ``partial`` (up to its
    last complete chunk; a step counts when its ``/gyro`` message, the last of a step, reached the file), with the
    recording's metadata and a ``starenv.outcome`` of status ``recovered``.  Returns the number of steps kept.

    Everything kept is checked first (metadata, topics, schemas, every message decoded): a recording that would not
    read back is refused (:class:`RecordingError`), nothing written.  ``out`` is written under a unique temporary
    name and moved into place; an existing ``out`` is replaced only with ``replace`` (else FileExistsError)."""
    schemas, channels, metadata, msgs = _complete_records(partial)
    names = {m.name: dict(m.metadata) for m in metadata}
    if "starenv.run" not in names:
        raise _fail(partial, "nothing recoverable (no starenv.run metadata reached the file)")
    info = run_info(names, partial)
    checked = _Channels(partial, info["heads"])
    for record in [*schemas.values(), *channels.values()]:
        checked.take(record)
    gyro = {cid for cid, c in channels.items() if c.topic == "/gyro"}
    done = {m.log_time for m in msgs if m.channel_id in gyro}
    kept = [m for m in msgs if m.log_time in done]
    for m in kept:
        checked.decode(m)
    with atomic_file(out, replace=replace) as f:
        writer = Writer(f, compression=CompressionType.ZSTD, enable_data_crcs=True)
        writer.start(profile="", library=f"{LIBRARY_IDENTIFIER} starenv/{starenv.__version__}")
        for m in metadata:
            if m.name != "starenv.outcome":
                writer.add_metadata(m.name, dict(m.metadata))
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in schemas.items()}
        channel_ids = {cid: writer.register_channel(c.topic, c.message_encoding, schema_ids[c.schema_id],
                                                    dict(c.metadata)) for cid, c in channels.items()}
        for m in kept:
            writer.add_message(channel_ids[m.channel_id], log_time=m.log_time, data=m.data,
                               publish_time=m.publish_time, sequence=m.sequence)
        writer.add_metadata("starenv.outcome", {
            "status": "recovered", "steps": str(len(done)),
            "error": f"the run stopped before its recording was finished; {len(done)} complete steps recovered",
            "reproduce": reproduce_command("scenario.toml", info["seed"], len(done), info["agents"]),
            "scenario_toml": "the 'toml' entry of the starenv.scenario metadata record",
        })
        writer.finish()
    return len(done)
