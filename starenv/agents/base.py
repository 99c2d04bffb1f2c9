"""The contracts of a star-sensor pipeline: one small protocol per agent role, the policy that env loops and the
benchmark drive, and the data they pass along.

Agents see only what a sensor would (``StepInput``: images, gyro samples, times, calibrated cameras), never truth.
Pixel positions are distorted (measured) pixel coordinates of a head's image unless a name says ``ideal``; attitudes
are scipy ``Rotation`` inertial -> body; vectors are unit 3-vectors.  Star lists are :class:`StarMeasurements`
(measured or predicted positions on an image); the simulator's truth is :class:`~starenv.sim.render.StarTruth`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.scenario import AGENT_ROLES
from starenv.sim.gyro import GyroSamples
from starenv.sim.optics import Camera
from starenv.sim.sky import CatalogFile, StarCatalog

# Event levels (StepReport.events), as foxglove.Log numbers them.
INFO, WARNING, ERROR = 2, 3, 4

MAX_STARS = 256  # rows of the per-head star lists in an action


@dataclass(frozen=True)
class SensorInfo:
    """What a policy knows of the sensor before the first frame: the calibrated cameras, the gyro's sample rate (Hz,
    from its datasheet), the catalogue epoch (Julian year) the onboard catalogue is propagated to and the onboard
    catalogue's file (None: the bundled Hipparcos-2)."""

    cameras: list[Camera]
    gyro_rate_hz: float
    epoch: float
    catalog: CatalogFile | None = None


@dataclass
class StepInput:
    """What the pipeline knows at one step (from the observation and the sensor's calibration)."""

    images: list[np.ndarray]  # per head, uint16 (H, W); meaningless where frame_valid is False
    frame_valid: np.ndarray  # (heads,) bool
    time_s: float  # mid-exposure time of the frame
    exposure_s: float
    gyro: GyroSamples  # samples since the previous step
    cameras: list[Camera]  # calibrated models
    # (3,) m/s, ICRS axes: the sensor's velocity (navigation), for the stars' aberration; zeros when not given
    observer_velocity_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))


def step_input(obs: dict, sensor: SensorInfo) -> StepInput:
    """The :class:`StepInput` of one env observation: the gyro samples cut to their ``count``, each head's image."""
    gyro = obs["gyro"]
    n = int(gyro["count"])
    return StepInput(
        images=list(obs["frames"]),
        # a head blinded by the Sun, Moon or Earth delivers a frame no star can be trusted on
        frame_valid=np.asarray(obs["frame_valid"], dtype=bool) & ~np.asarray(obs.get("blinded", 0), dtype=bool),
        time_s=float(obs["time_s"]),
        exposure_s=float(obs["exposure_s"]),
        gyro=GyroSamples(np.asarray(gyro["t"][:n]), np.asarray(gyro["rate"][:n]), 1.0 / sensor.gyro_rate_hz),
        cameras=sensor.cameras,
        observer_velocity_m_s=np.asarray(obs.get("observer_velocity_m_s", np.zeros(3)), dtype=np.float64),
    )


@dataclass
class StarMeasurements:
    """Stars measured (or predicted) on one head's frame: positions (n, 2) px, flux (n,) DN above background, catalog
    ids (n,; -1 none)."""

    xy: np.ndarray
    flux: np.ndarray = field(default_factory=lambda: np.zeros(0))
    catalog_id: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self):
        self.xy = np.asarray(self.xy, dtype=np.float64).reshape(-1, 2)
        n = len(self.xy)
        self.flux = np.zeros(n) if len(self.flux) != n else np.asarray(self.flux, dtype=np.float64)
        ids = np.asarray(self.catalog_id, dtype=np.int64)
        self.catalog_id = np.full(n, -1, dtype=np.int64) if len(ids) != n else ids

    def __len__(self) -> int:
        return len(self.xy)


@dataclass
class Prediction:
    """A predictor's output for the current frame: the attitude at mid-exposure (None: no state yet) and, per head,
    the stars expected on it (ids and positions)."""

    attitude: Rotation | None
    stars: list[StarMeasurements]


@runtime_checkable
class Predictor(Protocol):
    """Carries the attitude (and star positions) from one frame to the next with the gyro."""

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None: ...

    def predict(self, step: StepInput) -> Prediction:
        """Propagate the last state to ``step.time_s`` with ``step.gyro``."""
        ...

    def update(self, attitude: Rotation, stars: list[StarMeasurements], time_s: float) -> None:
        """Take the pipeline's estimate for the frame at ``time_s`` as the new state."""
        ...


@runtime_checkable
class AttitudeFilter(Predictor, Protocol):
    """A predictor that fuses: ``update`` takes the identified (measured) stars even when nothing was solved, and
    ``posterior`` is the pipeline's estimate -- attitude, gyro bias (3,) rad/s and error covariance -- or None.  An
    ``events`` attribute, if it has one, lists the last update's events (level, text) for the recording's log."""

    def posterior(self) -> tuple[Rotation, np.ndarray, np.ndarray] | None: ...


@runtime_checkable
class Deblurrer(Protocol):
    """Restores one head's smeared image, knowing the gyro samples over its exposure."""

    def deblur(self, image: np.ndarray, head: int, step: StepInput) -> np.ndarray: ...


@runtime_checkable
class StarDetector(Protocol):
    """Finds stars (detection and centroiding) on one head's image."""

    def detect(self, image: np.ndarray, camera: Camera) -> StarMeasurements: ...


@runtime_checkable
class DistortionCorrector(Protocol):
    """Maps measured pixel positions to the positions the calibrated camera would give the same directions (learning
    on the way), and back: ``uncorrect`` is the inverse of ``correct`` (calibrated -> measured), which puts predicted
    stars where they will be measured."""

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None: ...

    def correct(self, stars: StarMeasurements, head: int, camera: Camera) -> StarMeasurements: ...

    def uncorrect(self, stars: StarMeasurements, head: int, camera: Camera) -> StarMeasurements: ...

    def learn(self, stars: StarMeasurements, head: int, camera: Camera, attitude: Rotation,
              catalog: StarCatalog) -> None:
        """Update from one head's identified stars (corrected positions, catalogue ids) and the solved attitude."""
        ...


@runtime_checkable
class Identifier(Protocol):
    """Labels detections with catalog ids, all heads at once; ``prior`` is a predicted attitude or None."""

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None: ...

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """Catalog ids for ``stars`` (one list per head).  ``images`` holds each head's frame as the detector saw it
        (None where the frame was dropped) for identifiers that read pixels; others ignore it."""
        ...


@runtime_checkable
class AttitudeSolver(Protocol):
    """Wahba's problem: the rotation A (inertial -> body) minimising sum w |b_i - A r_i|^2."""

    def solve(self, body: np.ndarray, inertial: np.ndarray, weights: np.ndarray | None = None) -> Rotation: ...


ROLE_PROTOCOLS = dict(zip(AGENT_ROLES, (Predictor, Deblurrer, StarDetector, DistortionCorrector, Identifier,
                                        AttitudeSolver), strict=True))


@dataclass
class Restoration:
    """One head's deblurring at one step: the image before and after (DN) and the deblurrer's ``last_info``."""

    raw: np.ndarray
    restored: np.ndarray
    info: dict = field(default_factory=dict)


@dataclass
class StepReport:
    """What a policy reports about its last step: wall time per role (s), where the attitude came from ("solved",
    "predicted" or "none"), per head the restoration (None where nothing was restored; empty without a deblurrer),
    the detector that scores restorations (None without one), a filter's gyro bias estimate and covariance, and the
    agents' events of the step (a filter's gate rejections and restarts), for the recording's log."""

    latency_s: dict[str, float] = field(default_factory=dict)
    source: str = "none"
    restorations: list[Restoration | None] = field(default_factory=list)
    detector: StarDetector | None = None
    gyro_bias: np.ndarray | None = None  # (3,) rad/s, a filter's bias estimate
    covariance: np.ndarray | None = None  # (6, 6) a filter's error covariance (attitude rad^2 first, then bias)
    events: list[tuple[int, str]] = field(default_factory=list)  # (level, text): what the agents did of note


@runtime_checkable
class Policy(Protocol):
    """Observation -> action, what ``env.step`` loops and the benchmark drive: ``reset`` before each episode with
    what the sensor is known to be, then one call per observation; ``report`` describes the last call."""

    report: StepReport

    def reset(self, sensor: SensorInfo) -> None: ...

    def __call__(self, obs: dict) -> dict: ...

    def describe(self) -> dict[str, str | None]:
        """Role -> the agent's ``"module:Class"`` (None where the role is empty), for recordings and reports."""
        ...
