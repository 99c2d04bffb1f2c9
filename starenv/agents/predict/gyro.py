"""Gyro-driven predictors: the attitude and the star positions of the next frame from the last estimate.

Two :class:`~starenv.agents.base.Predictor` agents:

* :class:`FirstOrderPredictor` -- paper 000's model (its Eqs. 1, 2, 5, 6, 7): measured star positions are turned into
  direction vectors once, rotated by the first-order increment ``I - [w x] dt`` per gyro sample and projected back.
* :class:`QuaternionPredictor` -- the rotation of every gyro sample applied exactly, with a two-sample coning
  correction; the predicted stars are catalog stars projected with the calibrated cameras.

Timeline (both).  A gyro sample stamped ``t_k`` is the average body rate (rad/s, body frame) over ``(t_{k-1}, t_k]``
(over ``(t_k - dt, t_k]`` for the first sample seen), so a gap between records is bridged by the next sample's rate.
Samples are kept across steps: those delivered with a frame reach past its mid-exposure time and are needed to reach
the next one.  ``predict`` carries the state from its time to ``step.time_s`` and keeps it at a sample boundary: the
latest one before ``time_s`` behind which two newer samples are already held.  The rest, up to ``time_s``, is applied
to a copy for the returned prediction only, so a run of predictions without update (dropped frames) applies every
sample interval once and whole.  Parts of an interval (after an update's time, before the prediction's time) use the
rate interpolated linearly inside the sample, ``r_k + s_k (t - centre_k)``, with the slope ``s_k`` from the
neighbouring samples (``numpy.gradient``, second order): it keeps the sample's average, so the parts of a split
interval add up to its delta-angle exactly.  Beyond the newest sample (and before the oldest) the nearest sample's
line is extrapolated; with no sample at all the rate is taken as zero.  Held at the sample's average instead, a
part would err by up to ``s dt^2 / 8`` (``s`` the rate's slope, ``dt`` the sample interval: the split at the
sample's centre); interpolated, only the rate's curvature is left, an error of order ``dt^3``.

``margin_px`` (both): predicted stars are those imaged within this many pixels of the sensor (0: on the sensor).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from starenv import checks
from starenv.agents.base import Prediction, StarMeasurements, StepInput
from starenv.sim.conventions import skew
from starenv.sim.gyro import GyroSamples
from starenv.sim.optics import Camera, NoDistortion, RadialXY
from starenv.sim.sky import StarCatalog

TIME_TOLERANCE_S = 1e-9  # instants closer than this (s) are the same: frame and gyro times share one clock
FIELD_PAD_RAD = 1e-3  # widening (rad) of the cone of directions imaged near the sensor, for stars on its rim


class _GyroHistory:
    """Gyro samples kept across steps, cut into the pieces that carry a state from one time to another.

    ``start``/``end`` (n,) s bound the interval each sample covers, ``rate`` (n, 3) rad/s is its average body rate.
    """

    def __init__(self):
        self.start = np.zeros(0)
        self.end = np.zeros(0)
        self.rate = np.zeros((0, 3))

    def add(self, record: GyroSamples) -> None:
        """Append a record's samples newer than the newest held; NaN/inf or unordered samples raise ValueError."""
        t = checks.finite("gyro.t", record.t)
        rate = checks.finite("gyro.rate", record.rate)
        if t.ndim != 1 or rate.shape != (len(t), 3):
            raise ValueError(f"gyro.t must have shape (n,) and gyro.rate (n, 3), got {t.shape} and {rate.shape}")
        dt = checks.non_negative("gyro.dt", record.dt, unit="s")
        if np.any(np.diff(t) <= 0.0):
            raise ValueError(f"gyro.t must increase strictly, got {t.tolist()}")
        if len(self.end):
            fresh = t > self.end[-1] + TIME_TOLERANCE_S
            t, rate = t[fresh], rate[fresh]
        if not len(t):
            return
        first_start = self.end[-1] if len(self.end) else t[0] - dt
        self.start = np.concatenate([self.start, [first_start], t[:-1]])
        self.end = np.concatenate([self.end, t])
        self.rate = np.concatenate([self.rate, rate])

    def forget_before(self, t: float) -> None:
        """Drop the samples that end before time ``t`` (s), keeping the last two of them (for the coning term's
        previous delta-angle and the rate slopes of the samples around ``t``)."""
        first = max(int(np.searchsorted(self.end, t + TIME_TOLERANCE_S, side="right")) - 2, 0)
        self.start, self.end, self.rate = self.start[first:], self.end[first:], self.rate[first:]

    def last_boundary(self, t0: float, t1: float) -> float:
        """The latest end (s) in ``[t0, t1]`` of a sample followed by two more, or ``t0`` when none: a partial
        interval before it then has its rate slope from neighbours on both sides, or from three samples."""
        ends = self.end[:-2]
        ends = ends[(ends >= t0 - TIME_TOLERANCE_S) & (ends <= t1 + TIME_TOLERANCE_S)]
        return float(ends[-1]) if len(ends) else t0

    def pieces(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``[t0, t1]`` (s) cut at the sample boundaries: each piece's delta-angle (m, 3) rad, body frame, its
        coning term (m, 3) rad, ``(1/12) dtheta_{k-1} x dtheta_k`` of its sample scaled by (piece / sample length)^3
        (zero without a previous sample, and outside the samples), and its length (m,) s."""
        if t1 - t0 <= TIME_TOLERANCE_S:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
        n = len(self.end)
        if not n:
            return np.zeros((1, 3)), np.zeros((1, 3)), np.array([t1 - t0])
        bounds = np.concatenate([self.start[:1], self.end])
        cuts = np.concatenate([[t0], bounds[(bounds > t0 + TIME_TOLERANCE_S) & (bounds < t1 - TIME_TOLERANCE_S)], [t1]])
        span = np.diff(cuts)
        middle = cuts[:-1] + 0.5 * span
        k = np.minimum(np.searchsorted(self.end, middle), n - 1)
        inside = (middle > self.start[k]) & (middle <= self.end[k])
        length = self.end - self.start
        centre = self.start + 0.5 * length
        slope = np.gradient(self.rate, centre, axis=0, edge_order=min(n - 1, 2)) if n > 1 else np.zeros((1, 3))
        rate = self.rate[k] + slope[k] * (middle - centre[k])[:, None]
        whole = self.rate * length[:, None]
        previous = np.concatenate([np.zeros((1, 3)), whole[:-1]])
        fraction = np.where(inside, span / np.where(length[k] > 0.0, length[k], 1.0), 0.0)
        coning = np.cross(previous[k], whole[k]) / 12.0 * fraction[:, None] ** 3
        return rate * span[:, None], coning, span


def _field_radius(camera: Camera, margin_px: float) -> float:
    """Half-angle (rad) of the cone around the boresight holding every direction imaged within ``margin_px`` of the
    sensor: the pinhole angle of the grown sensor's corners, plus the distortion's angular shift at the sensor's
    corners and a small pad."""
    pinhole = dataclasses.replace(camera, distortion=NoDistortion())

    def corner_angles(cam: Camera, grow_px: float) -> np.ndarray:
        left_top, right, bottom = -0.5 - grow_px, camera.width - 0.5 + grow_px, camera.height - 0.5 + grow_px
        corners = np.array([[left_top, left_top], [right, left_top], [left_top, bottom], [right, bottom]])
        return np.arccos(np.clip(cam.unproject(corners)[:, 2], -1.0, 1.0))

    reach = corner_angles(pinhole, margin_px).max()
    shift = np.abs(corner_angles(camera, 0.0) - corner_angles(pinhole, 0.0)).max()
    return float(min(reach + shift + FIELD_PAD_RAD, np.pi / 2))


def _no_stars(n_heads: int) -> list[StarMeasurements]:
    return [StarMeasurements(np.zeros((0, 2))) for _ in range(n_heads)]


class _GyroPropagator:
    """What both predictors share: the gyro history, the state's time, validation and the predict/update flow.

    Subclasses give ``_state_from`` (the state an update sets), ``_propagated`` (a state carried through pieces of
    delta-angle and coning term) and ``_prediction`` (the Prediction of a state).
    """

    def __init__(self, margin_px: float = 0.0):
        self.margin_px = checks.non_negative("margin_px", margin_px, unit="px")
        self._cameras: list[Camera] | None = None  # None until reset
        self._catalog: StarCatalog | None = None
        self._gyro = _GyroHistory()
        self._time: float | None = None  # s, time of the state; None before the first update
        self._state = None

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        """Forget every state and sample; ``cameras`` are the calibrated models, ``catalog`` the onboard catalog."""
        self._cameras = list(cameras)
        self._catalog = catalog
        self._gyro = _GyroHistory()
        self._time = None
        self._state = None

    def predict(self, step: StepInput) -> Prediction:
        """Attitude (inertial -> body) and stars per head at ``step.time_s``; ``Prediction(None, empty)`` before the
        first update.  The state moves on to a sample boundary before ``step.time_s`` (see the module docstring)."""
        self._require_reset()
        time_s = float(checks.finite("step.time_s", step.time_s, shape=()))
        self._gyro.add(step.gyro)
        if len(step.cameras) != len(self._cameras):
            raise ValueError(f"step.cameras has {len(step.cameras)} heads, reset gave {len(self._cameras)}")
        self._cameras = list(step.cameras)
        if self._time is None:
            self._gyro.forget_before(time_s)
            return Prediction(None, _no_stars(len(self._cameras)))
        if time_s < self._time - TIME_TOLERANCE_S:
            raise ValueError(f"step.time_s {time_s:.9f} s precedes the state's time {self._time:.9f} s")
        commit = self._gyro.last_boundary(self._time, time_s)
        self._state = self._propagated(self._state, *self._gyro.pieces(self._time, commit))
        self._time = commit
        self._gyro.forget_before(commit)
        return self._prediction(self._propagated(self._state, *self._gyro.pieces(commit, time_s)))

    def _require_reset(self) -> None:
        if self._cameras is None:
            raise RuntimeError(f"call {type(self).__name__}.reset(cameras, catalog) first")

    def update(self, attitude: Rotation, stars: list[StarMeasurements], time_s: float) -> None:
        """Take the estimate for ``time_s`` (s): attitude inertial -> body and the stars seen on each head."""
        self._require_reset()
        if not isinstance(attitude, Rotation) or not attitude.single:
            raise ValueError("attitude must be a single scipy Rotation (inertial -> body)")
        checks.finite("attitude", attitude.as_quat(), shape=(4,))
        stars = list(stars)
        if len(stars) != len(self._cameras):
            raise ValueError(f"stars must hold one StarMeasurements per head ({len(self._cameras)}), got {len(stars)}")
        self._time = float(checks.finite("time_s", time_s, shape=()))
        self._state = self._state_from(attitude, stars)
        self._gyro.forget_before(self._time)


class FirstOrderPredictor(_GyroPropagator):
    """Paper 000's star-spot predictor (its Sec. 2.2-2.3), carrying the stars given in ``update``.

    * Eq. 1: measured positions are corrected with the calibrated camera's :class:`~starenv.sim.optics.RadialXY`
      coefficients when it has that model, else not at all (the paper knows no other distortion model).
    * Eq. 2: corrected positions become direction vectors ``((x - cx)/fx, (y - cy)/fy, 1)``, normalised.  The paper
      writes ``(x - x0, y - y0, -f)``: its image coordinates lie on the physical focal plane behind the lens, ours
      on the positive image plane of a camera whose +Z is the boresight.  The two vectors differ by an overall sign,
      which commutes with Eqs. 5-6, so only Eq. 7's signs change (below).
    * Eqs. 5-6: each vector is multiplied by ``I - [theta x]`` per gyro sample interval, ``theta = w dt`` with
      ``dt`` that sample's own interval (what sampled rates call for; the paper's ``dt`` is the prediction interval
      with one rate per frame, a reading that makes a single, larger first-order step per frame).  An interval split
      by an update's or a prediction's time is applied as its parts.  Vectors are kept in the body frame
      (``I - [theta x]`` in the camera frame is the same map, mounted).
    * Eq. 7: projection back, ``x' = cx + fx X'/Z'``, ``y' = cy + fy Y'/Z'``, then re-distortion to measured pixels.
      Applied to one increment this is Eq. 7 on principal-point-relative coordinates ``X = x - cx``,
      ``Y = y - cy`` (f = fx = fy, ``theta`` in the camera frame) with our signs::

          D = 1 + (X theta_y - Y theta_x) / f
          X' = (X + Y theta_z - f theta_y) / D,   Y' = (Y - X theta_z + f theta_x) / D

      (the paper's ``-f`` flips the ``f theta`` terms and D's terms).  Relative coordinates throughout avoid the
      paper's mix of absolute and relative ones (seed notes, Sec. 2.3).  Carrying the vector through the increments
      and projecting once equals applying Eq. 7 recursively, as projection ignores the vector's length.
    * The attitude is propagated with the same increments, each re-orthonormalised (polar decomposition).

    Error per increment of angle ``|theta|`` (rad): the increment differs from the exact rotation by ``[theta x]^2
    / 2`` + O(theta^3), of norm at most ``|theta|^2 / 2``.  On a direction at angle ``beta`` from the rotation axis
    that stretches the component across the axis by ``sqrt(1 + theta^2)``, turning the direction by about
    ``(theta^2 / 2) sin(beta) cos(beta) <= theta^2 / 4``, and rotates by ``atan|theta|`` instead of ``|theta|``
    (``theta^3 / 3`` short).  Re-orthonormalised, the attitude is left with the shortfall alone: a rotation by
    exactly ``atan|theta|`` about the increment's axis.  The model carries no coning correction either.  The
    stretch adds up over increments about one axis: ``N theta^2 / 4`` after ``N`` increments, against the attitude's
    ``N theta^3 / 3`` (on paper_000, 1 deg/s per axis at 500 Hz for 15 s, these come to about 1.4 and 1e-4 arcsec).
    """

    def _state_from(self, attitude: Rotation, stars: list[StarMeasurements]):
        directions = [
            cam.mounting.inv().apply(_paper_camera(cam).unproject(s.xy))
            for cam, s in zip(self._cameras, stars, strict=True)
        ]
        return attitude.as_matrix(), directions, [s.catalog_id.copy() for s in stars]

    def _propagated(self, state, delta_angles: np.ndarray, coning: np.ndarray, span: np.ndarray):
        attitude, directions, ids = state
        carried = np.eye(3)
        for increment in np.eye(3) - skew(delta_angles):
            attitude = _orthonormalised(increment @ attitude)
            carried = increment @ carried
        moved = [d @ carried.T for d in directions]
        return attitude, [d / np.linalg.norm(d, axis=1, keepdims=True) for d in moved], ids

    def _prediction(self, state) -> Prediction:
        attitude, directions, ids = state
        stars = []
        for cam, body, head_ids in zip(self._cameras, directions, ids, strict=True):
            paper = _paper_camera(cam)
            v = cam.mounting.apply(body)
            near = v[:, 2] >= np.cos(_field_radius(paper, self.margin_px))
            xy, _ = paper.project(v[near])
            keep = paper.in_frame(xy, self.margin_px)
            stars.append(StarMeasurements(xy[keep], catalog_id=head_ids[near][keep]))
        return Prediction(Rotation.from_matrix(attitude), stars)


def _paper_camera(camera: Camera) -> Camera:
    """The camera as paper 000's model sees it: its RadialXY distortion if it has one, else an ideal pinhole."""
    if isinstance(camera.distortion, RadialXY | NoDistortion):
        return camera
    return dataclasses.replace(camera, distortion=NoDistortion())


def _orthonormalised(matrix: np.ndarray) -> np.ndarray:
    """The rotation matrix nearest ``matrix`` (3, 3): the orthogonal factor of its polar decomposition."""
    u, _, vt = np.linalg.svd(matrix)
    return u @ vt


class QuaternionPredictor(_GyroPropagator):
    """Exact attitude propagation from the gyro, and the catalog stars imaged at the predicted attitude.

    Per sample interval the attitude turns by the rotation vector ``phi_k = dtheta_k + (1/12) dtheta_{k-1} x
    dtheta_k`` (the two-sample coning correction, Savage / Bortz), ``A <- Rotation.from_rotvec(-phi_k) * A``: exact
    when the rate keeps its axis; under coning at angular frequency Omega the drift it leaves is of fourth order in
    ``Omega h`` (h the sample interval), against second order without the term.  Parts of a sample interval get
    the term scaled by (part / interval)^3, so that the parts compose to the whole to that order.
    ``coning_correction=False`` drops the term (for comparison).

    Predicted stars per head: the identified stars of the last update (ids found in the catalog) still imaged within
    ``margin_px`` of the sensor, in their order, then the other catalog stars imaged there (those that entered the
    field, from a cone query around the head's predicted boresight), brightest first; positions are the calibrated
    camera's projection of the catalog directions.  Stars without a catalog id are not carried.
    """

    def __init__(self, margin_px: float = 0.0, coning_correction: bool = True):
        super().__init__(margin_px)
        self.coning_correction = bool(coning_correction)
        self._hip_sorted = np.zeros(0, dtype=np.int64)
        self._hip_rows = np.zeros(0, dtype=np.intp)

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        super().reset(cameras, catalog)
        self._hip_rows = np.argsort(catalog.hip, kind="stable")
        self._hip_sorted = catalog.hip[self._hip_rows]

    def _catalog_rows(self, ids: np.ndarray) -> np.ndarray:
        """Catalog rows of the HIP numbers ``ids`` found in the catalog, first occurrences in their order."""
        if not len(self._hip_sorted):
            return np.zeros(0, dtype=np.intp)
        position = np.minimum(np.searchsorted(self._hip_sorted, ids), len(self._hip_sorted) - 1)
        found = (ids >= 0) & (self._hip_sorted[position] == ids)
        rows = self._hip_rows[position[found]]
        _, first = np.unique(rows, return_index=True)
        return rows[np.sort(first)]

    def _state_from(self, attitude: Rotation, stars: list[StarMeasurements]):
        return attitude, [self._catalog_rows(s.catalog_id) for s in stars]

    def _propagated(self, state, delta_angles: np.ndarray, coning: np.ndarray, span: np.ndarray):
        attitude, seen = state
        rotation_vectors = delta_angles + coning if self.coning_correction else delta_angles
        for phi in rotation_vectors:
            attitude = Rotation.from_rotvec(-phi) * attitude
        return attitude, seen

    def _prediction(self, state) -> Prediction:
        attitude, seen = state
        stars = [self._stars_on(cam, rows, attitude) for cam, rows in zip(self._cameras, seen, strict=True)]
        return Prediction(attitude, stars)

    def _stars_on(self, camera: Camera, seen_rows: np.ndarray, attitude: Rotation) -> StarMeasurements:
        """Catalog stars imaged within ``margin_px`` of ``camera``'s sensor at ``attitude``, last seen ones first."""
        to_camera = camera.inertial_to_camera(attitude)
        in_cone = self._catalog.cone(to_camera.inv().apply([0.0, 0.0, 1.0]), _field_radius(camera, self.margin_px))
        entering = np.setdiff1d(in_cone, seen_rows)
        entering = entering[np.argsort(self._catalog.magnitude[entering], kind="stable")]
        rows = np.concatenate([seen_rows[np.isin(seen_rows, in_cone)], entering])
        xy, front = camera.project(to_camera.apply(self._catalog.unit[rows]))
        keep = front & camera.in_frame(xy, self.margin_px)
        return StarMeasurements(xy[keep], catalog_id=self._catalog.hip[rows[keep]])
