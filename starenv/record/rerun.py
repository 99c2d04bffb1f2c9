"""Rerun review of an episode: from an MCAP recording (:func:`mcap_to_rrd`) or live from the env (``RerunRecorder``).

Both paths log each step through one :class:`Review`, so they produce the same entities:

* ``head{h}/image``: the frame as displayed, an 8-bit asinh stretch above its background (``starenv.view.stretch``:
  the background black, the frame's 99.99th percentile white), and ``head{h}/raw``: the raw 16-bit counts, drawn
  fully transparent above it, so that hovering the frame reads the counts (raise its opacity to see them); both
  cleared on a dropped frame, which ``head{h}/image/dropped`` (a red outline) and ``head{h}/image/dropped/label``
  (FRAME DROPPED) mark;
* overlays, each a marker class of the annotation context at ``/`` (:data:`CLASSES`: label and colour; the
  ``legend`` text document names them all): ``head{h}/image/truth`` (true trail centroids, green rings),
  ``head{h}/image/detections`` (squares: identified right, identified wrong, no id), ``head{h}/image/wrong_ids``
  (the wrong identifications again, larger and labelled ``HIP n?``: the only labels shown; every other marker's
  ``HIP n`` shows on hover) and ``head{h}/image/predictions`` (reticles).  A claimed id is judged as the scorer does
  (``starenv.scoring.HeadFrame.claims``) against the true trail centroids (recordings keep no trail ends).  Rerun's
  image coordinates put (0, 0) at the top-left pixel's corner, so markers are starenv's positions + 0.5 px;
* ``metrics/{group}/{metric}`` (a per-head metric: ``metrics/{group}/head{h}/{metric}``): every metric of the
  step's flat score record as a scalar series, named without its unit, in its group's panel
  (``starenv.metrics.GROUPS``; a group's metrics of another unit get their own panel, and a per-head group one panel
  per head, under that head's frame; ``other`` for a key no metric declares, from an older file); per-axis errors
  coloured by axis (x red, y green, z / roll blue), other arcsec errors (angles) grey, those panels without a legend
  (the title names the colours); every panel's tooltip lists all its series at the hovered time;
* ``status/{flag}`` (each flag of the record, unit ``0/1``: yes / no / no value) and ``status/frames`` (all
  delivered, or the heads whose frame was dropped): the status timeline, a state logged when it changes (the flags'
  series are logged too, but laid out there rather than as overlapping 0/1 lines);
* ``log``: the recording's own log lines (dropped frames, steps without a solution, a fusion filter's start, gate
  rejections and restarts, the error that stopped a run);
  ``log/events``: the review's own, from the step sequence: the first fix, each loss of fix and re-acquisition (a fix:
  solved and within the threshold, as ``starenv.datasheet`` counts them) and every wrong identification;
* ``attitude/true`` and ``attitude/estimate``: 3-D arrows in ICRS (unit sphere): the body's +X, +Y, +Z axes (red,
  green, blue; the estimate's at 0.9 length and paler, so both stay visible when they coincide; only the truth's
  labelled) and each head's boresight (the calibrated mounting's +Z; white for the truth, grey for the estimate),
  from the attitude ICRS -> body (conjugated: arrows are body directions written in ICRS); ``attitude/stars/truth``:
  the true stars' trail centroids seen through the calibrated cameras at the true attitude, and
  ``attitude/stars/detections``: the detections at the estimated attitude (their marker classes), on the unit
  sphere, labelled on hover; ``attitude/bodies`` (a scenario with ``[sky] bodies``): the Sun, the Moon, the planets
  and, from an orbit, the Earth's centre on the unit sphere, seen from the spacecraft, each labelled;
* ``filter/...`` (a fusion filter's pipeline only), per body axis ``x``, ``y``, ``z``:
  ``filter/attitude_error_arcsec/{axis}/{error,plus_3sigma,minus_3sigma}`` (the rotation vector of
  ``A_est A_true^T`` against the filter's own 3-sigma), ``filter/bias_error_deg_hr/{axis}/{error,plus_3sigma,
  minus_3sigma}`` (estimate - truth) and ``filter/bias_deg_hr/{axis}/{estimate,true}``;
* ``gyro/rate_dps/{x,y,z}``: every gyro sample (deg/s, body frame) at its own time on ``sim_time`` (on ``frame`` all
  of a step's samples share the frame's index).

The layout (:func:`blueprint`) is sent with the first step, when the record's keys say which panels have data: a
group no key of the record belongs to (restoration without a deblurrer, a filter's without a filter) gets no panel.

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
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from starenv import metrics
from starenv import scenario as scenario_mod
from starenv.agents.base import AttitudeFilter
from starenv.record.step import ERROR, INFO, WARNING, FilterState, Stars2D, StepData, from_step_log
from starenv.sim.bodies import body_directions

APPLICATION_ID = "starenv"
FLUSH_BYTES = 1 << 21  # a chunk is cut once this many bytes of rows are pending (Rerun's default size)
FLUSH_NEVER_S = 1e9  # the batcher's wall-clock tick, in s: never within a run
PIXEL_ORIGIN = 0.5
LEVELS = {INFO: "INFO", WARNING: "WARN", ERROR: "ERROR"}
AXIS_COLORS = np.array([(230, 40, 40), (40, 200, 40), (60, 90, 255)])  # x, y, z (roll: about z)
AXES = {"x": 0, "y": 1, "z": 2, "roll": 2}
UNIT_WORDS = {"arcsec", "px", "ms", "db", "deg", "hr", "error"}  # left out of a series' name: its panel states the unit
MAGNITUDE_COLOR = (170, 170, 170)  # an arcsec error that is an angle, not about one axis
BODY_COLORS = {"sun": (255, 220, 40), "moon": (235, 235, 235), "earth": (70, 130, 255), "planet": (255, 150, 60)}
AXIS_NAMES = ("red", "green", "blue")
# The other series' colours, in a panel's order: Okabe and Ito's colour-blind-safe set (white for its black, on the
# viewer's dark background), named in the legend panel.
PALETTE = (((230, 159, 0), "orange"), ((86, 180, 233), "sky blue"), ((0, 158, 115), "bluish green"),
           ((240, 228, 66), "yellow"), ((0, 114, 178), "blue"), ((213, 94, 0), "vermillion"),
           ((204, 121, 167), "reddish purple"), ((255, 255, 255), "white"))
FLAG_UNIT = "0/1"  # a flag's unit: shown as a state (yes / no) on the status timeline, not as a series
UNIT_NAMES = {"": "unitless", None: "mixed units"}


@dataclass(frozen=True)
class MarkerClass:
    """An overlay's marker class (a class id of the annotation context): its label, colour (RGB) and shape, as the
    legend names them."""

    label: str
    color: tuple[int, int, int]
    colour_name: str
    shape: str


TRUTH, IDENTIFIED, WRONG, UNIDENTIFIED, PREDICTION, PREDICTION_OFF, DROPPED = 1, 2, 3, 4, 5, 6, 7
CLASSES = {
    TRUTH: MarkerClass("true star (trail centroid)", (60, 220, 60), "green", "ring"),
    IDENTIFIED: MarkerClass("detection, identified right", (0, 200, 255), "cyan", "square"),
    WRONG: MarkerClass("detection, identified WRONG", (255, 0, 200), "magenta", "large square, labelled HIP n?"),
    UNIDENTIFIED: MarkerClass("detection, no id", (255, 190, 0), "yellow", "square"),
    PREDICTION: MarkerClass("predicted position of a true star", (170, 120, 255), "violet", "reticle (four ticks)"),
    PREDICTION_OFF: MarkerClass("predicted position, no such star on the frame (too faint)", (110, 90, 150),
                                "dim violet", "reticle"),
    DROPPED: MarkerClass("frame dropped", (255, 60, 60), "red", "outline of the frame, FRAME DROPPED"),
}
YES, NO, NONE = (60, 200, 60), (230, 50, 50), (120, 120, 120)  # state timeline colours


def analytics_off() -> None:
    """Keep Rerun's usage analytics off for this process and the viewers it starts: Rerun's analytics pipeline does
    not start while the ``CI`` environment variable is set (``rerun analytics disable`` turns it off for good)."""
    os.environ.setdefault("CI", "1")


def _head_of(key: str) -> int | None:
    """The head of a per-head flat-record key (a metric whose name holds ``{head}``), else None."""
    found = metrics.find(key)
    return None if found is None or "head" not in found[1] else int(found[1]["head"])


def metric_path(key: str) -> str:
    """The entity path of a flat-record key: ``metrics/{group}/{key}``, a per-head key's
    ``metrics/{group}/head{h}/{key}``."""
    head = _head_of(key)
    return f"metrics/{metrics.group_of(key)}/" + ("" if head is None else f"head{head}/") + key


def series_name(key: str) -> str:
    """A flat-record key's name in its panel's legend: without its unit and head (the panel states both); a
    latency's, its agent role."""
    found = metrics.find(key)
    if found is not None and "role" in found[1]:
        return found[1]["role"]
    head = _head_of(key)
    words = [w for w in key.split("_") if w.lower() not in UNIT_WORDS and w != f"head{head}"]
    return " ".join(words) or key


def _axis_color(key: str) -> tuple[tuple[int, int, int], str] | None:
    """The fixed colour (RGB, name) of a key's series: a per-axis error's axis colour (its last word naming an axis),
    grey for another arcsec error (an angle: the total, across the boresight); None for the rest."""
    axes = [AXES[w] for w in key.split("_") if w in AXES]
    if axes:
        return tuple(int(c) for c in AXIS_COLORS[axes[-1]]), AXIS_NAMES[axes[-1]]
    found = metrics.find(key)
    return (MAGNITUDE_COLOR, "grey") if found is not None and found[0].unit == "arcsec" else None


def series_colours(keys) -> dict[str, tuple[tuple[int, int, int], str]]:
    """The colour (RGB, name) of each of one panel's ``keys``: an axis' or an angle's fixed colour, else the next of
    :data:`PALETTE` in the keys' order (so no panel needs a legend over its lines)."""
    out, free = {}, iter(PALETTE * (1 + len(keys) // len(PALETTE)))
    for key in keys:
        out[key] = _axis_color(key) or next(free)
    return out


def _unit(key: str) -> str | None:
    found = metrics.find(key)
    return None if found is None else found[0].unit


class Panel(NamedTuple):
    """A metric panel: its origin (``metrics/{group}``, a head's ``metrics/{group}/head{h}``), title, the entity
    paths it shows (none: its origin's subtree), their colours (RGB, in the paths' order) and, for the legend
    panel, (series name, colour name) of each (none: the title names them).  No panel draws a legend over its lines.
    """

    origin: str
    title: str
    paths: tuple[str, ...] = ()
    rgb: tuple[tuple[int, int, int], ...] = ()
    colours: tuple[tuple[str, str], ...] = ()


def _title(group: str, unit: str | None) -> str:
    if group not in metrics.GROUPS:
        return "other metrics (keys no metric declares)"
    return metrics.GROUPS[group].title.format(unit=UNIT_NAMES.get(unit, unit))


def metric_panels(keys=None, head: int | None = None) -> list[Panel]:
    """The metric panels of a flat record's ``keys`` (those of no head, or of head ``head``): one per group
    (:data:`starenv.metrics.GROUPS` order, then ``other``) and unit that a key belongs to, flags (unit ``0/1``) left
    to the status timeline; with ``keys=None``, one per group."""
    if keys is None:
        return [Panel(f"metrics/{group}", _title(group, None)) for group in metrics.GROUPS]
    chosen: dict[tuple[str, str | None], list[str]] = {}
    for key in sorted(keys):
        if key not in metrics.INDEX_KEYS and _head_of(key) == head and _unit(key) != FLAG_UNIT:
            chosen.setdefault((metrics.group_of(key), _unit(key)), []).append(key)
    rank = {g: i for i, g in enumerate((*metrics.GROUPS, "other"))}
    out = []
    for group, unit in sorted(chosen, key=lambda gu: (rank[gu[0]], str(gu[1]))):
        group_keys = metrics.order(chosen[group, unit])
        origin = f"metrics/{group}" + ("" if head is None else f"/head{head}")
        title = _title(group, unit) if head is None else f"head {head}: {_title(group, unit)}"
        colours = series_colours(group_keys)
        named = () if all(_axis_color(k) for k in group_keys) else tuple(
            (series_name(k), colours[k][1]) for k in group_keys)
        out.append(Panel(origin, title, tuple(metric_path(k) for k in group_keys),
                         tuple(colours[k][0] for k in group_keys), named))
    return out


def flag_keys(keys) -> list[str]:
    """The flags (unit ``0/1``) of a flat record's ``keys``, in declaration order: rows of the status timeline."""
    return metrics.order(k for k in keys if k not in metrics.INDEX_KEYS and _unit(k) == FLAG_UNIT)


FILTER_VIEWS = {"filter/attitude_error_arcsec": "filter: attitude error (arcsec) about body x y z: red green blue, "
                "its +-3 sigma paler",
                "filter/bias_error_deg_hr": "filter: gyro bias error (deg/h) x y z: red green blue, its +-3 sigma "
                "paler",
                "filter/bias_deg_hr": "filter: gyro bias estimate (deg/h) x y z: red green blue, the truth paler"}
FILTER_SERIES = {"error": "", "plus_3sigma": " +3 sigma", "minus_3sigma": " -3 sigma", "estimate": " estimate",
                 "true": " true"}  # a filter series' name after its axis; the first and "estimate" in full colour
BLACK_SIGMA = 1.0  # the frames' black point above the background (noise sigmas): the panels show them small
IMAGE_DRAW_ORDER, RAW_DRAW_ORDER = 0.0, 5.0  # the raw counts above the stretched frame, both below the markers
STRETCH_NOTE = "asinh stretch above the background"


def legend_markdown(panels: list[Panel] = ()) -> str:
    """The legend panel's text: every marker class, the frames' stretch, the 3-D view, the status timeline, the
    plots (the colour of each series of ``panels`` whose title does not name them), the log."""
    markers = "\n".join(f"- **{c.colour_name} {c.shape}**: {c.label}" for c in CLASSES.values())
    colours = "".join(f"\n- *{p.title}*: " + ", ".join(f"{name} {colour}" for name, colour in p.colours)
                      for p in panels if p.colours)
    return f"""**Markers** (hover one for its HIP number; only wrong identifications are labelled):
{markers}

**Frames**: {STRETCH_NOTE} (`starenv.view.stretch`), per frame: black up to the background (median)
plus {BLACK_SIGMA:g} noise sigma, white from its 99.99th percentile (at least 20 sigma).  Hover a frame for its raw
16-bit counts (`head{{h}}/raw`, a transparent layer: raise its opacity to see it).

**3-D attitude** (ICRS, unit sphere): body +X, +Y, +Z red, green, blue and the boresights white (truth, labelled
at their tips); the estimate's paler, 0.9 long.  Stars: true (green) at the true attitude, detections (their
classes) at the estimated one.

**Status**: a row per flag (green: holds, red: does not) and one for the frames (red: a head's dropped).

**Plots** (no legend over the lines; hover a plot for every series' value): errors about an axis x red, y green,
z / roll blue; angles grey; the other series:{colours}

**Log**: dropped frames, steps without a solution, first fix, fix lost / re-acquired, wrong identifications, a
filter's gate rejections and restarts, the error that stopped a run.
"""


def _series_view(panel: Panel):
    """A time-series view of ``panel``: the tooltip lists every series at the hovered time; no legend over the lines
    (the title or the legend panel names the colours)."""
    import rerun.blueprint as rrb

    contents = [f"+ {p}" for p in panel.paths] or ["+ $origin/**"]
    return rrb.TimeSeriesView(origin=panel.origin, name=panel.title, contents=contents,
                              plot_legend=rrb.PlotLegend(visible=False),
                              interaction=rrb.PlotInteraction(tooltip_mode=rrb.components.TooltipMode.All))


def _head_view(h: int, size: tuple[int, int]):
    """Head ``h``'s frame (``size``: width, height px) with its overlays, on black (a dropped frame shows none)."""
    import rerun.blueprint as rrb

    width, height = size
    return rrb.Spatial2DView(origin=f"head{h}", name=f"head {h} ({STRETCH_NOTE})", background=(0, 0, 0),
                             visual_bounds=rrb.VisualBounds2D(x_range=[0, width], y_range=[0, height]))


def _log_view():
    """The log: level and text (the text names the frame)."""
    import rerun.blueprint as rrb
    from rerun.blueprint.encodings import TextLogColumn, TextLogColumnKind, TimelineColumn

    columns = rrb.TextLogColumns(timeline_columns=[TimelineColumn(t, visible=False) for t in ("frame", "sim_time")],
                                 text_log_columns=[TextLogColumn(TextLogColumnKind.LogLevel),
                                                   TextLogColumn(TextLogColumnKind.Body),
                                                   TextLogColumn(TextLogColumnKind.EntityPath, visible=False)])
    return rrb.TextLogView(origin="log", name="log: events", columns=columns)


GYRO = Panel("gyro", "gyro rate (deg/s) about body x y z: red green blue")


def blueprint(sizes: list[tuple[int, int]], keys=(), with_filter: bool = False, eye=None):
    """The default layout for heads of ``sizes`` (width, height px) and a first step's flat-record ``keys``: each
    head's frame above its own metric panels (side by side; 4 heads: 2 x 2), the status timeline (flags, frames
    delivered), the 3-D attitude, the legend and the log below; on the right a panel per metric group and unit with
    data (and a fusion filter's state when ``with_filter``) and the gyro; ``eye``: the 3-D view's
    (``rrb.EyeControls3D``, none: the viewer's)."""
    import rerun.blueprint as rrb

    cells = []
    for h, size in enumerate(sizes):
        panels = [_series_view(p) for p in metric_panels(keys, head=h)]
        cells.append(rrb.Vertical(_head_view(h, size), *panels, row_shares=[3] + [1] * len(panels))
                     if panels else _head_view(h, size))
    heads = rrb.Grid(*cells, grid_columns=2) if len(cells) == 4 else rrb.Horizontal(*cells)
    series = [_series_view(p) for p in metric_panels(keys)]
    if with_filter:
        series += [_series_view(Panel(origin, name)) for origin, name in FILTER_VIEWS.items()]
    series.append(_series_view(GYRO))
    status = rrb.StateTimelineView(origin="status", name="status: flags and frames delivered")
    sky = rrb.Spatial3DView(origin="attitude", name="attitude: true vs estimate (ICRS)", eye_controls=eye,
                            background=rrb.Background(kind=rrb.BackgroundKind.GradientDark), line_grid=False)
    below = rrb.Horizontal(sky,
                           rrb.TextDocumentView(origin="legend", name="legend"),
                           _log_view(), column_shares=[2, 2, 3])
    left = rrb.Vertical(heads, status, below, row_shares=[9, 5, 5])
    rows = [series[0]] + [rrb.Horizontal(*series[i:i + 2]) if i + 1 < len(series) else series[i]
                          for i in range(1, len(series), 2)]
    right = rrb.Vertical(*rows)
    return rrb.Blueprint(rrb.Horizontal(left, right, column_shares=[3, 2]), collapse_panels=True)


def open_stream(path: str | os.PathLike, recording_id: str, name: str):
    """A recording stream saving to ``path`` (``.rrd``) with a fixed id and no wall-clock timeline; its layout comes
    with the first step (:class:`Review`).  Chunks are cut by size alone (Rerun's default 2 MiB), never by its
    wall-clock flush tick, so the same data is cut into the same chunks however loaded the machine is."""
    import rerun as rr

    batcher = rr.ChunkBatcherConfig(flush_tick=FLUSH_NEVER_S, flush_num_bytes=FLUSH_BYTES)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id, send_properties=False,
                             batcher_config=batcher)
    rec.set_log_time_enabled(False)
    rec.save(str(path))
    rec.send_recording_name(name)
    return rec


def _attitude_arrows(q: np.ndarray, boresights_body: np.ndarray, estimate: bool) -> tuple[np.ndarray, np.ndarray]:
    """Vectors (n, 3) and colours (n, 3) of the body axes and head boresights in ICRS for attitude ``q``
    ``[x, y, z, w]`` (ICRS -> body): arrows from the origin, the estimate's shorter and paler."""
    from scipy.spatial.transform import Rotation

    body_to_icrs = Rotation.from_quat(q).inv()
    scale = 0.9 if estimate else 1.0
    vectors = body_to_icrs.apply(np.vstack([np.eye(3), boresights_body])) * scale
    bore = (150, 150, 150) if estimate else (255, 255, 255)
    colors = np.vstack([AXIS_COLORS // 2 + 100 if estimate else AXIS_COLORS, [bore] * len(boresights_body)])
    return vectors, colors


def _axis_labels(n_heads: int) -> list[str]:
    return ["+X", "+Y", "+Z"] + [f"head {h}" for h in range(n_heads)]


def _tip_labels(boresights_body: np.ndarray) -> list[str]:
    """The labels shown at the arrows' tips: a boresight along a body axis joins that axis's label (one label, not
    two on top of each other)."""
    labels = _axis_labels(len(boresights_body))
    for h, bore in enumerate(boresights_body):
        along = np.flatnonzero(np.eye(3) @ bore > np.cos(np.radians(1.0)))
        if len(along):
            labels[along[0]] += f" / head {h}"
            labels[3 + h] = ""
    return labels


def _eye(q: np.ndarray, boresights_body: np.ndarray):
    """The 3-D view's eye at attitude ``q`` (ICRS -> body): behind the origin, looking along the heads' mean
    boresight (ICRS), so the boresights fan out with their stars at their tips."""
    import rerun.blueprint as rrb
    from scipy.spatial.transform import Rotation

    body_to_icrs = Rotation.from_quat(q).inv()
    mean = body_to_icrs.apply(boresights_body.mean(axis=0))
    view = mean / np.linalg.norm(mean) if np.linalg.norm(mean) > 0.1 else body_to_icrs.apply([0.0, 0.0, 1.0])
    side = np.cross(view, [0.0, 0.0, 1.0])
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 0.1 else np.array([1.0, 0.0, 0.0])
    up = np.cross(side, view)
    return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=-2.2 * view + 0.9 * up + 0.6 * side,
                             look_target=0.4 * view, eye_up=up)


def _sky(cameras, q: np.ndarray, layers, classes=None) -> tuple[np.ndarray, list[str], list[int]]:
    """ICRS unit directions (n, 3), labels and marker classes of image points ``layers[h]`` (``Stars2D``) of each
    head, seen through the calibrated ``cameras`` at attitude ``q`` ``[x, y, z, w]`` (ICRS -> body); ``classes[h]``:
    the points' marker classes (none: all ``TRUTH``)."""
    from scipy.spatial.transform import Rotation

    body_to_icrs = Rotation.from_quat(q).inv()
    dirs, labels, ids = [np.zeros((0, 3))], [], []
    for h, (cam, stars) in enumerate(zip(cameras, layers, strict=True)):
        if len(stars.xy):
            dirs.append(body_to_icrs.apply(cam.mounting.inv().apply(cam.unproject(stars.xy))))
            labels += [f"HIP {i}" if i >= 0 else "" for i in stars.ids]
            ids += [TRUTH] * len(stars.ids) if classes is None else list(classes[h])
    return np.vstack(dirs), labels, ids


def judge(truth: Stars2D, detections: Stars2D) -> np.ndarray:
    """Marker class of each detection (:data:`CLASSES`): its claimed id judged by the scorer
    (``starenv.scoring.HeadFrame.claims``) against the true trail centroids (point trails)."""
    from starenv.scoring import HeadFrame
    from starenv.sim.render import StarTruth

    n = len(truth.ids)
    point = StarTruth(catalog_id=truth.ids, magnitude=np.zeros(n), xy_mid=truth.xy, xy_centroid=truth.xy,
                      xy_start=truth.xy, xy_end=truth.xy, electrons=np.zeros(n), peak_electrons=np.zeros(n),
                      detectable=np.ones(n, dtype=bool))
    claims = HeadFrame(point, detected_xy=detections.xy, claimed_ids=detections.ids).claims
    return np.where(claims.correct, IDENTIFIED, np.where(claims.claimed, WRONG, UNIDENTIFIED)).astype(np.uint16)


def _rings(xy: np.ndarray, radius: float, n: int = 24) -> np.ndarray:
    """Closed circles (len(xy), n + 1, 2) of ``radius`` px about the points ``xy``."""
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return xy[:, None, :] + radius * np.stack([np.cos(a), np.sin(a)], axis=1)[None]


def _reticles(xy: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """Reticles: four ticks (4 len(xy), 2, 2) from ``inner`` to ``outer`` px left, right, above and below each point
    ``xy``, its centre left clear; strips ordered tick by tick (each tick's strips for all points together)."""
    ticks = [np.array([[sx * inner, sy * inner], [sx * outer, sy * outer]]) for sx, sy in
             ((-1, 0), (1, 0), (0, -1), (0, 1))]
    return np.concatenate([xy[:, None, :] + t[None] for t in ticks])


def _labels(stars: Stars2D) -> list[str]:
    return [f"HIP {i}" if i >= 0 else "no id" for i in stars.ids]


def _frames_state(dropped: list[int]) -> str:
    """The status timeline's frames state: ``all delivered`` or the heads whose frame was dropped."""
    return "all delivered" if not dropped else "dropped: head " + ", ".join(map(str, dropped))


def _frame_states(n_heads: int) -> list[str]:
    """Every frames state of ``n_heads`` heads, ``all delivered`` first."""
    subsets = [[h for h in range(n_heads) if mask >> h & 1] for mask in range(1 << n_heads)]
    return [_frames_state(s) for s in sorted(subsets, key=lambda s: (len(s), s))]


class Review:
    """Logs an episode, step by step, to the recording stream ``rec``: the one place both review paths write Rerun
    data (module docstring).  ``cameras``: the heads' calibrated cameras (their sizes and, for the 3-D view,
    projections); ``with_filter``: lay out a fusion filter's panels."""

    def __init__(self, rec, cameras, with_filter: bool = False, bodies=None):
        """``bodies``: :func:`starenv.sim.bodies.body_directions` of the scenario (None: no bodies drawn)."""
        self.rec, self.cameras, self.with_filter, self.bodies = rec, list(cameras), with_filter, bodies
        self.sizes = [(int(c.width), int(c.height)) for c in self.cameras]
        self.boresights = np.array([c.mounting.inv().apply([0.0, 0.0, 1.0]) for c in self.cameras]).reshape(-1, 3)
        self._laid_out = False
        self._named: set[str] = set()
        self._state: dict[str, str] = {}
        self._ever_fixed = False
        self._lost_ns: int | None = None  # sim time of the loss of fix not yet re-acquired
        self._colours: dict[str, tuple[int, int, int]] = {}  # metric entity path -> its series' colour

    def _layout(self, data: StepData | None) -> None:
        """Send the layout (panels for the groups the first step's record keys belong to, the 3-D eye at its true
        attitude) and the static legend, classes and states."""
        import rerun as rr

        keys = {} if data is None else data.record
        eye = None if data is None or not data.heads else _eye(data.attitude_true, self.boresights)
        self.rec.send_blueprint(blueprint(self.sizes, keys, self.with_filter, eye))
        panels = [p for head in (None, *range(len(self.sizes))) for p in metric_panels(keys, head)]
        self._colours = {path: rgb for p in panels for path, rgb in zip(p.paths, p.rgb, strict=True)}
        self.rec.log("/", rr.AnnotationContext([(k, c.label, c.color) for k, c in CLASSES.items()]), static=True)
        self.rec.log("legend", rr.TextDocument(legend_markdown(panels), media_type="text/markdown"), static=True)
        for key in flag_keys(keys):
            name = series_name(key)
            self.rec.log(f"status/{key}", rr.StateConfiguration(values=["yes", "no", "none"],
                                                                labels=[name, f"not {name}", f"{name}: no value"],
                                                                colors=[YES, NO, NONE]), static=True)
        frames = _frame_states(len(self.sizes))
        self.rec.log("status/frames", rr.StateConfiguration(values=frames, labels=frames,
                                                            colors=[YES] + [NO] * (len(frames) - 1)), static=True)
        for i, (axis, color) in enumerate(zip("xyz", AXIS_COLORS, strict=True)):
            self.rec.log(f"gyro/rate_dps/{axis}", rr.SeriesLines(colors=[color], names=axis), static=True)
            for origin in FILTER_VIEWS if self.with_filter else ():
                for leaf in ("estimate", "true") if origin.endswith("bias_deg_hr") else ("error", "plus_3sigma",
                                                                                          "minus_3sigma"):
                    full = leaf in ("error", "estimate")
                    self.rec.log(f"{origin}/{axis}/{leaf}", rr.SeriesLines(
                        colors=[color if full else AXIS_COLORS[i] // 2 + 100], names=axis + FILTER_SERIES[leaf],
                        widths=2.0 if full else 1.0), static=True)
        self._laid_out = True

    def step(self, data: StepData) -> None:
        """Log one step."""
        if not self._laid_out:
            self._layout(data)
        rec = self.rec
        rec.set_time("frame", sequence=int(data.frame))
        rec.set_time("sim_time", duration=np.timedelta64(int(data.time_ns), "ns"))
        wrong = [self._log_head(h, head) for h, head in enumerate(data.heads)]
        self._log_metrics(data.record)
        for level, text in data.logs:
            rec.log("log", self._text_log(level, text))
        if data.heads:  # not the closing entry of a run stopped by an error
            self._log_status(data, wrong)
            self._log_attitude(data, [judge(h.truth, h.detections) for h in data.heads])
        if data.filter is not None:
            _log_filter(rec, data.filter, data.attitude_true)
        if len(data.gyro_t):
            import rerun as rr

            times = rr.TimeColumn("sim_time",
                                  duration=np.round(np.asarray(data.gyro_t) * 1e9).astype("timedelta64[ns]"))
            frames = rr.TimeColumn("frame", sequence=np.full(len(data.gyro_t), int(data.frame)))
            for axis, values in zip("xyz", np.degrees(np.asarray(data.gyro_rate)).T, strict=True):
                rec.send_columns(f"gyro/rate_dps/{axis}", indexes=[frames, times],
                                 columns=rr.Scalars.columns(scalars=values))

    def close(self) -> None:
        """Send the layout if no step did (a run stopped before its first step)."""
        if not self._laid_out:
            self._layout(None)

    @staticmethod
    def _text_log(level: int, text: str):
        import rerun as rr

        return rr.TextLog(text, level=LEVELS.get(level, "INFO"))

    def _log_head(self, h: int, head) -> list[int]:
        """Head ``h``'s frame (stretched and raw) and overlays; the catalog ids it identified wrong."""
        import rerun as rr

        from starenv.view import stretch

        rec, (width, height) = self.rec, self.sizes[h]
        base = f"head{h}/image"
        if head.image is not None:
            rec.log(base, rr.Image(stretch(head.image, BLACK_SIGMA), draw_order=IMAGE_DRAW_ORDER))
            rec.log(f"head{h}/raw", rr.Image(head.image, draw_order=RAW_DRAW_ORDER, opacity=0.0))
            rec.log(f"{base}/dropped", rr.Boxes2D(mins=np.zeros((0, 2)), sizes=np.zeros((0, 2))))
            rec.log(f"{base}/dropped/label", rr.Points2D(np.zeros((0, 2))))
        else:
            rec.log(base, rr.Clear(recursive=False))
            rec.log(f"head{h}/raw", rr.Clear(recursive=False))
            rec.log(f"{base}/dropped", rr.Boxes2D(mins=[(0, 0)], sizes=[(width, height)], labels="frame dropped",
                                                  show_labels=False, class_ids=DROPPED, radii=-2.0))
            rec.log(f"{base}/dropped/label", rr.Points2D([(width / 2, height / 2)], labels="FRAME DROPPED",
                                                         show_labels=True, class_ids=DROPPED, radii=-3.0))
        radius = max(width, height) / 40.0  # a true star's ring: 2.5 % of the frame, the detection's square inside
        truth, det, pred = head.truth, head.detections, head.predictions
        rec.log(f"{base}/truth", rr.LineStrips2D(_rings(truth.xy + PIXEL_ORIGIN, radius), labels=_labels(truth),
                                                 class_ids=TRUTH, show_labels=False, radii=-0.75))
        classes = judge(truth, det)
        rec.log(f"{base}/detections", rr.Boxes2D(centers=det.xy + PIXEL_ORIGIN,
                                                 half_sizes=np.full((len(det.ids), 2), 0.6 * radius),
                                                 labels=_labels(det), class_ids=classes, show_labels=False,
                                                 radii=-0.75))
        bad = classes == WRONG
        rec.log(f"{base}/wrong_ids", rr.Boxes2D(centers=det.xy[bad] + PIXEL_ORIGIN,
                                                half_sizes=np.full((int(bad.sum()), 2), 1.5 * radius),
                                                labels=[f"HIP {i}?" for i in det.ids[bad]], class_ids=WRONG,
                                                show_labels=True, radii=-1.5))
        on_frame = np.isin(pred.ids, truth.ids)  # as the scorer counts predictions of stars on the frame
        rec.log(f"{base}/predictions", rr.LineStrips2D(_reticles(pred.xy + PIXEL_ORIGIN, 1.15 * radius, 1.7 * radius),
                                                       labels=_labels(pred) * 4, show_labels=False, radii=-0.75,
                                                       class_ids=np.tile(np.where(on_frame, PREDICTION,
                                                                                  PREDICTION_OFF), 4)))
        return [int(i) for i in det.ids[bad]]

    def _log_metrics(self, record: dict) -> None:
        import rerun as rr

        for key in sorted(record):
            value = record[key]
            if key in metrics.INDEX_KEYS or value is None:
                continue
            path = metric_path(key)
            if path not in self._named:
                fixed = _axis_color(key)  # a key the first step's record did not hold: its fixed colour, if any
                color = self._colours.get(path, None if fixed is None else fixed[0])
                self.rec.log(path, rr.SeriesLines(names=series_name(key), colors=None if color is None else [color]),
                             static=True)
                self._named.add(path)
            self.rec.log(path, rr.Scalars(float(value)))

    def _set_state(self, path: str, state: str) -> None:
        """A state timeline's value, logged when it changes."""
        import rerun as rr

        if self._state.get(path) != state:
            self.rec.log(path, rr.StateChange(state=state))
            self._state[path] = state

    def _log_status(self, data: StepData, wrong: list[list[int]]) -> None:
        """The state timelines and the review's events: first fix, fix lost / re-acquired, wrong identifications."""
        fixed = data.record.get("fixed") == 1.0
        available = data.attitude_estimate is not None
        for key in flag_keys(data.record):
            value = data.record[key]
            self._set_state(f"status/{key}", "none" if value is None else "yes" if value == 1.0 else "no")
        self._set_state("status/frames", _frames_state([h for h, head in enumerate(data.heads) if head.image is None]))
        events = []
        if fixed and not self._ever_fixed:
            events.append((INFO, "first fix (solved, within the threshold)"))
            self._ever_fixed = True
        elif fixed and self._lost_ns is not None:
            events.append((INFO, f"fix re-acquired, {(data.time_ns - self._lost_ns) / 1e9:.3g} s after it was lost"))
            self._lost_ns = None
        elif not fixed and self._ever_fixed and self._lost_ns is None:
            why = "no attitude" if not available else {"solved": "solved outside the threshold"}.get(
                data.source, "attitude carried by the predictor")
            events.append((WARNING, f"fix lost: {why}"))
            self._lost_ns = data.time_ns
        for h, ids in enumerate(wrong):
            if ids:
                events.append((WARNING, f"head {h}: {len(ids)} wrong identification(s): "
                               + ", ".join(f"HIP {i}" for i in ids)))
        for level, text in events:
            self.rec.log("log/events", self._text_log(level, f"frame {data.frame}: {text}"))

    def _log_attitude(self, data: StepData, classes: list[np.ndarray]) -> None:
        """The 3-D view: true and estimated body axes and boresights, true stars and detections on the sky."""
        import rerun as rr

        rec, cameras, bores = self.rec, self.cameras, self.boresights
        labels = _axis_labels(len(bores))
        vectors, colors = _attitude_arrows(data.attitude_true, bores, estimate=False)
        rec.log("attitude/true", rr.Arrows3D(vectors=vectors, colors=colors, labels=labels, show_labels=False,
                                             radii=0.012))
        rec.log("attitude/axis_labels", rr.Points3D(vectors * 1.1, labels=_tip_labels(bores), show_labels=True,
                                                    colors=colors, radii=-1.0))  # beyond the tips, not at the origin
        dirs, labels, ids = _sky(cameras, data.attitude_true, [h.truth for h in data.heads])
        rec.log("attitude/stars/truth", rr.Points3D(dirs, labels=labels, class_ids=ids, show_labels=False,
                                                    radii=-2.5))
        if data.attitude_estimate is not None:
            vectors, colors = _attitude_arrows(data.attitude_estimate, bores, estimate=True)
            rec.log("attitude/estimate", rr.Arrows3D(vectors=vectors, colors=colors, show_labels=False, radii=0.006,
                                                     labels=[f"{label} (estimate)" for label in labels]))
            dirs, labels, ids = _sky(cameras, data.attitude_estimate, [h.detections for h in data.heads], classes)
            rec.log("attitude/stars/detections", rr.Points3D(dirs, labels=labels, class_ids=ids, show_labels=False,
                                                             radii=-1.5))
        else:
            rec.log("attitude/estimate", rr.Clear(recursive=False))
            rec.log("attitude/stars/detections", rr.Clear(recursive=False))
        if self.bodies is not None:
            names, unit = self.bodies(data.time_ns * 1e-9)
            rec.log("attitude/bodies", rr.Points3D(unit, labels=names, show_labels=True, radii=-6.0,
                                                   colors=[BODY_COLORS.get(n, BODY_COLORS["planet"]) for n in names]))


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
    name = f"{meta['starenv.scenario']['name']} seed {meta['starenv.run']['seed']}"
    rrd_path = Path(rrd_path)
    rec = open_stream(rrd_path, str(uuid.UUID(bytes=digest.digest()[:16])), name)
    scenario = scenario_mod.load(tomllib.loads(meta["starenv.scenario"]["toml"]))
    cameras = [h.calibrated for h in scenario.heads]
    review = Review(rec, cameras, with_filter="/filter" in topics(mcap_path), bodies=body_directions(scenario))
    for data in read_steps(mcap_path):
        review.step(data)
        if on_step is not None:
            on_step()
    review.close()
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
        self._period_ns = int(round(sc.frame_period_s * 1e9))
        self._last = None
        agents = None if pipeline is None else pipeline.describe()
        key = json.dumps([sc.to_toml(), int(seed), agents]).encode()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        rec_id = str(uuid.UUID(bytes=hashlib.sha256(key).digest()[:16]))
        with_filter = isinstance(getattr(pipeline, "agents", {}).get("predictor"), AttitudeFilter)
        self._rec = open_stream(self.path, rec_id, f"{sc.name} seed {seed}")
        self._review = Review(self._rec, env.unwrapped.cameras, with_filter, body_directions(sc))

    def step(self, log) -> None:
        data = from_step_log(log, self._sizes)
        self._review.step(data)
        self._last = data

    def close(self, error: BaseException | None = None) -> None:
        if self._rec is None:
            return
        if error is not None:
            frame = 0 if self._last is None else self._last.frame + 1
            t = 0 if self._last is None else self._last.time_ns + self._period_ns
            text = f"frame {frame}: run stopped by {type(error).__name__}: {error}"
            self._review.step(StepData(frame, t, [], np.zeros(4), None, "none", {}, {}, np.zeros(0),
                                       np.zeros((0, 3)), [(ERROR, text)]))
        self._review.close()
        self._rec.flush()
        self._rec.disconnect()
        self._rec = None
