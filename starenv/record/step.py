"""One step of an episode as a recording sees it: the record every recorder writes and every reviewer reads.

``StepData`` is built from the episode loop's ``StepLog`` (:func:`from_step_log`) or decoded back from an MCAP file
(``starenv.record.mcap.read_steps``); the Rerun review logs it with one function whichever way it came.  Pixel
positions are starenv's (distorted pixel coordinates, (0, 0) the centre of the top-left pixel); quaternions are
``[x, y, z, w]`` ICRS -> body at mid-exposure; times are integer nanoseconds of simulation time (mid-exposure).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from starenv.agents.base import ERROR, INFO, WARNING  # noqa: F401  log levels, as foxglove.Log numbers them


@dataclass
class Stars2D:
    """Points on one head's image: positions (n, 2) px and catalog ids (n,; -1 = none)."""

    xy: np.ndarray
    ids: np.ndarray

    @classmethod
    def empty(cls) -> Stars2D:
        return cls(np.zeros((0, 2)), np.zeros(0, dtype=np.int64))


@dataclass
class HeadData:
    """One head's frame (uint16 (H, W); None when dropped) with the true stars (trail centroids), the pipeline's
    detections (with the ids it claimed) and its predicted star positions."""

    image: np.ndarray | None
    truth: Stars2D
    detections: Stars2D
    predictions: Stars2D


@dataclass
class FilterState:
    """A fusion filter's state at one step (``starenv.agents.base.AttitudeFilter``): its attitude ``[x, y, z, w]``
    ICRS -> body at mid-exposure, its gyro bias estimate and the gyro's true bias (3,) deg/h (body axes), and the
    1-sigma of its attitude error (3,) arcsec (rotation about the body axes) and of its bias error (3,) deg/h: the
    square roots of its covariance's diagonal."""

    attitude: np.ndarray
    bias_deg_hr: np.ndarray
    bias_true_deg_hr: np.ndarray
    attitude_sigma_arcsec: np.ndarray
    bias_sigma_deg_hr: np.ndarray


def filter_state(attitude, gyro_bias, covariance, true_bias) -> FilterState:
    """The :class:`FilterState` of a filter's attitude (``[x, y, z, w]``), bias estimate (3,) rad/s, covariance (6, 6)
    (rad^2 attitude first, then (rad/s)^2 bias) and the true bias (3,) rad/s."""
    sigma = np.sqrt(np.diag(np.asarray(covariance, dtype=np.float64)))
    return FilterState(np.asarray(attitude, dtype=np.float64), np.degrees(np.asarray(gyro_bias)) * 3600.0,
                       np.degrees(np.asarray(true_bias, dtype=np.float64)) * 3600.0,
                       np.degrees(sigma[:3]) * 3600.0, np.degrees(sigma[3:]) * 3600.0)


@dataclass
class StepData:
    """Everything recorded about one step."""

    frame: int
    time_ns: int
    heads: list[HeadData]
    attitude_true: np.ndarray  # (4,)
    attitude_estimate: np.ndarray | None  # (4,), None when the step was unavailable
    source: str  # "solved", "predicted" or "none"
    scores: dict  # info["scores"]
    record: dict[str, float | None]  # flat metric -> value
    gyro_t: np.ndarray  # (n,) s
    gyro_rate: np.ndarray  # (n, 3) rad/s, body frame
    logs: list[tuple[int, str]] = field(default_factory=list)  # (level, text)
    filter: FilterState | None = None  # a fusion filter's state; None for other pipelines


def time_ns(t_s: float) -> int:
    """Simulation time (s) as integer nanoseconds."""
    return int(round(float(t_s) * 1e9))


def _masked(xy: np.ndarray, ids: np.ndarray, mask: np.ndarray) -> Stars2D:
    keep = np.asarray(mask, dtype=bool)
    return Stars2D(np.asarray(xy, dtype=np.float64)[keep], np.asarray(ids, dtype=np.int64)[keep])


def from_step_log(log, sizes: list[tuple[int, int]]) -> StepData:
    """A ``StepLog`` as ``StepData``; ``sizes`` are the heads' (height, width), to crop the observation's padding."""
    obs, truth, action = log.obs, log.truth, log.action
    heads = []
    valid = np.asarray(obs["frame_valid"], dtype=bool)
    for h, (height, width) in enumerate(sizes):
        stars = truth["stars"][h]
        true = Stars2D(np.asarray(stars["xy_centroid"], dtype=np.float64).reshape(-1, 2),
                       np.asarray(stars["catalog_id"], dtype=np.int64))
        det = pred = Stars2D.empty()
        if action is not None and "detection_mask" in action:
            det = _masked(action["detections_xy"][h], action["catalog_ids"][h], action["detection_mask"][h])
        if action is not None and "prediction_mask" in action:
            pred = _masked(action["predicted_xy"][h], action["predicted_ids"][h], action["prediction_mask"][h])
        image = np.array(obs["frames"][h, :height, :width]) if valid[h] else None  # a copy: recorders may write later
        heads.append(HeadData(image, true, det, pred))
    t = time_ns(truth["time_s"])
    logs = [(WARNING, f"frame {log.index}: head {h} frame dropped") for h in range(len(sizes)) if not valid[h]]
    if log.pipeline is not None and log.source == "predicted":
        logs.append((WARNING, f"frame {log.index}: no attitude solution, reporting the gyro prediction"))
    elif log.pipeline is not None and log.source == "none":
        logs.append((WARNING, f"frame {log.index}: no attitude (no solution and no prediction)"))
    logs += [(level, f"frame {log.index}: {text}") for level, text in log.events]
    estimate = None
    if action is not None and log.scores["available"]:
        q = np.asarray(action["attitude"], dtype=np.float64)
        estimate = q / np.linalg.norm(q)
    state = None
    if log.covariance is not None and action is not None:  # a filter's posterior is the action
        state = filter_state(action["attitude"], log.gyro_bias, log.covariance, truth["gyro_bias"])
    gyro = obs["gyro"]
    n = int(gyro["count"])
    return StepData(
        frame=int(truth["frame"]), time_ns=t, heads=heads,
        attitude_true=np.asarray(truth["attitude"], dtype=np.float64), attitude_estimate=estimate,
        source=log.source, scores=log.scores, record=dict(log.record),
        gyro_t=np.array(gyro["t"][:n], dtype=np.float64), gyro_rate=np.array(gyro["rate"][:n], dtype=np.float64),
        logs=logs, filter=state,
    )
