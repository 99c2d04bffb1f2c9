"""Per-step scores of a pipeline's estimate against truth: the one place every metric is computed.

Attitude error is the angle of ``R_est R_true^T`` (arcsec).  Its split per head is taken in that head's camera
frame: with the error rotation vector ``e`` (body frame) mapped to the camera, ``cross_boresight`` is
``hypot(e_x, e_y)`` (pitch about camera X, yaw about camera Y) and ``roll`` is ``|e_z|`` about the boresight.

Star-level metrics use the truth of one head's frame:

* centroid: each detection is matched one-to-one (Hungarian assignment) to a true star's intensity-weighted trail
  centroid (``xy_centroid``) within ``gate_px``; error = Euclidean distance (px).  Recall = matched detectable stars /
  detectable stars; precision = matched detections / detections.
* identification: a claimed catalog id is correct when the trail of the star with that id (the segment from
  ``xy_start`` to ``xy_end``; a point for a still star) passes within ``gate_px`` of its detection (so either member
  of an unresolved double counts for the blended spot, and a smeared star placed a few pixels along its own trail
  is that star, not a false id).  ID rate = correct / detectable stars;
  false-ID rate = wrong ids / claimed ids; the frame is solved when >= 3 ids are correct and none is wrong.
* correction: for each detection with a correct id, the corrector's offset (measured - corrected) against the true
  offset of its star (``xy_centroid`` minus where the calibrated camera images the star's true direction,
  :func:`calibrated_positions`); the difference is the distortion left after correction, free of centroid noise
  (Euclidean mean, and mean |error| per axis, px); ``distortion_px_mean`` is the true offset's mean length on the
  same stars (what an absent corrector leaves).
* prediction: predicted positions (catalog id, x, y) against the true mid-exposure position ``xy_mid`` of the same
  star; counted on dropped frames too (truth exists for every frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from starenv.sim.conventions import ARCSEC_PER_RAD
from starenv.sim.optics import Camera
from starenv.sim.render import StarTruth

CENTROID_GATE_PX = 3.0
SOLVED_MIN_CORRECT = 3


def attitude_error(estimate: Rotation, truth: Rotation, mountings: list[Rotation]) -> dict:
    """Total error (arcsec) and, per head, cross-boresight / pitch / yaw / roll errors (arcsec)."""
    error = (estimate * truth.inv()).as_rotvec()  # body frame, rad
    per_head = []
    for m in mountings:
        e = m.apply(error) * ARCSEC_PER_RAD
        per_head.append(
            {
                "pitch_arcsec": float(abs(e[0])),
                "yaw_arcsec": float(abs(e[1])),
                "roll_arcsec": float(abs(e[2])),
                "cross_boresight_arcsec": float(np.hypot(e[0], e[1])),
            }
        )
    return {"total_arcsec": float(np.linalg.norm(error) * ARCSEC_PER_RAD), "heads": per_head}


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


@dataclass
class StarScores:
    """Star-level scores of one head's frame (None where the stage produced nothing to score)."""

    centroid_error_px_mean: float | None = None
    centroid_error_px_max: float | None = None
    detection_recall: float | None = None
    detection_precision: float | None = None
    id_rate: float | None = None
    false_id_rate: float | None = None
    ids_correct: int = 0
    ids_wrong: int = 0
    solved: bool = False
    correction_error_px_mean: float | None = None
    correction_error_x_px: float | None = None
    correction_error_y_px: float | None = None
    distortion_px_mean: float | None = None
    prediction_error_px_mean: float | None = None
    prediction_error_px_max: float | None = None
    predictions_scored: int = 0


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
    """Score one head's detections (n, 2) px, their claimed catalog ids (n,; -1 = none), their corrected positions
    (n, 2) px against the true stars' positions in the calibrated camera (``calibrated_xy``, one per true star), and
    predictions."""
    s = StarScores()
    detectable = truth.detectable
    n_detectable = int(detectable.sum())
    if detected_xy is not None:
        det, tru, dist = match(detected_xy, truth.xy_centroid, gate_px)
        if len(dist):
            s.centroid_error_px_mean = float(dist.mean())
            s.centroid_error_px_max = float(dist.max())
        if n_detectable:
            s.detection_recall = float(detectable[tru].sum() / n_detectable)
        if len(detected_xy):
            s.detection_precision = float(len(det) / len(detected_xy))
        if claimed_ids is not None:
            claimed = claimed_ids >= 0
            rows = {int(h): i for i, h in enumerate(truth.catalog_id)}
            star = np.array([rows.get(int(h), -1) for h in claimed_ids], dtype=np.intp)
            near = np.zeros(len(star), dtype=bool)
            known = star >= 0  # the claimed id is a star on this frame (none are when the frame holds no star)
            near[known] = trail_distance(detected_xy[known], truth.xy_start[star[known]],
                                         truth.xy_end[star[known]]) <= gate_px
            correct = claimed & known & near
            s.ids_correct = int(correct.sum())
            s.ids_wrong = int((claimed & ~correct).sum())
            if n_detectable:
                s.id_rate = min(1.0, s.ids_correct / n_detectable)
            if claimed.any():
                s.false_id_rate = s.ids_wrong / int(claimed.sum())
            s.solved = s.ids_correct >= SOLVED_MIN_CORRECT and s.ids_wrong == 0
            if corrected_xy is not None and calibrated_xy is not None and correct.any():
                true_offset = truth.xy_centroid[star[correct]] - calibrated_xy[star[correct]]
                err = (detected_xy[correct] - corrected_xy[correct]) - true_offset
                s.correction_error_px_mean = float(np.linalg.norm(err, axis=1).mean())
                s.correction_error_x_px, s.correction_error_y_px = (float(v) for v in np.abs(err).mean(axis=0))
                s.distortion_px_mean = float(np.linalg.norm(true_offset, axis=1).mean())
    if predicted_ids is not None and predicted_xy is not None and len(predicted_ids):
        lookup = {int(h): i for i, h in enumerate(truth.catalog_id)}
        pairs = [(j, lookup[int(h)]) for j, h in enumerate(predicted_ids) if int(h) in lookup]
        if pairs:
            pj, ti = np.array(pairs).T
            err = np.linalg.norm(predicted_xy[pj] - truth.xy_mid[ti], axis=1)
            s.prediction_error_px_mean = float(err.mean())
            s.prediction_error_px_max = float(err.max())
            s.predictions_scored = len(pairs)
    return s


def calibrated_positions(xy: np.ndarray, camera: Camera, calibrated: Camera) -> np.ndarray:
    """Where the ``calibrated`` camera images the directions that the true ``camera`` images at ``xy`` (n, 2) px."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if camera == calibrated or not len(xy):
        return xy.copy()
    return calibrated.project(camera.unproject(xy))[0]


def flatten(scores: dict, latency_s: dict[str, float] | None = None) -> dict[str, float | None]:
    """One step's scores (``info["scores"]``) and agent latencies as a flat ``metric -> value`` record.

    Star metrics are pooled over heads (mean of the heads that have a value; counts summed; solved if any head is).
    """
    att = scores["attitude"]
    rec: dict[str, float | None] = {
        "frame": scores["frame"],
        "available": float(scores["available"]),
        "within_threshold": float(scores["within_threshold"]),
        "attitude_error_arcsec": att["total_arcsec"] if att else None,
        "cross_boresight_error_arcsec": float(np.mean([h["cross_boresight_arcsec"] for h in att["heads"]]))
        if att else None,
        "roll_error_arcsec": float(np.mean([h["roll_arcsec"] for h in att["heads"]])) if att else None,
    }
    heads = scores["heads"]
    for key in ("centroid_error_px_mean", "detection_recall", "detection_precision", "id_rate", "false_id_rate",
                "correction_error_px_mean", "correction_error_x_px", "correction_error_y_px", "distortion_px_mean",
                "prediction_error_px_mean", "prediction_error_px_max"):
        values = [h[key] for h in heads if h[key] is not None]
        rec[key] = float(np.mean(values)) if values else None
    rec["solved"] = float(any(h["solved"] for h in heads))
    for role, seconds in (latency_s or {}).items():
        rec[f"latency_{role}_ms"] = seconds * 1e3
    return rec


def summarize(records: list[dict]) -> dict[str, dict[str, float]]:
    """Median, p95 and mean of every metric over steps (skipping steps where it has no value), and its count."""
    keys = sorted({k for r in records for k in r if k != "frame"})
    out = {}
    for k in keys:
        values = np.array([r[k] for r in records if r.get(k) is not None], dtype=np.float64)
        if len(values):
            out[k] = {"median": float(np.median(values)), "p95": float(np.percentile(values, 95)),
                      "mean": float(values.mean()), "count": len(values)}
    return out


def psnr_db(image: np.ndarray, reference: np.ndarray) -> float:
    """Peak signal-to-noise ratio (dB) of ``image`` against ``reference``: ``10 log10(peak^2 / MSE)``, with the peak
    the reference's range (max - min), so a constant offset such as the bias does not count as signal."""
    mse = float(np.mean((np.asarray(image, np.float64) - reference) ** 2))
    peak = float(np.max(reference) - np.min(reference))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


def score_restoration(truth: StarTruth, blurred: np.ndarray, restored: np.ndarray, detector, camera,
                      clean: np.ndarray | None = None, info: dict | None = None,
                      gate_px: float = CENTROID_GATE_PX) -> dict:
    """Restoration scores of one head's frame: the same ``detector`` on the blurred and on the restored image.

    Centroid errors (px, mean over matched stars) are against the true mid-exposure position ``xy_mid``, not the
    trail centroid: a restorer undoes the trail and puts the star where it was at mid-exposure (where the attitude
    truth is taken), while the blurred image's centre of light is the trail centroid; the two differ where the motion
    is not uniform (arcs, acceleration).  ``stars_before`` / ``stars_after``: detections matched one-to-one to a true
    star within ``gate_px``.  ``psnr_gain_db``: PSNR of the restored minus that of the blurred image against
    ``clean`` (the still, noise-free frame of :meth:`starenv.sim.sensor.StarSensor.still_frame`; None: not scored).
    ``iterations``: ``info["iterations"]`` of the deblurrer (None when not given).
    """
    scores = {}
    for key, image in (("blurred", blurred), ("restored", restored)):
        stars = detector.detect(image, camera)
        _, _, dist = match(stars.xy, truth.xy_mid, gate_px)
        scores[key] = (float(dist.mean()) if len(dist) else None, len(dist))
    gain = None
    if clean is not None:
        gain = psnr_db(restored, clean) - psnr_db(blurred, clean)
    iterations = None if not info or info.get("iterations") is None else int(info["iterations"])
    return {
        "centroid_error_px": scores["restored"][0],
        "centroid_error_blurred_px": scores["blurred"][0],
        "stars_before": scores["blurred"][1],
        "stars_after": scores["restored"][1],
        "psnr_gain_db": gain,
        "iterations": iterations,
    }


def pool_restoration(per_head: list[dict]) -> dict[str, float | None]:
    """Restoration scores of the heads as flat ``restoration_*`` record entries: means of the heads that have a value
    (errors, PSNR gain, iterations), sums of the star counts."""
    rec: dict[str, float | None] = {}
    for key in ("centroid_error_px", "centroid_error_blurred_px", "psnr_gain_db", "iterations"):
        values = [h[key] for h in per_head if h[key] is not None]
        rec[f"restoration_{key}"] = float(np.mean(values)) if values else None
    for key in ("stars_before", "stars_after"):
        rec[f"restoration_{key}"] = float(sum(h[key] for h in per_head)) if per_head else None
    return rec
