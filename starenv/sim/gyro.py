"""Three-axis rate-integrating gyro: sampled body rate with datasheet error terms, plus an Allan deviation tool.

Sample ``k`` (``k = 1, 2, ...``) carries the timestamp ``t_k = k / rate_hz + time_offset_s`` and reports the average
body rate (rad/s, body frame) over ``(t_k - dt, t_k]``, ``dt = 1 / rate_hz``:

    rate_k = (I + diag(scale_factor) + M) * mean(w over the interval) + bias + b_rrw_k + b_gm_k + n_arw_k

then, if a quantum is set, the delta-angle ``rate_k * dt`` is quantized with carry.  Datasheet units appear only in
:class:`GyroSpec`; everything inside is SI.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.signal import lfilter

from starenv import checks
from starenv.sim.conventions import ARCSEC, DEG

# IEEE Std 952: the bias-instability coefficient B relates to the flat floor of the Allan deviation by 0.664 B.
IEEE_FLICKER_FLOOR = 0.664

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(5)
_GL_WEIGHTS = _GL_WEIGHTS / 2.0  # weights of the interval *average*: they sum to 1
_BLOCK_SAMPLES = 1 << 16  # samples generated per internal block, bounding memory on long records
_NOISE_SOURCES = 3  # standard normals drawn per sample and axis: ARW, RRW, Gauss-Markov, in that order


def gauss_markov_allan_variance(tau, sigma: float, correlation_s: float) -> np.ndarray:
    """Allan variance ((rad/s)^2) at averaging times ``tau`` (s) of a first-order Gauss-Markov rate process.

    ``sigma`` is its steady-state standard deviation (rad/s) and ``correlation_s`` its correlation time T (s):
    ``AVAR(tau) = (2 sigma^2 T / tau) [1 - (T / (2 tau)) (3 - 4 exp(-tau/T) + exp(-2 tau/T))]``.
    """
    x = np.asarray(tau, dtype=np.float64) / correlation_s
    return 2.0 * sigma**2 / x * (1.0 - (3.0 - 4.0 * np.exp(-x) + np.exp(-2.0 * x)) / (2.0 * x))


def _gauss_markov_peak() -> tuple[float, float]:
    """(tau / T, Allan deviation / sigma) at the peak of a Gauss-Markov process's Allan deviation."""
    found = minimize_scalar(
        lambda x: -gauss_markov_allan_variance(x, 1.0, 1.0), bounds=(0.1, 20.0), method="bounded",
        options={"xatol": 1e-10},
    )
    return float(found.x), float(np.sqrt(-found.fun))


GM_PEAK_TAU_PER_T, GM_PEAK_ADEV_PER_SIGMA = _gauss_markov_peak()  # about 1.89 and 0.618


def _vector_in_range(name: str, value, shape: tuple[int, ...], bound: float, unit: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` whose every element lies in [-bound, bound]."""
    arr = checks.finite(name, value, shape=shape)
    if np.any(np.abs(arr) > bound):
        raise ValueError(f"{name} elements must be in [{-bound:g}, {bound:g}] {unit}, got {arr.tolist()}")
    return arr


@dataclass(frozen=True)
class GyroSpec:
    """Datasheet parameters of a three-axis gyro; units are in the field names.

    Defaults describe a tactical-grade fibre-optic gyro (ARW 0.01 deg/sqrt(h), RRW 0.005 deg/h/sqrt(h), bias
    instability 0.05 deg/h) with its deterministic errors calibrated out (zero bias, scale factor and
    misalignment) and no output quantization.

    * ``rate_hz`` in [100, 1000]; ``time_offset_s`` in [0, 1/rate_hz) shifts the sample grid.
    * ``arw_deg_rthr``: angle random walk N in [0, 10] deg/sqrt(h).
    * ``rrw_deg_hr_rthr``: rate random walk K in [0, 1000] deg/h/sqrt(h) (bias random walk starting at zero).
    * ``bias_instability_deg_hr``: B in [0, 1000] deg/h, modelled as a first-order Gauss-Markov bias with correlation
      time ``bias_correlation_s`` in (0, 1e6] s whose Allan deviation peaks at 0.664 B.
    * ``bias_deg_hr``: constant bias per axis, each in [-1e4, 1e4] deg/h.
    * ``scale_factor_ppm``: scale-factor error per axis, each in [-1e5, 1e5] ppm.
    * ``misalignment_mrad``: 3x3 matrix M with zero diagonal; M[i, j] couples true body rate about axis j into gyro
      axis i (six independent small angles), each in [-100, 100] mrad.
    * ``quantization_arcsec``: delta-angle quantum (one LSB) in [0, 100] arcsec; 0 disables quantization.

    Vector and matrix fields accept any array-like and are stored as tuples.
    """

    rate_hz: float = 200.0
    time_offset_s: float = 0.0
    arw_deg_rthr: float = 0.01
    rrw_deg_hr_rthr: float = 0.005
    bias_instability_deg_hr: float = 0.05
    bias_correlation_s: float = 300.0
    bias_deg_hr: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale_factor_ppm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    misalignment_mrad: tuple[tuple[float, float, float], ...] = ((0.0, 0.0, 0.0),) * 3
    quantization_arcsec: float = 0.0

    def __post_init__(self):
        rate_hz = checks.in_range("rate_hz", self.rate_hz, 100.0, 1000.0, unit="Hz")
        scalars = {
            "rate_hz": rate_hz,
            "time_offset_s": checks.in_range("time_offset_s", self.time_offset_s, 0.0, 1.0 / rate_hz,
                                             high_open=True, unit="s"),
            "arw_deg_rthr": checks.in_range("arw_deg_rthr", self.arw_deg_rthr, 0.0, 10.0, unit="deg/sqrt(h)"),
            "rrw_deg_hr_rthr": checks.in_range("rrw_deg_hr_rthr", self.rrw_deg_hr_rthr, 0.0, 1000.0,
                                               unit="deg/h/sqrt(h)"),
            "bias_instability_deg_hr": checks.in_range("bias_instability_deg_hr", self.bias_instability_deg_hr,
                                                       0.0, 1000.0, unit="deg/h"),
            "bias_correlation_s": checks.in_range("bias_correlation_s", self.bias_correlation_s, 0.0, 1e6,
                                                  low_open=True, unit="s"),
            "quantization_arcsec": checks.in_range("quantization_arcsec", self.quantization_arcsec, 0.0, 100.0,
                                                   unit="arcsec"),
        }
        bias = _vector_in_range("bias_deg_hr", self.bias_deg_hr, (3,), 1e4, "deg/h")
        scale = _vector_in_range("scale_factor_ppm", self.scale_factor_ppm, (3,), 1e5, "ppm")
        misalignment = _vector_in_range("misalignment_mrad", self.misalignment_mrad, (3, 3), 100.0, "mrad")
        if np.any(np.diag(misalignment) != 0.0):
            raise ValueError(f"misalignment_mrad must have a zero diagonal, got {misalignment.tolist()}")
        for name, value in scalars.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "bias_deg_hr", tuple(bias.tolist()))
        object.__setattr__(self, "scale_factor_ppm", tuple(scale.tolist()))
        object.__setattr__(self, "misalignment_mrad", tuple(tuple(row) for row in misalignment.tolist()))

    @property
    def sample_interval_s(self) -> float:
        """Sample interval dt = 1 / rate_hz (s)."""
        return 1.0 / self.rate_hz


@dataclass
class GyroSamples:
    """Gyro output: ``t`` (n,) s sample timestamps (end of each interval); ``rate`` (n, 3) rad/s body frame,
    the measured average body rate over ``(t - dt, t]``; ``dt`` the sample interval 1 / rate_hz (s)."""

    t: np.ndarray
    rate: np.ndarray
    dt: float


class Gyro:
    """A gyro following :class:`GyroSpec`, producing samples on demand with its error state carried between calls.

    All randomness comes from ``rng``.  The constructor draws three standard normals (the steady-state initial
    Gauss-Markov bias); each sample then draws nine, ordered (ARW, RRW, Gauss-Markov) x (x, y, z) whatever terms are
    enabled, so a record produced in consecutive chunks is bit-identical to one produced in a single call, and
    switching one error term on or off leaves the realisation of the others unchanged.  The rate random walk and the
    quantization remainder start at zero at t = 0.
    """

    def __init__(self, spec: GyroSpec, rng: np.random.Generator):
        self.spec = spec
        self._rng = rng
        dt = spec.sample_interval_s
        self._sensor_matrix = (
            np.eye(3) + np.diag(np.asarray(spec.scale_factor_ppm) * 1e-6) + np.asarray(spec.misalignment_mrad) * 1e-3
        )
        self._bias_rad_s = np.asarray(spec.bias_deg_hr) * DEG / 3600.0
        self._arw_sigma_rad_s = spec.arw_deg_rthr * DEG / 60.0 / math.sqrt(dt)
        self._rrw_step_rad_s = spec.rrw_deg_hr_rthr * DEG / 3600.0 / 60.0 * math.sqrt(dt)
        gm_sigma_rad_s = IEEE_FLICKER_FLOOR * spec.bias_instability_deg_hr * DEG / 3600.0 / GM_PEAK_ADEV_PER_SIGMA
        self._gm_decay = math.exp(-dt / spec.bias_correlation_s)
        self._gm_step_rad_s = gm_sigma_rad_s * math.sqrt(-math.expm1(-2.0 * dt / spec.bias_correlation_s))
        self._quantum_rad = spec.quantization_arcsec * ARCSEC
        # Filter states (scipy.signal.lfilter ``zi``, shape (1, 3)) of the two bias processes.
        self._rrw_state = np.zeros((1, 3))
        self._gm_state = self._gm_decay * gm_sigma_rad_s * rng.standard_normal(3)[None, :]
        self._quanta_accumulated = np.zeros(3)  # delta-angle accumulated since t = 0, in quanta
        self._samples_delivered = 0
        self._last_bias = self._bias_rad_s + self._gm_state[0] / self._gm_decay  # the bias before the first sample

    @property
    def bias_rad_s(self) -> np.ndarray:
        """The total bias (3,) rad/s (gyro axes, the body axes up to the misalignment) of the last delivered sample:
        constant + rate random walk + Gauss-Markov bias; before any sample, the bias at t = 0."""
        return self._last_bias.copy()

    @property
    def last_time_s(self) -> float:
        """Timestamp (s) of the last delivered sample, or of sample 0 (``time_offset_s``) before the first one."""
        return self._samples_delivered / self.spec.rate_hz + self.spec.time_offset_s

    def sample_until(self, body_rate: Callable[[np.ndarray], np.ndarray], t_end: float,
                     mean_rate: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> GyroSamples:
        """All samples with timestamp in (last delivered, ``t_end``] (s).

        ``body_rate(t)`` maps an (m,) array of times (s) to the true body rate (m, 3) rad/s in the body frame (a (3,)
        result is broadcast as a constant rate); each sample's mean over its interval is a 5-point Gauss-Legendre
        rule, unless ``mean_rate(t0, t1)`` gives the exact mean (m, 3) rad/s over intervals (t0, t1] (a motion
        whose rate jumps, :class:`starenv.sim.attitude_files.AttitudeHistory`).
        """
        t_end = float(checks.finite("t_end", t_end, shape=()))
        rate_hz, offset = self.spec.rate_hz, self.spec.time_offset_s
        last_index = max(math.floor((t_end - offset) * rate_hz), self._samples_delivered)
        while (last_index + 1) / rate_hz + offset <= t_end:
            last_index += 1
        while last_index > self._samples_delivered and last_index / rate_hz + offset > t_end:
            last_index -= 1
        blocks = [
            self._sample_block(body_rate, first, min(first + _BLOCK_SAMPLES, last_index + 1), mean_rate)
            for first in range(self._samples_delivered + 1, last_index + 1, _BLOCK_SAMPLES)
        ]
        self._samples_delivered = last_index
        if not blocks:
            return GyroSamples(t=np.empty(0), rate=np.empty((0, 3)), dt=self.spec.sample_interval_s)
        return GyroSamples(t=np.concatenate([b.t for b in blocks]), rate=np.concatenate([b.rate for b in blocks]),
                           dt=self.spec.sample_interval_s)

    def _sample_block(self, body_rate, first: int, stop: int, exact_mean=None) -> GyroSamples:
        """Samples with indices ``first .. stop - 1``, advancing the error state."""
        rate_hz, offset, dt = self.spec.rate_hz, self.spec.time_offset_s, self.spec.sample_interval_s
        index = np.arange(first, stop, dtype=np.float64)
        n = index.size
        centres = (index - 0.5) / rate_hz + offset
        if exact_mean is not None:
            mean_rate = np.asarray(exact_mean((index - 1.0) / rate_hz + offset, index / rate_hz + offset))
        else:
            node_times = (centres[:, None] + (0.5 * dt) * _GL_NODES[None, :]).ravel()
            true_rate = _evaluate_body_rate(body_rate, node_times).reshape(n, _GL_NODES.size, 3)
            mean_rate = np.einsum("m,nmc->nc", _GL_WEIGHTS, true_rate)

        normals = self._rng.standard_normal((n, _NOISE_SOURCES, 3))
        rrw_bias, self._rrw_state = lfilter([self._rrw_step_rad_s], [1.0, -1.0], normals[:, 1], axis=0,
                                            zi=self._rrw_state)
        gm_bias, self._gm_state = lfilter([self._gm_step_rad_s], [1.0, -self._gm_decay], normals[:, 2], axis=0,
                                          zi=self._gm_state)
        if n:
            self._last_bias = self._bias_rad_s + rrw_bias[-1] + gm_bias[-1]
        measured = (mean_rate @ self._sensor_matrix.T + self._bias_rad_s + rrw_bias + gm_bias
                    + self._arw_sigma_rad_s * normals[:, 0])
        if self._quantum_rad > 0.0:
            increments = measured * (dt / self._quantum_rad)
            accumulated = np.cumsum(np.concatenate([self._quanta_accumulated[None, :], increments]), axis=0)
            self._quanta_accumulated = accumulated[-1]
            measured = np.diff(np.floor(accumulated), axis=0) * (self._quantum_rad / dt)
        return GyroSamples(t=index / rate_hz + offset, rate=measured, dt=dt)


def _evaluate_body_rate(body_rate, times: np.ndarray) -> np.ndarray:
    """``body_rate(times)`` checked to be finite and broadcast to shape (len(times), 3) rad/s."""
    values = np.asarray(body_rate(times), dtype=np.float64)
    try:
        values = np.broadcast_to(values, (times.size, 3))
    except ValueError as exc:
        raise ValueError(f"body_rate must return shape ({times.size}, 3) or (3,), got {values.shape}") from exc
    if not np.all(np.isfinite(values)):
        raise ValueError("body_rate must return finite values (no NaN or inf)")
    return values


def allan_deviation(rate: np.ndarray, dt: float, taus: np.ndarray) -> np.ndarray:
    """Overlapping Allan deviation of a rate record at averaging times ``taus`` (s).

    ``rate`` is (n,) or (n, k) sampled every ``dt`` seconds (any unit; the result has the same unit); each column is
    an axis.  Each tau is rounded to the nearest multiple m * dt, 1 <= m <= n / 2.  Returns (len(taus),) or
    (len(taus), k).  Computed from the cumulative sum (the angle record) after removing the mean rate, which the
    Allan variance ignores and which would otherwise cost precision.
    """
    rate = checks.finite("rate", rate)
    if rate.ndim not in (1, 2) or rate.shape[0] < 2:
        raise ValueError(f"rate must have shape (n,) or (n, k) with n >= 2, got shape {rate.shape}")
    dt = checks.positive("dt", dt, unit="s")
    taus = checks.finite("taus", taus)
    if taus.ndim != 1:
        raise ValueError(f"taus must be a 1-D array, got shape {taus.shape}")
    n = rate.shape[0]
    cluster_sizes = np.rint(taus / dt).astype(np.int64)
    if np.any(cluster_sizes < 1) or np.any(2 * cluster_sizes > n):
        raise ValueError(f"taus must be in [{dt:g}, {(n // 2) * dt:g}] s for this record, got {taus.tolist()}")
    angle = np.concatenate([np.zeros((1,) + rate.shape[1:]), np.cumsum((rate - rate.mean(axis=0)) * dt, axis=0)])
    deviation = np.empty((taus.size,) + rate.shape[1:])
    for i, m in enumerate(cluster_sizes):
        second_difference = angle[2 * m :] - 2.0 * angle[m:-m] + angle[: -2 * m]
        deviation[i] = np.sqrt(np.mean(second_difference**2, axis=0) / 2.0) / (m * dt)
    return deviation
