"""``Pipeline``: agents composed into a policy from a ``StarSensorEnv`` observation to its action.

Per step: the predictor propagates the last estimate with the gyro to the frame's mid-exposure; on each head with a
valid frame the deblurrer (optional) restores the image, the detector finds and centroids stars and the distortion
corrector (optional) maps their positions to the calibrated camera's; the identifier labels them (all heads at once,
with the prediction as prior); the solver turns the identified stars of all heads into one attitude.  When fewer
than two stars are identified (a dropped or smeared-out frame), the predicted attitude is reported instead, so the
predictor carries the pipeline through; the estimate (solved or predicted) becomes the predictor's new state.  With a
solved attitude the corrector learns from the identified stars.  The solver takes the catalogue directions
aberrated for the observation's observer velocity (``correct_aberration``), so that the attitude is not biased by the
~20 arcsec the sensor's motion moves every star.  The action reports the measured positions
(``detections_xy``), the corrected ones (``corrected_xy``, the same rows) and the predicted stars where they will be
measured (the predictor's positions in the calibrated camera mapped back through the corrector).

Agents are given as instances, classes or ``"module:Class"`` strings (a path an agent had before it moved is
refused with its new one).  A string is data: only a class under ``starenv`` (or under a module prefix the caller
trusts, ``trust=``) that implements its role's protocol is imported and constructed, see :func:`load_agent`.
``Pipeline`` is a :class:`~starenv.agents.base.Policy`: after each call ``report`` holds the step's wall time per
role (s), where the attitude came from and, with a deblurrer, each head's restoration.
"""

from __future__ import annotations

import importlib
import inspect
import sys
import time
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.agents import MOVED
from starenv.agents.base import (
    MAX_STARS,
    ROLE_PROTOCOLS,
    AttitudeFilter,
    Prediction,
    Restoration,
    SensorInfo,
    StarMeasurements,
    StepReport,
    step_input,
)
from starenv.agents.identify.database import field_mag_limit
from starenv.scenario import PipelineSpec
from starenv.sim.ephemeris import aberrate
from starenv.sim.sky import load_catalog

ONBOARD_MAX_MAG = 7.5
DEFAULTS = {
    "predictor": "starenv.agents.predict:QuaternionPredictor",
    "deblurrer": None,
    "detector": "starenv.agents.detect:CentroidDetector",
    "corrector": None,
    "identifier": "starenv.agents.identify:TrackingIdentifier",
    "solver": "starenv.agents.solve:QuestSolver",
}


TRUSTED = ("starenv",)  # module prefixes agents may be loaded from without an explicit trust


def _trusted(module: str, trust: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in (*TRUSTED, *trust))


def check_trust(trust: Any) -> tuple[str, ...]:
    """``trust`` as a tuple of module prefixes (``"mypkg"`` trusts ``mypkg`` and ``mypkg.*``), or ValueError."""
    if isinstance(trust, str):
        trust = (trust,)
    ok = isinstance(trust, list | tuple) and all(
        isinstance(p, str) and p and all(part.isidentifier() for part in p.split(".")) for p in trust)
    if not ok:
        raise ValueError(f"trust: expected module prefixes like 'mypkg' or 'mypkg.agents', got {trust!r}")
    return tuple(trust)


def _protocol_methods(protocol: type) -> dict[str, int]:
    """Public method name -> number of positional parameters after ``self`` that the pipeline passes."""
    out = {}
    for name, fn in vars(protocol).items():
        if callable(fn) and not name.startswith("_"):
            out[name] = len(inspect.signature(fn).parameters) - 1
    return out


def check_agent_class(cls: type, role: str) -> None:
    """Refuse a class that does not implement ``role``'s protocol (methods present and callable with the arguments
    the pipeline passes), without constructing it."""
    protocol = ROLE_PROTOCOLS[role]
    for name, n_args in _protocol_methods(protocol).items():
        method = inspect.getattr_static(cls, name, None)
        if method is None or not callable(getattr(cls, name, None)):
            raise ValueError(f"{role}: {cls.__name__} does not implement the {protocol.__name__} protocol "
                             f"(no method {name})")
        try:
            inspect.signature(getattr(cls, name)).bind(*[None] * (n_args + 1))
        except TypeError as exc:
            raise ValueError(f"{role}: {cls.__name__}.{name} cannot take the {n_args} arguments of "
                             f"{protocol.__name__}.{name} ({exc})") from exc
        except ValueError:  # no signature (a builtin): nothing more to check
            pass


def load_agent(spec: Any, role: str, *, trust: tuple[str, ...] = (), **kwargs) -> Any:
    """An agent for ``role`` from an instance, a class or a ``"module:Class"`` string (kwargs go to the class).

    A string is data (it may come from a scenario or bench file): its module is imported only when it lies under
    ``starenv`` or a prefix in ``trust``, and only a class defined there that implements the role's protocol is
    constructed; anything else is refused before any of its code runs."""
    if role not in ROLE_PROTOCOLS:
        raise ValueError(f"unknown agent role {role!r}; roles are {', '.join(ROLE_PROTOCOLS)}")
    trust = check_trust(trust)
    if spec is None:
        return None
    if isinstance(spec, str):
        if spec in MOVED:
            raise ValueError(f"{role}: agent {spec!r} has moved: write {MOVED[spec]!r}")
        module_name, sep, class_name = spec.partition(":")
        if not sep or not module_name or not class_name:
            raise ValueError(f"{role}: agent {spec!r} must be written 'module:Class', e.g. {DEFAULTS['detector']!r}")
        if not _trusted(module_name, trust):
            raise ValueError(f"{role}: agent {spec!r}: module {module_name!r} is outside starenv and not trusted; "
                             f"trust it explicitly if you trust its code: add --trust {module_name.split('.')[0]} "
                             f"after the command (starenv run SCENARIO --trust {module_name.split('.')[0]} ..., "
                             f"starenv bench BENCH --trust {module_name.split('.')[0]} ...), or pass "
                             f"trust=[{module_name.split('.')[0]!r}] in Python")
        try:
            spec = getattr(importlib.import_module(module_name), class_name)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f"{role}: cannot load agent {module_name}:{class_name} ({exc})") from exc
        if not isinstance(spec, type):
            raise ValueError(f"{role}: {module_name}:{class_name} is not a class (expected an agent class)")
        if not _trusted(spec.__module__, trust):
            raise ValueError(f"{role}: {module_name}:{class_name} is defined in {spec.__module__!r}, which is not "
                             "trusted (name the class where it is defined)")
    if isinstance(spec, type):
        check_agent_class(spec, role)
        try:
            inspect.signature(spec).bind(**kwargs)
        except TypeError as exc:
            raise ValueError(f"{role}: options {sorted(kwargs)} do not fit {spec.__name__} ({exc})") from exc
        except ValueError:  # no signature to check (a builtin): the constructor checks
            pass
        try:
            agent = spec(**kwargs)
        except TypeError as exc:  # an option of the wrong type
            raise ValueError(f"{role}: {spec.__name__} refused its options {kwargs} ({exc})") from exc
    elif kwargs:
        raise ValueError(f"{role}: options {sorted(kwargs)} can only be given with a class or 'module:Class'")
    else:
        agent = spec
    if not isinstance(agent, ROLE_PROTOCOLS[role]):
        raise ValueError(f"{role}: {type(agent).__name__} does not implement the "
                         f"{ROLE_PROTOCOLS[role].__name__} protocol")
    return agent


def class_path(cls: type) -> str:
    """``"module:Class"`` for ``cls``: the package door that exports it (the outermost one), else its module."""
    parts = cls.__module__.split(".")
    for n in range(1, len(parts)):
        door = sys.modules.get(".".join(parts[:n]))
        if cls.__name__ in getattr(door, "__all__", ()) and getattr(door, cls.__name__, None) is cls:
            return f"{door.__name__}:{cls.__name__}"
    return f"{cls.__module__}:{cls.__name__}"


class Pipeline:
    """Predictor, deblurrer, detector, distortion corrector, identifier and solver as one policy.

    ``catalog_mag_limit`` is the onboard catalog's magnitude limit (the sensor's own star catalog, separate from the
    simulator's sky); None picks the limit that puts ~30 stars in the narrowest head's field (at most Hp 7.5): deep
    enough for tracking, while the lost-in-space database takes its own brighter cut.  ``options`` maps a role to
    constructor options for agents given as class or string; ``trust``: module prefixes outside ``starenv`` that
    ``"module:Class"`` strings may load agents from (see :func:`load_agent`); ``correct_aberration``: whether the
    solver's reference directions are aberrated for the observer velocity (off only to show the bias it removes).
    """

    def __init__(self, catalog_mag_limit: float | None = None, options: dict[str, dict] | None = None, *,
                 trust: tuple[str, ...] = (), correct_aberration: bool = True, **agents):
        unknown = set(agents) - set(ROLE_PROTOCOLS)
        if unknown:
            raise ValueError(f"unknown agent roles {sorted(unknown)}; roles are {', '.join(ROLE_PROTOCOLS)}")
        options = options or {}
        specs = {**DEFAULTS, **agents}
        self.agents = {role: load_agent(specs[role], role, trust=trust, **options.get(role, {}))
                       for role in ROLE_PROTOCOLS}
        if self.agents["detector"] is None or self.agents["identifier"] is None or self.agents["solver"] is None:
            raise ValueError("a pipeline needs at least a detector, an identifier and a solver")
        self.catalog_mag_limit = catalog_mag_limit
        self.correct_aberration = bool(correct_aberration)
        self.catalog = None
        self.sensor: SensorInfo | None = None
        self.report = StepReport()

    @classmethod
    def from_spec(cls, spec: PipelineSpec, trust: tuple[str, ...] = ()) -> Pipeline:
        """The pipeline a :class:`~starenv.scenario.PipelineSpec` describes (``trust``: see :func:`load_agent`)."""
        return cls(spec.catalog_mag_limit, spec.options, trust=trust, **spec.agents)

    @classmethod
    def for_scenario(cls, scenario, agents: dict | None = None, options: dict | None = None,
                     trust: tuple[str, ...] = ()) -> Pipeline:
        """The pipeline a scenario's ``[pipeline]`` table asks for, with ``agents`` / ``options`` taking precedence."""
        return cls.from_spec(scenario.pipeline.replaced_by(PipelineSpec(agents or {}, options or {})), trust)

    @property
    def cameras(self) -> list:
        return [] if self.sensor is None else self.sensor.cameras

    def describe(self) -> dict[str, str]:
        """Role -> agent class path (``None`` where the role is empty), through its package door where the door
        exports it (``starenv.agents.identify:TrackingIdentifier``)."""
        return {r: None if a is None else class_path(type(a)) for r, a in self.agents.items()}

    def reset(self, sensor: SensorInfo) -> None:
        """Prepare for an episode of a sensor (``env.unwrapped.sensor_info``): cameras, onboard catalog."""
        self.sensor = sensor
        epoch = sensor.epoch
        limit = self.catalog_mag_limit
        source = sensor.catalog  # the scenario's onboard catalogue file; None: the bundled Hipparcos-2

        def onboard(mag_limit: float):
            return load_catalog(mag_limit, epoch) if source is None else source.load(mag_limit, epoch)

        if limit is None:
            limit = min(field_mag_limit(self.cameras, onboard(8.0).magnitude, 30.0), ONBOARD_MAX_MAG)
        self.catalog = onboard(limit)
        for role in ("predictor", "identifier", "corrector"):
            if self.agents[role] is not None:
                self.agents[role].reset(self.cameras, self.catalog)
        self.report = StepReport()

    def _timed(self, role: str, fn, *args):
        t0 = time.perf_counter()
        out = fn(*args)
        latency = self.report.latency_s
        latency[role] = latency.get(role, 0.0) + time.perf_counter() - t0
        return out

    def __call__(self, obs: dict) -> dict:
        """The action for one observation."""
        if self.catalog is None:
            raise RuntimeError("call Pipeline.reset(env.unwrapped.sensor_info) before using it")
        ag = self.agents
        report = self.report = StepReport(detector=ag["detector"] if ag["deblurrer"] is not None else None)
        t_start = time.perf_counter()
        step = step_input(obs, self.sensor)
        prediction = Prediction(None, [StarMeasurements(np.zeros((0, 2))) for _ in self.cameras])
        if ag["predictor"] is not None:
            prediction = self._timed("predictor", ag["predictor"].predict, step)
        found, seen = [], []
        corrector = ag["corrector"]
        report.restorations = [None] * len(self.cameras) if ag["deblurrer"] is not None else []
        for h, cam in enumerate(self.cameras):
            if not step.frame_valid[h]:
                found.append(StarMeasurements(np.zeros((0, 2))))
                seen.append(None)
                continue
            image = step.images[h][: cam.height, : cam.width]
            if ag["deblurrer"] is not None:
                raw = image
                image = self._timed("deblurrer", ag["deblurrer"].deblur, image, h, step)
                info = dict(getattr(ag["deblurrer"], "last_info", {}) or {})
                report.restorations[h] = Restoration(raw, image, info)
            seen.append(image)
            stars = self._timed("detector", ag["detector"].detect, image, cam)
            if corrector is not None:
                stars = self._timed("corrector", corrector.correct, stars, h, cam)
            found.append(stars)
        identified = self._timed("identifier", ag["identifier"].identify, found, self.cameras, prediction.attitude,
                                 seen)
        attitude = self._solve(identified, step.observer_velocity_m_s)
        measured, predicted = identified, prediction.stars
        if corrector is not None:  # back to the image, with the weights the detections were corrected with
            measured = [self._timed("corrector", corrector.uncorrect, s, h, cam)
                        for h, (s, cam) in enumerate(zip(identified, self.cameras, strict=True))]
            predicted = [self._timed("corrector", corrector.uncorrect, s, h, cam)
                         for h, (s, cam) in enumerate(zip(prediction.stars, self.cameras, strict=False))]
        if attitude is not None:
            report.source = "solved"
            if corrector is not None:
                for h, cam in enumerate(self.cameras):
                    self._timed("corrector", corrector.learn, identified[h], h, cam, attitude, self.catalog)
        elif prediction.attitude is not None:
            attitude, report.source = prediction.attitude, "predicted"
        if isinstance(ag["predictor"], AttitudeFilter):
            # a filter fuses the measured stars and its posterior is the action (its own prediction when none)
            if attitude is not None:
                self._timed("predictor", ag["predictor"].update, attitude, identified, step.time_s)
                attitude, report.gyro_bias, report.covariance = ag["predictor"].posterior()
                report.events.extend(getattr(ag["predictor"], "events", ()))
        elif attitude is not None and ag["predictor"] is not None:
            carried = identified if report.source == "solved" else prediction.stars
            self._timed("predictor", ag["predictor"].update, attitude, carried, step.time_s)
        report.latency_s["pipeline"] = time.perf_counter() - t_start
        return self._action(attitude, identified, measured, predicted)

    def _solve(self, identified: list[StarMeasurements], velocity_m_s: np.ndarray) -> Rotation | None:
        """The attitude from the identified stars of all heads; the catalogue directions are made apparent for the
        observer velocity ``velocity_m_s`` (m/s, ICRS axes) first, unless it is zero or the correction is off."""
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
        references = np.vstack(inertial)
        if self.correct_aberration and np.any(velocity_m_s):
            references = aberrate(references, velocity_m_s)
        try:
            return self._timed("solver", self.agents["solver"].solve, np.vstack(body), references, None)
        except ValueError:  # e.g. all identified stars (nearly) parallel: no attitude from this frame
            return None

    def _action(self, attitude: Rotation | None, identified: list[StarMeasurements], measured: list[StarMeasurements],
                predicted: list[StarMeasurements]) -> dict:
        n_heads = len(self.cameras)
        action = {
            "attitude": np.array([0.0, 0.0, 0.0, 1.0]) if attitude is None else attitude.as_quat(),
            "attitude_valid": np.int8(attitude is not None),
            "detections_xy": np.zeros((n_heads, MAX_STARS, 2)),
            "corrected_xy": np.zeros((n_heads, MAX_STARS, 2)),
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
            action["detections_xy"][h, :k] = measured[h].xy[order]
            action["corrected_xy"][h, :k] = stars.xy[order]
            action["catalog_ids"][h, :k] = stars.catalog_id[order]
            action["detection_mask"][h, :k] = 1
            pred = predicted[h] if h < len(predicted) else StarMeasurements(np.zeros((0, 2)))
            known = np.flatnonzero((pred.catalog_id >= 0) & np.all(np.isfinite(pred.xy), axis=1))[:MAX_STARS]
            k = len(known)
            action["predicted_xy"][h, :k] = pred.xy[known]
            action["predicted_ids"][h, :k] = pred.catalog_id[known]
            action["prediction_mask"][h, :k] = 1
        return action
