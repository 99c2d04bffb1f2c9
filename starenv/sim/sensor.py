"""The star sensor simulator: a scenario's heads, gyro and drop channels stepped frame by frame, with truth.

Frame ``k`` opens its exposure at ``t = k / frame_rate_hz``; a rolling shutter opens row ``r`` ``r * line_time_s``
later.  The frame's attitude truth is taken at head 0's mid-exposure time (with a rolling shutter: the middle of the
whole readout).  The gyro samples delivered with frame ``k`` are those stamped after the previous frame's delivery
and up to the end of frame ``k``'s exposure window on head 0.

Randomness: one seed makes independent streams (``SeedSequence.spawn``) for each head's fixed pattern, each head's
pixel noise, each head's drop channel and the gyro, so adding a head does not change another head's images.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.sim.conventions import ARCSEC, row_window
from starenv.sim.drops import DropChannel, DropModel
from starenv.sim.gyro import Gyro, GyroSamples, GyroSpec
from starenv.sim.imager import Detector, DetectorSpec
from starenv.sim.motion import Trajectory
from starenv.sim.optics import Camera
from starenv.sim.photometry import Photometry, StrayLight
from starenv.sim.render import DETECTABLE_SNR, StarRenderer, StarTruth, still_image
from starenv.sim.sky import StarCatalog, load_catalog


@dataclass
class HeadSpec:
    """One camera head: the true camera, what the sensor believes it is, PSF, throughput, detector, stray light."""

    name: str
    camera: Camera
    calibrated: Camera
    photometry: Photometry
    detector: DetectorSpec
    stray_light: StrayLight

    @property
    def psf_sigma_px(self) -> float:
        """The true spot's Gaussian sigma (px); the calibrated camera carries the same value."""
        return self.camera.psf_sigma_px

class SensorSpec(Protocol):
    """What the sensor is built from (a loaded :class:`~starenv.scenario.Scenario` is one): timing (s, Hz), the
    simulated sky's magnitude limit, epoch (Julian year) and sky brightness (mag/arcsec^2), the seed, the true
    trajectory, the gyro, the drop model and the heads."""

    seed: int
    frame_rate_hz: float
    exposure_s: float
    mag_limit: float
    epoch: float
    sky_mag_per_arcsec2: float
    trajectory: Trajectory
    gyro: GyroSpec
    drops: DropModel
    heads: list[HeadSpec]


@dataclass
class HeadFrame:
    """One head's frame: the uint16 image as delivered (zeros when dropped) and the truth of its stars."""

    image: np.ndarray
    dropped: bool
    truth: StarTruth
    t_mid: float
    n_instants: int


@dataclass
class Frame:
    """Everything the simulator produced for one frame: images, gyro samples and truth at mid-exposure."""

    index: int
    t_start: float
    t_mid: float
    attitude: Rotation
    body_rate: np.ndarray
    heads: list[HeadFrame]
    gyro: GyroSamples
    gyro_bias: np.ndarray  # (3,) rad/s: the gyro's total bias at its last sample delivered with this frame

class StarSensor:
    """Steps a :class:`SensorSpec` (e.g. a scenario): call :meth:`reset` with a seed, then :meth:`next_frame`."""

    def __init__(self, scenario: SensorSpec, catalog: StarCatalog | None = None):
        """``catalog``: the sky to render (default: the scenario's, Hp <= ``mag_limit`` at its ``epoch``); dataset
        generators pass an edited one (stars removed, false stars added, positions or magnitudes perturbed)."""
        self.scenario = scenario
        self.catalog = load_catalog(scenario.mag_limit, scenario.epoch) if catalog is None else catalog
        self.renderers = []
        self.backgrounds = []
        for head in scenario.heads:
            cam = head.camera
            self.renderers.append(
                StarRenderer(self.catalog, cam, head.photometry, head.psf_sigma_px, head.detector.line_time_s)
            )
            pixel_sr_arcsec2 = (cam.pixel_pitch_m / cam.focal_length_m / ARCSEC) ** 2
            sky = head.photometry.sky_electrons_per_px_s(scenario.sky_mag_per_arcsec2, pixel_sr_arcsec2)
            stray = head.stray_light
            bg = sky + (stray.map(cam.width, cam.height, cam.fx, cam.cx, cam.cy) if stray.level_e_per_px_s else 0.0)
            self.backgrounds.append(bg)
        self.reset(scenario.seed)

    def reset(self, seed: int | np.random.SeedSequence) -> None:
        """Start an episode: new noise streams, hot-pixel patterns, drop channels and gyro state from ``seed``."""
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        n = len(self.scenario.heads)
        streams = ss.spawn(3 * n + 1)  # gyro first, then three per head, so appending a head changes no stream
        self.detectors = [
            Detector(h.detector, h.camera.width, h.camera.height, h.camera.pixel_pitch_m, bg,
                     np.random.default_rng(streams[1 + 3 * i]))
            for i, (h, bg) in enumerate(zip(self.scenario.heads, self.backgrounds, strict=True))
        ]
        self.noise_rngs = [np.random.default_rng(streams[2 + 3 * i]) for i in range(n)]
        self.drop_rngs = [np.random.default_rng(streams[3 + 3 * i]) for i in range(n)]
        self.drop_channels = [DropChannel(self.scenario.drops) for _ in range(n)]
        self.gyro = Gyro(self.scenario.gyro, np.random.default_rng(streams[0]))
        self.index = 0

    def next_frame(self) -> Frame:
        """Simulate the next frame (the first after :meth:`reset` is frame 0 at t = 0)."""
        sc = self.scenario
        k = self.index
        t_start = k / sc.frame_rate_hz
        heads = []
        for renderer, detector, noise, drops, drop_rng in zip(
            self.renderers, self.detectors, self.noise_rngs, self.drop_channels, self.drop_rngs, strict=True
        ):
            rendered = renderer.render(sc.trajectory, t_start, sc.exposure_s)
            truth = rendered.truth
            truth.detectable = detector.peak_snr(truth.peak_electrons, truth.xy_mid, sc.exposure_s) >= DETECTABLE_SNR
            image = detector.read_out(rendered.signal, sc.exposure_s, noise)
            dropped = drops.dropped(drop_rng)
            if dropped:
                image = np.zeros_like(image)
            heads.append(HeadFrame(image, dropped, truth, rendered.t_mid, rendered.n_instants))
        t_mid = heads[0].t_mid
        first = sc.heads[0]
        _, window_end = row_window(t_start, sc.exposure_s, first.detector.line_time_s, first.camera.height - 1)
        gyro = self.gyro.sample_until(sc.trajectory.body_rate, window_end)
        self.index += 1
        return Frame(
            index=k,
            t_start=t_start,
            t_mid=t_mid,
            attitude=sc.trajectory.attitude(t_mid),
            body_rate=sc.trajectory.body_rate(t_mid),
            heads=heads,
            gyro=gyro,
            gyro_bias=self.gyro.bias_rad_s,
        )

    def still_frame(self, head: int, truth: StarTruth) -> np.ndarray:
        """Noise-free reference of head ``head``'s frame as a still sensor would see it, float64 DN (H, W): each
        star's on-sensor electrons as the static PSF at its mid-exposure position ``xy_mid``, plus the mean
        background (sky, stray light and dark current over the exposure), through the gain and bias; no noise, no hot
        pixels, no ADC rounding or clipping."""
        spec = self.scenario.heads[head]
        cam, det = spec.camera, spec.detector
        exposure = self.scenario.exposure_s
        stars = still_image(truth.xy_mid, truth.electrons, (cam.height, cam.width), spec.psf_sigma_px)
        background = (self.backgrounds[head] + det.dark_current_e_per_s) * exposure
        return det.bias_dn + (stars + background) / det.gain_e_per_dn
