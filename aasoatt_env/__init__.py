"""aasoatt_env: acceleration-actuated multi-robot environment and CBF-QP safety filter.

Layers, each importing only those before it: ``errors``/``validation``, ``model``, ``sim``, ``safety``, ``api``,
``analysis``, ``apps`` (with :mod:`agents`, :mod:`train`).  Importing it registers the env ids (``docs/env.md``).
"""

from aasoatt_env.api import ENV_IDS, AASOATTGymEnv, env, make_batched_env, make_env, parallel_env, register_all
from aasoatt_env.errors import (
    AASOATTError,
    ActionError,
    ConfigError,
    DataFileError,
    ResetNeeded,
    ScenarioError,
    SolverError,
    StateError,
    UnknownKeywordError,
    UsageError,
)
from aasoatt_env.model import PRESETS, RobotParams, Team, make_team
from aasoatt_env.safety import AASOATTFilter, FilterConfig, FilterReport, FilterResult, SafetyFilter
from aasoatt_env.sim import SCENARIOS, AASOATTParallelEnv, BatchedAASOATTEnv, RewardConfig, Scenario, get_scenario
from aasoatt_env.sim.sharded import ShardedBatchedEnv

__version__ = "0.1.0"

register_all()


def __getattr__(name: str):
    """``make_tensor_env`` on first use (:mod:`aasoatt_env.tensor` imports torch; ``import aasoatt_env`` does not)."""
    if name == "make_tensor_env":
        try:
            from aasoatt_env.tensor.env import make_tensor_env
        except ModuleNotFoundError as exc:
            if exc.name != "torch":
                raise
            raise ImportError("make_tensor_env needs torch: pip install torch (or the 'train' extra)") from exc
        return make_tensor_env
    raise AttributeError(f"module 'aasoatt_env' has no attribute {name!r}")

__all__ = [
    "ENV_IDS", "PRESETS", "SCENARIOS", "AASOATTError", "AASOATTFilter", "AASOATTGymEnv", "AASOATTParallelEnv",
    "ActionError", "BatchedAASOATTEnv", "ConfigError", "DataFileError", "FilterConfig", "FilterReport", "FilterResult",
    "ResetNeeded", "RewardConfig", "RobotParams", "SafetyFilter", "Scenario", "ScenarioError", "ShardedBatchedEnv",
    "SolverError", "StateError", "Team", "UnknownKeywordError", "UsageError", "env", "get_scenario",
    "make_batched_env", "make_env", "make_team", "parallel_env",
]
