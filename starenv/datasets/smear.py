"""Smeared frames with their sharp reference, for learning restoration (paper 000's iteration model and later ones).

A sample is frame 0 of a scenario started from ``seed`` exactly as ``StarSensorEnv.reset(seed=seed)`` starts it
(the same image and gyro samples), plus the scene over a vanishing exposure centred on the frame's mid-exposure time,
scaled to the real exposure: the sharp, noise-free star image (DN above bias, no background) a perfect restorer
would return.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from starenv.scenario import Scenario
from starenv.sim.gyro import GyroSamples
from starenv.sim.optics import Camera
from starenv.sim.sensor import StarSensor

SHARP_EXPOSURE_S = 1e-6  # the "sharp" reference: the scene over a vanishing exposure, scaled to the real one


@dataclass
class SmearedFrame:
    """Head 0's frame (uint16 DN), the gyro samples delivered with it, its mid-exposure time and exposure (s), the
    calibrated cameras, and the sharp reference (float64 DN above bias, the frame's shape)."""

    image: np.ndarray
    gyro: GyroSamples
    time_s: float
    exposure_s: float
    cameras: list[Camera]
    sharp: np.ndarray


def smeared_frame(scenario: Scenario, seed: int) -> SmearedFrame:
    """Frame 0 of ``scenario`` from ``seed`` and its sharp reference (module docstring)."""
    sensor = StarSensor(scenario)
    episode_rng = np.random.default_rng(seed)  # what gymnasium seeds an env's np_random with
    sensor.reset(np.random.SeedSequence(int(episode_rng.integers(0, 2**63 - 1))))
    frame = sensor.next_frame()
    return SmearedFrame(frame.heads[0].image, frame.gyro, frame.t_mid, scenario.exposure_s,
                        [h.calibrated for h in scenario.heads], sharp_reference(sensor, frame.t_mid))


def sharp_reference(sensor: StarSensor, t_mid: float, head: int = 0) -> np.ndarray:
    """Head ``head``'s scene over a vanishing exposure at ``t_mid`` (s), scaled to the sensor's exposure: the sharp,
    noise-free star image in DN above bias, no background (float64, the frame's shape)."""
    scenario = sensor.scenario
    sharp = sensor.renderers[head].render(scenario.trajectory, t_mid - SHARP_EXPOSURE_S / 2, SHARP_EXPOSURE_S)
    gain = scenario.heads[head].detector.gain_e_per_dn
    return sharp.signal.image() * (scenario.exposure_s / SHARP_EXPOSURE_S) / gain
