"""Gymnasium ids for the bundled scenarios (registered on ``import starenv``; registering twice is harmless)."""

from __future__ import annotations

import gymnasium as gym

from starenv.scenario import bundled_names, load

ENTRY_POINT = "starenv.env:StarSensorEnv"
VECTOR_ENTRY_POINT = "starenv.vector:make_vector_env"  # what gym.make_vec builds when given no vectorization_mode


def env_id(scenario_name: str) -> str:
    """``paper_002`` -> ``StarEnv/Paper002-v0``."""
    return "StarEnv/" + "".join(part.capitalize() for part in scenario_name.split("_")) + "-v0"


def register_envs() -> list[str]:
    """Register every bundled scenario (with ``max_episode_steps``: the steps until the env truncates) and
    ``StarEnv/Scenario-v0`` (whose length depends on its scenario: the env truncates it itself), each with
    :func:`starenv.vector.make_vector_env` as its vector entry point; returns the ids."""
    ids = []
    for name in bundled_names():
        ids.append(env_id(name))
        if ids[-1] not in gym.registry:
            gym.register(ids[-1], entry_point=ENTRY_POINT, kwargs={"scenario": name}, disable_env_checker=False,
                         max_episode_steps=load(name).n_steps - 1, vector_entry_point=VECTOR_ENTRY_POINT)
    if "StarEnv/Scenario-v0" not in gym.registry:
        gym.register("StarEnv/Scenario-v0", entry_point=ENTRY_POINT, vector_entry_point=VECTOR_ENTRY_POINT)
    ids.append("StarEnv/Scenario-v0")
    return ids
