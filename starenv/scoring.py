"""Per-step scores of a pipeline's estimate against truth: every metric of :mod:`starenv.metrics` is computed here.

Each metric is declared once in ``starenv.metrics.METRICS`` with the function that computes it from its scope's
input; this module builds those inputs (:class:`StepFrame`, :class:`HeadFrame`, :class:`RestoredFrame`,
:class:`FilterFrame`) with the intermediate results their metrics share, each computed once, runs the declared
functions, and flattens a step's scores into one record (:func:`flatten`, which carries every declared metric and
refuses a score no metric declares).

Attitude error, and the sign of every per-axis error: the error rotation is ``R_est R_true^T`` (``estimate *
truth.inv()``, both ICRS -> body attitudes as scipy ``Rotation``), its rotation vector ``e`` (body frame; rad in the
``attitude`` scope, arcsec in the scores).  ``attitude.body`` holds ``e`` about body +X, +Y, +Z; ``attitude.heads[h]``
holds ``M e``, with ``M`` head h's body -> camera mounting: about camera +X and +Y (``x_arcsec``, ``y_arcsec``: across
the boresight) and +Z (``roll_arcsec``: about the boresight), each signed, and ``cross_boresight_arcsec = hypot(x,
y)``.  So an estimate ``Rotation.from_rotvec(a * u) * truth`` (``a`` rad, ``u`` a unit body axis) scores ``+a`` on
``u`` and 0 on the axes across it (exactly for a rotation about one axis; the components of a small rotation
otherwise), and ``-a`` when turned the other way; ``total_arcsec`` is ``|e|``.

Star-level metrics use the truth of one head's frame:

* centroid: each detection is matched one-to-one (Hungarian assignment) to a true star's intensity-weighted trail
  centroid (``xy_centroid``) within ``gate_px``.
* identification: a claimed catalog id is correct when the trail of the star with that id (the segment from
  ``xy_start`` to ``xy_end``; a point for a still star) passes within ``gate_px`` of its detection (so either member
  of an unresolved double counts for the blended spot, and a smeared star placed a few pixels along its own trail
  is that star, not a false id).
* correction: for each detection with a correct id, the corrector's offset (measured - corrected) against the true
  offset of its star (``xy_centroid`` minus where the calibrated camera images the star's true direction,
  :func:`calibrated_positions`); the difference is the distortion left after correction, free of centroid noise.
* prediction: predicted positions (catalog id, x, y) against the true mid-exposure position ``xy_mid`` of the same
  star; counted on dropped frames too (truth exists for every frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from types import SimpleNamespace
from typing import Any, NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from starenv import metrics
from starenv.metrics import POOLS, STATISTICS, declared
from starenv.sim.conventions import ARCSEC_PER_RAD
from starenv.sim.optics import Camera
from starenv.sim.render import StarTruth

CENTROID_GATE_PX = 3.0  # px, the gate of every match of a detection to a true star


def attitude_error(estimate: Rotation, truth: Rotation, mountings: list[Rotation]) -> dict:
    """``info["scores"]["attitude"]``: the ``attitude`` scope's metrics of the error rotation vector (rad, body frame),
    the ``body_attitude`` scope's of it in arcsec (``body``) and, per head (``heads``; ``mountings``: body -> camera),
    the ``head_attitude`` scope's of that vector in the head's camera frame (arcsec); signs in the module doc."""
    error = (estimate * truth.inv()).as_rotvec()  # body frame, rad
    per_head = []
    for m in mountings:
        e = m.apply(error) * ARCSEC_PER_RAD
        per_head.append({metric.key: metric.compute(e) for metric in declared("head_attitude")})
    body = {metric.key: metric.compute(error * ARCSEC_PER_RAD) for metric in declared("body_attitude")}
    return {**{metric.key: metric.compute(error) for metric in declared("attitude")}, "body": body, "heads": per_head}


def threshold_errors(attitude: dict, threshold) -> list[tuple[float, float]]:
    """(error, its bound) pairs, arcsec, of ``info["scores"]["attitude"]`` under an availability threshold
    (``starenv.scenario.AvailabilityThreshold``): the total angle, or every head's cross-boresight error and the
    size of its roll error.  The attitude is within the threshold when each error is under its bound."""
    if threshold.total_arcsec is not None:
        return [(attitude["total_arcsec"], threshold.total_arcsec)]
    cross, roll = threshold.cross_boresight_arcsec, threshold.roll_arcsec
    return [pair for h in attitude["heads"] for pair in ((h["cross_boresight_arcsec"], cross),
                                                         (abs(h["roll_arcsec"]), roll))]


def match(detected_xy: np.ndarray, true_xy: np.ndarray, gate_px: float = CENTROID_GATE_PX):
    """One-to-one matching of detections to true positions within ``gate_px``: (detection idx, truth idx, distance)."""
    if len(detected_xy) == 0 or len(true_xy) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty, np.zeros(0)
    d = np.linalg.norm(detected_xy[:, None, :] - true_xy[None, :, :], axis=2)
    cost = np.where(d <= gate_px, d, 1e9)
    rows, cols = linear_sum_assignment(cost)
    ok = d[rows, cols] <= gate_px
    return rows[ok], cols[ok], d[rows[ok], cols[ok]]


def trail_distance(xy: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Distance (px) of each point (n, 2) from its segment ``start`` -> ``end`` (n, 2 each)."""
    d = end - start
    length2 = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("ij,ij->i", xy - start, d) / np.where(length2 > 0.0, length2, 1.0), 0.0, 1.0)
    return np.linalg.norm(xy - (start + t[:, None] * d), axis=1)


class Match(NamedTuple):
    """Detections matched one-to-one to true stars: detection rows, truth rows, distances (px)."""

    detections: np.ndarray
    stars: np.ndarray
    px: np.ndarray


class Claims(NamedTuple):
    """Claimed ids judged against the truth, per detection: an id was claimed, it is correct, the truth row of the
    claimed star (-1: not on the frame)."""

    claimed: np.ndarray
    correct: np.ndarray
    star: np.ndarray


class Correction(NamedTuple):
    """On the correctly identified stars (n, 2) px: the corrector's offset minus the true one, and the true one."""

    error_px: np.ndarray
    true_offset_px: np.ndarray


@dataclass(eq=False)
class HeadFrame:
    """The ``head`` scope's input: one head's truth and what the action gave for it (None where it gave nothing):
    detections (n, 2) px, their claimed catalog ids (n,; -1 = none) and corrected positions (n, 2) px, the true
    stars' positions in the calibrated camera (one per true star, px), predicted ids and positions (px)."""

    truth: StarTruth
    detected_xy: np.ndarray | None = None
    claimed_ids: np.ndarray | None = None
    predicted_ids: np.ndarray | None = None
    predicted_xy: np.ndarray | None = None
    corrected_xy: np.ndarray | None = None
    calibrated_xy: np.ndarray | None = None
    gate_px: float = CENTROID_GATE_PX

    @cached_property
    def n_detectable(self) -> int:
        return int(self.truth.detectable.sum())

    @cached_property
    def matched(self) -> Match | None:
        """Detections matched to true trail centroids within the gate (None without detections)."""
        if self.detected_xy is None:
            return None
        return Match(*match(self.detected_xy, self.truth.xy_centroid, self.gate_px))

    @cached_property
    def claims(self) -> Claims | None:
        """The claimed ids judged (None without detections or ids)."""
        if self.detected_xy is None or self.claimed_ids is None:
            return None
        truth = self.truth
        claimed = self.claimed_ids >= 0
        rows = {int(h): i for i, h in enumerate(truth.catalog_id)}
        star = np.array([rows.get(int(h), -1) for h in self.claimed_ids], dtype=np.intp)
        near = np.zeros(len(star), dtype=bool)
        known = star >= 0  # the claimed id is a star on this frame (none are when the frame holds no star)
        near[known] = trail_distance(self.detected_xy[known], truth.xy_start[star[known]],
                                     truth.xy_end[star[known]]) <= self.gate_px
        return Claims(claimed, claimed & known & near, star)

    @cached_property
    def ids_correct(self) -> int:
        return 0 if self.claims is None else int(self.claims.correct.sum())

    @cached_property
    def ids_wrong(self) -> int:
        return 0 if self.claims is None else int((self.claims.claimed & ~self.claims.correct).sum())

    @cached_property
    def correction(self) -> Correction | None:
        """The correction on the correctly identified stars (None without corrected positions or correct ids)."""
        c = self.claims
        if c is None or self.corrected_xy is None or self.calibrated_xy is None or not c.correct.any():
            return None
        true_offset = self.truth.xy_centroid[c.star[c.correct]] - self.calibrated_xy[c.star[c.correct]]
        return Correction((self.detected_xy[c.correct] - self.corrected_xy[c.correct]) - true_offset, true_offset)

    @cached_property
    def prediction_px(self) -> np.ndarray | None:
        """Distance (px) of each prediction of a star on the frame from its true mid-exposure position (None when
        there is none)."""
        if self.predicted_ids is None or self.predicted_xy is None or not len(self.predicted_ids):
            return None
        lookup = {int(h): i for i, h in enumerate(self.truth.catalog_id)}
        pairs = [(j, lookup[int(h)]) for j, h in enumerate(self.predicted_ids) if int(h) in lookup]
        if not pairs:
            return None
        pj, ti = np.array(pairs).T
        return np.linalg.norm(self.predicted_xy[pj] - self.truth.xy_mid[ti], axis=1)


class StarScores(SimpleNamespace):
    """Star-level scores of one head's frame: one attribute per ``head``-scope metric (None where the action gave
    nothing to score)."""


def score_stars(
    truth: StarTruth,
    detected_xy: np.ndarray | None = None,
    claimed_ids: np.ndarray | None = None,
    predicted_ids: np.ndarray | None = None,
    predicted_xy: np.ndarray | None = None,
    corrected_xy: np.ndarray | None = None,
    calibrated_xy: np.ndarray | None = None,
    gate_px: float = CENTROID_GATE_PX,
) -> StarScores:
    """Score one head's frame (the arguments are :class:`HeadFrame`'s): every ``head``-scope metric."""
    frame = HeadFrame(truth, detected_xy, claimed_ids, predicted_ids, predicted_xy, corrected_xy, calibrated_xy,
                      gate_px)
    return StarScores(**{m.key: m.compute(frame) for m in declared("head")})


@dataclass
class StepFrame:
    """The ``step`` scope's input: the estimate (None: unavailable), ``info["scores"]["attitude"]`` (empty when
    unavailable) and the scenario's ``availability_threshold_arcsec`` (``starenv.scenario.AvailabilityThreshold``)."""

    estimate: Rotation | None
    attitude: dict
    threshold: Any

    @cached_property
    def within(self) -> bool:
        """The attitude is within the threshold (:func:`threshold_errors`); False when unavailable."""
        return bool(self.attitude) and all(e < bound for e, bound in threshold_errors(self.attitude, self.threshold))


def score_step(action: dict, frame, scenario) -> dict:
    """``info["scores"]``: a parsed action (``starenv.env.parse_action``) against the truth of ``frame``
    (``starenv.sim.sensor.Frame``) of ``scenario`` (``starenv.scenario.Scenario``)."""
    estimate = None if action["attitude"] is None else Rotation.from_quat(action["attitude"])
    mountings = [h.camera.mounting for h in scenario.heads]
    att = attitude_error(estimate, frame.attitude, mountings) if estimate is not None else {}
    heads = []
    for i, h in enumerate(frame.heads):
        spec = scenario.heads[i]
        heads.append(vars(score_stars(
            h.truth, detected_xy=action["detections_xy"][i], claimed_ids=action["catalog_ids"][i],
            predicted_ids=action["predicted_ids"][i], predicted_xy=action["predicted_xy"][i],
            corrected_xy=action["corrected_xy"][i],
            calibrated_xy=calibrated_positions(h.truth.xy_centroid, h.camera or spec.camera, spec.calibrated))))
    step = StepFrame(estimate, att, scenario.availability_threshold_arcsec)
    return {"frame": frame.index, "time_s": float(frame.t_mid), **{m.key: m.compute(step) for m in declared("step")},
            "attitude": att, "heads": heads}


def calibrated_positions(xy: np.ndarray, camera: Camera, calibrated: Camera) -> np.ndarray:
    """Where the ``calibrated`` camera images the directions that the true ``camera`` images at ``xy`` (n, 2) px."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if camera == calibrated or not len(xy):
        return xy.copy()
    return calibrated.project(camera.unproject(xy))[0]


def _check(values: dict, scope: str, where: str, structure: tuple[str, ...] = ()) -> None:
    """``ValueError`` unless ``values`` holds exactly the keys of the scope's metrics (and ``structure``)."""
    keys = {m.key for m in declared(scope)}
    unknown, missing = set(values) - keys - set(structure), keys - set(values)
    if unknown:
        raise ValueError(f"flatten: {where} holds {sorted(unknown)}, which no {scope!r} metric declares: declare "
                         "each in starenv.metrics.METRICS (flatten carries every declared metric and drops none)")
    if missing:
        raise ValueError(f"flatten: {where} lacks the declared {scope!r} metrics {sorted(missing)}")


def _pool(metric: metrics.Metric, per_head: list, n_heads: int) -> dict[str, float | None]:
    """A per-head scope's values (one per head, None: no value) as the metric's record entries."""
    if metric.pool == "each":
        per_head = per_head + [None] * (n_heads - len(per_head))
        return {metric.name.format(head=h): None if v is None else float(v) for h, v in enumerate(per_head)}
    values = [v for v in per_head if v is not None]
    return {metric.name: POOLS[metric.pool].function(values) if values else None}


def _pool_scope(scope: str, per_head: list[dict], where: str, n_heads: int) -> dict[str, float | None]:
    """The record entries of a per-head scope's dicts (``where[h]``, checked by :func:`_check`)."""
    for h, values in enumerate(per_head):
        _check(values, scope, f"{where}[{h}]")
    out: dict[str, float | None] = {}
    for m in declared(scope):
        out.update(_pool(m, [values[m.key] for values in per_head], n_heads))
    return out


def flatten(scores: dict, latency_s: dict[str, float] | None = None, restoration: list[dict] | None = None,
            filter_scores: dict | None = None) -> dict[str, float | None]:
    """One step's flat ``metric -> value`` record, indexed by ``frame`` and ``time_s`` (when the scores carry it): its
    scores (``info["scores"]``), agent latencies (s per role), the restoration scores of each restored head
    (:func:`score_restoration`; None: no deblurrer, no restoration keys) and a filter's scores (:func:`score_filter`;
    None: no filter, no filter keys), then the ``record`` scope's metrics of them.  Per-head values are pooled over
    heads by each metric's ``pool``.  ``ValueError`` when a scores dict holds a key no metric declares (or lacks a
    declared one): nothing is dropped silently."""
    _check(scores, "step", "scores", ("frame", "time_s", "attitude", "heads"))
    rec: dict[str, float | None] = {"frame": scores["frame"]}
    if "time_s" in scores:  # scores decoded from a recording carry the time in the message, not here
        rec["time_s"] = float(scores["time_s"])
    rec.update({m.name: float(scores[m.key]) for m in declared("step")})
    att, heads = scores["attitude"], scores["heads"]
    if att:
        _check(att, "attitude", "scores.attitude", ("heads", "body"))
        _check(att["body"], "body_attitude", "scores.attitude.body")
    for m in declared("attitude"):
        rec[m.name] = float(att[m.key]) if att else None
    for m in declared("body_attitude"):
        rec[m.name] = float(att["body"][m.key]) if att else None
    rec.update(_pool_scope("head_attitude", att["heads"] if att else [], "scores.attitude.heads", len(heads)))
    rec.update(_pool_scope("head", heads, "scores.heads", len(heads)))
    if restoration is not None:
        rec.update(_pool_scope("restoration", restoration, "restoration", len(restoration)))
    if filter_scores is not None:
        _check(filter_scores, "filter", "filter scores")
        rec.update({m.name: filter_scores[m.key] for m in declared("filter")})
    for role, seconds in (latency_s or {}).items():
        rec.update({m.name.format(role=role): m.compute(seconds) for m in declared("latency")})
    return derive(rec)


def derive(record: dict) -> dict:
    """``record`` with the ``record`` scope's metrics it lacks computed from it (records of older run files lack
    those added since)."""
    out = dict(record)
    for m in declared("record"):
        if m.name not in out:
            out[m.name] = m.compute(out)
    return out


def summarize(records: list[dict]) -> dict[str, dict[str, float]]:
    """Median, p95 and mean of every metric over steps (skipping steps where it has no value), and its count."""
    keys = sorted({k for r in records for k in r if k not in metrics.INDEX_KEYS})
    out = {}
    for k in keys:
        values = np.array([r[k] for r in records if r.get(k) is not None], dtype=np.float64)
        if len(values):
            out[k] = {**{s: STATISTICS[s].function(values) for s in ("median", "p95", "mean")},
                      "count": len(values)}
    return out


def psnr_db(image: np.ndarray, reference: np.ndarray) -> float:
    """Peak signal-to-noise ratio (dB) of ``image`` against ``reference``: ``10 log10(peak^2 / MSE)``, with the peak
    the reference's range (max - min), so a constant offset such as the bias does not count as signal."""
    mse = float(np.mean((np.asarray(image, np.float64) - reference) ** 2))
    peak = float(np.max(reference) - np.min(reference))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


@dataclass(eq=False)
class RestoredFrame:
    """The ``restoration`` scope's input: one head's truth, its blurred and restored frames, the policy's detector
    and the head's calibrated camera, the still noise-free frame (``clean``; None: no PSNR) and the deblurrer's
    ``info``.  Centroids are matched to the true mid-exposure position ``xy_mid``, not the trail centroid: a
    restorer undoes the trail and puts the star where it was at mid-exposure (where the attitude truth is taken),
    while the blurred image's centre of light is the trail centroid; the two differ where the motion is not uniform
    (arcs, acceleration)."""

    truth: StarTruth
    blurred: np.ndarray
    restored: np.ndarray
    detector: Any
    camera: Camera
    clean: np.ndarray | None = None
    info: dict | None = None
    gate_px: float = CENTROID_GATE_PX

    @cached_property
    def matched_px(self) -> dict[str, np.ndarray]:
        """``blurred`` / ``restored``: distances (px) of that frame's detections matched to a true star."""
        out = {}
        for key, image in (("blurred", self.blurred), ("restored", self.restored)):
            stars = self.detector.detect(image, self.camera)
            out[key] = match(stars.xy, self.truth.xy_mid, self.gate_px)[2]
        return out

    @cached_property
    def psnr_gain_db(self) -> float | None:
        """PSNR (dB) of the restored minus that of the blurred frame against ``clean`` (None without it)."""
        if self.clean is None:
            return None
        return psnr_db(self.restored, self.clean) - psnr_db(self.blurred, self.clean)


def score_restoration(truth: StarTruth, blurred: np.ndarray, restored: np.ndarray, detector, camera,
                      clean: np.ndarray | None = None, info: dict | None = None,
                      gate_px: float = CENTROID_GATE_PX) -> dict:
    """Restoration scores of one head's frame (the arguments are :class:`RestoredFrame`'s; ``clean``: the still,
    noise-free frame of :meth:`starenv.sim.sensor.StarSensor.still_frame`): every ``restoration``-scope metric,
    by its key."""
    frame = RestoredFrame(truth, blurred, restored, detector, camera, clean, info, gate_px)
    return {m.key: m.compute(frame) for m in declared("restoration")}


@dataclass(eq=False)
class FilterFrame:
    """The ``filter`` scope's input: a filter's gyro bias estimate (3,) rad/s (None: none given) and the true bias
    (3,) rad/s, its covariance (6, 6) (rad^2 attitude first; None: none given), the attitude it gave ``[x, y, z, w]``
    (None: unavailable) and the true one."""

    gyro_bias: np.ndarray | None
    gyro_bias_true: np.ndarray
    covariance: np.ndarray | None
    estimate: np.ndarray | None
    attitude_true: np.ndarray

    @cached_property
    def bias_error(self) -> np.ndarray | None:
        """Bias estimate minus truth (3,) rad/s."""
        return None if self.gyro_bias is None else np.asarray(self.gyro_bias) - np.asarray(self.gyro_bias_true)

    @cached_property
    def attitude_error(self) -> np.ndarray | None:
        """Rotation vector (3,) rad of ``A_est A_true^T``."""
        if self.estimate is None:
            return None
        return (Rotation.from_quat(self.estimate) * Rotation.from_quat(self.attitude_true).inv()).as_rotvec()


def score_filter(gyro_bias: np.ndarray | None, covariance: np.ndarray | None, action: dict | None,
                 truth: dict) -> dict | None:
    """A filter's scores against the frame's ``truth`` (``info["truth"]``): every ``filter``-scope metric, by its
    key; None when neither a bias estimate nor a covariance is given (no filter)."""
    if gyro_bias is None and covariance is None:
        return None
    valid = action is not None and action.get("attitude_valid", 1)
    frame = FilterFrame(gyro_bias, truth["gyro_bias"], covariance, action["attitude"] if valid else None,
                        truth["attitude"])
    return {m.key: m.compute(frame) for m in declared("filter")}
