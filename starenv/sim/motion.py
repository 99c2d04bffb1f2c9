"""Spacecraft attitude motion profiles.

A :class:`Motion` is relative: the attitude (inertial -> body, see :mod:`starenv.sim.conventions`) is
``A(t) = delta(t) * A0``, with ``delta(0) = identity`` for every profile except an :class:`Oscillation` whose angles are
non-zero at t = 0 (it oscillates about ``A0``).  Kinematics ``dA/dt = -[w x] A`` is left-multiplicative, so the body
rate ``w`` (rad/s, body frame) does not depend on ``A0``.  Every method accepts a time in seconds, either a float
(giving a single rotation / a (3,) rate) or a 1-D array of n times (giving n rotations / an (n, 3) array).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.integrate import OdeSolution, solve_ivp
from scipy.spatial.transform import Rotation

from starenv import checks

MU_EARTH = 3.986004418e14  # m^3/s^2
R_EARTH = 6378137.0  # m, WGS-84 equatorial radius


def _times(t) -> tuple[np.ndarray, bool]:
    """Times as a 1-D float array, and whether the caller passed a scalar."""
    arr = checks.finite("t", t)
    if arr.ndim > 1:
        raise ValueError(f"t must be a scalar or a 1-D array of seconds, got shape {arr.shape}")
    return np.atleast_1d(arr), arr.ndim == 0


def _interval(t0, t1) -> tuple[float, float]:
    lo = checks.in_range("t0", t0, unit="s")
    hi = checks.in_range("t1", t1, lo, unit="s")
    return lo, hi


def _vec3(name: str, value) -> np.ndarray:
    return checks.finite(name, value, shape=(3,)).copy()


def _rotation_out(rot: Rotation, scalar: bool) -> Rotation:
    return rot[0] if scalar else rot


def _vector_out(vectors: np.ndarray, scalar: bool) -> np.ndarray:
    return vectors[0] if scalar else vectors


class Motion(ABC):
    """Relative attitude motion: ``delta(t)`` (normally identity at t = 0) and body rate ``w(t)`` (rad/s, body)."""

    @abstractmethod
    def delta(self, t) -> Rotation:
        """Rotation ``delta(t)`` with ``A(t) = delta(t) * A(0)``; t in seconds (float or (n,) array)."""

    @abstractmethod
    def body_rate(self, t) -> np.ndarray:
        """Body angular rate (rad/s, body frame), shape (3,) or (n, 3)."""

    @abstractmethod
    def max_rate(self, t0, t1) -> float:
        """Upper bound of ``|w|`` (rad/s) over ``[t0, t1]`` seconds."""


@dataclass
class Trajectory:
    """Absolute attitude: ``motion`` applied to ``initial``, the inertial -> body rotation at t = 0."""

    motion: Motion
    initial: Rotation

    def __post_init__(self):
        if not isinstance(self.motion, Motion):
            raise ValueError(f"motion must be a Motion, got {type(self.motion).__name__}")
        if not isinstance(self.initial, Rotation) or not self.initial.single:
            raise ValueError("initial must be a single scipy Rotation (inertial -> body at t = 0)")

    def attitude(self, t) -> Rotation:
        """Inertial -> body rotation at time(s) t (s)."""
        return self.motion.delta(t) * self.initial

    def body_rate(self, t) -> np.ndarray:
        """Body angular rate (rad/s, body frame) at time(s) t (s)."""
        return self.motion.body_rate(t)

    @property
    def orbit(self) -> LeoNadir | None:
        """The orbit the spacecraft flies (a :class:`LeoNadir` motion, with or without superposed jitter), or None:
        then the observer is taken at the geocentre."""
        motion = self.motion
        while isinstance(motion, Superposed):
            motion = motion.base
        return motion if isinstance(motion, LeoNadir) else None


class ConstantRate(Motion):
    """Constant body rate ``rate`` (3,) rad/s in the body frame: ``delta(t) = Rotation.from_rotvec(-rate * t)``."""

    def __init__(self, rate):
        self.rate = _vec3("rate", rate)

    def delta(self, t) -> Rotation:
        ts, scalar = _times(t)
        return _rotation_out(Rotation.from_rotvec(-np.outer(ts, self.rate)), scalar)

    def body_rate(self, t) -> np.ndarray:
        ts, scalar = _times(t)
        return _vector_out(np.tile(self.rate, (ts.size, 1)), scalar)

    def max_rate(self, t0, t1) -> float:
        _interval(t0, t1)
        return float(np.linalg.norm(self.rate))


class Slew(Motion):
    """Rest-to-rest eigen-axis slew by ``angle`` (rad) about the body-fixed ``axis``, starting at ``start`` (s).

    The rate profile is trapezoidal, or triangular when ``max_rate`` (rad/s) is not reached, with acceleration
    ``max_accel`` (rad/s^2): ``delta(t) = Rotation.from_rotvec(-axis * theta(t))``.  The attitude holds before
    ``start`` and after the end.  ``duration`` is the time (s) at which the slew is complete, ``start`` included.
    """

    def __init__(self, axis, angle, max_rate, max_accel, start=0.0):
        axis = _vec3("axis", axis)
        norm = np.linalg.norm(axis)
        if norm == 0.0:
            raise ValueError("axis must be a non-zero 3-vector")
        self.axis = axis / norm
        self.angle = checks.in_range("angle", angle, unit="rad")
        self.rate_limit = checks.positive("max_rate", max_rate, unit="rad/s")
        self.accel_limit = checks.positive("max_accel", max_accel, unit="rad/s^2")
        self.start = checks.in_range("start", start, unit="s")
        magnitude = abs(self.angle)
        self._sign = 1.0 if self.angle >= 0.0 else -1.0
        if magnitude == 0.0:
            self.peak_rate, accel_time, cruise_time = 0.0, 0.0, 0.0
        elif magnitude >= self.rate_limit**2 / self.accel_limit:  # trapezoid
            self.peak_rate = self.rate_limit
            accel_time = self.peak_rate / self.accel_limit
            cruise_time = magnitude / self.peak_rate - accel_time
        else:  # triangle
            self.peak_rate = float(np.sqrt(magnitude * self.accel_limit))
            accel_time = self.peak_rate / self.accel_limit
            cruise_time = 0.0
        self._accel_time = accel_time
        self._cruise_time = cruise_time
        self._length = 2.0 * accel_time + cruise_time

    @classmethod
    def between(cls, a0: Rotation, a1: Rotation, max_rate, max_accel, start=0.0) -> Slew:
        """Slew taking attitude ``a0`` to ``a1`` (inertial -> body): ``delta(end) * a0 == a1``."""
        for name, rot in (("a0", a0), ("a1", a1)):
            if not isinstance(rot, Rotation) or not rot.single:
                raise ValueError(f"{name} must be a single scipy Rotation")
        rotvec = (a1 * a0.inv()).as_rotvec()
        angle = float(np.linalg.norm(rotvec))
        axis = -rotvec / angle if angle > 0.0 else np.array([0.0, 0.0, 1.0])
        return cls(axis, angle, max_rate, max_accel, start)

    @property
    def duration(self) -> float:
        """Time (s) at which the slew is complete: ``start`` plus the manoeuvre length."""
        return self.start + self._length

    @property
    def phase_times(self) -> tuple[float, float, float, float]:
        """Times (s) of: start, end of acceleration, start of deceleration, end."""
        t_accel_end = self.start + self._accel_time
        return self.start, t_accel_end, t_accel_end + self._cruise_time, self.duration

    def _profile(self, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed slew angle theta (rad) and its rate (rad/s) at times ts."""
        tau = np.clip(ts - self.start, 0.0, self._length)
        ta, tc = self._accel_time, self._cruise_time
        to_go = self._length - tau
        accel = self.accel_limit
        cruising = 0.5 * accel * ta**2 + self.peak_rate * (tau - ta)
        braking = abs(self.angle) - 0.5 * accel * to_go**2
        theta = np.where(tau < ta, 0.5 * accel * tau**2, np.where(tau < ta + tc, cruising, braking))
        rate = np.where(tau < ta, accel * tau, np.where(tau < ta + tc, self.peak_rate, accel * to_go))
        return self._sign * theta, self._sign * rate

    def delta(self, t) -> Rotation:
        ts, scalar = _times(t)
        theta, _ = self._profile(ts)
        return _rotation_out(Rotation.from_rotvec(-np.outer(theta, self.axis)), scalar)

    def body_rate(self, t) -> np.ndarray:
        ts, scalar = _times(t)
        _, rate = self._profile(ts)
        return _vector_out(np.outer(rate, self.axis), scalar)

    def max_rate(self, t0, t1) -> float:
        lo, hi = _interval(t0, t1)
        # |theta'| rises, plateaus, then falls: its maximum over [lo, hi] is at the peak time clipped into it.
        t_peak = np.clip(self.start + self._accel_time, lo, hi)
        return float(abs(self._profile(np.array([t_peak]))[1][0]))


def _inertia_tensor(inertia) -> np.ndarray:
    tensor = checks.finite("inertia", inertia, shape=(3, 3))
    scale = np.max(np.abs(tensor))
    if not np.allclose(tensor, tensor.T, rtol=0.0, atol=1e-9 * scale):
        raise ValueError("inertia must be a symmetric 3x3 matrix (kg m^2)")
    tensor = 0.5 * (tensor + tensor.T)
    moments = np.linalg.eigvalsh(tensor)
    if moments[0] <= 0.0:
        raise ValueError(f"inertia must be positive definite, got principal moments {moments} kg m^2")
    if moments[2] > (moments[0] + moments[1]) * (1.0 + 1e-12):
        raise ValueError(f"inertia principal moments must satisfy the triangle inequality, got {moments} kg m^2")
    return tensor


class TorqueFree(Motion):
    """Torque-free rigid body with inertia tensor ``inertia`` (3x3, kg m^2, body frame) and body rate ``rate0``
    (rad/s) at t = 0.

    Euler's equations ``I w' = -w x (I w)`` and the quaternion kinematics of ``delta`` are integrated with DOP853,
    extended in chunks as later times are requested; only t >= 0 is defined.
    """

    _CHUNK_S = 100.0

    def __init__(self, inertia, rate0):
        self.inertia = _inertia_tensor(inertia)
        self.rate0 = _vec3("rate0", rate0)
        self._inertia_inv = np.linalg.inv(self.inertia)
        self._ts = np.array([0.0])
        self._interpolants: list = []
        self._solution: OdeSolution | None = None
        self._state_end = np.concatenate([self.rate0, [0.0, 0.0, 0.0, 1.0]])
        moment_min = np.linalg.eigvalsh(self.inertia)[0]
        momentum = np.linalg.norm(self.inertia @ self.rate0)
        energy2 = self.rate0 @ self.inertia @ self.rate0
        # Conserved |h| and 2E bound |w|: |h| >= I_min |w| and 2E >= I_min |w|^2.
        self._rate_bound = float(min(momentum / moment_min, np.sqrt(energy2 / moment_min)))

    def _derivative(self, _t, state):
        wx, wy, wz, qx, qy, qz, qw = state
        w = state[:3]
        hx, hy, hz = self.inertia @ w
        w_dot = self._inertia_inv @ np.array([hy * wz - hz * wy, hz * wx - hx * wz, hx * wy - hy * wx])
        # dq/dt = -0.5 [w; 0] (x) q (Hamilton product, scalar-last), from dA/dt = -[w x] A.
        return np.array(
            [
                w_dot[0],
                w_dot[1],
                w_dot[2],
                -0.5 * (qw * wx + wy * qz - wz * qy),
                -0.5 * (qw * wy + wz * qx - wx * qz),
                -0.5 * (qw * wz + wx * qy - wy * qx),
                0.5 * (wx * qx + wy * qy + wz * qz),
            ]
        )

    def _extend(self, t_max: float) -> None:
        t_end = self._ts[-1]
        if self._solution is not None and t_max <= t_end:
            return
        new_end = max(t_max, t_end + self._CHUNK_S)
        sol = solve_ivp(
            self._derivative,
            (t_end, new_end),
            self._state_end,
            method="DOP853",
            rtol=1e-12,
            atol=1e-14,
            dense_output=True,
        )
        if not sol.success:
            raise RuntimeError(f"torque-free integration failed: {sol.message}")
        self._ts = np.concatenate([self._ts, sol.sol.ts[1:]])
        self._interpolants.extend(sol.sol.interpolants)
        self._solution = OdeSolution(self._ts, self._interpolants)
        state = sol.y[:, -1].copy()
        state[3:] /= np.linalg.norm(state[3:])
        self._state_end = state

    def _states(self, t) -> tuple[np.ndarray, bool]:
        ts, scalar = _times(t)
        if ts.size == 0:
            return np.empty((0, 7)), scalar
        if ts.min() < 0.0:
            raise ValueError(f"t must be >= 0 s for TorqueFree, got {ts.min():g}")
        self._extend(float(ts.max()))
        return self._solution(ts).T.reshape(ts.size, 7), scalar

    def delta(self, t) -> Rotation:
        states, scalar = self._states(t)
        return _rotation_out(Rotation.from_quat(states[:, 3:]), scalar)

    def body_rate(self, t) -> np.ndarray:
        states, scalar = self._states(t)
        return _vector_out(states[:, :3].copy(), scalar)

    def max_rate(self, t0, t1) -> float:
        _interval(t0, t1)
        return self._rate_bound


def _right_jacobian_apply(phi: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``J_r(phi) v`` for stacks (n, 3): ``v - (1 - cos a)/a^2 phi x v + (a - sin a)/a^3 phi x (phi x v)``."""
    a = np.linalg.norm(phi, axis=-1)
    small = a < 1e-2
    a_safe = np.where(small, 1.0, a)
    a2 = a**2
    c1 = np.where(small, 0.5 - a2 / 24.0 + a2**2 / 720.0, 2.0 * np.sin(0.5 * a_safe) ** 2 / a_safe**2)
    c2 = np.where(small, 1.0 / 6.0 - a2 / 120.0 + a2**2 / 5040.0, (a_safe - np.sin(a_safe)) / a_safe**3)
    phi_x_v = np.cross(phi, v)
    return v - c1[:, None] * phi_x_v + c2[:, None] * np.cross(phi, phi_x_v)


class Oscillation(Motion):
    """Coning / jitter: ``delta(t) = Rotation.from_rotvec(-phi(t))`` with, per body axis k,
    ``phi_k(t) = amplitude_k sin(2 pi frequency_k t + phase_k)``; amplitude in rad, frequency in Hz, phase in rad.

    The body rate is exact: ``w = J_r(phi) phi'`` with ``J_r`` the SO(3) right Jacobian.  The motion is centred on
    the initial attitude, so ``delta(0) = Rotation.from_rotvec(-phi(0))`` is not the identity when ``phi(0) != 0``.
    """

    def __init__(self, amplitude, frequency, phase=(0.0, 0.0, 0.0)):
        self.amplitude = _vec3("amplitude", amplitude)
        if np.any(self.amplitude < 0.0):
            raise ValueError(f"amplitude must be >= 0 rad on every axis, got {self.amplitude}")
        self.frequency = _vec3("frequency", frequency)
        if np.any(self.frequency < 0.0):
            raise ValueError(f"frequency must be >= 0 Hz on every axis, got {self.frequency}")
        self.phase = _vec3("phase", phase)

    @classmethod
    def coning(cls, half_angle, frequency) -> Oscillation:
        """Body z axis circling a cone of ``half_angle`` (rad) at ``frequency`` (Hz)."""
        a = checks.in_range("half_angle", half_angle, 0.0, np.pi, high_open=True, unit="rad")
        f = checks.non_negative("frequency", frequency, unit="Hz")
        return cls((a, a, 0.0), (f, f, 0.0), (np.pi / 2, 0.0, 0.0))

    def _angles(self, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        omega = 2.0 * np.pi * self.frequency
        arg = np.outer(ts, omega) + self.phase
        return self.amplitude * np.sin(arg), self.amplitude * omega * np.cos(arg)

    def delta(self, t) -> Rotation:
        ts, scalar = _times(t)
        phi, _ = self._angles(ts)
        return _rotation_out(Rotation.from_rotvec(-phi), scalar)

    def body_rate(self, t) -> np.ndarray:
        ts, scalar = _times(t)
        phi, phi_dot = self._angles(ts)
        return _vector_out(_right_jacobian_apply(phi, phi_dot), scalar)

    def max_rate(self, t0, t1) -> float:
        _interval(t0, t1)
        # ||J_r|| <= 1, so |w| <= |phi'| <= the norm of the per-axis peak rates.
        return float(np.linalg.norm(2.0 * np.pi * self.frequency * self.amplitude))


class Superposed(Motion):
    """``perturbation`` (e.g. jitter) on top of ``base`` (e.g. pointing): ``delta = delta_p(t) * delta_b(t)``.

    Body rate (rad/s, body frame): ``w = w_p + delta_p(t).apply(w_b)``.
    """

    def __init__(self, base: Motion, perturbation: Motion):
        for name, motion in (("base", base), ("perturbation", perturbation)):
            if not isinstance(motion, Motion):
                raise ValueError(f"{name} must be a Motion, got {type(motion).__name__}")
        self.base = base
        self.perturbation = perturbation

    def delta(self, t) -> Rotation:
        return self.perturbation.delta(t) * self.base.delta(t)

    def body_rate(self, t) -> np.ndarray:
        return self.perturbation.body_rate(t) + self.perturbation.delta(t).apply(self.base.body_rate(t))

    def max_rate(self, t0, t1) -> float:
        return self.base.max_rate(t0, t1) + self.perturbation.max_rate(t0, t1)


class LeoNadir(ConstantRate):
    """Nadir pointing on a circular Earth orbit; body frame = LVLH.

    +z towards nadir (-r), +y along the negative orbit normal (-h), +x = y x z (along the velocity).  ``altitude``
    in m above the equatorial radius; ``inclination``, ``raan`` (right ascension of the ascending node) and
    ``arg_latitude0`` (argument of latitude at t = 0) in rad.  Positions are ECI (taken as the inertial frame), m.
    The body rate is the constant ``(0, -n, 0)`` rad/s, n the mean motion.
    """

    def __init__(self, altitude, inclination, raan=0.0, arg_latitude0=0.0):
        self.altitude = checks.positive("altitude", altitude, unit="m")
        self.inclination = checks.in_range("inclination", inclination, 0.0, np.pi, unit="rad")
        self.raan = checks.in_range("raan", raan, unit="rad")
        self.arg_latitude0 = checks.in_range("arg_latitude0", arg_latitude0, unit="rad")
        self.semi_major_axis = R_EARTH + self.altitude
        super().__init__((0.0, -self.mean_motion, 0.0))
        cos_raan, sin_raan = np.cos(self.raan), np.sin(self.raan)
        cos_inc, sin_inc = np.cos(self.inclination), np.sin(self.inclination)
        self._node = np.array([cos_raan, sin_raan, 0.0])  # towards the ascending node
        self._in_plane = np.array([-cos_inc * sin_raan, cos_inc * cos_raan, sin_inc])  # 90 deg ahead in the orbit
        self._normal = np.cross(self._node, self._in_plane)

    @property
    def mean_motion(self) -> float:
        """Mean motion n = sqrt(mu / a^3), rad/s."""
        return float(np.sqrt(MU_EARTH / self.semi_major_axis**3))

    @property
    def period(self) -> float:
        """Orbital period, s."""
        return 2.0 * np.pi / self.mean_motion

    def _arg_latitude(self, t) -> tuple[np.ndarray, bool]:
        ts, scalar = _times(t)
        return self.arg_latitude0 + self.mean_motion * ts, scalar

    def position(self, t) -> np.ndarray:
        """ECI position (m), shape (3,) or (n, 3)."""
        u, scalar = self._arg_latitude(t)
        r = self.semi_major_axis * (np.outer(np.cos(u), self._node) + np.outer(np.sin(u), self._in_plane))
        return _vector_out(r, scalar)

    def velocity(self, t) -> np.ndarray:
        """ECI velocity (m/s), shape (3,) or (n, 3)."""
        u, scalar = self._arg_latitude(t)
        speed = self.semi_major_axis * self.mean_motion
        v = speed * (np.outer(-np.sin(u), self._node) + np.outer(np.cos(u), self._in_plane))
        return _vector_out(v, scalar)

    def initial_attitude(self) -> Rotation:
        """Inertial (ECI) -> LVLH rotation at t = 0."""
        u = self.arg_latitude0
        along_track = -np.sin(u) * self._node + np.cos(u) * self._in_plane
        nadir = -(np.cos(u) * self._node + np.sin(u) * self._in_plane)
        return Rotation.from_matrix(np.stack([along_track, -self._normal, nadir]))

    def trajectory(self) -> Trajectory:
        """The nadir-pointing attitude history starting from :meth:`initial_attitude`."""
        return Trajectory(self, self.initial_attitude())


class Sequence(Motion):
    """Scripted ``(motion, duration_s)`` segments run back to back, each starting where the previous one ended.

    Segment k runs on its own clock ``t - t_k`` (s) from the attitude reached at ``t_k``:
    ``delta(t) = delta_k(t - t_k) * delta_k(0)^-1 * delta(t_k)``, so the attitude is continuous even for a segment whose
    own ``delta_k(0)`` is not the identity (the first segment is used as is).  After the last segment's duration the
    last motion continues.  Body rate (rad/s, body frame) is that of the active segment.
    """

    def __init__(self, segments: Iterable[tuple[Motion, float]]):
        pairs = list(segments)
        if not pairs:
            raise ValueError("segments must hold at least one (motion, duration_s) pair")
        motions, durations = [], []
        for i, pair in enumerate(pairs):
            if not isinstance(pair, tuple | list) or len(pair) != 2 or not isinstance(pair[0], Motion):
                raise ValueError(f"segments[{i}] must be a (Motion, duration_s) pair, got {pair!r}")
            motions.append(pair[0])
            durations.append(checks.non_negative(f"segments[{i}] duration", pair[1], unit="s"))
        self.motions = motions
        self.durations = np.array(durations)
        self.starts = np.concatenate([[0.0], np.cumsum(self.durations)[:-1]])
        offsets = [Rotation.identity()]  # segment k: delta(t) = delta_k(t - t_k) * offsets[k]
        for k in range(1, len(motions)):
            reached = motions[k - 1].delta(durations[k - 1]) * offsets[-1]
            offsets.append(motions[k].delta(0.0).inv() * reached)
        self._offsets = Rotation.concatenate(offsets)

    @property
    def duration(self) -> float:
        """Total scripted time (s)."""
        return float(self.durations.sum())

    def _segment_index(self, ts: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.starts, ts, side="right") - 1, 0, len(self.motions) - 1)

    def delta(self, t) -> Rotation:
        ts, scalar = _times(t)
        index = self._segment_index(ts)
        quats = np.empty((ts.size, 4))
        for k in np.unique(index):
            mask = index == k
            quats[mask] = (self.motions[k].delta(ts[mask] - self.starts[k]) * self._offsets[k]).as_quat()
        return _rotation_out(Rotation.from_quat(quats), scalar)

    def body_rate(self, t) -> np.ndarray:
        ts, scalar = _times(t)
        index = self._segment_index(ts)
        rates = np.empty((ts.size, 3))
        for k in np.unique(index):
            mask = index == k
            rates[mask] = self.motions[k].body_rate(ts[mask] - self.starts[k])
        return _vector_out(rates, scalar)

    def max_rate(self, t0, t1) -> float:
        lo, hi = _interval(t0, t1)
        bound = 0.0
        last = len(self.motions) - 1
        for k, motion in enumerate(self.motions):
            seg_lo = -np.inf if k == 0 else self.starts[k]
            seg_hi = np.inf if k == last else self.starts[k] + self.durations[k]
            if seg_hi < lo or seg_lo > hi or (seg_lo == seg_hi and k != last):
                continue
            start = self.starts[k]
            bound = max(bound, motion.max_rate(max(lo, seg_lo) - start, min(hi, seg_hi) - start))
        return bound
