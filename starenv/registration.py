"""Gymnasium ids for the bundled scenarios (registered on ``import starenv``; registering twice is harmless)."""

from __future__ import annotations

import gymnasium as gym

from starenv.scenario import bundled_names

ENTRY_POINT = "starenv.env:StarSensorEnv"


def env_id(scenario_name: str) -> str:
    """``paper_002`` -> ``StarEnv/Paper002-v0``."""
    return "StarEnv/" + "".join(part.capitalize() for part in scenario_name.split("_")) + "-v0"


def register_envs() -> list[str]:
    """Register every bundled scenario and ``StarEnv/Scenario-v0``; returns the ids."""
    ids = []
    for name in bundled_names():
        ids.append(env_id(name))
        if ids[-1] not in gym.registry:
            gym.register(ids[-1], entry_point=ENTRY_POINT, kwargs={"scenario": name}, disable_env_checker=False)
    if "StarEnv/Scenario-v0" not in gym.registry:
        gym.register("StarEnv/Scenario-v0", entry_point=ENTRY_POINT)
    ids.append("StarEnv/Scenario-v0")
    return ids
