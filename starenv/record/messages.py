"""starenv's own protobuf messages in recordings, built at run time with ``descriptor_pb2`` (no protoc needed).

``starenv.StepScores``: every score of one step.  Typed fields for the metrics of ``info["scores"]``, derived from
``starenv.metrics.METRICS``: the ``step`` scope's in ``StepScores``, the ``attitude`` scope's in ``AttitudeError``, the
``body_attitude`` scope's in ``BodyAttitudeError`` (its ``body``), the ``head_attitude`` scope's in
``HeadAttitudeError`` (one per head) and the ``head`` scope's in ``HeadScores`` (one per head), each numbered in
declaration order with the numbers the message's other fields leave free (so a metric added after the last of its scope
leaves older files readable); and the whole flat record (``StepLog.record``) as a ``map<string, double>`` plus the list
of its keys that had no value this step; per-head scores no metric declares go to that head's ``extra`` map.
``starenv.GyroSamples``: the gyro samples delivered with one frame (s, rad/s, body frame).  ``starenv.FilterState``: a
fusion filter's state at one frame (``starenv.record.step.FilterState``: attitude ``[x, y, z, w]`` ICRS -> body, bias
estimate and true bias in deg/h, 1-sigma in arcsec and deg/h, body axes).  The file is proto2 so that "no value" (Python
``None``) stays distinguishable from 0.
"""

from __future__ import annotations

from functools import cache

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from starenv import metrics

F = descriptor_pb2.FieldDescriptorProto
DOUBLE, INT64, UINT32, BOOL, STRING, MESSAGE = (F.TYPE_DOUBLE, F.TYPE_INT64, F.TYPE_UINT32, F.TYPE_BOOL, F.TYPE_STRING,
                                                F.TYPE_MESSAGE)
OPTIONAL, REPEATED = F.LABEL_OPTIONAL, F.LABEL_REPEATED

PROTO_TYPES = {float: DOUBLE, int: INT64, bool: BOOL}  # a metric's dtype -> its field type
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


Layout = tuple[tuple[str, tuple[tuple[str, type], ...]], ...]
TYPED_SCOPES = ("step", "attitude", "body_attitude", "head_attitude", "head")


def layout() -> Layout:
    """The typed score fields, per scope, from the metric schema: ``(scope, ((key, dtype), ...))``."""
    return tuple((scope, tuple((m.key, m.dtype) for m in metrics.declared(scope))) for scope in TYPED_SCOPES)


def _message(fd, name: str, structure: dict, scores: tuple[tuple[str, type], ...]) -> None:
    """Message ``name``: its ``structure`` fields (name -> (number, adder)) and the typed ``scores``, numbered in
    order with the numbers ``structure`` leaves free; fields are added by number."""
    msg = fd.message_type.add(name=name)
    taken = {number for number, _ in structure.values()}
    free = (n for n in range(1, 1 << 29) if n not in taken)
    fields = dict(structure)
    for key, dtype in scores:
        fields[key] = (next(free), lambda m, k, n, t=PROTO_TYPES[dtype]: _field(m, k, n, t))
    for key, (number, add) in sorted(fields.items(), key=lambda item: item[1][0]):
        add(msg, key, number)


def _file(typed: Layout) -> descriptor_pb2.FileDescriptorProto:
    scores = dict(typed)
    fd = descriptor_pb2.FileDescriptorProto(name="starenv/recording.proto", package=PACKAGE, syntax="proto2")
    _message(fd, "HeadAttitudeError", {}, scores["head_attitude"])
    _message(fd, "BodyAttitudeError", {}, scores["body_attitude"])
    _message(fd, "AttitudeError", {
        "heads": (2, lambda m, k, n: _field(m, k, n, MESSAGE, REPEATED, "HeadAttitudeError")),
        "body": (3, lambda m, k, n: _field(m, k, n, MESSAGE, OPTIONAL, "BodyAttitudeError")),
    }, scores["attitude"])
    _message(fd, "HeadScores", {"extra": (100, lambda m, k, n: _map(m, k, n, "ExtraEntry"))}, scores["head"])
    _message(fd, "StepScores", {
        "frame": (1, lambda m, k, n: _field(m, k, n, UINT32)),
        "time_s": (2, lambda m, k, n: _field(m, k, n, DOUBLE)),
        "source": (3, lambda m, k, n: _field(m, k, n, STRING)),
        "attitude": (6, lambda m, k, n: _field(m, k, n, MESSAGE, OPTIONAL, "AttitudeError")),
        "heads": (7, lambda m, k, n: _field(m, k, n, MESSAGE, REPEATED, "HeadScores")),
        "record": (8, lambda m, k, n: _map(m, k, n, "RecordEntry")),
        "record_without_value": (9, lambda m, k, n: _field(m, k, n, STRING, REPEATED)),
    }, scores["step"])
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


def classes() -> dict[str, type]:
    """The message classes by short name (``StepScores``, ``GyroSamples``, ...) of the current metric schema."""
    return _classes(layout())


@cache
def _classes(typed: Layout) -> dict[str, type]:
    """Built once per process and schema."""
    pool = descriptor_pool.DescriptorPool()
    pool.Add(_file(typed))
    names = ("HeadAttitudeError", "BodyAttitudeError", "AttitudeError", "HeadScores", "StepScores", "GyroSamples",
             "FilterState")
    return {n: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{PACKAGE}.{n}")) for n in names}


def _set(msg, typed: tuple[tuple[str, type], ...], values: dict) -> None:
    """The typed fields of ``msg`` from ``values`` (a None stays unset)."""
    for key, dtype in typed:
        if values[key] is not None:
            setattr(msg, key, dtype(values[key]))


def encode_scores(frame: int, time_s: float, source: str, scores: dict, record: dict):
    """``info["scores"]`` and the flat record of one step as a ``StepScores`` message."""
    typed = dict(layout())
    msg = classes()["StepScores"](frame=int(frame), time_s=float(time_s), source=source)
    _set(msg, typed["step"], scores)
    att = scores.get("attitude")
    if att:  # empty (or None in older callers) when the step had no estimate
        _set(msg.attitude, typed["attitude"], att)
        if "body" in att:  # absent in scores made before the body's errors were scored
            _set(msg.attitude.body, typed["body_attitude"], att["body"])
        for h in att["heads"]:
            _set(msg.attitude.heads.add(), typed["head_attitude"], h)
    head_keys = dict(typed["head"])
    for h in scores["heads"]:
        head = msg.heads.add()
        _set(head, typed["head"], h)
        for key, value in h.items():
            if key not in head_keys and value is not None:
                head.extra[key] = float(value)
    for key, value in record.items():
        if value is None:
            msg.record_without_value.append(key)
        else:
            msg.record[key] = float(value)
    return msg


def decode_scores(msg) -> tuple[dict, dict]:
    """(scores, record) back from a ``StepScores`` message: the inverse of :func:`encode_scores`."""
    typed = dict(layout())
    att = {}
    if msg.HasField("attitude"):
        att = {**{k: getattr(msg.attitude, k) for k, _ in typed["attitude"]},
               "heads": [{k: getattr(h, k) for k, _ in typed["head_attitude"]} for h in msg.attitude.heads]}
        if msg.attitude.HasField("body"):
            att["body"] = {k: getattr(msg.attitude.body, k) for k, _ in typed["body_attitude"]}
    heads = []
    for h in msg.heads:
        d = {k: getattr(h, k) if h.HasField(k) else None for k, _ in typed["head"]}
        d.update(h.extra)
        heads.append(d)
    scores = {"frame": msg.frame, **{k: getattr(msg, k) for k, _ in typed["step"]}, "attitude": att, "heads": heads}
    record = {**dict(msg.record), **dict.fromkeys(msg.record_without_value)}
    return scores, record
