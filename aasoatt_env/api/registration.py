"""Environment ids registered with PettingZoo and Gymnasium on ``import aasoatt_env`` (``docs/env.md``)."""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium
import pettingzoo
from pettingzoo.utils.conversions import parallel_to_aec

from aasoatt_env.api.factory import make_env

__all__ = ["ENV_IDS", "env", "parallel_env", "register_all"]

ENV_IDS: dict[str, str] = {
    "aasoatt/CircleSwap-v0": "circle_swap",
    "aasoatt/CircleSwapObstacles-v0": "circle_obstacles",
    "aasoatt/Tracking-v0": "tracking",
    "aasoatt/PositionSwap-v0": "position_swap",
    "aasoatt/RandomGoals-v0": "random_goals",
}
"""Registered id -> scenario."""


#: The PettingZoo parallel env of a scenario: PettingZoo's name for :func:`aasoatt_env.make_env`.
parallel_env = make_env


def env(scenario: str = "circle_swap", **kwargs: Any) -> Any:
    """Create the AEC version of :func:`parallel_env` (PettingZoo's ``parallel_to_aec``)."""
    return parallel_to_aec(parallel_env(scenario, **kwargs))


def register_all() -> None:
    """Register every id with PettingZoo (parallel and AEC) and Gymnasium (idempotent)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for env_id, scenario in ENV_IDS.items():
            if env_id not in pettingzoo.parallel_registry:
                pettingzoo.register("parallel", env_id, entry_point=parallel_env, kwargs={"scenario": scenario})
            if env_id not in pettingzoo.aec_registry:
                pettingzoo.register("aec", env_id, entry_point=env, kwargs={"scenario": scenario})
            if env_id not in gymnasium.registry:
                gymnasium.register(id=env_id, entry_point="aasoatt_env.api.gym_env:AASOATTGymEnv",
                                   kwargs={"scenario": scenario}, disable_env_checker=False)
