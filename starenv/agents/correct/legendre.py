"""Paper 003's 2-D Legendre network (2DLNN) as a distortion corrector, with its online learners.

The model (paper 003, Eqs. 20-21): a measured centroid ``(u, v)`` px is normalised to ``x = (u - cx)/s``,
``y = (v - cy)/s`` (``s`` = half the sensor width, so the sensor spans about [-1, 1]^2), expanded in the normalised
Legendre modes ``b_m(x, y) = L_{l-k}(x) L_k(y)`` of total order <= ``order`` (21 modes at order 5,
:func:`~starenv.sim.optics.legendre_basis`), and the offset ``F = W^T b`` (normalised units, one weight column per
axis) is subtracted: ``p_corr = p_mea - s F(p_mea)``.  The label of a star is ``(p_mea - p_ref)/s`` with ``p_ref``
the catalogue direction projected through the calibrated camera.  The network is linear in its weights, so its
least-squares fit has a closed form (:func:`fit_least_squares`), the reference every learner is measured against.

Online learners (one update per frame from the frame's identified stars):

* :class:`AdamLearner` -- the paper's on-orbit rule: per-frame RMSE loss ``J_f`` per axis (Eq. 27), its gradient
  (Eq. 28), Adam with the forgetting factor: ``W <- tau W - lr m_hat / (sqrt(v_hat) + eps)`` (Eq. 25, A1);
* :class:`RlsLearner` -- ours: recursive least squares in information form, ``A <- lam A + B^T B``,
  ``c <- lam c + B^T F``, ``W = A^-1 c``, with a Gaussian prior on ``W`` (``prior_px``) centred on the start weights;
  with ``lam = 1`` it is exactly the ridge-regularised least-squares fit of every star seen so far.

Observability.  On orbit the references come from the attitude solved from the corrected stars themselves, so a
field that a small rotation of the camera produces (a shift of the image by pitch or yaw, a turn about the boresight)
is absorbed by the attitude and never seen in the labels: whatever rotation-like part the weights hold persists.
:class:`LegendreCorrector` therefore keeps the weights' components along the three rotation fields at their start
values (zero, or the ground calibration's): after every update it projects them out of the change
(:func:`rotation_modes`; the modes are orthonormal, so the projection is a dot product of weight vectors).  The part
of a true distortion that looks like a rotation stays uncorrected: it is an attitude (mounting) bias no star-only
calibration can tell apart.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from starenv import checks
from starenv.agents.base import StarMeasurements
from starenv.agents.blocks import wahba_svd
from starenv.sim.optics import Camera, legendre_basis, legendre_mode_count
from starenv.sim.sky import StarCatalog

ORDER = 5
# The corrector's learner options unless told otherwise.  RLS forgets with lam = 0.98 a frame (a memory of about
# 1 / (1 - lam) = 50 frames), so a camera whose focal length and distortion drift with temperature is followed; a
# static field is then fitted from the last ~50 frames' stars instead of all of them (benchmarks/corrector_drift.py
# measures both against lam).
DEFAULT_LEARNER_OPTIONS: dict[str, dict] = {"rls": {"lam": 0.98}, "adam": {}}


def scale_px(camera: Camera) -> float:
    """The normalisation length ``s`` (px): half the sensor width (paper 003: 1024 for 2048 px)."""
    return camera.width / 2.0


def design(xy: np.ndarray, camera: Camera, order: int) -> np.ndarray:
    """Legendre modes (n, n_modes) of pixel positions ``xy`` (n, 2) normalised over ``camera``'s sensor."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    s = scale_px(camera)
    return legendre_basis((xy[:, 0] - camera.cx) / s, (xy[:, 1] - camera.cy) / s, order)


def labels(measured: np.ndarray, reference: np.ndarray, camera: Camera) -> np.ndarray:
    """Normalised offsets ``(p_mea - p_ref)/s`` (n, 2), the network's targets."""
    return (np.asarray(measured, np.float64) - np.asarray(reference, np.float64)) / scale_px(camera)


def fit_least_squares(measured: np.ndarray, reference: np.ndarray, camera: Camera, order: int = ORDER) -> np.ndarray:
    """Closed-form least-squares weights (n_modes, 2), normalised units, of the offsets ``measured - reference``
    expanded at the measured positions (n, 2) px."""
    b = design(measured, camera, order)
    if len(b) < b.shape[1]:
        raise ValueError(f"least squares at order {order} needs at least {b.shape[1]} stars, got {len(b)}")
    w, *_ = np.linalg.lstsq(b, labels(measured, reference, camera), rcond=None)
    return w


def rotation_modes(camera: Camera, order: int = ORDER, step_rad: float = 1e-6) -> np.ndarray:
    """Orthonormal basis (3, 2 n_modes) of the weight vectors (x column then y column, flattened) of the pixel fields
    that small rotations of ``camera`` about its X, Y and Z axes produce, each fitted by least squares on a 41 x 41
    grid over the sensor (pitch and yaw are a shift plus a few per cent of quadratic terms; roll is exact)."""
    u = np.linspace(-0.5, camera.width - 0.5, 41)
    v = np.linspace(-0.5, camera.height - 0.5, 41)
    xy = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    dirs = np.stack([(xy[:, 0] - camera.cx) / camera.fx, (xy[:, 1] - camera.cy) / camera.fy, np.ones(len(xy))], 1)
    ideal = np.stack([camera.fx * dirs[:, 0] + camera.cx, camera.fy * dirs[:, 1] + camera.cy], 1)
    b = design(xy, camera, order)
    fields = []
    for axis in np.eye(3):
        turned = Rotation.from_rotvec(axis * step_rad).apply(dirs)
        moved = np.stack([camera.fx * turned[:, 0] / turned[:, 2] + camera.cx,
                          camera.fy * turned[:, 1] / turned[:, 2] + camera.cy], 1)
        w, *_ = np.linalg.lstsq(b, (moved - ideal) / (step_rad * scale_px(camera)), rcond=None)
        fields.append(w.T.ravel())
    q, _ = np.linalg.qr(np.array(fields).T)
    return q.T


@dataclass
class LegendreModel:
    """Weights (n_modes, 2) of the network in normalised units, column 0 for x, column 1 for y."""

    weights: np.ndarray

    def __post_init__(self):
        w = checks.finite("LegendreModel.weights", self.weights)
        n = w.shape[0] if w.ndim == 2 else 0
        order = int(round((np.sqrt(8 * n + 1) - 3) / 2)) if n else -1
        if w.ndim != 2 or w.shape[1] != 2 or order < 0 or legendre_mode_count(order) != n:
            raise ValueError(f"LegendreModel.weights must have shape ((n+1)(n+2)/2, 2), got {w.shape}")
        self.weights = w.astype(np.float64, copy=True)
        self.order = order

    @classmethod
    def zeros(cls, order: int = ORDER) -> LegendreModel:
        checks.integer("order", order, 0, 20)
        return cls(np.zeros((legendre_mode_count(order), 2)))

    def offset(self, xy: np.ndarray, camera: Camera) -> np.ndarray:
        """Estimated distortion offsets (n, 2) px at measured positions ``xy`` (n, 2) px."""
        return scale_px(camera) * (design(xy, camera, self.order) @ self.weights)

    def correct(self, xy: np.ndarray, camera: Camera) -> np.ndarray:
        """Corrected positions ``xy - offset(xy)`` (n, 2) px."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return xy - self.offset(xy, camera)

    def uncorrect(self, xy: np.ndarray, camera: Camera, iterations: int = 8) -> np.ndarray:
        """Measured positions whose correction is ``xy`` (n, 2) px: the fixed point of ``p = xy + offset(p)``,
        which contracts by the field's gradient (~1e-3 for pixel-sized fields) per iteration."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        p = xy.copy()
        for _ in range(iterations):
            p = xy + self.offset(p, camera)
        return p

    def save(self, path: str | Path) -> None:
        """Write the weights to ``path`` (``.npz``: ``weights``, ``order``)."""
        np.savez(path, weights=self.weights, order=self.order)

    @classmethod
    def load(cls, path: str | Path) -> LegendreModel:
        with np.load(path) as data:
            return cls(np.array(data["weights"]))


@dataclass
class AdamLearner:
    """The paper's online rule: one Adam step with forgetting factor ``tau`` per frame on the per-frame RMSE loss of
    each axis (module docstring); ``lr``, ``tau``, ``beta1``, ``beta2``, ``eps`` as its Eq. 25 and A1."""

    lr: float = 1e-4
    tau: float = 0.999
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    m: np.ndarray | None = field(default=None, repr=False)
    v: np.ndarray | None = field(default=None, repr=False)
    t: int = 0

    def __post_init__(self):
        checks.in_range("lr", self.lr, 0.0, 1.0, low_open=True)
        checks.in_range("tau", self.tau, 0.0, 1.0, low_open=True)

    def update(self, model: LegendreModel, b: np.ndarray, f: np.ndarray) -> None:
        """One step on a frame's design matrix ``b`` (n, n_modes) and labels ``f`` (n, 2)."""
        w = model.weights
        if self.m is None:
            self.m, self.v = np.zeros_like(w), np.zeros_like(w)
        e = f - b @ w  # (n, 2)
        rmse = np.sqrt(np.mean(e * e, axis=0))  # J_f per axis
        grad = -(b.T @ e) / (len(b) * np.maximum(rmse, 1e-300))  # Eq. 28
        self.t += 1
        self.m = self.beta1 * self.m + (1 - self.beta1) * grad
        self.v = self.beta2 * self.v + (1 - self.beta2) * grad * grad
        m_hat = self.m / (1 - self.beta1**self.t)
        v_hat = self.v / (1 - self.beta2**self.t)
        model.weights = self.tau * w - self.lr * m_hat / (np.sqrt(v_hat) + self.eps)


@dataclass
class RlsLearner:
    """Recursive least squares (information form) with forgetting ``lam`` and a prior of ``prior_px`` (1 sigma, px
    at the sensor half-width, per weight) around the weights it starts from, relative to a centroid noise of
    ``noise_px`` (module docstring)."""

    lam: float = 1.0
    prior_px: float = 3.0
    noise_px: float = 0.1
    a: np.ndarray | None = field(default=None, repr=False)
    c: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        checks.in_range("lam", self.lam, 0.0, 1.0, low_open=True)
        checks.positive("prior_px", self.prior_px, "px")
        checks.positive("noise_px", self.noise_px, "px")

    def update(self, model: LegendreModel, b: np.ndarray, f: np.ndarray) -> None:
        """Fold a frame's design matrix ``b`` (n, n_modes) and labels ``f`` (n, 2) into the solution."""
        if self.a is None:
            ridge = (self.noise_px / self.prior_px) ** 2
            self.a = ridge * np.eye(b.shape[1])
            self.c = self.a @ model.weights
        self.a = self.lam * self.a + b.T @ b
        self.c = self.lam * self.c + b.T @ f
        model.weights = np.linalg.solve(self.a, self.c)


LEARNERS = {"rls": RlsLearner, "adam": AdamLearner}


class LegendreCorrector:
    """Paper 003's on-orbit distortion corrector (a :class:`~starenv.agents.base.DistortionCorrector`).

    ``correct`` subtracts the network's offset from every detection; ``learn`` takes the frame's identified stars,
    their catalogue directions through the solved attitude and the calibrated camera as references, and updates the
    weights with ``learner`` (``"rls"``, ours, or ``"adam"``, the paper's) and its ``learner_options``.  ``weights``:
    an ``.npz`` of ground-trained weights (:meth:`LegendreModel.save`) to start from, or None to start from zero (the
    identity correction) at ``order``.  ``fix_rotation``: keep the rotation-like components of the weights at their
    start values (module docstring).  ``learner_options`` are merged over :data:`DEFAULT_LEARNER_OPTIONS` (RLS:
    forgetting ``lam = 0.98``; ``{"lam": 1.0}`` fits every star seen, for a camera known not to drift).  A star
    whose label is more than ``gate_px`` from the current model's offset is left out of the update (a wrong
    identification); a frame with fewer than ``min_stars`` is skipped.
    """

    def __init__(self, order: int = ORDER, learner: str = "rls", weights: str | None = None, gate_px: float = 5.0,
                 min_stars: int = 5, fix_rotation: bool = True, learner_options: dict | None = None):
        checks.choice("learner", learner, sorted(LEARNERS))
        self.start = LegendreModel.zeros(order) if weights is None else LegendreModel.load(weights)
        self.learner_name = learner
        self.learner_options = {**DEFAULT_LEARNER_OPTIONS[learner], **(learner_options or {})}
        LEARNERS[learner](**self.learner_options)  # options checked now, not at the first frame
        self.gate_px = checks.positive("gate_px", gate_px, "px")
        self.min_stars = checks.integer("min_stars", min_stars, 1, 10**6)
        if not isinstance(fix_rotation, bool):
            raise ValueError(f"fix_rotation must be true or false, got {fix_rotation!r}")
        self.fix_rotation = fix_rotation
        self._rotation: dict[int, np.ndarray] = {}
        self.models: dict[int, LegendreModel] = {}
        self.learners: dict[int, AdamLearner | RlsLearner] = {}
        self.frames_learned: dict[int, int] = {}

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        """Start every head from the start weights with a fresh learner."""
        self.models = {h: LegendreModel(self.start.weights) for h in range(len(cameras))}
        self.learners = {h: LEARNERS[self.learner_name](**self.learner_options) for h in range(len(cameras))}
        self.frames_learned = dict.fromkeys(range(len(cameras)), 0)
        self._rotation = {}

    def _model(self, head: int) -> LegendreModel:
        if head not in self.models:
            self.models[head] = LegendreModel(self.start.weights)
            self.learners[head] = LEARNERS[self.learner_name](**self.learner_options)
            self.frames_learned[head] = 0
        return self.models[head]

    def correct(self, stars: StarMeasurements, head: int, camera: Camera) -> StarMeasurements:
        return StarMeasurements(self._model(head).correct(stars.xy, camera), stars.flux.copy(),
                                stars.catalog_id.copy())

    def uncorrect(self, stars: StarMeasurements, head: int, camera: Camera) -> StarMeasurements:
        return StarMeasurements(self._model(head).uncorrect(stars.xy, camera), stars.flux.copy(),
                                stars.catalog_id.copy())

    def learn(self, stars: StarMeasurements, head: int, camera: Camera, attitude: Rotation,
              catalog: StarCatalog) -> None:
        ok = stars.catalog_id >= 0
        if ok.sum() < self.min_stars:
            return
        model = self._model(head)
        corrected = stars.xy[ok]
        measured = model.uncorrect(corrected, camera)
        rows = np.searchsorted(catalog.hip, stars.catalog_id[ok])
        reference, front = camera.project(camera.inertial_to_camera(attitude).apply(catalog.unit[rows]))
        keep = front & (np.linalg.norm(corrected - reference, axis=1) <= self.gate_px)
        if keep.sum() < self.min_stars:
            return
        b = design(measured[keep], camera, model.order)
        self.learners[head].update(model, b, labels(measured[keep], reference[keep], camera))
        if self.fix_rotation:
            if head not in self._rotation:
                self._rotation[head] = rotation_modes(camera, model.order)
            g = self._rotation[head]
            change = (model.weights - self.start.weights).T.ravel()
            change -= g.T @ (g @ change)
            model.weights = self.start.weights + change.reshape(2, -1).T
        self.frames_learned[head] += 1


def learn_frame(corrector: LegendreCorrector, measured: np.ndarray, catalog_id: np.ndarray, camera: Camera,
                catalog: StarCatalog, head: int = 0) -> Rotation:
    """One on-orbit step without images: correct the measured positions (n, 2) px of correctly identified stars
    (``catalog_id``, HIP numbers of ``catalog``), solve the attitude from them (SVD Wahba, unweighted) and let the
    corrector learn with it, as the pipeline does.  Returns the solved attitude (inertial -> body)."""
    stars = corrector.correct(StarMeasurements(measured, catalog_id=catalog_id), head, camera)
    body = camera.mounting.inv().apply(camera.unproject(stars.xy))
    inertial = catalog.unit[np.searchsorted(catalog.hip, catalog_id)]
    attitude = Rotation.from_matrix(wahba_svd(body, inertial))
    corrector.learn(stars, head, camera, attitude, catalog)
    return attitude


def attitude_fit_residual(model: LegendreModel, distorted: np.ndarray, catalog_id: np.ndarray, camera: Camera,
                          catalog: StarCatalog) -> np.ndarray:
    """Per-axis mean |corrected - reference| (2,) px of stars at their noise-free distorted positions (n, 2) px, the
    reference projected through the attitude solved (SVD Wahba) from the corrected stars themselves: the part of the
    distortion the model leaves that no solved attitude absorbs."""
    corrected = model.correct(distorted, camera)
    inertial = catalog.unit[np.searchsorted(catalog.hip, catalog_id)]
    attitude = Rotation.from_matrix(wahba_svd(camera.mounting.inv().apply(camera.unproject(corrected)), inertial))
    fitted = camera.project(camera.inertial_to_camera(attitude).apply(inertial))[0]
    return np.abs(corrected - fitted).mean(axis=0)
