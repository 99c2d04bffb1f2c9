"""The star sensor simulator: a scenario's heads, gyro and drop channels stepped frame by frame, with truth.

Frame ``k`` opens its exposure at ``t = k / frame_rate_hz``; a rolling shutter opens row ``r`` ``r * line_time_s``
later.  The frame's attitude truth is taken at head 0's mid-exposure time (with a rolling shutter: the middle of the
whole readout).  The gyro samples delivered with frame ``k`` are those stamped after the previous frame's delivery
and up to the end of frame ``k``'s exposure window on head 0 (a scenario's recorded gyro log, ``gyro_replay``, is
delivered the same way, in place of the gyro model).

Randomness: one seed makes independent streams (``SeedSequence.spawn``) for each head's fixed pattern, each head's
pixel noise, each head's drop channel and the gyro, so adding a head does not change another head's images.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.parallel import POOL_WORKER_ENV, usable_cores
from starenv.sim.attitude_files import GyroRecord, GyroReplay
from starenv.sim.bodies import Baffle, HeadBodies, SkyBodies, SkySpec, add_signal
from starenv.sim.conventions import ARCSEC, frame_span_s, row_window
from starenv.sim.drops import DropChannel, DropModel
from starenv.sim.ephemeris import ObserverVelocity
from starenv.sim.gyro import Gyro, GyroSamples, GyroSpec
from starenv.sim.imager import Detector, DetectorSpec
from starenv.sim.motion import Trajectory
from starenv.sim.optics import Camera
from starenv.sim.photometry import Photometry, StrayLight
from starenv.sim.render import DETECTABLE_SNR, RenderedFrame, StarRenderer, StarTruth, still_image
from starenv.sim.sky import CatalogFile, StarCatalog, load_catalog
from starenv.sim.thermal import Thermal

_noise_threads: dict[int, ThreadPoolExecutor] = {}  # per process id (a forked child cannot use its parent's)


def noise_thread_default() -> bool:
    """Whether a sensor left to choose (``noise_thread=None``) draws its read-out noise on a second thread: where this
    process may run on two cores or more and is not a worker of a pool of processes, whose siblings keep the cores
    busy: a multiprocessing child (a vector env's worker, a local pool's) or a Ray worker of the bench or dataset
    runners (``POOL_WORKER_ENV`` set)."""
    return usable_cores() >= 2 and multiprocessing.parent_process() is None and not os.environ.get(POOL_WORKER_ENV)


def _noise_thread() -> ThreadPoolExecutor:
    """This process's thread that draws read-out noise while the stars render."""
    pid = os.getpid()
    if pid not in _noise_threads:
        _noise_threads.clear()
        _noise_threads[pid] = ThreadPoolExecutor(1, thread_name_prefix="starenv-noise")
    return _noise_threads[pid]


@dataclass
class HeadSpec:
    """One camera head: the true camera, what the sensor believes it is, PSF, throughput, detector, stray light."""

    name: str
    camera: Camera
    calibrated: Camera
    photometry: Photometry
    detector: DetectorSpec
    stray_light: StrayLight
    thermal: Thermal | None = None  # sensor temperature along the run and its effects; None: none
    baffle: Baffle = field(default_factory=Baffle)  # stray light and exclusion angles of bright bodies ([sky] bodies)

    @property
    def psf_sigma_px(self) -> float:
        """The true spot's Gaussian sigma (px); the calibrated camera carries the same value."""
        return self.camera.psf_sigma_px

class SensorSpec(Protocol):
    """What the sensor is built from (a loaded :class:`~starenv.scenario.Scenario` is one): timing (s, Hz), the
    simulated sky's magnitude limit, epoch (Julian year) and sky brightness (mag/arcsec^2), the seed, the true
    trajectory, the gyro, the drop model, the heads and which solar-system effects to simulate."""

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
    sky: SkySpec
    sky_catalog: CatalogFile | None  # the rendered stars' file; None: the bundled Hipparcos-2
    gyro_replay: GyroRecord | None  # a recorded gyro log delivered instead of the gyro model; None: the model


@dataclass
class HeadFrame:
    """One head's frame: the uint16 image as delivered (zeros when dropped) and the truth of its stars."""

    image: np.ndarray
    dropped: bool
    truth: StarTruth
    t_mid: float
    n_instants: int
    camera: Camera | None = None  # the true camera of this frame when the temperature moved it, else None
    bodies: HeadBodies | None = None  # the Sun, Moon, Earth and planets on this head ([sky] bodies), else None


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
    # (3,) m/s, ICRS axes: the observer's velocity the stars were aberrated for, at mid-exposure (zero without)
    observer_velocity_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))

class StarSensor:
    """Steps a :class:`SensorSpec` (e.g. a scenario): call :meth:`reset` with a seed, then :meth:`next_frame`."""

    def __init__(self, scenario: SensorSpec, catalog: StarCatalog | None = None, readout_block: int = 1,
                 noise_thread: bool | None = None):
        """``catalog``: the sky to render (default: the scenario's, Hp <= ``mag_limit`` at its ``epoch``); dataset
        generators pass an edited one (stars removed, false stars added, positions or magnitudes perturbed).
        ``readout_block`` > 1 delivers each frame as its ``readout_block``-px block means (float64 DN, drawn by
        :meth:`~starenv.sim.imager.Detector.read_out_binned` without the whole frame), for dataset generators whose
        samples are binned frames.  ``noise_thread``: draw each frame's read-out noise on a second thread while its
        stars render (the same frames bit for bit, sooner where a core is free); None: :func:`noise_thread_default`."""
        if noise_thread is not None and not isinstance(noise_thread, bool):
            raise ValueError(f"noise_thread must be True, False or None, got {noise_thread!r}")
        self.scenario = scenario
        self.readout_block = int(readout_block)
        self.noise_thread = noise_thread_default() if noise_thread is None else noise_thread
        sky_file = scenario.sky_catalog
        if catalog is None:
            catalog = (load_catalog(scenario.mag_limit, scenario.epoch) if sky_file is None
                       else sky_file.load(scenario.mag_limit, scenario.epoch))
        self.catalog = catalog
        self.observer_velocity = None  # callable of t (s) -> m/s, ICRS axes, when the stars are aberrated
        if scenario.sky.aberration:
            orbit = scenario.trajectory.orbit
            self.observer_velocity = ObserverVelocity(scenario.epoch, None if orbit is None else orbit.velocity)
        self.bodies = None  # the solar-system bodies, frame by frame, when the scenario draws them
        if scenario.sky.bodies:
            self.bodies = SkyBodies(scenario.epoch, scenario.trajectory.orbit, scenario.sky, self.observer_velocity)
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
        replay = self.scenario.gyro_replay
        self.gyro = (Gyro(self.scenario.gyro, np.random.default_rng(streams[0])) if replay is None
                     else GyroReplay(replay))
        self.index = 0

    def next_frame(self) -> Frame:
        """Simulate the next frame (the first after :meth:`reset` is frame 0 at t = 0)."""
        sc = self.scenario
        k = self.index
        t_start = k / sc.frame_rate_hz
        states = [self._thermal_state(spec, renderer, t_start + 0.5 * sc.exposure_s)
                  for spec, renderer in zip(sc.heads, self.renderers, strict=True)]
        pending = self._backgrounds_ahead([dark for dark, _ in states])
        try:  # the stars and the gyro while the noise is drawn, then the read-outs
            rendered = [self._rendered_head(h, t_start, dark, camera) for h, (dark, camera) in enumerate(states)]
            gyro = self._gyro_samples(t_start)
            heads = [self._head_frame(h, *rendered[h], *states[h], pending[h]) for h in range(len(states))]
        finally:  # (after an error, the draws end before anything else may use the streams)
            wait([future for future in pending if future is not None])
        t_mid = heads[0].t_mid
        self.index += 1
        velocity = np.zeros(3) if self.observer_velocity is None else np.array(self.observer_velocity(t_mid))
        return Frame(
            index=k,
            t_start=t_start,
            t_mid=t_mid,
            attitude=sc.trajectory.attitude(t_mid),
            body_rate=sc.trajectory.body_rate(t_mid),
            heads=heads,
            gyro=gyro,
            gyro_bias=self.gyro.bias_rad_s,
            observer_velocity_m_s=velocity,
        )

    def _gyro_samples(self, t_start: float) -> GyroSamples:
        """The gyro samples delivered with the frame opening at ``t_start`` (s): up to the end of head 0's exposure
        window."""
        sc = self.scenario
        first = sc.heads[0]
        _, window_end = row_window(t_start, sc.exposure_s, first.detector.line_time_s, first.camera.height - 1)
        # a motion whose rate jumps between samples (an attitude file) gives each gyro interval's exact mean
        mean_rate = getattr(sc.trajectory.motion, "mean_body_rate", None)
        return (self.gyro.sample_until(sc.trajectory.body_rate, window_end) if mean_rate is None
                else self.gyro.sample_until(sc.trajectory.body_rate, window_end, mean_rate))

    def _backgrounds_ahead(self, darks: list[float]) -> list[Future | None]:
        """Per head, its read-out's background frame (:meth:`~starenv.sim.imager.Detector.draw_background`: the
        noise, the frame's largest cost) started on the noise thread, to be drawn while the stars render; None where
        the read-out draws it itself: no noise thread, a binned read-out, or bright bodies (whose stray light sets the
        background only after the render).  The frames are the same bit for bit either way: a head's noise stream
        serves its read-out alone."""
        if not self.noise_thread or self.readout_block != 1 or self.bodies is not None:
            return [None] * len(darks)
        executor, exposure = _noise_thread(), self.scenario.exposure_s
        return [executor.submit(detector.draw_background, exposure, rng, dark)
                for detector, rng, dark in zip(self.detectors, self.noise_rngs, darks, strict=True)]

    def _rendered_head(self, h: int, t_start: float, dark: float,
                       camera: Camera | None) -> tuple[RenderedFrame, HeadBodies | None]:
        """Head ``h``'s stars rendered for the frame opening at ``t_start`` (s), with the bright bodies it sees (None
        without ``[sky] bodies``) and each star's detectability, given its dark-current factor and camera
        (:meth:`_thermal_state`): (the rendered frame, the bodies)."""
        sc = self.scenario
        spec, detector = sc.heads[h], self.detectors[h]
        rendered = self.renderers[h].render(sc.trajectory, t_start, sc.exposure_s, self.observer_velocity)
        bodies = None
        if self.bodies is not None:
            bodies = self.bodies.head_view(spec, camera or spec.camera, sc.trajectory.attitude(rendered.t_mid),
                                           rendered.t_mid, sc.exposure_s)
            rendered.signal = add_signal(rendered.signal, bodies.index, bodies.electrons)
            detector.set_background(self.backgrounds[h] + bodies.stray_e_per_px_s)
        truth = rendered.truth
        truth.detectable = detector.peak_snr(truth.peak_electrons, truth.xy_mid, sc.exposure_s, dark) >= DETECTABLE_SNR
        return rendered, bodies

    def _head_frame(self, h: int, rendered: RenderedFrame, bodies: HeadBodies | None, dark: float,
                    camera: Camera | None, drawn: Future | None) -> HeadFrame:
        """Head ``h``'s frame: its rendered signal read out (on its background frame being drawn, ``drawn``, from
        :meth:`_backgrounds_ahead`) and passed through its drop channel."""
        sc = self.scenario
        detector, noise = self.detectors[h], self.noise_rngs[h]
        image = (detector.read_out(rendered.signal, sc.exposure_s, noise, dark, drawn) if self.readout_block == 1
                 else detector.read_out_binned(rendered.signal, sc.exposure_s, noise, self.readout_block, dark))
        dropped = self.drop_channels[h].dropped(self.drop_rngs[h])
        if dropped:
            image = np.zeros_like(image)
        return HeadFrame(image, dropped, rendered.truth, rendered.t_mid, rendered.n_instants, camera, bodies)

    @staticmethod
    def _thermal_state(spec: HeadSpec, renderer: StarRenderer, t: float) -> tuple[float, Camera | None]:
        """A head's dark-current factor at time ``t`` (s) and, when its temperature moves the optics, the true camera
        then (the renderer is switched to it); 1.0 and None without a thermal model."""
        if spec.thermal is None:
            return 1.0, None
        camera = None
        if spec.thermal.moves_optics:
            camera = spec.thermal.camera(spec.camera, t)
            renderer.use_camera(camera)
        return spec.thermal.dark_factor(t), camera

    def still_frame(self, head: int, truth: StarTruth, frame: int | None = None) -> np.ndarray:
        """Noise-free reference of head ``head``'s frame as a still sensor would see it, float64 DN (H, W): each
        star's on-sensor electrons as the static PSF (the camera's spot there) at its mid-exposure position ``xy_mid``,
        plus the mean background (sky, stray light and dark current over the exposure, at the reference temperature,
        without fixed patterns), through the gain and bias; no noise, no hot pixels, no ADC rounding or clipping.
        With ``[sky] bodies`` and the frame's index ``frame``, the bodies as that frame draws them (the Moon's disk
        and the planets at mid-exposure) and their stray light are added; without ``frame`` they are left out."""
        spec = self.scenario.heads[head]
        cam, det = spec.camera, spec.detector
        exposure = self.scenario.exposure_s
        spot = None if cam.spot is None else cam.spot_shape(truth.xy_mid)
        stars = still_image(truth.xy_mid, truth.electrons, (cam.height, cam.width), spec.psf_sigma_px, spot)
        background = (self.backgrounds[head] + det.dark_current_e_per_s) * exposure
        if self.bodies is not None and frame is not None:
            view = self._frame_bodies(head, frame)
            np.add.at(stars.reshape(-1), view.index, view.electrons)
            background = background + view.stray_e_per_px_s * exposure
        return det.bias_dn + (stars + background) / det.gain_e_per_dn

    def _frame_bodies(self, head: int, frame: int) -> HeadBodies:
        """The bodies on head ``head`` of frame ``frame``, as :meth:`next_frame` draws them (a function of time)."""
        sc = self.scenario
        spec = sc.heads[head]
        t_start = frame / sc.frame_rate_hz
        camera = spec.camera
        if spec.thermal is not None and spec.thermal.moves_optics:
            camera = spec.thermal.camera(spec.camera, t_start + 0.5 * sc.exposure_s)
        t_mid = t_start + 0.5 * frame_span_s(sc.exposure_s, spec.detector.line_time_s, spec.camera.height)
        return self.bodies.head_view(spec, camera, sc.trajectory.attitude(t_mid), t_mid, sc.exposure_s)
