"""Gyro-star fusion: a multiplicative extended Kalman filter (MEKF) on attitude and gyro bias.

State: the attitude ``A`` (inertial -> body, a scipy ``Rotation``) and the gyro bias ``b`` (rad/s, body frame); the
error state ``x = (dtheta, db)`` with ``A_true = exp([dtheta x]) A`` and ``b_true = b + db`` (Lefferts, Markley and
Shuster 1982; Markley and Crassidis 2014, Sec. 6.2), covariance ``P`` (6, 6).

Propagation, per gyro piece of length ``h`` (the sample intervals of :class:`~starenv.agents.predict.gyro.
QuaternionPredictor`, coning term included) with the bias-corrected rate ``w = dtheta / h - b``:
``A <- exp(-[w h x]) A``; ``P <- Phi P Phi^T + Q`` with ``Phi = I + F h``, ``F = [[-[w x], I], [0, 0]]`` and the
discrete noise of angle random walk ``sigma_v`` and bias random walk ``sigma_u``:
``Q = [[sv^2 h + su^2 h^3 / 3, su^2 h^2 / 2], [su^2 h^2 / 2, su^2 h]]`` (per axis).  The datasheet values map as
``sigma_v = ARW (deg/sqrt h) * pi/180 / 60`` rad/sqrt(s) and ``sigma_u = RRW (deg/h/sqrt h) * pi/180 / 3600 / 60``
rad/s/sqrt(s); the bias instability ``B`` (deg/h) is the simulator's first-order Gauss-Markov bias
(``starenv.sim.gyro``: steady-state sigma ``s = 0.664 B / 0.618``, correlation time ``tau``), folded into the bias walk
as ``2 s^2 / tau`` per second: the variance rate of that process's increments over intervals short against ``tau``.
The walk does not pull the estimate back to zero as the Gauss-Markov process would, so a constant (uncalibrated) bias
is estimated too; the state stays at six -- a choice stated here.

Update, per identified star (HIP id in the catalogue): its body-frame unit vector ``b_m`` (the calibrated camera's
``unproject`` and mounting) against ``b_hat = A r`` of its catalogue direction ``r``: innovation ``b_m - b_hat``,
``H = [-[b_hat x], 0]``, noise ``R = s_c^2 I + (s_a^2 - s_c^2) t t^T`` with ``t`` the unit direction of the star's
trail (``w x b_hat``, ``w`` the bias-corrected mean gyro rate of the step), ``L = |w x b_hat| * exposure`` its length
(rad) and ``f`` the head's focal length in pixels: across the trail ``s_c^2 = (centroid_noise_px / f)^2 +
(smear_noise_fraction * L)^2``, along it ``s_a^2 = s_c^2 + (along_trail_fraction * L)^2``.  The trail terms are an
error budget, not a trail model.  A trail's centroid errs along the trail several times more than across it (the
faint ends fall under a threshold, a neighbour or a noise peak pulls them), so the defaults weigh 1 % of the trail's
length across it and 5 % along it, set from the identified stars' errors that ``docs/fusion.md`` reports.  Weighted
isotropically, the along-trail errors of stars left and right of the motion become roll errors that the filter,
believing its centroid noise, keeps for frames.
A star whose innovation's squared Mahalanobis distance exceeds ``gate`` (chi-square, 2 degrees of freedom
-- a unit vector error has two -- at 99.9 %: 13.8) is rejected; a frame whose accepted stars' normalised innovation
squared exceeds the 99.9 % chi-square bound of its degrees of freedom is rejected whole.  The accepted stars update
the state in one batch (Joseph form).

In the pipeline the filter is the predictor (an :class:`~starenv.agents.base.AttitudeFilter`): ``predict`` carries it
to the frame and predicts the stars; ``update`` fuses the identified stars; ``posterior`` is the action.  With no
estimate yet, the first solved attitude starts it as the point the first update is linearised about, with a loose
prior (``initial_attitude_sigma_arcsec``, 1 deg by default; ``initial_bias_sigma_deg_hr``): the solver weighs its
stars alike, so taken as a tight prior its roll would outweigh the stars' trail-aware weights; with the loose one the
first posterior is the weighted least-squares attitude of the first frame's stars.  After ``restart_after``
consecutive frames rejected (whole, or every star of them) while the pipeline solved them, the filter starts again
the same way from that frame's solution, keeping its bias estimate: a state the stars keep contradicting is not
coasted on.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import block_diag
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from starenv import checks
from starenv.agents.base import INFO, WARNING, Prediction, StarMeasurements, StepInput
from starenv.agents.predict.gyro import QuaternionPredictor
from starenv.sim.conventions import ARCSEC, DEG
from starenv.sim.gyro import GM_PEAK_ADEV_PER_SIGMA, IEEE_FLICKER_FLOOR
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog

STAR_GATE = float(chi2.ppf(0.999, 2))  # 13.8: a star's innovation beyond this is rejected
FRAME_CONFIDENCE = 0.999


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix [v x] (3, 3) of a 3-vector."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def process_noise(h: float, sigma_v: float, sigma_u: float) -> np.ndarray:
    """Discrete process noise (6, 6) of one step of ``h`` s: angle random walk ``sigma_v`` (rad/sqrt s) and bias
    random walk ``sigma_u`` (rad/s/sqrt s), per axis (module docstring)."""
    eye = np.eye(3)
    q = np.zeros((6, 6))
    q[:3, :3] = (sigma_v**2 * h + sigma_u**2 * h**3 / 3.0) * eye
    q[:3, 3:] = q[3:, :3] = (sigma_u**2 * h**2 / 2.0) * eye
    q[3:, 3:] = sigma_u**2 * h * eye
    return q


class MekfPredictor(QuaternionPredictor):
    """The MEKF (module docstring) as a predictor that also gives the pipeline its action.

    Options (the gyro's datasheet, the sensor's centroid noise, the start): ``arw_deg_rthr``, ``rrw_deg_hr_rthr``,
    ``bias_instability_deg_hr``, ``bias_correlation_s``, ``centroid_noise_px``, ``smear_noise_fraction``,
    ``along_trail_fraction``, ``initial_attitude_sigma_arcsec``, ``initial_bias_sigma_deg_hr``, ``gate`` (per-star
    chi-square bound), ``restart_after`` (frames), plus ``margin_px``.
    """

    def __init__(self, arw_deg_rthr: float = 0.01, rrw_deg_hr_rthr: float = 0.005, bias_instability_deg_hr: float = 0.0,
                 bias_correlation_s: float = 300.0, centroid_noise_px: float = 0.2, smear_noise_fraction: float = 0.01,
                 along_trail_fraction: float = 0.05, initial_attitude_sigma_arcsec: float = 3600.0,
                 initial_bias_sigma_deg_hr: float = 10.0, gate: float = STAR_GATE, restart_after: int = 3,
                 margin_px: float = 0.0):
        super().__init__(margin_px, coning_correction=True)
        arw = checks.non_negative("arw_deg_rthr", arw_deg_rthr, unit="deg/sqrt(h)")
        rrw = checks.non_negative("rrw_deg_hr_rthr", rrw_deg_hr_rthr, unit="deg/h/sqrt(h)")
        bias_inst = checks.non_negative("bias_instability_deg_hr", bias_instability_deg_hr, unit="deg/h")
        tau = checks.positive("bias_correlation_s", bias_correlation_s, unit="s")
        self.sigma_v = arw * DEG / 60.0
        gm_sigma = IEEE_FLICKER_FLOOR * bias_inst / GM_PEAK_ADEV_PER_SIGMA * DEG / 3600.0  # rad/s
        self.sigma_u = math.sqrt((rrw * DEG / 3600.0 / 60.0) ** 2 + 2.0 * gm_sigma**2 / tau)
        self.centroid_noise_px = checks.positive("centroid_noise_px", centroid_noise_px, unit="px")
        self.smear_noise_fraction = checks.non_negative("smear_noise_fraction", smear_noise_fraction)
        self.along_trail_fraction = checks.non_negative("along_trail_fraction", along_trail_fraction)
        self._rate, self._exposure = np.zeros(3), 0.0  # mean gyro rate (rad/s) and exposure (s) of the last step
        sigma_att = checks.positive("initial_attitude_sigma_arcsec", initial_attitude_sigma_arcsec) * ARCSEC
        sigma_bias = checks.non_negative("initial_bias_sigma_deg_hr", initial_bias_sigma_deg_hr) * DEG / 3600.0
        self.p0 = np.diag([sigma_att**2] * 3 + [sigma_bias**2] * 3)
        self.gate = checks.positive("gate", gate)
        self.restart_after = checks.integer("restart_after", restart_after, 1, 1_000_000)
        self._rejected_run = 0  # consecutive frames rejected whole
        self._predicted = None  # the state carried to the last prediction's time
        self.stars_used = 0
        self.stars_rejected = 0
        self.frame_rejected = False
        self.events: list[tuple[int, str]] = []  # the last update's gate rejections and restart (level, text)

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        super().reset(cameras, catalog)
        self._predicted = None
        self._rate, self._exposure = np.zeros(3), 0.0
        self._rejected_run = 0

    def predict(self, step: StepInput) -> Prediction:
        rate = np.asarray(step.gyro.rate, dtype=np.float64).reshape(-1, 3)
        self._rate = rate.mean(axis=0) if len(rate) else np.zeros(3)
        self._exposure = float(step.exposure_s)
        return super().predict(step)

    def star_covariance(self, camera: Camera, direction: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """The noise covariance (3, 3; rad^2, body frame) of a star seen by ``camera`` along the body-frame unit
        ``direction`` during the last predicted step, with the gyro bias estimate ``bias`` (rad/s): ``s_c`` across
        its trail, ``s_a`` along it (module docstring)."""
        motion = np.cross(self._rate - bias, direction)
        speed = float(np.linalg.norm(motion))
        trail = speed * self._exposure
        cross2 = (self.centroid_noise_px / min(camera.fx, camera.fy)) ** 2 + (self.smear_noise_fraction * trail) ** 2
        cov = cross2 * np.eye(3)
        if speed > 0.0:
            along = motion / speed
            cov += (self.along_trail_fraction * trail) ** 2 * np.outer(along, along)
        return cov

    # state: (attitude, seen rows, bias (3,), covariance (6, 6))
    def _propagated(self, state, delta_angles: np.ndarray, coning: np.ndarray, span: np.ndarray):
        attitude, seen, bias, cov = state
        for dtheta, cone, h in zip(delta_angles, coning, span, strict=True):
            phi = dtheta + cone - bias * h
            attitude = Rotation.from_rotvec(-phi) * attitude
            if h > 0.0:
                w = phi / h
                f = np.zeros((6, 6))
                f[:3, :3] = -skew(w)
                f[:3, 3:] = np.eye(3)
                step = np.eye(6) + f * h
                cov = step @ cov @ step.T + process_noise(h, self.sigma_v, self.sigma_u)
        return attitude, seen, bias, cov

    def _prediction(self, state):
        self._predicted = state
        return super()._prediction(state[:2])

    def _state_from(self, attitude: Rotation, stars: list[StarMeasurements]):
        """The posterior at the update's time: the carried prior (or ``attitude`` to start from) updated with the
        identified stars."""
        rows = [self._catalog_rows(s.catalog_id) for s in stars]
        prior = self._predicted
        self._predicted = None
        self.events = []
        if prior is None:
            self._rejected_run = 0
            posterior = self._measurement_update(attitude, np.zeros(3), self.p0.copy(), stars, rows)
            self.events = [(INFO, f"filter started from the frame's solution ({self.stars_used} stars)")]
            self._note_rejections()
            return posterior
        carried, _, bias, cov = prior
        posterior = self._measurement_update(carried, bias, cov, stars, rows)
        self._note_rejections()
        contradicted = self.frame_rejected or (self.stars_used == 0 and self.stars_rejected > 0)
        self._rejected_run = self._rejected_run + 1 if contradicted else 0
        if self._rejected_run < self.restart_after:
            return posterior
        self._rejected_run = 0  # start again from the solution, keeping the bias and its covariance
        start = self.p0.copy()
        start[3:, 3:] = cov[3:, 3:]
        posterior = self._measurement_update(attitude, bias, start, stars, rows)
        self.events.append((WARNING, f"filter restarted from the frame's solution after {self.restart_after} "
                                     f"contradicted frames ({self.stars_used} stars)"))
        return posterior

    def _note_rejections(self) -> None:
        """The last measurement update's gate rejections as events."""
        if self.frame_rejected:
            self.events.append((WARNING, "filter rejected the frame whole (normalised innovation beyond its "
                                         f"{FRAME_CONFIDENCE:.1%} chi-square bound)"))
        elif self.stars_rejected:
            level = WARNING if self.stars_used == 0 else INFO
            self.events.append((level, f"filter gate rejected {self.stars_rejected} of "
                                       f"{self.stars_rejected + self.stars_used} stars"))

    def _measurement_update(self, attitude, bias, cov, stars, rows):
        residuals, jacobians, noises = [], [], []
        for cam, s in zip(self._cameras, stars, strict=True):
            ids = s.catalog_id
            known = np.flatnonzero(ids >= 0)
            if not len(known):
                continue
            star_rows = np.searchsorted(self._hip_sorted, ids[known])
            star_rows = np.minimum(star_rows, len(self._hip_sorted) - 1)
            found = self._hip_sorted[star_rows] == ids[known]
            known, star_rows = known[found], self._hip_rows[star_rows[found]]
            measured = cam.mounting.inv().apply(cam.unproject(s.xy[known]))
            predicted = attitude.apply(self._catalog.unit[star_rows])
            for m, p in zip(measured, predicted, strict=True):
                h = np.zeros((3, 6))
                h[:, :3] = -skew(p)
                residuals.append(m - p)
                jacobians.append(h)
                noises.append(self.star_covariance(cam, p, bias))
        accepted = []
        for nu, h, noise in zip(residuals, jacobians, noises, strict=True):
            s_matrix = h @ cov @ h.T + noise
            accepted.append(float(nu @ np.linalg.solve(s_matrix, nu)) <= self.gate)
        self.stars_rejected = len(accepted) - int(np.sum(accepted))
        keep = [i for i, ok in enumerate(accepted) if ok]
        self.stars_used, self.frame_rejected = len(keep), False
        if keep:
            h = np.vstack([jacobians[i] for i in keep])
            nu = np.concatenate([residuals[i] for i in keep])
            r = block_diag(*[noises[i] for i in keep])
            s_matrix = h @ cov @ h.T + r
            nis = float(nu @ np.linalg.solve(s_matrix, nu))
            if nis > chi2.ppf(FRAME_CONFIDENCE, 2 * len(keep)):
                self.frame_rejected, self.stars_used = True, 0
            else:
                gain = np.linalg.solve(s_matrix, h @ cov).T
                dx = gain @ nu
                attitude = Rotation.from_rotvec(dx[:3]) * attitude
                bias = bias + dx[3:]
                joseph = np.eye(6) - gain @ h
                cov = joseph @ cov @ joseph.T + gain @ r @ gain.T
        return attitude, rows, bias, 0.5 * (cov + cov.T)

    def posterior(self) -> tuple[Rotation, np.ndarray, np.ndarray] | None:
        """The filtered attitude (inertial -> body) at the last update, the gyro bias estimate (3,) rad/s (body
        frame) and the error covariance (6, 6) (rad^2, rad^2/s, rad^2/s^2); None before the first update."""
        if self._state is None:
            return None
        attitude, _, bias, cov = self._state
        return attitude, bias.copy(), cov.copy()
