"""``StarSensorEnv``: the Gymnasium environment around the star-sensor simulator.

Timeline.  ``reset`` returns the observation of frame 0; each ``step(action)`` takes the pipeline's estimate *for the
frame it last observed*, scores it against that frame's truth, simulates the next frame and returns it.  So
``info["scores"]`` of a step scores the action against frame ``info["scores"]["frame"]`` (the previous observation)
while ``info["truth"]`` is the truth of the observation returned with it.

Observation (``Dict``), as the sensor delivers it -- never truth:

* ``frames``: uint16 (heads, H, W) raw images (heads smaller than the largest are zero-padded at the bottom/right);
  a dropped frame is all zeros with ``frame_valid = 0``, never a stale image.
* ``frame_valid``: int8 (heads,).
* ``gyro``: ``{"t": float64 (N,), "rate": float64 (N, 3), "count": int64 ()}``: the ``count`` samples stamped since
  the previous observation (s; rad/s, body frame, average rate over each sample interval), padded with zeros up to
  ``N = ceil(rate_hz / frame_rate_hz) + 1``.
* ``time_s``: float64 (), mid-exposure time of the frame; ``exposure_s``: float64 ().
* ``observer_velocity_m_s``: float64 (3,), the sensor's velocity (m/s, ICRS axes) at mid-exposure as navigation gives
  it to flight software: the Earth's barycentric velocity plus the orbital one, the velocity the stars are aberrated
  for (``[sky] aberration``); zeros when the scenario renders geometric star directions.
* ``blinded``: int8 (heads,), 1 where the Sun, the Moon or the Earth's limb lies within the head's exclusion angle
  (``[sky] bodies``, ``[heads.baffle]``): the frame is delivered but fogged or saturated by stray light, as the
  sensor's status word flags it.

Action (``Dict``): ``attitude`` float64 (4,) quaternion ``[x, y, z, w]`` (inertial -> body, at mid-exposure of the
observed frame; normalised on receipt) and ``attitude_valid`` int8 (); optionally per-head star lists padded to
``MAX_STARS`` rows, the rows in use flagged by a 0/1 mask: ``detections_xy`` (heads, MAX_STARS, 2) px with
``detection_mask`` (heads, MAX_STARS) and ``catalog_ids`` (heads, MAX_STARS) (-1: not identified), ``corrected_xy``
(heads, MAX_STARS, 2) px (the same rows after distortion correction: where the calibrated camera images each
detection's direction); ``predicted_xy``
(heads, MAX_STARS, 2) px with ``predicted_ids`` and ``prediction_mask`` (heads, MAX_STARS).  ``None``, a missing
``attitude`` or ``attitude_valid = 0`` makes the step *unavailable*; NaN/inf, a wrong shape or dtype raises
``ValueError`` naming the key.  Vector environments batch every key: start from :meth:`StarSensorEnv.null_action`.

Reward: ``max(0, 1 - error / threshold)`` for an available estimate (1 when exact, 0 at or beyond the scenario's
``availability_threshold_arcsec``; with a per-axis threshold the largest of every head's cross-boresight and roll error
over its bound), 0 when unavailable.  ``terminated`` once ``lost_after_steps`` consecutive steps had no available
estimate within the threshold ("lost", ``scores["within_threshold"]`` false); ``truncated`` after the scenario's last
frame (the bundled ids register the same count as ``max_episode_steps``: ``n_steps - 1`` steps).  A lost episode may
still be stepped (benchmarks score whole episodes); stepping after ``truncated`` raises ``gymnasium.error.ResetNeeded``:
there is no next frame.  ``reset(seed=...)`` takes a Python or numpy integer in [0, 2**63); ``reset`` takes no options
(``options`` must be None or empty: anything else raises ``ValueError`` rather than being ignored).

Prefetch.  ``prefetch=True`` simulates the next frame on a background thread as soon as a step (or ``reset``)
returns, while the caller works on the frame it was given; ``step`` then only scores the action and waits for that
frame.  The frames, gyro samples and scores are the same, bit for bit, as without it (the next frame never depends
on the action).  It pays where the caller's work between steps leaves a core free and releases the GIL (numpy,
OpenCV), the more so the longer a frame takes to simulate (``benchmarks/env_speed.py`` times the built-in pipeline
with and without it); in an async vector env, whose workers already keep the cores busy, it gains nothing.
Nothing else may use ``env.sensor`` while a frame is being prefetched.

Noise thread.  Within a step, each head's read-out noise (one float32 standard normal a pixel, the step's largest
cost) is drawn on a second thread while the stars render (``noise_thread=True``); the frames are the same bit for bit
as with ``noise_thread=False``, which draws it after the render.  The default (None) takes the thread where the
process may run on two cores or more and is not a worker of a pool of processes (a vector env's or a parallel
bench's), whose siblings already keep the cores busy (:func:`~starenv.sim.sensor.noise_thread_default`).

Bounds.  Every box is finite so that ``observation_space.sample()`` works: times lie in ``[0, T]`` with ``T`` the
episode's last mid-exposure time plus one frame period (``time_horizon_s``; an env stepped past truncation leaves
it), gyro rates in ``[-GYRO_RATE_BOUND, GYRO_RATE_BOUND]`` rad/s (3600 deg/s; a bound on the space, the gyro model
does not saturate).

Info.  ``reset`` returns ``{"truth"}``, ``step`` ``{"truth", "scores"}``:

* ``truth`` (of the returned observation's frame): ``frame`` int (index), ``time_s`` float (s, mid-exposure),
  ``attitude`` float64 (4,) ``[x, y, z, w]`` (ICRS -> body at mid-exposure), ``body_rate`` float64 (3,) (rad/s, body
  frame), ``gyro_bias`` float64 (3,) (rad/s, gyro axes: the total bias of the last gyro sample delivered with the
  frame, at the end of its exposure window), ``dropped`` list of bool per head, ``stars`` list per head of dicts of
  arrays, one row per star on the frame: ``catalog_id`` (HIP number), ``magnitude`` (Hipparcos Hp), ``xy_mid`` /
  ``xy_centroid`` / ``xy_start`` / ``xy_end`` (n, 2) px (distorted pixel coordinates; mid-exposure position, trail
  centroid, trail ends), ``electrons`` and ``peak_electrons`` (e-; total and brightest pixel), ``detectable`` bool.
  With ``[sky] bodies``: ``blinded`` (per head, the bodies blinding it, comma-separated, "" for none),
  ``stray_e_per_px_s`` (per head, the bodies' stray light, e-/px/s) and ``bodies`` (per head, one row per body:
  ``name``, ``xy_mid`` px (NaN behind the camera), ``angle_deg`` from the boresight (the Earth's: its limb's),
  ``magnitude`` (V), ``electrons`` drawn on the sensor, ``in_field``).
* ``scores`` (of the action, against frame ``scores["frame"]``, the previous observation): ``frame`` int and
  ``time_s`` float (s, that frame's mid-exposure time), the step's scores, ``attitude`` (empty when unavailable, so
  that vector envs can merge the infos) holding the error's ``body`` (its signed components about the body axes)
  and ``heads`` (one dict per head: its signed components about that head's camera axes), and ``heads`` (one dict
  per head: star-level scores, None where the action gave nothing to score; correction scores need the action's
  ``corrected_xy``).  Signs: the error rotation is ``estimate x truth^-1`` (ICRS -> body attitudes), its
  rotation vector ``e`` (body frame) gives ``body``, and ``M e`` (``M``: the head's body -> camera mounting) a
  head's: an estimate ``Rotation.from_rotvec(a * u) * truth`` scores ``+a`` about the unit axis ``u``.
  Every score, with its unit, in the table below, composed from ``starenv.metrics`` when this module is imported
  (``python -m starenv.metrics`` prints it):

"""

from __future__ import annotations

import math
import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from starenv import metrics
from starenv import scenario as scenario_mod
from starenv.agents.base import MAX_STARS, SensorInfo
from starenv.scoring import score_step, threshold_errors
from starenv.sim.sensor import Frame, StarSensor

GYRO_RATE_BOUND = math.radians(3600.0)  # rad/s, the observation space's bound on each gyro rate component
VELOCITY_BOUND_M_S = 1e5  # m/s, the observation space's bound on each observer velocity component
__doc__ += metrics.info_table() + "\n"


class StarSensorEnv(gym.Env):
    """A scenario's star sensor heads and gyro stepped frame by frame; see the module docstring for the contract."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scenario: str | dict = "paper_000",
        overrides: dict[str, Any] | None = None,
        render_mode: str | None = None,
        prefetch: bool = False,
        noise_thread: bool | None = None,
    ):
        if not isinstance(prefetch, bool):
            raise ValueError(f"prefetch must be True or False, got {prefetch!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        if not isinstance(scenario, str | os.PathLike | dict):
            raise ValueError("scenario: expected a bundled scenario name, a .toml path or a parsed scenario dict, "
                             f"got {type(scenario).__name__} {scenario!r}")
        self.scenario = scenario_mod.load(scenario, overrides)
        self.render_mode = render_mode
        self.sensor = StarSensor(self.scenario, noise_thread=noise_thread)
        sc = self.scenario
        self.metadata = {**self.metadata, "render_fps": max(1, int(round(sc.frame_rate_hz)))}
        n_heads = len(sc.heads)
        height = max(h.camera.height for h in sc.heads)
        width = max(h.camera.width for h in sc.heads)
        self.max_gyro = int(math.ceil(sc.gyro.rate_hz / sc.frame_rate_hz)) + 1
        horizon = self.time_horizon_s
        self.observation_space = spaces.Dict(
            {
                "frames": spaces.Box(0, 65535, (n_heads, height, width), np.uint16),
                "frame_valid": spaces.Box(0, 1, (n_heads,), np.int8),
                "gyro": spaces.Dict(
                    {
                        "t": spaces.Box(0.0, horizon, (self.max_gyro,), np.float64),
                        "rate": spaces.Box(-GYRO_RATE_BOUND, GYRO_RATE_BOUND, (self.max_gyro, 3), np.float64),
                        "count": spaces.Box(0, self.max_gyro, (), np.int64),
                    }
                ),
                "time_s": spaces.Box(0.0, horizon, (), np.float64),
                "exposure_s": spaces.Box(0.0, horizon, (), np.float64),
                "observer_velocity_m_s": spaces.Box(-VELOCITY_BOUND_M_S, VELOCITY_BOUND_M_S, (3,), np.float64),
                "blinded": spaces.Box(0, 1, (n_heads,), np.int8),
            }
        )
        self.action_space = spaces.Dict(
            {
                "attitude": spaces.Box(-1.0, 1.0, (4,), np.float64),
                "attitude_valid": spaces.Box(0, 1, (), np.int8),
                "detections_xy": spaces.Box(-1e4, 1e5, (n_heads, MAX_STARS, 2), np.float64),
                "detection_mask": spaces.Box(0, 1, (n_heads, MAX_STARS), np.int8),
                "corrected_xy": spaces.Box(-1e4, 1e5, (n_heads, MAX_STARS, 2), np.float64),
                "catalog_ids": spaces.Box(-1, 2**31 - 1, (n_heads, MAX_STARS), np.int64),
                "predicted_xy": spaces.Box(-1e4, 1e5, (n_heads, MAX_STARS, 2), np.float64),
                "predicted_ids": spaces.Box(-1, 2**31 - 1, (n_heads, MAX_STARS), np.int64),
                "prediction_mask": spaces.Box(0, 1, (n_heads, MAX_STARS), np.int8),
            }
        )
        self._frame: Frame | None = None
        self._steps = 0
        self._lost_steps = 0
        self.prefetch = prefetch
        self._prefetcher = self._new_prefetcher()
        self._next: Future | Frame | None = None  # the next frame, being prefetched or ready

    @property
    def time_horizon_s(self) -> float:
        """Upper bound of every time in an episode's observations (s): the last frame's end plus one frame period."""
        sc = self.scenario
        return (sc.n_steps + 1) * sc.frame_period_s + sc.exposure_s

    def null_action(self) -> dict:
        """A complete action that claims nothing (unavailable, empty star lists): a template to fill in, and what
        vector environments need since they batch every key of the action space."""
        return {k: np.zeros(space.shape, dtype=space.dtype) for k, space in self.action_space.spaces.items()}

    @property
    def cameras(self):
        """The calibrated camera model of each head, as the sensor knows it (may differ from the true optics)."""
        return [h.calibrated for h in self.scenario.heads]

    @property
    def sensor_info(self) -> SensorInfo:
        """What a policy may know of the sensor before the first frame: calibrated cameras, gyro rate, epoch, the
        onboard catalogue's file."""
        sc = self.scenario
        return SensorInfo(self.cameras, sc.gyro.rate_hz, sc.epoch, sc.onboard_catalog)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode: returns ``(observation of frame 0, {"truth": ...})``.

        ``seed`` (int) reseeds every noise source (the first reset without one uses the scenario's ``seed``);
        ``options`` must be None or empty (``ValueError`` otherwise).
        """
        if options is not None and (not isinstance(options, dict) or options):
            raise ValueError(f"reset options: StarSensorEnv takes none (expected None or {{}}), got {options!r}; "
                             "change the scenario with overrides instead")
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= int(seed) < 2**63:
                raise ValueError(f"seed: expected None or an integer in [0, 2**63), got {seed!r}")
            seed = int(seed)
        if seed is None and self._np_random is None:
            seed = self.scenario.seed
        super().reset(seed=seed)
        self._discard_next()
        self.sensor.reset(np.random.SeedSequence(int(self.np_random.integers(0, 2**63 - 1))))
        self._frame = self.sensor.next_frame()
        self._steps = 0
        self._lost_steps = 0
        self._start_next()
        return self._observation(self._frame), {"truth": self._truth(self._frame)}

    def step(self, action):
        """Score ``action`` (the estimate for the last observed frame), then simulate the next frame.

        Returns ``(observation, reward, terminated, truncated, info)``; ``info`` holds ``truth`` (of the returned
        frame) and ``scores`` (of the action); see the module docstring for every key and unit.
        """
        if self._frame is None:
            raise RuntimeError("call reset() before step()")
        if self._steps >= self.scenario.n_steps - 1:
            raise gym.error.ResetNeeded(f"the episode ended (truncated) after its last frame, step {self._steps}: "
                                        "call reset() before step()")
        parsed = parse_action(action, len(self.scenario.heads))
        scores = score_step(parsed, self._frame, self.scenario)
        reward = 0.0
        if scores["available"]:
            errors = threshold_errors(scores["attitude"], self.scenario.availability_threshold_arcsec)
            reward = max(0.0, 1.0 - max(e / bound for e, bound in errors))
        self._lost_steps = 0 if scores["within_threshold"] else self._lost_steps + 1
        self._steps += 1
        terminated = self._lost_steps >= self.scenario.lost_after_steps
        truncated = self._steps >= self.scenario.n_steps - 1
        self._frame = self._take_next()
        if not truncated:
            self._start_next()
        info = {"truth": self._truth(self._frame), "scores": scores}
        return self._observation(self._frame), float(reward), terminated, truncated, info

    def close(self):
        """Stop the prefetch thread, if any (from here on each frame is simulated in ``step``)."""
        self._discard_next()
        if self._prefetcher is not None:
            self._prefetcher.shutdown()
            self._prefetcher = None
        super().close()

    def __getstate__(self) -> dict:
        """A prefetched frame travels as the finished frame; the thread is made anew on unpickling."""
        state = self.__dict__.copy()
        if isinstance(self._next, Future):
            state["_next"] = self._next.result()
        state["_prefetcher"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._prefetcher = self._new_prefetcher()

    def _new_prefetcher(self) -> ThreadPoolExecutor | None:
        return ThreadPoolExecutor(1, thread_name_prefix="starenv-prefetch") if self.prefetch else None

    def _start_next(self) -> None:
        """With prefetch, start simulating the next frame."""
        if self._prefetcher is not None:
            self._next = self._prefetcher.submit(self.sensor.next_frame)

    def _take_next(self) -> Frame:
        """The next frame: the prefetched one (its exception re-raised here), else simulated now."""
        pending, self._next = self._next, None
        if pending is None:
            return self.sensor.next_frame()
        return pending.result() if isinstance(pending, Future) else pending

    def _discard_next(self) -> None:
        """Wait for a prefetched frame and drop it (the sensor is about to be reset or closed)."""
        pending, self._next = self._next, None
        if isinstance(pending, Future):
            pending.exception()  # waits; an error there concerns a frame nobody will see

    def render(self):
        """``render_mode="rgb_array"``: uint8 (H, W, 3) mosaic of the last frame's heads (a display stretch, not
        radiometry), true star trails overlaid; None in any other mode or before ``reset``."""
        if self.render_mode != "rgb_array" or self._frame is None:
            return None
        from starenv.view import mosaic, overlay

        return mosaic([overlay(h.image, h.truth, h.dropped) for h in self._frame.heads])

    def _observation(self, frame: Frame) -> dict:
        space = self.observation_space
        image = frame.heads[0].image
        if len(frame.heads) == 1 and image.shape == space["frames"].shape[1:] and image.dtype == np.uint16:
            frames = image[None]  # the read-out's new array itself (the env's frame keeps it for render() only)
        else:
            frames = np.empty(space["frames"].shape, dtype=np.uint16)  # only a smaller head's padding is zeroed
            for i, h in enumerate(frame.heads):
                rows, cols = h.image.shape
                frames[i, :rows, :cols] = h.image
                frames[i, rows:] = 0
                frames[i, :rows, cols:] = 0
        n = len(frame.gyro.t)
        if n > self.max_gyro:
            raise RuntimeError(f"{n} gyro samples in one step exceed the layout's {self.max_gyro}")
        t = np.zeros(self.max_gyro)
        rate = np.zeros((self.max_gyro, 3))
        t[:n], rate[:n] = frame.gyro.t, frame.gyro.rate
        return {
            "frames": frames,
            "frame_valid": np.array([not h.dropped for h in frame.heads], dtype=np.int8),
            "gyro": {"t": t, "rate": rate, "count": np.array(n, dtype=np.int64)},
            "time_s": np.array(frame.t_mid, dtype=np.float64),
            "exposure_s": np.array(self.scenario.exposure_s, dtype=np.float64),
            "observer_velocity_m_s": np.array(frame.observer_velocity_m_s, dtype=np.float64),
            "blinded": np.array([h.bodies is not None and h.bodies.blinded for h in frame.heads], dtype=np.int8),
        }

    @staticmethod
    def _truth(frame: Frame) -> dict:
        return {
            "frame": frame.index,
            "time_s": frame.t_mid,
            "attitude": frame.attitude.as_quat(),
            "body_rate": frame.body_rate,
            "gyro_bias": frame.gyro_bias,
            "dropped": [h.dropped for h in frame.heads],
            "stars": [h.truth.as_dict() for h in frame.heads],
        } | ({} if frame.heads[0].bodies is None else {
            "blinded": [h.bodies.blinded_by for h in frame.heads],
            "stray_e_per_px_s": [h.bodies.stray_e_per_px_s for h in frame.heads],
            "bodies": [h.bodies.truth for h in frame.heads],
        })


def _array(action: dict, key: str, shape: tuple, kind: str) -> np.ndarray:
    value = action[key]
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError, OverflowError) as exc:
        raise ValueError(f"action[{key!r}] must be an array of shape {shape}, got {value!r:.80} ({exc})") from exc
    if kind == "f" and arr.dtype.kind not in "fiu" or kind == "i" and arr.dtype.kind not in "iu":
        expected = "real numbers" if kind == "f" else "integers"
        raise ValueError(f"action[{key!r}] must hold {expected}, got dtype {arr.dtype}")
    if arr.shape != shape:
        raise ValueError(f"action[{key!r}] must have shape {shape}, got {arr.shape}")
    if kind == "f" and not np.all(np.isfinite(arr)):
        raise ValueError(f"action[{key!r}] must be finite (no NaN or inf)")
    return arr.astype(np.float64 if kind == "f" else np.int64)


def parse_action(action, n_heads: int) -> dict:
    """Validate an action; returns per-head lists (None where absent) and the attitude quaternion or None."""
    out: dict[str, Any] = {"attitude": None}
    keys = ("detections_xy", "catalog_ids", "corrected_xy", "predicted_xy", "predicted_ids")
    out.update({k: [None] * n_heads for k in keys})
    if action is None:
        return out
    if not isinstance(action, dict):
        raise ValueError(f"action must be a dict (see StarSensorEnv.action_space) or None, got {type(action).__name__}")
    bad_keys = [k for k in action if not isinstance(k, str)]
    if bad_keys:
        raise ValueError(f"action keys must be strings, got {bad_keys[0]!r}")
    unknown = set(action) - {"attitude", "attitude_valid", "detection_mask", "prediction_mask", *keys}
    if unknown:
        raise ValueError(f"action has unknown keys {sorted(unknown)}")
    valid = True
    if "attitude_valid" in action:
        flag = _array(action, "attitude_valid", (), "i")
        if flag not in (0, 1):
            raise ValueError(f"action['attitude_valid'] must be 0 or 1, got {int(flag)}")
        valid = bool(flag)
    if "attitude" in action:
        q = _array(action, "attitude", (4,), "f")
        scale = float(np.max(np.abs(q)))
        q = q / scale if scale > 0 else q  # so the norm cannot overflow (a quaternion's scale carries no meaning)
        norm = float(np.linalg.norm(q))
        if valid and scale < 1e-6:
            raise ValueError("action['attitude'] must be a quaternion [x, y, z, w] of non-zero norm (it is normalised)")
        out["attitude"] = q / norm if valid else None
    for list_key, mask_key, xy_key, id_key in (
        ("detections", "detection_mask", "detections_xy", "catalog_ids"),
        ("predictions", "prediction_mask", "predicted_xy", "predicted_ids"),
    ):
        if xy_key not in action and id_key not in action:
            continue
        if mask_key not in action:
            raise ValueError(f"action has {list_key} but no {mask_key!r} saying which rows are in use")
        mask = _array(action, mask_key, (n_heads, MAX_STARS), "i")
        if np.any((mask != 0) & (mask != 1)):
            raise ValueError(f"action[{mask_key!r}] must hold 0 or 1")
        xy = _array(action, xy_key, (n_heads, MAX_STARS, 2), "f") if xy_key in action else None
        ids = _array(action, id_key, (n_heads, MAX_STARS), "i") if id_key in action else None
        corrected = None
        if xy_key == "detections_xy" and "corrected_xy" in action:
            corrected = _array(action, "corrected_xy", (n_heads, MAX_STARS, 2), "f")
        for h in range(n_heads):
            rows = mask[h].astype(bool)
            out[xy_key][h] = None if xy is None else xy[h, rows]
            out[id_key][h] = None if ids is None else ids[h, rows]
            if corrected is not None:
                out["corrected_xy"][h] = corrected[h, rows]
    if out["detections_xy"][0] is None:
        out["catalog_ids"] = [None] * n_heads  # ids are scored through their detections
        out["corrected_xy"] = [None] * n_heads
    return out
