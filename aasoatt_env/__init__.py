"""aasoatt_env: acceleration-actuated multi-robot environment and CBF-QP safety filter.

Importing the package registers the environment ids of
:mod:`aasoatt_env.api.registration` with PettingZoo and Gymnasium.
"""

from aasoatt_env.sim.env import AASOATTParallelEnv, RewardConfig, SimState
from aasoatt_env.errors import AASOATTError, ActionError, ConfigError, ScenarioError, SolverError
from aasoatt_env.api.gym_env import AASOATTGymEnv
from aasoatt_env.model.params import PRESETS, RobotParams, Team, make_team
from aasoatt_env.api.registration import ENV_IDS, env, parallel_env, register_all
from aasoatt_env.safety import FilterConfig, FilterResult, SafetyFilter
from aasoatt_env.safety.wrapper import AASOATTFilter
from aasoatt_env.sim.scenarios import SCENARIOS, Scenario, get_scenario

__version__ = "0.1.0"

register_all()

__all__ = [
    "ENV_IDS",
    "PRESETS",
    "SCENARIOS",
    "AASOATTError",
    "AASOATTFilter",
    "AASOATTGymEnv",
    "AASOATTParallelEnv",
    "ActionError",
    "ConfigError",
    "FilterConfig",
    "FilterResult",
    "RewardConfig",
    "RobotParams",
    "Scenario",
    "SafetyFilter",
    "ScenarioError",
    "SimState",
    "SolverError",
    "Team",
    "env",
    "get_scenario",
    "make_team",
    "parallel_env",
]
