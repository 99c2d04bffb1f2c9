"""Camera heads: pinhole projection, lens distortion and the body -> camera mounting.

A head's camera frame has +Z along the boresight, +X along image columns and +Y along image rows; pixel centres sit at
integer coordinates with (0, 0) the centre of the top-left pixel.  Projection of a camera-frame direction ``(X, Y, Z)``
is the pinhole ``u = fx X/Z + cx``, ``v = fy Y/Z + cy`` (the *ideal* pixel position), followed by a distortion model
that maps ideal -> distorted (measured) pixel positions.  Each model has a closed form in one direction and is inverted
numerically (Newton) in the other, so both ``distort`` and ``undistort`` are available for every model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import legendre as npleg
from scipy.spatial.transform import Rotation

from starenv import checks


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole parameters in pixels: focal lengths ``fx, fy`` and principal point ``cx, cy``; sensor size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


class Distortion:
    """Ideal -> distorted pixel mapping.  Subclasses give a closed form for one direction; Newton gives the other."""

    def distort(self, xy: np.ndarray, k: Intrinsics) -> np.ndarray:
        """Distorted pixel positions (n, 2) of ideal pinhole positions ``xy`` (n, 2)."""
        return _newton_inverse(lambda p: self.undistort(p, k), xy)

    def undistort(self, xy: np.ndarray, k: Intrinsics) -> np.ndarray:
        """Ideal pinhole positions (n, 2) of distorted (measured) positions ``xy`` (n, 2)."""
        return _newton_inverse(lambda p: self.distort(p, k), xy)


def _central_jacobian(forward, p: np.ndarray, h: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Columns d forward / dx and d forward / dy (each (n, 2)) by central differences."""
    jx = (forward(p + [h, 0.0]) - forward(p - [h, 0.0])) / (2 * h)
    jy = (forward(p + [0.0, h]) - forward(p - [0.0, h])) / (2 * h)
    return jx, jy


def _newton_inverse(forward, target: np.ndarray, jacobian=None, tol_px: float = 1e-9, max_iter: int = 50) -> np.ndarray:
    """Solve ``forward(p) = target`` per point by Newton's method; ``jacobian(p)`` gives the columns
    (d/dx, d/dy) of forward's 2x2 Jacobian (central differences when None)."""
    target = np.asarray(target, dtype=np.float64)
    p = target.copy()
    for _ in range(max_iter):
        r = forward(p) - target
        if np.all(np.abs(r) < tol_px):
            return p
        jx, jy = jacobian(p) if jacobian is not None else _central_jacobian(forward, p)
        det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
        if np.any(np.abs(det) < 1e-12):
            break
        dx = (jy[:, 1] * r[:, 0] - jy[:, 0] * r[:, 1]) / det
        dy = (-jx[:, 1] * r[:, 0] + jx[:, 0] * r[:, 1]) / det
        p = p - np.stack([dx, dy], axis=1)
    r = np.abs(forward(p) - target)
    if not np.all(r < 1e-6):
        raise ValueError(f"distortion model is not invertible here (residual up to {np.nanmax(r):.3g} px)")
    return p


@dataclass(frozen=True)
class NoDistortion(Distortion):
    """The ideal pinhole."""

    def distort(self, xy, k):
        return np.asarray(xy, dtype=np.float64)

    def undistort(self, xy, k):
        return np.asarray(xy, dtype=np.float64)


@dataclass(frozen=True)
class BrownConrady(Distortion):
    """Brown-Conrady radial (k1, k2, k3) and decentering (p1, p2) distortion in normalised coordinates.

    Same convention as OpenCV: with ``x = (u - cx)/fx``, ``y = (v - cy)/fy`` and ``r^2 = x^2 + y^2``,
    ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)`` and
    ``y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y``.
    """

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self):
        for name in ("k1", "k2", "k3", "p1", "p2"):
            checks.finite(f"BrownConrady.{name}", getattr(self, name), shape=())

    def distort(self, xy, k):
        xy = np.asarray(xy, dtype=np.float64)
        x = (xy[:, 0] - k.cx) / k.fx
        y = (xy[:, 1] - k.cy) / k.fy
        r2 = x * x + y * y
        radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return np.stack([xd * k.fx + k.cx, yd * k.fy + k.cy], axis=1)


@dataclass(frozen=True)
class RadialXY(Distortion):
    """Paper 000's per-axis second-order radial model (its Eq. 1), in pixels.

    The closed form is the *correction* the paper applies to a measured (distorted) position ``(x_d, y_d)``:
    ``x - x0 = (x_d - x0)(1 + kx r^2)``, ``y - y0 = (y_d - y0)(1 + ky r^2)`` with ``r`` the distance of the measured
    point from the distortion centre ``(x0, y0)`` in pixels (the principal point unless given) and ``kx, ky`` in px^-2.
    The forward (ideal -> distorted) direction is its Newton inverse.
    """

    kx: float = 0.0
    ky: float = 0.0
    center: tuple[float, float] | None = None

    def __post_init__(self):
        checks.finite("RadialXY.kx", self.kx, shape=())
        checks.finite("RadialXY.ky", self.ky, shape=())
        if self.center is not None:
            checks.finite("RadialXY.center", self.center, shape=(2,))

    def undistort(self, xy, k):
        xy = np.asarray(xy, dtype=np.float64)
        x0, y0 = self._centre(k)
        dx, dy = xy[:, 0] - x0, xy[:, 1] - y0
        r2 = dx * dx + dy * dy
        return np.stack([x0 + dx * (1 + self.kx * r2), y0 + dy * (1 + self.ky * r2)], axis=1)

    def distort(self, xy, k):
        return _newton_inverse(lambda p: self.undistort(p, k), xy, lambda p: self._undistort_jacobian(p, k))

    def _centre(self, k: Intrinsics) -> tuple[float, float]:
        return self.center if self.center is not None else (k.cx, k.cy)

    def _undistort_jacobian(self, xy: np.ndarray, k: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Columns d(undistort)/dx and d(undistort)/dy, each (n, 2), in closed form."""
        x0, y0 = self._centre(k)
        dx, dy = xy[:, 0] - x0, xy[:, 1] - y0
        r2 = dx * dx + dy * dy
        cross = 2 * dx * dy
        jx = np.stack([1 + self.kx * (r2 + 2 * dx * dx), self.ky * cross], axis=1)
        jy = np.stack([self.kx * cross, 1 + self.ky * (r2 + 2 * dy * dy)], axis=1)
        return jx, jy


def legendre_mode_count(order: int) -> int:
    """Number of 2-D Legendre modes of total order <= ``order``: (n + 1)(n + 2)/2 (paper 003, Eq. 13)."""
    return (order + 1) * (order + 2) // 2


def legendre_basis(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    """Normalised 2-D Legendre modes ``b_m(x, y) = L_{l-k}(x) L_k(y)`` on [-1, 1]^2, shape (n, n_modes).

    Mode index ``m = l(l + 1)/2 + k`` for ``0 <= k <= l <= order`` (paper 003, Eqs. 16-17), with
    ``L_n = P_n sqrt((2n + 1)/2)`` (Eqs. 14-15).
    """
    eye = np.eye(order + 1)
    norm = np.sqrt((2 * np.arange(order + 1) + 1) / 2.0)
    lx = npleg.legval(np.asarray(x, dtype=np.float64), eye.T * norm[:, None]).T  # (n, order + 1): L_0..L_order
    ly = npleg.legval(np.asarray(y, dtype=np.float64), eye.T * norm[:, None]).T
    cols = [lx[:, total - k] * ly[:, k] for total in range(order + 1) for k in range(total + 1)]
    return np.stack(cols, axis=1)


@dataclass(frozen=True)
class LegendreField(Distortion):
    """Paper 003's 2-D Legendre distortion field (its Eq. 18): ``p_d = p + sum_m w_m b_m(p_n)``.

    ``p_n`` is the ideal pixel position mapped to [-1, 1]^2 over the sensor (pixel edges -0.5 and W - 0.5 map to -1
    and +1); ``coeffs_x``, ``coeffs_y`` hold one weight per mode in pixels, ordered as :func:`legendre_basis`.
    """

    coeffs_x: tuple[float, ...] = ()
    coeffs_y: tuple[float, ...] = ()
    order: int = field(init=False)

    def __post_init__(self):
        cx = checks.finite("LegendreField.coeffs_x", self.coeffs_x)
        cy = checks.finite("LegendreField.coeffs_y", self.coeffs_y)
        n = cx.size
        order = int(round((math.sqrt(8 * n + 1) - 3) / 2)) if n else 0
        if n == 0 or legendre_mode_count(order) != n or cy.size != n:
            raise ValueError(
                "LegendreField.coeffs_x and coeffs_y must each hold (n+1)(n+2)/2 weights for a total order n "
                f"(1, 3, 6, 10, 15, 21, ...), got {cx.size} and {cy.size}"
            )
        object.__setattr__(self, "order", order)

    def distort(self, xy, k):
        xy = np.asarray(xy, dtype=np.float64)
        xn = (xy[:, 0] + 0.5) * (2.0 / k.width) - 1.0
        yn = (xy[:, 1] + 0.5) * (2.0 / k.height) - 1.0
        b = legendre_basis(xn, yn, self.order)
        return xy + np.stack([b @ np.asarray(self.coeffs_x), b @ np.asarray(self.coeffs_y)], axis=1)


class FocalPlaneField(Distortion):
    """Paper 003's distortion types on the focal plane normalised by the paper's rule: ``x = (u - cx)/s``,
    ``y = (v - cy)/s`` with ``s`` = half the sensor width in px (1024 for its 2048 px sensor), so the sensor spans
    about [-1, 1]^2.  A subclass gives the normalised offset ``(dx, dy)`` of an ideal point; the distorted position
    is ``u + s dx, v + s dy`` (true -> measured, the paper's Eq. 3).  Coefficients are dimensionless (normalised)."""

    def offset(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def distort(self, xy, k):
        xy = np.asarray(xy, dtype=np.float64)
        s = k.width / 2.0
        dx, dy = self.offset((xy[:, 0] - k.cx) / s, (xy[:, 1] - k.cy) / s)
        return xy + s * np.stack([dx, dy], axis=1)


def _coefficients(owner: object, *names: str) -> None:
    for name in names:
        checks.finite(f"{type(owner).__name__}.{name}", getattr(owner, name), shape=())


@dataclass(frozen=True)
class Radial(FocalPlaneField):
    """Radial distortion (paper 003, Eq. 4 with n = 2): ``dx = x (q1 r^2 + q2 r^4)``, ``dy = y (q1 r^2 + q2 r^4)``;
    barrel for negative, pincushion for positive coefficients."""

    q1: float = 0.0
    q2: float = 0.0

    def __post_init__(self):
        _coefficients(self, "q1", "q2")

    def offset(self, x, y):
        r2 = x * x + y * y
        f = r2 * (self.q1 + self.q2 * r2)
        return x * f, y * f


@dataclass(frozen=True)
class Tangential(FocalPlaneField):
    """Tangential (decentering) distortion (paper 003, Eq. 5): ``dx = p1 (3x^2 + y^2) + 2 p2 x y``,
    ``dy = 2 p1 x y + p2 (x^2 + 3y^2)``."""

    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self):
        _coefficients(self, "p1", "p2")

    def offset(self, x, y):
        return (self.p1 * (3 * x * x + y * y) + 2 * self.p2 * x * y,
                2 * self.p1 * x * y + self.p2 * (x * x + 3 * y * y))


@dataclass(frozen=True)
class ThinPrism(FocalPlaneField):
    """Thin-prism distortion (paper 003, Eq. 6): ``dx = s1 (x^2 + y^2)``, ``dy = s2 (x^2 + y^2)``."""

    s1: float = 0.0
    s2: float = 0.0

    def __post_init__(self):
        _coefficients(self, "s1", "s2")

    def offset(self, x, y):
        r2 = x * x + y * y
        return self.s1 * r2, self.s2 * r2


@dataclass(frozen=True)
class Shear(FocalPlaneField):
    """Shear of the image plane: ``x' = x + tan(phi_x) y``, ``y' = y + tan(phi_y) x`` (angles in rad).

    Paper 003's Eq. 7 reads as a diagonal (scaling) matrix in its text, which is no shear; this is the off-diagonal
    form its name and Fig. 2 describe."""

    phi_x: float = 0.0
    phi_y: float = 0.0

    def __post_init__(self):
        _coefficients(self, "phi_x", "phi_y")
        if max(abs(self.phi_x), abs(self.phi_y)) >= math.pi / 4:
            raise ValueError(f"Shear.phi_x and phi_y must be below 45 deg, got {self.phi_x!r}, {self.phi_y!r} rad")

    def offset(self, x, y):
        return math.tan(self.phi_x) * y, math.tan(self.phi_y) * x


@dataclass(frozen=True)
class Perspective(FocalPlaneField):
    """Perspective (homography) of the normalised image plane (paper 003, Eqs. 8-9):
    ``x' = (h11 x + h12 y + h13)/w``, ``y' = (h21 x + h22 y + h23)/w``, ``w = h31 x + h32 y + 1``; ``h`` holds
    (h11, h12, h13, h21, h22, h23, h31, h32)."""

    h: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

    def __post_init__(self):
        h = checks.finite("Perspective.h", self.h, shape=(8,))
        object.__setattr__(self, "h", tuple(float(v) for v in h))
        if abs(h[6]) + abs(h[7]) >= 0.5:
            raise ValueError(f"Perspective.h31, h32 must keep w = h31 x + h32 y + 1 away from 0 on [-1, 1]^2, "
                             f"got {float(h[6])!r}, {float(h[7])!r}")

    def offset(self, x, y):
        h11, h12, h13, h21, h22, h23, h31, h32 = self.h
        w = h31 * x + h32 * y + 1.0
        return (h11 * x + h12 * y + h13) / w - x, (h21 * x + h22 * y + h23) / w - y


@dataclass(frozen=True)
class Composite(Distortion):
    """Distortion models applied in turn (ideal -> the first model -> the second ...); for the small fields of a
    star sensor this is the superposition of their offsets to first order."""

    models: tuple[Distortion, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "models", tuple(self.models))
        if not self.models or not all(isinstance(m, Distortion) for m in self.models):
            raise ValueError("Composite.models must be a non-empty sequence of Distortion models")

    def distort(self, xy, k):
        out = np.asarray(xy, dtype=np.float64)
        for model in self.models:
            out = model.distort(out, k)
        return out


# Paper 003's six types with its Table 3 / Table 4 forms, scaled to the magnitudes its text states (the table values'
# units are not given and reproduce them in no single unit): about 2 px at the edge of the image for the optical
# types, about 3 px at most for the image transformations.  Signs: barrel negative, pincushion positive; the ratios
# p2/p1 ~ 2.0 and s2/s1 ~ 1.3 follow Table 3, phi_y/phi_x ~ 1/45 Table 4, and the homography is Table 4's as given
# (applied to normalised coordinates, where it peaks at 3.6 px in a corner).
DISTORTION_PRESETS: dict[str, FocalPlaneField] = {
    "barrel": Radial(q1=-1.6e-3, q2=-0.35e-3),
    "pincushion": Radial(q1=1.6e-3, q2=0.35e-3),
    "tangential": Tangential(p1=0.4e-3, p2=0.8e-3),
    "thin_prism": ThinPrism(s1=1.2e-3, s2=1.55e-3),
    "shear": Shear(phi_x=math.atan(2.9e-3), phi_y=math.atan(2.9e-3 / 45.7)),
    "perspective": Perspective((0.999, 0.000625, 0.0005, 0.0, 0.999248, 0.0010, 0.0, 0.001250)),
}


# The camera fields' valid ranges (low, high, whether low itself is excluded; integers where the bounds are), in the
# units of their names: written once, checked by Camera, the renderer and scenario files (in the files' units).
CAMERA_RANGES: dict[str, tuple[float, float, bool]] = {
    "width": (8, 16384, False),
    "height": (8, 16384, False),
    "pixel_pitch_m": (0.0, 1e-3, True),
    "focal_length_m": (0.0, 2.0, True),
    "aperture_m": (0.0, 1.0, True),
    "f_number": (0.5, 32.0, False),
    "psf_sigma_px": (0.1, 20.0, False),
}


def check_camera_field(name: str, value, unit: str = "") -> float:
    """``value`` checked against :data:`CAMERA_RANGES` ``[name]``."""
    low, high, low_open = CAMERA_RANGES[name]
    if isinstance(low, int):
        return checks.integer(name, value, low, int(high))
    return checks.in_range(name, value, low, high, low_open=low_open, unit=unit)


# Spread of the sub-points that draw a spot's radial elongation (FieldSpot), in its sigmas either side.
SPOT_SPAN_SIGMA = 3.0


@dataclass(frozen=True)
class SpotShape:
    """A spot at given field positions: the light's centroid ``offset`` (n, 2) px from the geometric image, the
    isotropic ``sigma`` (n,) px, the extra ``radial_sigma`` (n,) px along the unit ``radial`` direction (n, 2) (away
    from the principal point); covariance ``sigma^2 I + radial_sigma^2 radial radial^T``."""

    offset: np.ndarray
    sigma: np.ndarray
    radial_sigma: np.ndarray
    radial: np.ndarray

    def subset(self, index: np.ndarray) -> SpotShape:
        """The spots at ``index``."""
        return SpotShape(self.offset[index], self.sigma[index], self.radial_sigma[index], self.radial[index])

    def covariance(self) -> np.ndarray:
        """Covariance (n, 2, 2) px^2 of each spot."""
        outer = self.radial[:, :, None] * self.radial[:, None, :]
        return (self.sigma**2)[:, None, None] * np.eye(2) + (self.radial_sigma**2)[:, None, None] * outer


@dataclass(frozen=True)
class FieldSpot:
    """A Gaussian spot that changes across the field with the field dependence of the Seidel aberrations.

    With ``h`` the distance of an image point from the principal point over the field radius (the farthest sensor
    corner, so ``h = 1`` there) and ``r`` the unit vector away from the principal point, each term a standard
    deviation (px) at the corner, added in quadrature to the camera's ``psf_sigma_px``:

    * ``defocus_sigma_px``: isotropic, the same everywhere (a focus error);
    * ``field_curvature_sigma_px``: isotropic, growing as ``h^2`` (the focal surface curving off the sensor);
    * ``astigmatism_sigma_px``: along ``r`` only, growing as ``h^2`` (the sensor at the sagittal focus);
    * ``coma_px``: third-order coma of a uniformly lit circular pupil, ray error ``C h rho^2 (2 + cos 2t, sin 2t)``
      (along ``r`` and across it) with ``C = coma_px``: its mean over the pupil moves the light's centroid by
      ``C h`` along ``r``, and its variances are ``C^2 h^2 / 2`` along ``r`` and ``C^2 h^2 / 6`` across.

    Covariance ``(s0^2 + d^2 + f^2 h^4 + C^2 h^2 / 6) I + (a^2 h^4 + C^2 h^2 / 3) r r^T`` (:meth:`shape`).
    """

    defocus_sigma_px: float = 0.0
    field_curvature_sigma_px: float = 0.0
    astigmatism_sigma_px: float = 0.0
    coma_px: float = 0.0

    def __post_init__(self):
        for name in ("defocus_sigma_px", "field_curvature_sigma_px", "astigmatism_sigma_px"):
            checks.in_range(f"spot.{name}", getattr(self, name), 0.0, 20.0, unit="px")
        checks.in_range("spot.coma_px", self.coma_px, -20.0, 20.0, unit="px")

    @staticmethod
    def field_radius_px(k: Intrinsics) -> float:
        """Distance (px) from the principal point to the farthest sensor corner: ``h = 1`` there."""
        return math.hypot(max(k.cx + 0.5, k.width - 0.5 - k.cx), max(k.cy + 0.5, k.height - 0.5 - k.cy))

    def shape(self, xy: np.ndarray, k: Intrinsics, psf_sigma_px: float) -> SpotShape:
        """The spot at pixel positions ``xy`` (n, 2) of a camera with intrinsics ``k`` whose on-axis sigma is
        ``psf_sigma_px`` (px)."""
        d = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - [k.cx, k.cy]
        dist = np.hypot(d[:, 0], d[:, 1])
        h = dist / self.field_radius_px(k)
        radial = np.where(dist[:, None] > 0, d / np.where(dist > 0, dist, 1.0)[:, None], [1.0, 0.0])
        c2h2 = (self.coma_px * h) ** 2
        sigma2 = psf_sigma_px**2 + self.defocus_sigma_px**2 + (self.field_curvature_sigma_px * h * h) ** 2 + c2h2 / 6
        radial2 = (self.astigmatism_sigma_px * h * h) ** 2 + c2h2 / 3
        return SpotShape((self.coma_px * h)[:, None] * radial, np.sqrt(sigma2), np.sqrt(radial2), radial)

    def reach_px(self, k: Intrinsics, psf_sigma_px: float) -> tuple[float, float]:
        """The largest isotropic sigma and the farthest a spot's light reaches beyond its sigma's band (radial spread
        and centroid offset), px, over the sensor (both grow with ``h``: their values at the farthest corner)."""
        corner = np.array([[k.cx + self.field_radius_px(k), k.cy]])
        s = self.shape(corner, k, psf_sigma_px)
        return float(s.sigma[0]), float(SPOT_SPAN_SIGMA * 1.02 * s.radial_sigma[0] + abs(self.coma_px))


@dataclass(frozen=True)
class Camera:
    """One camera head: resolution, pinhole intrinsics (px), distortion and the body -> camera mounting rotation.

    ``pixel_pitch_m`` and ``focal_length_m`` are the physical values (``fx = focal_length_m / pixel_pitch_m``);
    ``aperture_m`` is the entrance-pupil diameter used for photometry; ``psf_sigma_px`` the Gaussian sigma of a still
    star's spot (px), part of a sensor's calibration (detectors and deblurrers default to it); ``spot`` a spot that
    changes across the field on top of it (None: the same Gaussian everywhere).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    pixel_pitch_m: float
    aperture_m: float
    distortion: Distortion = NoDistortion()
    mounting: Rotation = field(default_factory=Rotation.identity)
    psf_sigma_px: float = 1.0
    spot: FieldSpot | None = None

    def __post_init__(self):
        check_camera_field("width", self.width)
        check_camera_field("height", self.height)
        checks.positive("fx", self.fx, "px")
        checks.positive("fy", self.fy, "px")
        checks.in_range("cx", self.cx, -0.5, self.width - 0.5, unit="px")
        checks.in_range("cy", self.cy, -0.5, self.height - 0.5, unit="px")
        check_camera_field("pixel_pitch_m", self.pixel_pitch_m, "m")
        check_camera_field("aperture_m", self.aperture_m, "m")
        check_camera_field("psf_sigma_px", self.psf_sigma_px, "px")
        if not isinstance(self.mounting, Rotation) or not self.mounting.single:
            raise ValueError("mounting must be a single scipy Rotation (body -> camera)")
        checks.finite("mounting", self.mounting.as_quat(), shape=(4,))
        if self.spot is not None and not isinstance(self.spot, FieldSpot):
            raise ValueError(f"spot must be a FieldSpot or None, got {type(self.spot).__name__}")
        if not isinstance(self.distortion, Distortion):
            raise ValueError(f"distortion must be a Distortion model, got {type(self.distortion).__name__}")
        fov_x, fov_y = self.fov
        if max(fov_x, fov_y) >= math.pi * 0.999:
            raise ValueError(f"field of view must be below 180 deg, got {math.degrees(max(fov_x, fov_y)):.1f} deg")

    @classmethod
    def from_focal_length(
        cls,
        focal_length_m: float,
        pixel_pitch_m: float,
        width: int,
        height: int,
        f_number: float = 1.4,
        **kwargs,
    ) -> Camera:
        """A head from physical focal length and pixel pitch (m), principal point at the sensor centre."""
        f = check_camera_field("focal_length_m", focal_length_m, "m")
        pitch = check_camera_field("pixel_pitch_m", pixel_pitch_m, "m")
        n = check_camera_field("f_number", f_number)
        fpx = f / pitch
        kwargs.setdefault("cx", (width - 1) / 2.0)
        kwargs.setdefault("cy", (height - 1) / 2.0)
        return cls(width=width, height=height, fx=fpx, fy=fpx, pixel_pitch_m=pitch, aperture_m=f / n, **kwargs)

    @classmethod
    def from_fov(
        cls,
        fov_deg: float,
        width: int,
        height: int,
        pixel_pitch_m: float,
        f_number: float = 1.4,
        **kwargs,
    ) -> Camera:
        """A head whose full horizontal field of view (edge to edge of the sensor) is ``fov_deg`` degrees."""
        fov = checks.in_range("fov_deg", fov_deg, 0.0, 180.0, low_open=True, high_open=True, unit="deg")
        check_camera_field("width", width)
        check_camera_field("pixel_pitch_m", pixel_pitch_m, "m")
        fpx = (width / 2.0) / math.tan(math.radians(fov) / 2.0)
        return cls.from_focal_length(fpx * pixel_pitch_m, pixel_pitch_m, width, height, f_number, **kwargs)

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def spot_shape(self, xy: np.ndarray) -> SpotShape:
        """The spot at pixel positions ``xy`` (n, 2): :attr:`spot`'s, else ``psf_sigma_px`` everywhere."""
        if self.spot is not None:
            return self.spot.shape(xy, self.intrinsics, self.psf_sigma_px)
        n = len(np.asarray(xy).reshape(-1, 2))
        return SpotShape(np.zeros((n, 2)), np.full(n, self.psf_sigma_px), np.zeros(n), np.tile([1.0, 0.0], (n, 1)))

    @property
    def focal_length_m(self) -> float:
        return self.fx * self.pixel_pitch_m

    @property
    def fov(self) -> tuple[float, float]:
        """Full field of view (rad) across columns and rows, edge to edge of the sensor, ideal pinhole."""
        fx = math.atan((self.cx + 0.5) / self.fx) + math.atan((self.width - 0.5 - self.cx) / self.fx)
        fy = math.atan((self.cy + 0.5) / self.fy) + math.atan((self.height - 0.5 - self.cy) / self.fy)
        return fx, fy

    @property
    def half_diagonal(self) -> float:
        """Largest angle (rad) between the boresight and any sensor corner, ideal pinhole."""
        dx = max(self.cx + 0.5, self.width - 0.5 - self.cx) / self.fx
        dy = max(self.cy + 0.5, self.height - 0.5 - self.cy) / self.fy
        return math.atan(math.hypot(dx, dy))

    def project(self, v_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted pixel positions (n, 2) of camera-frame directions (n, 3), and a mask of those in front (Z > 0).

        Directions behind the camera get NaN positions.
        """
        v = np.asarray(v_cam, dtype=np.float64).reshape(-1, 3)
        front = v[:, 2] > 1e-12
        z = np.where(front, v[:, 2], np.nan)
        ideal = np.stack([self.fx * v[:, 0] / z + self.cx, self.fy * v[:, 1] / z + self.cy], axis=1)
        if np.all(front):
            return self.distortion.distort(ideal, self.intrinsics), front
        out = np.full_like(ideal, np.nan)
        if np.any(front):
            out[front] = self.distortion.distort(ideal[front], self.intrinsics)
        return out, front

    def unproject(self, xy: np.ndarray) -> np.ndarray:
        """Camera-frame unit directions (n, 3) of distorted pixel positions (n, 2)."""
        ideal = self.distortion.undistort(np.asarray(xy, dtype=np.float64).reshape(-1, 2), self.intrinsics)
        v = np.stack([(ideal[:, 0] - self.cx) / self.fx, (ideal[:, 1] - self.cy) / self.fy, np.ones(len(ideal))], 1)
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def inertial_to_camera(self, attitude: Rotation) -> Rotation:
        """Inertial -> camera rotation(s) of this head for body attitude(s) ``attitude`` (inertial -> body)."""
        return self.mounting * attitude

    def in_frame(self, xy: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Mask of pixel positions that fall on the sensor (pixel edges at -0.5 and size - 0.5), grown by a margin."""
        xy = np.asarray(xy, dtype=np.float64)
        lo = -0.5 - margin_px
        return (
            (xy[..., 0] >= lo)
            & (xy[..., 0] <= self.width - 0.5 + margin_px)
            & (xy[..., 1] >= lo)
            & (xy[..., 1] <= self.height - 0.5 + margin_px)
        )
