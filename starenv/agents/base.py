"""The agent roles of a star-sensor pipeline: one small protocol per role, and the data they pass along.

Agents see only what a sensor would (``StepInput``: images, gyro samples, times, calibrated cameras), never truth.
Pixel positions are distorted (measured) pixel coordinates of a head's image unless a name says ``ideal``; attitudes
are scipy ``Rotation`` inertial -> body; vectors are unit 3-vectors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.optics import Camera
from starenv.sky import StarCatalog

AGENT_ROLES = ("predictor", "deblurrer", "detector", "corrector", "identifier", "solver")


@dataclass
class GyroRecord:
    """Gyro samples: timestamps (n,) s and average body rates (n, 3) rad/s over ``(t - dt, t]``; ``dt`` in s."""

    t: np.ndarray
    rate: np.ndarray
    dt: float


@dataclass
class StepInput:
    """What the pipeline knows at one step (from the observation and the sensor's calibration)."""

    images: list[np.ndarray]  # per head, uint16 (H, W); meaningless where frame_valid is False
    frame_valid: np.ndarray  # (heads,) bool
    time_s: float  # mid-exposure time of the frame
    exposure_s: float
    gyro: GyroRecord  # samples since the previous step
    cameras: list[Camera]  # calibrated models


@dataclass
class Stars:
    """Stars on one head's frame: positions (n, 2) px, flux (n,) DN above background, catalog ids (n,; -1 none)."""

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
    stars: list[Stars]


@runtime_checkable
class Predictor(Protocol):
    """Carries the attitude (and star positions) from one frame to the next with the gyro."""

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None: ...

    def predict(self, step: StepInput) -> Prediction:
        """Propagate the last state to ``step.time_s`` with ``step.gyro``."""
        ...

    def update(self, attitude: Rotation, stars: list[Stars], time_s: float) -> None:
        """Take the pipeline's estimate for the frame at ``time_s`` as the new state."""
        ...


@runtime_checkable
class Deblurrer(Protocol):
    """Restores one head's smeared image, knowing the gyro samples over its exposure."""

    def deblur(self, image: np.ndarray, head: int, step: StepInput) -> np.ndarray: ...


@runtime_checkable
class StarDetector(Protocol):
    """Finds stars (detection and centroiding) on one head's image."""

    def detect(self, image: np.ndarray, camera: Camera) -> Stars: ...


@runtime_checkable
class DistortionCorrector(Protocol):
    """Maps measured pixel positions to the calibrated camera's distorted positions (learning on the way)."""

    def correct(self, stars: Stars, head: int, camera: Camera) -> Stars: ...

    def learn(self, stars: Stars, head: int, camera: Camera, attitude: Rotation, catalog: StarCatalog) -> None: ...


@runtime_checkable
class Identifier(Protocol):
    """Labels detections with catalog ids, all heads at once; ``prior`` is a predicted attitude or None."""

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None: ...

    def identify(self, stars: list[Stars], cameras: list[Camera], prior: Rotation | None) -> list[Stars]: ...


@runtime_checkable
class AttitudeSolver(Protocol):
    """Wahba's problem: the rotation A (inertial -> body) minimising sum w |b_i - A r_i|^2."""

    def solve(self, body: np.ndarray, inertial: np.ndarray, weights: np.ndarray | None = None) -> Rotation: ...
