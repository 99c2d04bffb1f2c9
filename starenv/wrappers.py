"""Observation wrappers for reinforcement-learning libraries, which want a single array or a flat ``Dict`` of boxes.

* :class:`ImageObservation`: the raw frames only, a uint16 ``Box`` (heads, H, W) (or (H, W, heads) with
  ``channels_last``, the layout of image CNN policies); a dropped head's image is all zeros.
* :class:`FlatStateObservation`: a flat ``Dict`` with the frames and one float64 ``state`` vector holding everything
  else, in this order: ``frame_valid`` (heads), ``gyro.count``, ``gyro.t`` (N, s), ``gyro.rate`` (N x 3 row-major,
  rad/s, body), ``time_s``, ``exposure_s`` (s), ``observer_velocity_m_s`` (3, m/s, ICRS axes), ``blinded`` (heads).
  :meth:`FlatStateObservation.state_names` names each entry.

``gymnasium.wrappers.FlattenObservation`` also works on the env (everything, the frames included, in one float64
vector).  Both wrappers keep the env's action space, reward and info.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class ImageObservation(gym.ObservationWrapper):
    """The raw frames alone: uint16 (heads, H, W), or (H, W, heads) when ``channels_last``."""

    def __init__(self, env: gym.Env, channels_last: bool = False):
        super().__init__(env)
        self.channels_last = channels_last
        frames = env.observation_space["frames"]
        shape = frames.shape[1:] + frames.shape[:1] if channels_last else frames.shape
        self.observation_space = spaces.Box(0, 65535, shape, np.uint16)

    def observation(self, observation: dict) -> np.ndarray:
        frames = observation["frames"]
        return np.ascontiguousarray(np.moveaxis(frames, 0, -1)) if self.channels_last else frames


class FlatStateObservation(gym.ObservationWrapper):
    """``{"frames": uint16 (heads, H, W), "state": float64 (k,)}``: no nested dicts (see the module docstring)."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        space = env.observation_space
        gyro = space["gyro"]
        parts = [space["frame_valid"], gyro["count"], gyro["t"], gyro["rate"], space["time_s"], space["exposure_s"],
                 space["observer_velocity_m_s"], space["blinded"]]
        low = np.concatenate([np.ravel(p.low).astype(np.float64) for p in parts])
        high = np.concatenate([np.ravel(p.high).astype(np.float64) for p in parts])
        self.observation_space = spaces.Dict(
            {"frames": space["frames"], "state": spaces.Box(low, high, low.shape, np.float64)}
        )

    def state_names(self) -> list[str]:
        """Name of each entry of ``state`` (``gyro.rate[i,j]``: sample i, body axis j)."""
        space = self.env.observation_space
        n_heads, n_gyro = space["frame_valid"].shape[0], space["gyro"]["t"].shape[0]
        return ([f"frame_valid[{h}]" for h in range(n_heads)] + ["gyro.count"]
                + [f"gyro.t[{i}]" for i in range(n_gyro)]
                + [f"gyro.rate[{i},{j}]" for i in range(n_gyro) for j in range(3)] + ["time_s", "exposure_s"]
                + [f"observer_velocity_m_s[{j}]" for j in range(3)] + [f"blinded[{h}]" for h in range(n_heads)])

    def observation(self, observation: dict) -> dict:
        g = observation["gyro"]
        state = np.concatenate([
            np.ravel(observation["frame_valid"]), np.ravel(g["count"]), np.ravel(g["t"]), np.ravel(g["rate"]),
            np.ravel(observation["time_s"]), np.ravel(observation["exposure_s"]),
            np.ravel(observation["observer_velocity_m_s"]), np.ravel(observation["blinded"]),
        ]).astype(np.float64)
        return {"frames": observation["frames"], "state": state}
