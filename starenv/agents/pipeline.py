"""``Pipeline``: agents composed into a policy from a ``StarSensorEnv`` observation to its action.

Per step: the predictor propagates the last estimate with the gyro to the frame's mid-exposure; on each head with a
valid frame the deblurrer (optional) restores the image, the detector finds and centroids stars and the distortion
corrector (optional) fixes their positions; the identifier labels them (all heads at once, with the prediction as
prior); the solver turns the identified stars of all heads into one attitude.  When fewer than two stars are
identified (a dropped or smeared-out frame), the predicted attitude is reported instead, so the predictor carries
the pipeline through; the estimate (solved or predicted) becomes the predictor's new state.

Agents are given as instances, classes or ``"module:Class"`` strings.  Every agent call is timed:
``latency_s`` holds the last step's wall time per role (s) and ``source`` says where the attitude came from.  With a
deblurrer, ``restorations`` holds per head the last step's ``(raw, restored)`` images (None for a head without a
valid frame) and ``deblur_info`` the deblurrer's ``last_info`` after that head (``{}`` if it sets none).
"""

from __future__ import annotations

import importlib
import time
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.agents.base import (
    AGENT_ROLES,
    AttitudeSolver,
    Deblurrer,
    DistortionCorrector,
    GyroRecord,
    Identifier,
    Prediction,
    Predictor,
    StarDetector,
    Stars,
    StepInput,
)
from starenv.agents.identify import field_mag_limit
from starenv.env import MAX_STARS
from starenv.sky import load_catalog

ONBOARD_MAX_MAG = 7.5
ROLES = dict(zip(AGENT_ROLES, (Predictor, Deblurrer, StarDetector, DistortionCorrector, Identifier, AttitudeSolver),
                 strict=True))
DEFAULTS = {
    "predictor": "starenv.agents.predict:QuaternionPredictor",
    "deblurrer": None,
    "detector": "starenv.agents.detect:CentroidDetector",
    "corrector": None,
    "identifier": "starenv.agents.identify:TrackingIdentifier",
    "solver": "starenv.agents.solve:QuestSolver",
}


def load_agent(spec: Any, role: str, **kwargs) -> Any:
    """An agent for ``role`` from an instance, a class or a ``"module:Class"`` string (kwargs go to the class)."""
    if role not in ROLES:
        raise ValueError(f"unknown agent role {role!r}; roles are {', '.join(ROLES)}")
    if spec is None:
        return None
    if isinstance(spec, str):
        module_name, sep, class_name = spec.partition(":")
        if not sep or not module_name or not class_name:
            raise ValueError(f"{role}: agent {spec!r} must be written 'module:Class', e.g. {DEFAULTS['detector']!r}")
        try:
            spec = getattr(importlib.import_module(module_name), class_name)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f"{role}: cannot load agent {module_name}:{class_name} ({exc})") from exc
    agent = spec(**kwargs) if isinstance(spec, type) else spec
    if kwargs and not isinstance(spec, type):
        raise ValueError(f"{role}: options {sorted(kwargs)} can only be given with a class or 'module:Class'")
    if not isinstance(agent, ROLES[role]):
        raise ValueError(f"{role}: {type(agent).__name__} does not implement the {ROLES[role].__name__} protocol")
    return agent


class Pipeline:
    """Predictor, deblurrer, detector, distortion corrector, identifier and solver as one policy.

    ``catalog_mag_limit`` is the onboard catalog's magnitude limit (the sensor's own star catalog, separate from the
    simulator's sky); None picks the limit that puts ~30 stars in the narrowest head's field (at most Hp 7.5): deep
    enough for tracking, while the lost-in-space database takes its own brighter cut.  ``options`` maps a role to
    constructor options for agents given as class or string.
    """

    def __init__(self, catalog_mag_limit: float | None = None, options: dict[str, dict] | None = None, **agents):
        unknown = set(agents) - set(ROLES)
        if unknown:
            raise ValueError(f"unknown agent roles {sorted(unknown)}; roles are {', '.join(ROLES)}")
        options = options or {}
        specs = {**DEFAULTS, **agents}
        self.agents = {role: load_agent(specs[role], role, **options.get(role, {})) for role in ROLES}
        if self.agents["detector"] is None or self.agents["identifier"] is None or self.agents["solver"] is None:
            raise ValueError("a pipeline needs at least a detector, an identifier and a solver")
        self.catalog_mag_limit = catalog_mag_limit
        self.catalog = None
        self.cameras = []
        self.gyro_dt = 0.0
        self.latency_s: dict[str, float] = {}
        self.source = "none"
        self.restorations: list[tuple[np.ndarray, np.ndarray] | None] = []
        self.deblur_info: list[dict] = []

    @classmethod
    def for_scenario(cls, scenario, agents: dict | None = None, options: dict | None = None) -> Pipeline:
        """The pipeline a scenario's ``[pipeline]`` table asks for, with ``agents`` / ``options`` taking precedence."""
        spec = scenario.pipeline
        merged = {**spec.options}
        for role, opts in (options or {}).items():
            merged[role] = {**merged.get(role, {}), **opts}
        return cls(spec.catalog_mag_limit, merged, **{**spec.agents, **(agents or {})})

    def describe(self) -> dict[str, str]:
        """Role -> agent class path (``None`` where the role is empty)."""
        return {r: None if a is None else f"{type(a).__module__}:{type(a).__name__}" for r, a in self.agents.items()}

    def reset(self, env) -> None:
        """Prepare for an episode of ``env`` (a ``StarSensorEnv``, possibly wrapped): cameras, onboard catalog."""
        base = env.unwrapped
        self.cameras = base.cameras
        self.gyro_dt = 1.0 / base.scenario.gyro.rate_hz  # the gyro's sample interval, part of its datasheet
        epoch = base.scenario.epoch
        limit = self.catalog_mag_limit
        if limit is None:
            limit = min(field_mag_limit(self.cameras, load_catalog(8.0, epoch).magnitude, 30.0), ONBOARD_MAX_MAG)
        self.catalog = load_catalog(limit, epoch)
        for role in ("predictor", "identifier"):
            if self.agents[role] is not None:
                self.agents[role].reset(self.cameras, self.catalog)
        self.source = "none"

    def _timed(self, role: str, fn, *args):
        t0 = time.perf_counter()
        out = fn(*args)
        self.latency_s[role] = self.latency_s.get(role, 0.0) + time.perf_counter() - t0
        return out

    def __call__(self, obs: dict) -> dict:
        """The action for one observation."""
        if self.catalog is None:
            raise RuntimeError("call Pipeline.reset(env) before using it")
        self.latency_s = {}
        t_start = time.perf_counter()
        gyro = obs["gyro"]
        n = int(gyro["count"])
        step = StepInput(
            images=list(obs["frames"]),
            frame_valid=np.asarray(obs["frame_valid"], dtype=bool),
            time_s=float(obs["time_s"]),
            exposure_s=float(obs["exposure_s"]),
            gyro=GyroRecord(gyro["t"][:n], gyro["rate"][:n], self.gyro_dt),
            cameras=self.cameras,
        )
        ag = self.agents
        prediction = Prediction(None, [Stars(np.zeros((0, 2))) for _ in self.cameras])
        if ag["predictor"] is not None:
            prediction = self._timed("predictor", ag["predictor"].predict, step)
        found = []
        self.restorations = [None] * len(self.cameras) if ag["deblurrer"] is not None else []
        self.deblur_info = [{} for _ in self.restorations]
        for h, cam in enumerate(self.cameras):
            if not step.frame_valid[h]:
                found.append(Stars(np.zeros((0, 2))))
                continue
            image = step.images[h][: cam.height, : cam.width]
            if ag["deblurrer"] is not None:
                raw = image
                image = self._timed("deblurrer", ag["deblurrer"].deblur, image, h, step)
                self.restorations[h] = (raw, image)
                self.deblur_info[h] = dict(getattr(ag["deblurrer"], "last_info", {}) or {})
            stars = self._timed("detector", ag["detector"].detect, image, cam)
            if ag["corrector"] is not None:
                stars = self._timed("corrector", ag["corrector"].correct, stars, h, cam)
            found.append(stars)
        identified = self._timed("identifier", ag["identifier"].identify, found, self.cameras, prediction.attitude)
        attitude = self._solve(identified)
        if attitude is not None:
            self.source = "solved"
            if ag["corrector"] is not None:
                for h, cam in enumerate(self.cameras):
                    self._timed("corrector", ag["corrector"].learn, identified[h], h, cam, attitude, self.catalog)
        elif prediction.attitude is not None:
            attitude, self.source = prediction.attitude, "predicted"
        else:
            self.source = "none"
        if attitude is not None and ag["predictor"] is not None:
            carried = identified if self.source == "solved" else prediction.stars
            self._timed("predictor", ag["predictor"].update, attitude, carried, step.time_s)
        self.latency_s["pipeline"] = time.perf_counter() - t_start
        return self._action(attitude, identified, prediction)

    def _solve(self, identified: list[Stars]) -> Rotation | None:
        body, inertial = [], []
        for cam, stars in zip(self.cameras, identified, strict=True):
            ok = stars.catalog_id >= 0
            if not ok.any():
                continue
            body.append(cam.mounting.inv().apply(cam.unproject(stars.xy[ok])))
            rows = np.searchsorted(self.catalog.hip, stars.catalog_id[ok])
            inertial.append(self.catalog.unit[rows])
        if sum(len(b) for b in body) < 2:
            return None
        try:
            return self._timed("solver", self.agents["solver"].solve, np.vstack(body), np.vstack(inertial), None)
        except ValueError:  # e.g. all identified stars (nearly) parallel: no attitude from this frame
            return None

    def _action(self, attitude: Rotation | None, identified: list[Stars], prediction: Prediction) -> dict:
        n_heads = len(self.cameras)
        action = {
            "attitude": np.array([0.0, 0.0, 0.0, 1.0]) if attitude is None else attitude.as_quat(),
            "attitude_valid": np.int8(attitude is not None),
            "detections_xy": np.zeros((n_heads, MAX_STARS, 2)),
            "detection_mask": np.zeros((n_heads, MAX_STARS), np.int8),
            "catalog_ids": np.full((n_heads, MAX_STARS), -1, np.int64),
            "predicted_xy": np.zeros((n_heads, MAX_STARS, 2)),
            "predicted_ids": np.full((n_heads, MAX_STARS), -1, np.int64),
            "prediction_mask": np.zeros((n_heads, MAX_STARS), np.int8),
        }
        for h in range(n_heads):
            stars = identified[h]
            order = np.argsort(-stars.flux, kind="stable")[:MAX_STARS]  # brightest first if there are too many
            k = len(order)
            action["detections_xy"][h, :k] = stars.xy[order]
            action["catalog_ids"][h, :k] = stars.catalog_id[order]
            action["detection_mask"][h, :k] = 1
            pred = prediction.stars[h] if h < len(prediction.stars) else Stars(np.zeros((0, 2)))
            known = np.flatnonzero((pred.catalog_id >= 0) & np.all(np.isfinite(pred.xy), axis=1))[:MAX_STARS]
            k = len(known)
            action["predicted_xy"][h, :k] = pred.xy[known]
            action["predicted_ids"][h, :k] = pred.catalog_id[known]
            action["prediction_mask"][h, :k] = 1
        return action
