"""Measured / reference star-position pairs for learning a distortion corrector (paper 003's data sets), and the
star-coverage rate of the focal plane.

A sample is one frame of head ``head`` of a scenario, reproducible alone from ``(seed, index)``
(``numpy.random.default_rng([seed, index])`` draws everything random in it): :func:`frame_pairs` at an attitude
drawn uniformly on SO(3) (the ground data set over random sky), :func:`orbit_pairs` at the scenario's trajectory
attitude at ``t = index / frame_rate_hz`` (the on-orbit sequence).  Each catalogue star (``scenario.mag_limit``)
seen by the head yields:

* ``distorted``: where the true optics image it (pinhole + the scenario's distortion), px;
* ``measured``: ``distorted`` plus independent Gaussian centroid noise of ``centroid_noise_px`` per axis (paper 003's
  Eq. 19 noise ``n_X, n_Y``, whose size the paper does not give);
* ``reference``: where the *calibrated* camera puts the same direction (the position a perfect corrector returns).

No image is rendered: the pairs are the geometry of the frame, which is what a ground calibration with a known
attitude (a star simulator or a collimated field) delivers.  Stars are kept when both positions fall on the sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from starenv import checks
from starenv.scenario import Scenario
from starenv.sim.sky import load_catalog

CENTROID_NOISE_PX = 0.05  # default per-axis centroid noise (px, 1 sigma)


@dataclass
class StarPairs:
    """One frame's pairs: catalogue ids (n,), measured, noise-free distorted and reference positions (n, 2) px,
    and the attitude (inertial -> body) the frame was taken at."""

    catalog_id: np.ndarray
    measured: np.ndarray
    distorted: np.ndarray
    reference: np.ndarray
    attitude: Rotation

    def __len__(self) -> int:
        return len(self.catalog_id)


def frame_pairs(scenario: Scenario, seed: int, index: int, centroid_noise_px: float = CENTROID_NOISE_PX,
                head: int = 0) -> StarPairs:
    """The pairs of frame ``index`` over random sky of the data set ``seed`` (module docstring)."""
    rng = _rng(seed, index)
    return attitude_pairs(scenario, Rotation.random(random_state=rng), rng, centroid_noise_px, head)


def orbit_pairs(scenario: Scenario, seed: int, index: int, centroid_noise_px: float = CENTROID_NOISE_PX,
                head: int = 0) -> StarPairs:
    """The pairs of frame ``index`` along the scenario's trajectory (``t = index / frame_rate_hz``), noise from
    ``seed``; a head whose temperature moves its optics images through its camera at ``t``."""
    rng = _rng(seed, index)
    t = index / scenario.frame_rate_hz
    return attitude_pairs(scenario, scenario.trajectory.attitude(t), rng, centroid_noise_px, head, time_s=t)


def _rng(seed: int, index: int) -> np.random.Generator:
    seed = checks.integer("seed", seed, 0, 2**63 - 1)
    index = checks.integer("index", index, 0, 2**63 - 1)
    return np.random.default_rng([seed, index])


def attitude_pairs(scenario: Scenario, attitude: Rotation, rng: np.random.Generator, centroid_noise_px: float,
                   head: int = 0, time_s: float | None = None) -> StarPairs:
    """The pairs of head ``head`` at ``attitude`` (inertial -> body), measurement noise from ``rng``; at ``time_s``
    (s) the head's temperature (its ``thermal`` model) sets the true camera, None: the camera as given."""
    noise = checks.non_negative("centroid_noise_px", centroid_noise_px, unit="px")
    checks.integer("head", head, 0, len(scenario.heads) - 1)
    spec = scenario.heads[head]
    true_cam, cal_cam = spec.camera, spec.calibrated
    if time_s is not None and spec.thermal is not None:
        true_cam = spec.thermal.camera(true_cam, time_s)
    catalog = load_catalog(scenario.mag_limit, scenario.epoch)
    to_cam = true_cam.inertial_to_camera(attitude)
    rows = catalog.cone(to_cam.inv().apply([0.0, 0.0, 1.0]), min(true_cam.half_diagonal * 1.05, np.pi / 2))
    v_cam = to_cam.apply(catalog.unit[rows])
    distorted, front = true_cam.project(v_cam)
    reference, _ = cal_cam.project(v_cam)
    keep = front & true_cam.in_frame(distorted) & cal_cam.in_frame(reference)
    distorted, reference = distorted[keep], reference[keep]
    measured = distorted + rng.normal(0.0, noise, distorted.shape) if noise > 0 else distorted.copy()
    return StarPairs(catalog.hip[rows][keep], measured, distorted, reference, attitude)


def pooled_pairs(scenario: Scenario, seed: int, frames: int, centroid_noise_px: float = CENTROID_NOISE_PX,
                 head: int = 0) -> StarPairs:
    """Frames ``0 .. frames - 1`` of the data set ``seed`` pooled into one :class:`StarPairs` (attitude: frame 0's)."""
    checks.integer("frames", frames, 1, 10**7)
    parts = [frame_pairs(scenario, seed, i, centroid_noise_px, head) for i in range(frames)]
    return StarPairs(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("catalog_id", "measured",
                                                                                   "distorted", "reference")),
                     parts[0].attitude)


def coverage(xy: np.ndarray, width: int, height: int, radius_px: float = 96.0, cell_px: float = 8.0) -> float:
    """Paper 003's star-coverage rate ``C_star`` (its Eq. 26): the fraction of the focal plane within ``radius_px`` of
    a star position ``xy`` (n, 2) px, on a raster of ``cell_px`` cells.  The paper takes the area of the stars'
    concave outline and gives no parameter for it; the disc radius plays that part (96 px, set so that the coverage
    over ``paper_003``'s orbit follows the paper's Table 1, which gives 42 %, 71 %, 98 % after 1, 50 and 500 frames;
    ``benchmarks/paper003_distortion.py`` prints ours beside it)."""
    from scipy.ndimage import distance_transform_edt

    checks.positive("radius_px", radius_px, "px")
    checks.positive("cell_px", cell_px, "px")
    nx, ny = int(np.ceil(width / cell_px)), int(np.ceil(height / cell_px))
    empty = np.ones((ny, nx), dtype=bool)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    col = np.clip(((xy[:, 0] + 0.5) / cell_px).astype(int), 0, nx - 1)
    row = np.clip(((xy[:, 1] + 0.5) / cell_px).astype(int), 0, ny - 1)
    empty[row, col] = False
    if empty.all():
        return 0.0
    return float(np.mean(distance_transform_edt(empty) * cell_px <= radius_px))
