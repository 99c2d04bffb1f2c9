"""One episode of a scenario driven by a pipeline, step by step, with observers (recorders) watching each step.

``run_episode`` is the loop every front end shares (``starenv run``, the benchmark runner, recorders): per step ``k``
the pipeline turns observation ``k`` into an action, ``env.step`` scores it against frame ``k``'s truth, and each
observer receives a :class:`StepLog` that holds frame ``k``, its truth, the action and its scores together.  Its flat
record (:func:`starenv.scoring.flatten`), indexed by ``frame`` and ``time_s`` (frame ``k``'s index and mid-exposure
simulation time, s; ``starenv.metrics.INDEX_KEYS``), holds every metric of ``starenv.metrics``: the env's scores
pooled over heads, the agents' latencies, and, when the pipeline has a deblurrer, the restoration scores of frame
``k``, when it is a filter, its bias and NEES against frame ``k``'s truth.  The table below, composed from
``starenv.metrics`` when this module is imported (``python -m starenv.metrics`` prints it), lists every record key
with its unit, where it comes from, its ``summary.csv`` columns and its Rerun panel:

"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from starenv import metrics
from starenv.agents.base import Policy, StepReport
from starenv.scoring import flatten, score_filter, score_restoration
from starenv.sim.render import StarTruth

__doc__ += metrics.record_table() + "\n"


@dataclass
class StepLog:
    """Everything about step ``index``: observation ``k`` (what the sensor delivered), the truth of that frame, the
    pipeline's action for it (None without a pipeline), its scores (``info["scores"]``) and the flat score record;
    for a filtered pipeline also the filter's bias estimate and covariance (None otherwise); the agents' events."""

    index: int
    obs: dict
    truth: dict
    action: dict | None
    scores: dict
    record: dict[str, float | None]
    source: str  # where the attitude came from: "solved", "predicted" or "none"
    latency_s: dict[str, float]
    pipeline: Any = None
    gyro_bias: np.ndarray | None = None  # (3,) rad/s body frame: a filter's bias estimate (StepReport.gyro_bias)
    covariance: np.ndarray | None = None  # (6, 6): a filter's error covariance (StepReport.covariance)
    events: list[tuple[int, str]] = field(default_factory=list)  # (level, text): the agents' (StepReport.events)


class Observer(Protocol):
    """Watches an episode: ``start`` once, ``step`` per scored step, ``close`` at the end (also after an error)."""

    def start(self, env, seed: int, pipeline) -> None: ...

    def step(self, log: StepLog) -> None: ...

    def close(self, error: BaseException | None = None) -> None: ...


@dataclass
class EpisodeResult:
    """Per-step flat score records, frames dropped per head, the step at which the lost rule fired, wall time (s)."""

    records: list[dict] = field(default_factory=list)
    dropped: np.ndarray | None = None
    lost_at: int | None = None
    wall_s: float = 0.0


def run_episode(env, pipeline: Policy | None = None, seed: int | None = None, steps: int | None = None,
                observers: tuple[Observer, ...] | list[Observer] = ()) -> EpisodeResult:
    """Run ``steps`` scored steps (default: the whole scenario) of ``env`` (a ``StarSensorEnv``) from ``seed``
    (default: the scenario's) with ``pipeline`` (None: every step unavailable).  Observers are closed even when a
    step raises, with the exception, so a recording ends readable; the exception propagates."""
    if pipeline is not None and not isinstance(pipeline, Policy):
        raise TypeError(f"pipeline: {type(pipeline).__name__} does not implement the Policy protocol (report, reset, "
                        "__call__, describe; see starenv.agents.base.Policy)")
    sc = env.unwrapped.scenario
    seed = sc.seed if seed is None else int(seed)
    steps = sc.n_steps - 1 if steps is None else int(steps)
    obs, info = env.reset(seed=seed)
    if pipeline is not None:
        pipeline.reset(env.unwrapped.sensor_info)
    result = EpisodeResult(dropped=np.zeros(len(sc.heads), dtype=int))
    started: list[Observer] = []
    error: BaseException | None = None
    t0 = time.perf_counter()
    try:
        for obs_ in observers:
            obs_.start(env, seed, pipeline)
            started.append(obs_)
        for k in range(steps):
            truth = info["truth"]
            result.dropped += np.array(truth["dropped"], dtype=int)
            action = pipeline(obs) if pipeline is not None else None
            report = pipeline.report if pipeline is not None else StepReport()
            latency = dict(report.latency_s)
            restoration = _restoration_scores(env, report, truth)
            filter_scores = score_filter(report.gyro_bias, report.covariance, action, truth)
            next_obs, _, terminated, truncated, info = env.step(action)
            record = flatten(info["scores"], latency, restoration, filter_scores)
            result.records.append(record)
            log = StepLog(k, obs, truth, action, info["scores"], record, report.source, latency, pipeline,
                          report.gyro_bias, report.covariance, list(report.events))
            for o in started:
                o.step(log)
            obs = next_obs
            if terminated and result.lost_at is None:
                result.lost_at = k
            if truncated:
                break
    except BaseException as exc:
        error = exc
        raise
    finally:
        result.wall_s = time.perf_counter() - t0
        for o in started:
            o.close(error)
    return result


def _restoration_scores(env, report: StepReport, truth: dict) -> list[dict] | None:
    """Restoration scores of each head the policy restored on the frame it just processed (None without a
    deblurrer): scored (:func:`~starenv.scoring.score_restoration`) with the policy's own detector against the
    frame's truth and its still, noise-free reference."""
    if report.detector is None:
        return None
    base = env.unwrapped
    per_head = []
    for h, restoration in enumerate(report.restorations):
        if restoration is None:
            continue
        stars = StarTruth(**{k: np.asarray(v) for k, v in truth["stars"][h].items()})
        clean = base.sensor.still_frame(h, stars, frame=truth["frame"])
        per_head.append(score_restoration(stars, restoration.raw, restoration.restored, report.detector,
                                          base.cameras[h], clean, restoration.info))
    return per_head
