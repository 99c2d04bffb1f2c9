"""Rerun review of an episode: from an MCAP recording (:func:`mcap_to_rrd`) or live from the env (``RerunRecorder``).

Both paths log each step with :func:`log_step`, so they produce the same entities:

* ``head{h}/image`` (the frame, uint16), with ``head{h}/image/truth`` (true trail centroids, green, ``HIP n``
  labels), ``head{h}/image/detections`` (red, labelled with the claimed id) and ``head{h}/image/predictions``
  (blue, labelled) as points; Rerun's image coordinates put (0, 0) at the top-left pixel's corner, so points are
  starenv's positions + 0.5 px;
* ``metrics/{group}/{metric}``: every metric of the step's flat score record as a scalar series, in its group's
  panel (``starenv.metrics.GROUPS``: one unit per panel; ``other`` for a key no metric declares, from an older file);
* ``log``: dropped frames, steps without a solution and the error that stopped a run, as text log entries;
* ``attitude/true`` and ``attitude/estimate``: 3-D arrows in ICRS (unit sphere): the body's +X, +Y, +Z axes (red,
  green, blue; the estimate's at 0.9 length and paler, so both stay visible when they coincide) and each head's
  boresight (the calibrated mounting's +Z; ``bore{h}``, white for the truth, grey for the estimate), from the
  attitude ICRS -> body (conjugated: arrows are body directions written in ICRS); ``attitude/stars/truth`` (green):
  the true stars' trail centroids seen through the calibrated cameras at the true attitude, and
  ``attitude/stars/detections`` (red): the detections at the estimated attitude, on the unit sphere with their ids;
* ``filter/...`` (a fusion filter's pipeline only), per body axis ``x``, ``y``, ``z``:
  ``filter/attitude_error_arcsec/{axis}/{error,plus_3sigma,minus_3sigma}`` (the rotation vector of
  ``A_est A_true^T`` against the filter's own 3-sigma), ``filter/bias_error_deg_hr/{axis}/{error,plus_3sigma,
  minus_3sigma}`` (estimate - truth) and ``filter/bias_deg_hr/{axis}/{estimate,true}``;
* ``gyro/rate_dps/{x,y,z}``: every gyro sample (deg/s, body frame) at its own time on ``sim_time`` (on ``frame`` all
  of a step's samples share the frame's index).

Timelines: ``frame`` (sequence: the frame index) and ``sim_time`` (duration: simulation time at mid-exposure).  No
wall-clock timeline (``log_time`` is switched off) and a recording id derived from the MCAP file's bytes (or, live,
from the scenario, seed and pipeline), so the same run gives the same recording content.  rerun-sdk is imported
inside the functions (it is heavy to import).
"""

from __future__ import annotations

import hashlib
import json
import os
import tomllib
import uuid
from pathlib import Path

import numpy as np

from starenv import metrics
from starenv import scenario as scenario_mod
from starenv.agents.base import AttitudeFilter
from starenv.record.step import ERROR, INFO, WARNING, FilterState, StepData, from_step_log

APPLICATION_ID = "starenv"
PIXEL_ORIGIN = 0.5
COLORS = {"truth": (50, 230, 50), "detections": (255, 80, 50), "predictions": (50, 180, 255)}
LEVELS = {INFO: "INFO", WARNING: "WARN", ERROR: "ERROR"}


def analytics_off() -> None:
    """Keep Rerun's usage analytics off for this process and the viewers it starts: Rerun's analytics pipeline does
    not start while the ``CI`` environment variable is set (``rerun analytics disable`` turns it off for good)."""
    os.environ.setdefault("CI", "1")


def metric_path(key: str) -> str:
    """The entity path of a flat-record metric: ``metrics/{group}/{key}``."""
    return f"metrics/{metrics.group_of(key)}/{key}"


def metric_panels(with_filter: bool = False) -> list[tuple[str, str]]:
    """(origin, title) of the metric panels, one per group of ``starenv.metrics.GROUPS`` (a filter's only
    ``with_filter``)."""
    return [(f"metrics/{key}", group.title) for key, group in metrics.GROUPS.items()
            if with_filter or not group.filter_only]


FILTER_VIEWS = {"filter/attitude_error_arcsec": "filter: attitude error vs 3-sigma (arcsec, body axes)",
                "filter/bias_error_deg_hr": "filter: gyro bias error vs 3-sigma (deg/h)",
                "filter/bias_deg_hr": "filter: gyro bias estimate and truth (deg/h)"}


def blueprint(n_heads: int, with_filter: bool = False):
    """The default layout: the heads' frames with overlays on the left, error series (and a fusion filter's state
    when ``with_filter``) and the log on the right."""
    import rerun.blueprint as rrb

    frames = rrb.Grid(*[rrb.Spatial2DView(origin=f"head{h}", name=f"head {h}") for h in range(n_heads)])
    series = [rrb.TimeSeriesView(origin=origin, name=title) for origin, title in metric_panels(with_filter)]
    if with_filter:
        series[1:1] = [rrb.TimeSeriesView(origin=origin, name=name) for origin, name in FILTER_VIEWS.items()]
    sky = rrb.Spatial3DView(origin="attitude", name="attitude: true vs estimate (ICRS)")
    gyro = rrb.TimeSeriesView(origin="gyro", name="gyro (deg/s, body)")
    return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(frames, rrb.Horizontal(sky, gyro), row_shares=[2, 1]),
                                        rrb.Vertical(*series, rrb.TextLogView(origin="log", name="log")),
                                        column_shares=[2, 1]), collapse_panels=True)


def open_stream(path: str | os.PathLike, recording_id: str, n_heads: int, name: str, with_filter: bool = False):
    """A recording stream saving to ``path`` (``.rrd``) with a fixed id, no wall-clock timeline, our blueprint."""
    import rerun as rr

    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id, send_properties=False)
    rec.set_log_time_enabled(False)
    rec.save(str(path), default_blueprint=blueprint(n_heads, with_filter))
    rec.send_recording_name(name)
    return rec


AXIS_COLORS = np.array([(230, 40, 40), (40, 200, 40), (60, 90, 255)])


def _attitude_arrows(q: np.ndarray, boresights_body: np.ndarray, estimate: bool):
    """Arrows3D of the body axes and head boresights in ICRS for attitude ``q`` ``[x, y, z, w]`` (ICRS -> body)."""
    import rerun as rr
    from scipy.spatial.transform import Rotation

    body_to_icrs = Rotation.from_quat(q).inv()
    scale = 0.9 if estimate else 1.0
    vectors = body_to_icrs.apply(np.vstack([np.eye(3), boresights_body])) * scale
    bore = (150, 150, 150) if estimate else (255, 255, 255)
    colors = np.vstack([AXIS_COLORS // 2 + 100 if estimate else AXIS_COLORS, [bore] * len(boresights_body)])
    labels = ["X", "Y", "Z"] + [f"bore{h}" for h in range(len(boresights_body))]
    return rr.Arrows3D(vectors=vectors, colors=colors, labels=labels, radii=0.01 if estimate else 0.02)


def _sky(cameras, q: np.ndarray, layers) -> tuple[np.ndarray, list[str]]:
    """ICRS unit directions (n, 3) and labels of image points ``layers[h]`` (``Stars2D``) of each head, seen through
    the calibrated ``cameras`` at attitude ``q`` ``[x, y, z, w]`` (ICRS -> body)."""
    from scipy.spatial.transform import Rotation

    body_to_icrs = Rotation.from_quat(q).inv()
    dirs, labels = [np.zeros((0, 3))], []
    for cam, stars in zip(cameras, layers, strict=True):
        if len(stars.xy):
            dirs.append(body_to_icrs.apply(cam.mounting.inv().apply(cam.unproject(stars.xy))))
            labels += [f"HIP {i}" if i >= 0 else "" for i in stars.ids]
    return np.vstack(dirs), labels


def log_step(rec, data: StepData, cameras=None) -> None:
    """Log one step to the recording stream ``rec``: the one place both review paths write Rerun data.
    ``cameras``: the heads' calibrated cameras, for the 3-D attitude view (none: no 3-D view)."""
    import rerun as rr

    rec.set_time("frame", sequence=int(data.frame))
    rec.set_time("sim_time", duration=np.timedelta64(int(data.time_ns), "ns"))
    for h, head in enumerate(data.heads):
        if head.image is not None:
            rec.log(f"head{h}/image", rr.Image(head.image))
        for layer, color in COLORS.items():
            stars = getattr(head, layer)
            labels = [f"HIP {i}" if i >= 0 else "" for i in stars.ids]
            rec.log(f"head{h}/image/{layer}", rr.Points2D(stars.xy + PIXEL_ORIGIN, labels=labels, colors=color,
                                                         radii=2.5 if layer == "truth" else 1.5))
    for key in sorted(data.record):
        value = data.record[key]
        if key not in metrics.INDEX_KEYS and value is not None:
            rec.log(metric_path(key), rr.Scalars(float(value)))
    for level, text in data.logs:
        rec.log("log", rr.TextLog(text, level=LEVELS.get(level, "INFO")))
    if data.heads and cameras is not None:  # not the closing entry of a run stopped by an error
        bores = np.array([cam.mounting.inv().apply([0.0, 0.0, 1.0]) for cam in cameras]).reshape(-1, 3)
        rec.log("attitude/true", _attitude_arrows(data.attitude_true, bores, estimate=False))
        dirs, labels = _sky(cameras, data.attitude_true, [h.truth for h in data.heads])
        rec.log("attitude/stars/truth", rr.Points3D(dirs, labels=labels, colors=COLORS["truth"], radii=0.006))
        if data.attitude_estimate is not None:
            rec.log("attitude/estimate", _attitude_arrows(data.attitude_estimate, bores, estimate=True))
            dirs, labels = _sky(cameras, data.attitude_estimate, [h.detections for h in data.heads])
            rec.log("attitude/stars/detections", rr.Points3D(dirs, labels=labels, colors=COLORS["detections"],
                                                             radii=0.004))
        else:
            rec.log("attitude/estimate", rr.Clear(recursive=False))
            rec.log("attitude/stars/detections", rr.Clear(recursive=False))
    if data.filter is not None:
        _log_filter(rec, data.filter, data.attitude_true)
    if len(data.gyro_t):
        times = rr.TimeColumn("sim_time", duration=np.round(np.asarray(data.gyro_t) * 1e9).astype("timedelta64[ns]"))
        frames = rr.TimeColumn("frame", sequence=np.full(len(data.gyro_t), int(data.frame)))
        for axis, values in zip("xyz", np.degrees(np.asarray(data.gyro_rate)).T, strict=True):
            rec.send_columns(f"gyro/rate_dps/{axis}", indexes=[frames, times],
                             columns=rr.Scalars.columns(scalars=values))


def _log_filter(rec, state: FilterState, attitude_true: np.ndarray) -> None:
    """A filter's errors against truth and its 3-sigma bounds, and its bias beside the true one (module docstring)."""
    import rerun as rr
    from scipy.spatial.transform import Rotation

    error = (Rotation.from_quat(state.attitude) * Rotation.from_quat(attitude_true).inv()).as_rotvec()
    series = {"attitude_error_arcsec": (np.degrees(error) * 3600.0, state.attitude_sigma_arcsec),
              "bias_error_deg_hr": (state.bias_deg_hr - state.bias_true_deg_hr, state.bias_sigma_deg_hr)}
    for i, axis in enumerate("xyz"):
        for name, (err, sigma) in series.items():
            rec.log(f"filter/{name}/{axis}/error", rr.Scalars(float(err[i])))
            rec.log(f"filter/{name}/{axis}/plus_3sigma", rr.Scalars(3.0 * float(sigma[i])))
            rec.log(f"filter/{name}/{axis}/minus_3sigma", rr.Scalars(-3.0 * float(sigma[i])))
        rec.log(f"filter/bias_deg_hr/{axis}/estimate", rr.Scalars(float(state.bias_deg_hr[i])))
        rec.log(f"filter/bias_deg_hr/{axis}/true", rr.Scalars(float(state.bias_true_deg_hr[i])))


def mcap_to_rrd(mcap_path: str | os.PathLike, rrd_path: str | os.PathLike, on_step=None) -> Path:
    """Build the Rerun recording of a finished MCAP recording; returns the .rrd path.  ``on_step()`` (optional) is
    called after each step is logged (a progress bar)."""
    from starenv.record.mcap import check_finished, read_metadata, read_steps, topics

    mcap_path = check_finished(mcap_path)
    digest = hashlib.sha256()
    with open(mcap_path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    meta = read_metadata(mcap_path)
    if "starenv.run" not in meta:
        raise ValueError(f"recording {str(mcap_path)!r}: an MCAP file, but not one starenv wrote (no starenv.run "
                         "metadata)")
    n_heads = int(meta["starenv.run"]["heads"])
    name = f"{meta['starenv.scenario']['name']} seed {meta['starenv.run']['seed']}"
    rrd_path = Path(rrd_path)
    with_filter = "/filter" in topics(mcap_path)
    rec = open_stream(rrd_path, str(uuid.UUID(bytes=digest.digest()[:16])), n_heads, name, with_filter)
    cameras = [h.calibrated for h in scenario_mod.load(tomllib.loads(meta["starenv.scenario"]["toml"])).heads]
    for data in read_steps(mcap_path):
        log_step(rec, data, cameras)
        if on_step is not None:
            on_step()
    rec.flush()
    rec.disconnect()
    return rrd_path


class RerunRecorder:
    """Observer (``starenv.episode.Observer``) that records an episode straight to a Rerun ``.rrd`` file."""

    def __init__(self, path_rrd: str | os.PathLike):
        self.path = Path(path_rrd)
        if self.path.suffix != ".rrd":
            raise ValueError(f"RerunRecorder path_rrd: expected a file name ending in .rrd, got {str(path_rrd)!r}")
        self._rec = None

    def start(self, env, seed: int, pipeline) -> None:
        sc = env.unwrapped.scenario
        self._sizes = [(h.camera.height, h.camera.width) for h in sc.heads]
        self._cameras = env.unwrapped.cameras
        self._period_ns = int(round(sc.frame_period_s * 1e9))
        self._last = None
        agents = None if pipeline is None else pipeline.describe()
        key = json.dumps([sc.to_toml(), int(seed), agents]).encode()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        rec_id = str(uuid.UUID(bytes=hashlib.sha256(key).digest()[:16]))
        with_filter = isinstance(getattr(pipeline, "agents", {}).get("predictor"), AttitudeFilter)
        self._rec = open_stream(self.path, rec_id, len(sc.heads), f"{sc.name} seed {seed}", with_filter)

    def step(self, log) -> None:
        data = from_step_log(log, self._sizes)
        log_step(self._rec, data, self._cameras)
        self._last = data

    def close(self, error: BaseException | None = None) -> None:
        if self._rec is None:
            return
        if error is not None:
            frame = 0 if self._last is None else self._last.frame + 1
            t = 0 if self._last is None else self._last.time_ns + self._period_ns
            text = f"frame {frame}: run stopped by {type(error).__name__}: {error}"
            log_step(self._rec, StepData(frame, t, [], np.zeros(4), None, "none", {}, {}, np.zeros(0),
                                         np.zeros((0, 3)), [(ERROR, text)]))
        self._rec.flush()
        self._rec.disconnect()
        self._rec = None
