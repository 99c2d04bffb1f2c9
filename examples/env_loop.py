"""Your own estimator in an ``env.step`` loop.

The estimator here is the simplest a flight engineer would write: solve the first frame with starenv's classical
pipeline (lost in space), then carry the attitude with the gyro alone (first-order quaternion integration of each
sample).  The env scores every action against truth, so the printout shows the gyro-only drift growing from the
solved start.  Replace ``GyroDeadReckoning`` with your own estimator: the action is ``{"attitude": [x, y, z, w]
(ICRS -> body, the frame's mid-exposure), "attitude_valid": 1}``.

    python examples/env_loop.py --steps 50 --seed 0
"""

from __future__ import annotations

import argparse
import json

import gymnasium as gym
import numpy as np
from scipy.spatial.transform import Rotation

import starenv  # noqa: F401  registers the StarEnv ids
from starenv.agents.pipeline import Pipeline


class GyroDeadReckoning:
    """Attitude from the first solved frame, then the gyro only.  Each gyro sample is the mean body rate (rad/s,
    body frame) over the interval ``(t - dt, t]`` before its time stamp ``t``; the attitude is carried through those
    intervals up to each frame's mid-exposure time, a sample that spans it split there."""

    def __init__(self, env):
        self.pipeline = Pipeline.for_scenario(env.unwrapped.scenario, {"identifier": "starenv.agents.identify:"
                                                                        "LostInSpaceIdentifier"})
        self.pipeline.reset(env.unwrapped.sensor_info)
        self.dt = 1.0 / env.unwrapped.sensor_info.gyro_rate_hz  # s
        self.attitude: Rotation | None = None  # ICRS -> body
        self.t = 0.0  # time (s) the attitude refers to
        self.samples: list[tuple[float, np.ndarray]] = []  # (time stamp s, rate rad/s) not yet fully used

    def __call__(self, obs: dict) -> dict:
        gyro = obs["gyro"]
        n = int(gyro["count"])
        self.samples += [(float(t), np.asarray(w, dtype=np.float64)) for t, w in zip(gyro["t"][:n], gyro["rate"][:n],
                                                                                     strict=True)]
        t_frame = float(obs["time_s"])
        if self.attitude is None:
            action = self.pipeline(obs)
            if action["attitude_valid"]:
                self.attitude, self.t = Rotation.from_quat(action["attitude"]), t_frame
            return {"attitude": action["attitude"], "attitude_valid": action["attitude_valid"]}
        while self.samples and self.t < t_frame:
            stamp, rate = self.samples[0]
            end = min(stamp, t_frame)
            if end > self.t:  # the body turns by rate * dt: ICRS -> body gains the inverse rotation
                start = max(self.t, stamp - self.dt)
                self.attitude = Rotation.from_rotvec(-rate * (end - start)) * self.attitude
                self.t = end
            if stamp <= t_frame:
                self.samples.pop(0)
        return {"attitude": self.attitude.as_quat(), "attitude_valid": 1}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper_002")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    env = gym.make("StarEnv/Scenario-v0", scenario=args.scenario, overrides={"motion.rate_dps": [0.0, 0.0, 1.0]})
    obs, info = env.reset(seed=args.seed)
    estimator = GyroDeadReckoning(env)
    errors = []
    for _ in range(args.steps):
        obs, reward, terminated, truncated, info = env.step(estimator(obs))
        errors.append(info["scores"]["attitude"].get("total_arcsec", float("nan")))
        if terminated or truncated:
            break
    result = {"steps": len(errors), "first_error_arcsec": errors[0], "last_error_arcsec": errors[-1]}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
