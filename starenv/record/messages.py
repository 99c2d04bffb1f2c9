"""starenv's own protobuf messages in recordings, built at run time with ``descriptor_pb2`` (no protoc needed).

``starenv.StepScores``: every score of one step.  Typed fields for the metrics known today (attitude errors per head,
star-level scores per head) and, so that no metric silently vanishes, the whole flat record (``StepLog.record``) as a
``map<string, double>`` plus the list of its keys that had no value this step; per-head scores the typed fields do not
know go to that head's ``extra`` map.  ``starenv.GyroSamples``: the gyro samples delivered with one frame (s, rad/s,
body frame).  ``starenv.FilterState``: a fusion filter's state at one frame (``starenv.record.step.FilterState``:
attitude ``[x, y, z, w]`` ICRS -> body, bias estimate and true bias in deg/h, 1-sigma in arcsec and deg/h, body axes).
The file is proto2 so that "no value" (Python ``None``) stays distinguishable from 0.
"""

from __future__ import annotations

from functools import cache

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

F = descriptor_pb2.FieldDescriptorProto
DOUBLE, INT64, UINT32, BOOL, STRING, MESSAGE = (F.TYPE_DOUBLE, F.TYPE_INT64, F.TYPE_UINT32, F.TYPE_BOOL, F.TYPE_STRING,
                                                F.TYPE_MESSAGE)
OPTIONAL, REPEATED = F.LABEL_OPTIONAL, F.LABEL_REPEATED

# Typed per-head star scores (``starenv.scoring.StarScores``): name -> protobuf type.
HEAD_FIELDS = {
    "centroid_error_px_mean": DOUBLE, "centroid_error_px_max": DOUBLE, "detection_recall": DOUBLE,
    "detection_precision": DOUBLE, "id_rate": DOUBLE, "false_id_rate": DOUBLE, "ids_correct": INT64,
    "ids_wrong": INT64, "solved": BOOL, "prediction_error_px_mean": DOUBLE, "prediction_error_px_max": DOUBLE,
    "predictions_scored": INT64, "correction_error_px_mean": DOUBLE, "correction_error_x_px": DOUBLE,
    "correction_error_y_px": DOUBLE, "distortion_px_mean": DOUBLE,
}
_PY = {DOUBLE: float, INT64: int, BOOL: bool}
HEAD_ATTITUDE_FIELDS = ("pitch_arcsec", "yaw_arcsec", "roll_arcsec", "cross_boresight_arcsec")
PACKAGE = "starenv"
# starenv.FilterState's vector fields: name in the message -> attribute of starenv.record.step.FilterState
FILTER_FIELDS = {"attitude_xyzw": "attitude", "bias_deg_hr": "bias_deg_hr", "bias_true_deg_hr": "bias_true_deg_hr",
                 "attitude_sigma_arcsec": "attitude_sigma_arcsec", "bias_sigma_deg_hr": "bias_sigma_deg_hr"}


def _field(msg, name: str, number: int, ftype: int, label: int = OPTIONAL, type_name: str | None = None) -> None:
    f = msg.field.add(name=name, number=number, type=ftype, label=label)
    if type_name:
        f.type_name = f".{PACKAGE}.{type_name}"


def _map(msg, name: str, number: int, entry: str) -> None:
    """A ``map<string, double>`` field: a repeated nested entry message flagged ``map_entry``."""
    nested = msg.nested_type.add(name=entry)
    nested.options.map_entry = True
    nested.field.add(name="key", number=1, type=STRING, label=OPTIONAL)
    nested.field.add(name="value", number=2, type=DOUBLE, label=OPTIONAL)
    f = msg.field.add(name=name, number=number, type=MESSAGE, label=REPEATED)
    f.type_name = f".{PACKAGE}.{msg.name}.{entry}"


def _file() -> descriptor_pb2.FileDescriptorProto:
    fd = descriptor_pb2.FileDescriptorProto(name="starenv/recording.proto", package=PACKAGE, syntax="proto2")
    head_att = fd.message_type.add(name="HeadAttitudeError")
    for i, name in enumerate(HEAD_ATTITUDE_FIELDS, 1):
        _field(head_att, name, i, DOUBLE)
    att = fd.message_type.add(name="AttitudeError")
    _field(att, "total_arcsec", 1, DOUBLE)
    _field(att, "heads", 2, MESSAGE, REPEATED, "HeadAttitudeError")
    head = fd.message_type.add(name="HeadScores")
    for i, (name, ftype) in enumerate(HEAD_FIELDS.items(), 1):
        _field(head, name, i, ftype)
    _map(head, "extra", 100, "ExtraEntry")
    step = fd.message_type.add(name="StepScores")
    _field(step, "frame", 1, UINT32)
    _field(step, "time_s", 2, DOUBLE)
    _field(step, "source", 3, STRING)
    _field(step, "available", 4, BOOL)
    _field(step, "within_threshold", 5, BOOL)
    _field(step, "attitude", 6, MESSAGE, OPTIONAL, "AttitudeError")
    _field(step, "heads", 7, MESSAGE, REPEATED, "HeadScores")
    _map(step, "record", 8, "RecordEntry")
    _field(step, "record_without_value", 9, STRING, REPEATED)
    gyro = fd.message_type.add(name="GyroSamples")
    _field(gyro, "frame", 1, UINT32)
    for i, name in enumerate(("t_s", "rate_x_rad_s", "rate_y_rad_s", "rate_z_rad_s"), 2):
        _field(gyro, name, i, DOUBLE, REPEATED)
        gyro.field[-1].options.packed = True
    state = fd.message_type.add(name="FilterState")
    _field(state, "frame", 1, UINT32)
    _field(state, "time_s", 2, DOUBLE)
    for i, name in enumerate(FILTER_FIELDS, 3):
        _field(state, name, i, DOUBLE, REPEATED)
        state.field[-1].options.packed = True
    return fd


@cache
def classes() -> dict[str, type]:
    """The message classes by short name (``StepScores``, ``GyroSamples``, ...), built once per process."""
    pool = descriptor_pool.DescriptorPool()
    pool.Add(_file())
    names = ("HeadAttitudeError", "AttitudeError", "HeadScores", "StepScores", "GyroSamples", "FilterState")
    return {n: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{PACKAGE}.{n}")) for n in names}


def encode_scores(frame: int, time_s: float, source: str, scores: dict, record: dict):
    """``info["scores"]`` and the flat record of one step as a ``StepScores`` message."""
    c = classes()
    msg = c["StepScores"](frame=int(frame), time_s=float(time_s), source=source,
                          available=bool(scores["available"]), within_threshold=bool(scores["within_threshold"]))
    att = scores.get("attitude")
    if att:  # empty (or None in older callers) when the step had no estimate
        msg.attitude.total_arcsec = att["total_arcsec"]
        for h in att["heads"]:
            msg.attitude.heads.add(**{k: h[k] for k in HEAD_ATTITUDE_FIELDS})
    for h in scores["heads"]:
        head = msg.heads.add()
        for key, value in h.items():
            if value is None:
                continue
            if key in HEAD_FIELDS:
                setattr(head, key, _PY[HEAD_FIELDS[key]](value))
            else:
                head.extra[key] = float(value)
    for key, value in record.items():
        if value is None:
            msg.record_without_value.append(key)
        else:
            msg.record[key] = float(value)
    return msg


def decode_scores(msg) -> tuple[dict, dict]:
    """(scores, record) back from a ``StepScores`` message: the inverse of :func:`encode_scores`."""
    att = {}
    if msg.HasField("attitude"):
        att = {"total_arcsec": msg.attitude.total_arcsec,
               "heads": [{k: getattr(h, k) for k in HEAD_ATTITUDE_FIELDS} for h in msg.attitude.heads]}
    heads = []
    for h in msg.heads:
        d = {k: getattr(h, k) if h.HasField(k) else None for k in HEAD_FIELDS}
        d.update(h.extra)
        heads.append(d)
    scores = {"frame": msg.frame, "available": msg.available, "within_threshold": msg.within_threshold,
              "attitude": att, "heads": heads}
    record = {**dict(msg.record), **dict.fromkeys(msg.record_without_value)}
    return scores, record
