"""Simulated beside real: the twin (a camera file, :func:`starenv.real.calibrate.camera_toml`) rendered at each real
frame's solved attitude, and the two frames measured the same way.

Per frame (:func:`compare_frame`): the twin renders the catalogue (Hp <= ``RENDER_MAG_LIMIT``, fainter than any
identified star, so the faint sky is there too) still at the frame's attitude through its camera, spot, throughput
and detector (its own noise seed); then both frames get

* the identified stars measured on their pixels (:func:`starenv.real.calibrate.measure_stars`, the same windows):
  the flux ratio real / simulated as a magnitude difference per star against its Hp, the spot sigma against the
  distance from the principal point;
* the centroid residuals: real, the fitted centroid minus the catalogue star projected through the twin under the
  frame's attitude refined on those stars (Wahba by SVD on the twin's unprojected centroids); simulated, the fitted
  centroid minus the renderer's true position (so both are what the twin's geometry leaves);
* the background level and noise (:func:`~starenv.agents.blocks.frame_background`);
* the stars the detector finds (:class:`~starenv.agents.detect.CentroidDetector` with the twin's spot).

:func:`summary` pools the frames into the agreement figures (:class:`Agreement`), :func:`markdown` makes the table
and :func:`plots` the figures (matplotlib, the ``report`` extra, imported there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.agents.blocks import frame_background, wahba_svd
from starenv.agents.detect import CentroidDetector
from starenv.real.calibrate import SolvedFrame, StarSample, measure_stars, saturation_dn
from starenv.sim.imager import Detector
from starenv.sim.motion import ConstantRate, Trajectory
from starenv.sim.optics import FieldSpot
from starenv.sim.render import StarRenderer
from starenv.sim.sensor import HeadSpec
from starenv.sim.sky import StarCatalog, load_catalog

RENDER_MAG_LIMIT = 10.0  # the twin's sky: well below what a star camera of this kind identifies


@dataclass
class FrameComparison:
    """One real frame and its simulated twin frame: the stars measured on both (``real``, ``sim``, same stars in the
    same order), the centroid residuals (n, 2) px of each (NaN where a fit failed), the background level and noise
    (DN) and the detected-star counts of each, and the stars' distance from the principal point over the
    half-diagonal (n,)."""

    name: str
    real: StarSample
    sim: StarSample
    real_residual_px: np.ndarray
    sim_residual_px: np.ndarray
    real_background: tuple[float, float]
    sim_background: tuple[float, float]
    real_detected: int
    sim_detected: int
    field_radius: np.ndarray
    sim_image: np.ndarray

    @property
    def delta_mag(self) -> np.ndarray:
        """-2.5 log10(real / simulated flux) per star (NaN where either flux is not positive)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = self.real.flux_dn / self.sim.flux_dn
        return np.where(ratio > 0, -2.5 * np.log10(np.where(ratio > 0, ratio, 1.0)), np.nan)

    @property
    def usable(self) -> np.ndarray:
        """Stars fit for the flux and spot comparisons on both frames (:attr:`StarSample.good`)."""
        return self.real.good & self.sim.good


def twin_frame(head: HeadSpec, attitude: Rotation, exposure_s: float, seed: int,
               catalog: StarCatalog | None = None) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The twin's frame (uint16 (H, W) DN) still at ``attitude`` (ICRS -> camera) over ``exposure_s`` (s), and each
    rendered star's true position (px) by HIP number."""
    cam = head.camera
    catalog = catalog if catalog is not None else load_catalog(RENDER_MAG_LIMIT)
    renderer = StarRenderer(catalog, cam, head.photometry, cam.psf_sigma_px, head.detector.line_time_s)
    trajectory = Trajectory(ConstantRate([0.0, 0.0, 0.0]), cam.mounting.inv() * attitude)
    rendered = renderer.render(trajectory, 0.0, exposure_s)
    streams = np.random.SeedSequence(seed).spawn(2)
    detector = Detector(head.detector, cam.width, cam.height, cam.pixel_pitch_m, 0.0, np.random.default_rng(streams[0]))
    image = detector.read_out(rendered.signal, exposure_s, np.random.default_rng(streams[1]))
    truth = rendered.truth
    return image, dict(zip(truth.catalog_id.tolist(), truth.xy_mid, strict=True))


def compare_frame(frame: SolvedFrame, head: HeadSpec, exposure_s: float, seed: int = 0,
                  catalog: StarCatalog | None = None, detector: CentroidDetector | None = None) -> FrameComparison:
    """A real frame (solved with the twin's camera ``head.camera``) beside the twin's frame at its attitude
    (module docstring); ``seed`` the twin's noise, ``catalog`` one holding the identified stars (Hp <= 14 by
    default)."""
    cam = head.camera
    catalog = catalog if catalog is not None else load_catalog(14.0)
    rows = np.searchsorted(catalog.hip, frame.hip)
    # The attitude refined on the identified stars through the twin.
    attitude = Rotation.from_matrix(wahba_svd(cam.unproject(frame.xy), catalog.unit[rows]))
    sim_image, truth = twin_frame(head, attitude, exposure_s, seed, load_catalog(RENDER_MAG_LIMIT, catalog.epoch))
    on_sim = np.array([h in truth for h in frame.hip.tolist()], bool)
    hip = frame.hip[on_sim]
    real_xy = frame.xy[on_sim]
    sim_true = np.array([truth[h] for h in hip.tolist()]).reshape(-1, 2)
    sigma = cam.psf_sigma_px
    spec = head.detector
    sim_top = min(float(spec.max_dn), spec.full_well_e / spec.gain_e_per_dn + spec.bias_dn)  # the twin's clip
    real = measure_stars(frame.image, real_xy, hip, catalog, cam, attitude, sigma, saturation_dn([frame.image]))
    sim = measure_stars(sim_image, sim_true, hip, catalog, cam, attitude, sigma,
                        sim_top if float(sim_image.max()) >= math.floor(sim_top) else None)
    predicted, _ = cam.project(attitude.apply(catalog.unit[rows[on_sim]]))
    detector = detector if detector is not None else CentroidDetector()
    half_diagonal = FieldSpot.field_radius_px(cam.intrinsics)
    return FrameComparison(
        frame.name, real, sim, real.xy - predicted, sim.xy - sim_true,
        frame_background(frame.image), frame_background(sim_image),
        len(detector.detect(frame.image, cam)), len(detector.detect(sim_image, cam)),
        np.hypot(*(real_xy - [cam.cx, cam.cy]).T) / half_diagonal, sim_image)


@dataclass
class Agreement:
    """The frames' agreement, pooled: stars compared; median and robust scatter (mag) of real - simulated magnitude;
    its slope per magnitude of Hp; median spot sigma (px) real and simulated, and in the outer half of the field
    (distance from the principal point over the half-diagonal >= 0.5); centroid residual RMS (px) real and simulated
    (over the same stars: isolated, unsaturated, SNR >= ``MIN_SNR`` on both frames);
    median background level and noise (DN) real and simulated; detected stars real and simulated (totals)."""

    frames: int
    stars: int
    delta_mag_median: float
    delta_mag_scatter: float
    delta_mag_slope: float
    spot_real_px: float
    spot_sim_px: float
    spot_outer_real_px: float
    spot_outer_sim_px: float
    centroid_rms_real_px: float
    centroid_rms_sim_px: float
    level_real_dn: float
    level_sim_dn: float
    noise_real_dn: float
    noise_sim_dn: float
    detected_real: int
    detected_sim: int


def _rms(residuals: list[np.ndarray]) -> float:
    r = np.concatenate(residuals)
    r = r[np.all(np.isfinite(r), axis=1)]
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else float("nan")


def _median(values) -> float:
    values = np.asarray(values, np.float64)
    values = values[np.isfinite(values)]
    return float(np.median(values)) if len(values) else float("nan")


def summary(comparisons: list[FrameComparison]) -> Agreement:
    """The frames' comparisons pooled into the agreement figures."""
    use = [c.usable for c in comparisons]
    dm = np.concatenate([c.delta_mag[u] for c, u in zip(comparisons, use, strict=True)])
    mag = np.concatenate([c.real.magnitude[u] for c, u in zip(comparisons, use, strict=True)])
    ok = np.isfinite(dm)
    dm, mag = dm[ok], mag[ok]
    slope = float(np.polyfit(mag, dm, 1)[0]) if len(dm) >= 3 and np.ptp(mag) > 0 else float("nan")
    outer = [u & (c.field_radius >= 0.5) for c, u in zip(comparisons, use, strict=True)]

    def pooled(attr, side, masks):
        return _median(np.concatenate([getattr(getattr(c, side), attr)[m]
                                       for c, m in zip(comparisons, masks, strict=True)]))

    return Agreement(
        len(comparisons), int(len(dm)), _median(dm), 1.4826 * _median(np.abs(dm - _median(dm))), slope,
        pooled("sigma_px", "real", use), pooled("sigma_px", "sim", use),
        pooled("sigma_px", "real", outer), pooled("sigma_px", "sim", outer),
        _rms([c.real_residual_px[u] for c, u in zip(comparisons, use, strict=True)]),
        _rms([c.sim_residual_px[u] for c, u in zip(comparisons, use, strict=True)]),
        _median([c.real_background[0] for c in comparisons]), _median([c.sim_background[0] for c in comparisons]),
        _median([c.real_background[1] for c in comparisons]), _median([c.sim_background[1] for c in comparisons]),
        sum(c.real_detected for c in comparisons), sum(c.sim_detected for c in comparisons))


def markdown(comparisons: list[FrameComparison], agreement: Agreement) -> str:
    """The comparison as markdown: the pooled agreement, then one row per frame."""
    a = agreement
    out = [f"# Real frames beside their simulated twin ({a.frames} frames, {a.stars} stars compared)", "",
           "| quantity | real | simulated |", "|---|---|---|",
           "| star flux, real - simulated (mag): median, robust scatter, slope per Hp mag | "
           f"{a.delta_mag_median:+.3f}, {a.delta_mag_scatter:.3f}, {a.delta_mag_slope:+.3f} | |",
           f"| spot sigma, median (px) | {a.spot_real_px:.3f} | {a.spot_sim_px:.3f} |",
           f"| spot sigma, outer half of the field (px) | {a.spot_outer_real_px:.3f} | {a.spot_outer_sim_px:.3f} |",
           f"| centroid residual RMS (px) | {a.centroid_rms_real_px:.3f} | {a.centroid_rms_sim_px:.3f} |",
           f"| background level, median (DN) | {a.level_real_dn:.2f} | {a.level_sim_dn:.2f} |",
           f"| background noise, median (DN) | {a.noise_real_dn:.3f} | {a.noise_sim_dn:.3f} |",
           f"| stars detected (all frames) | {a.detected_real} | {a.detected_sim} |", "",
           "| frame | stars | real - sim (mag) | spot real / sim (px) | centroid RMS real / sim (px) | "
           "level real / sim (DN) | noise real / sim (DN) | detected real / sim |",
           "|---|---|---|---|---|---|---|---|"]
    for c in comparisons:
        u = c.usable
        out.append(f"| {Path(c.name).name} | {int(u.sum())} | {_median(c.delta_mag[u]):+.3f} | "
                   f"{_median(c.real.sigma_px[u]):.2f} / {_median(c.sim.sigma_px[u]):.2f} | "
                   f"{_rms([c.real_residual_px[u]]):.3f} / {_rms([c.sim_residual_px[u]]):.3f} | "
                   f"{c.real_background[0]:.1f} / {c.sim_background[0]:.1f} | "
                   f"{c.real_background[1]:.2f} / {c.sim_background[1]:.2f} | {c.real_detected} / {c.sim_detected} |")
    return "\n".join(out) + "\n"


def plots(comparisons: list[FrameComparison], folder) -> list[str]:
    """Figures of the comparison in ``folder`` (PNG): flux difference against magnitude, spot sigma across the
    field, centroid residuals, background and noise per frame.  Returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = []

    def save(fig, name):
        fig.tight_layout()
        fig.savefig(folder / name, dpi=110)
        plt.close(fig)
        names.append(name)

    fig, ax = plt.subplots(figsize=(6, 4))
    for c in comparisons:
        u = c.usable
        ax.scatter(c.real.magnitude[u], c.delta_mag[u], s=10, alpha=0.7)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set(xlabel="Hp (mag)", ylabel="real - simulated (mag)", title="Star flux: real vs twin")
    save(fig, "flux_vs_mag.png")

    fig, ax = plt.subplots(figsize=(6, 4))
    for side, colour in (("real", "C0"), ("sim", "C3")):
        for k, c in enumerate(comparisons):
            u = c.usable
            ax.scatter(c.field_radius[u], getattr(c, side).sigma_px[u], s=10, alpha=0.6, color=colour,
                       label=("real" if side == "real" else "twin") if k == 0 else None)
    ax.set(xlabel="distance from the principal point / half-diagonal", ylabel="spot sigma (px)",
           title="Spot width across the field")
    ax.legend()
    save(fig, "spot_vs_field.png")

    fig, axes = plt.subplots(1, 2, figsize=(9, 4), sharex=True, sharey=True)
    for ax, side, label in ((axes[0], "real_residual_px", "real"), (axes[1], "sim_residual_px", "twin")):
        r = np.concatenate([getattr(c, side)[c.usable] for c in comparisons])
        ax.scatter(r[:, 0], r[:, 1], s=8, alpha=0.6)
        ax.set(xlabel="x residual (px)", ylabel="y residual (px)", title=f"Centroid residuals, {label}", aspect="equal")
    save(fig, "centroid_residuals.png")

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    idx = np.arange(len(comparisons))
    for ax, k, label in ((axes[0], 0, "background level (DN)"), (axes[1], 1, "background noise (DN)")):
        ax.bar(idx - 0.2, [c.real_background[k] for c in comparisons], 0.4, label="real")
        ax.bar(idx + 0.2, [c.sim_background[k] for c in comparisons], 0.4, label="twin")
        ax.set(xlabel="frame", ylabel=label)
        ax.legend()
    save(fig, "background.png")
    return names


def compare_files(paths: list, camera_path, exposure_s: float = 1.0, epoch: float = 2026.0,
                  seed: int = 0) -> tuple[list[FrameComparison], list]:
    """Read each file, solve it with the twin's camera (:func:`starenv.real.solve.solve_frame`) and compare the
    solved ones with the twin (:func:`compare_frame`, frame ``k`` with noise seed ``seed + k``).  Returns the
    comparisons and every file's solution."""
    from starenv.real.calibrate import solved_frame
    from starenv.real.read import read_frame
    from starenv.real.solve import solve_frame
    from starenv.scenario import load_camera

    head = load_camera(camera_path).head
    cam = head.camera
    catalog = load_catalog(14.0, epoch)
    detector = CentroidDetector()
    comparisons, solutions = [], []
    for k, path in enumerate(paths):
        image = read_frame(path)
        if image.shape != (cam.height, cam.width):
            raise ValueError(f"{path}: {image.shape[1]} x {image.shape[0]} px, but the twin in {camera_path} is "
                             f"{cam.width} x {cam.height}")
        solution = solve_frame(image, cam, epoch=epoch)
        solution.file = str(path)
        solutions.append(solution)
        if solution.solved:
            comparisons.append(compare_frame(solved_frame(image, solution), head, exposure_s, seed + k, catalog,
                                             detector))
    if not comparisons:
        raise ValueError(f"compare: none of the {len(paths)} frames solved with the camera of {camera_path}")
    return comparisons, solutions
