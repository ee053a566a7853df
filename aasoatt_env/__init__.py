"""aasoatt_env: acceleration-actuated multi-robot environment and CBF-QP safety filter.

Layers (each imports only those above it in this list):

1. :mod:`aasoatt_env.errors`, :mod:`aasoatt_env.validation`: errors and the one validation layer;
2. :mod:`aasoatt_env.model`: robot parameters, dynamics, neighbour geometry, the tracking law;
3. :mod:`aasoatt_env.sim`: the PettingZoo env, observations, rewards, scenarios, references, rendering;
4. :mod:`aasoatt_env.safety`: barriers, deadlock strategies, solvers, the filter core and wrapper;
5. :mod:`aasoatt_env.api`: :func:`make_env`, the Gymnasium view, the registered ids;
6. :mod:`aasoatt_env.analysis`: rollouts, recording, metrics, plots;
7. :mod:`aasoatt_env.apps`: the command line and the paper's reproduction (with :mod:`agents`, :mod:`train`).

Importing the package registers the environment ids of
:mod:`aasoatt_env.api.registration` with PettingZoo and Gymnasium.
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
from aasoatt_env.sim import (
    SCENARIOS,
    AASOATTParallelEnv,
    BatchedAASOATTEnv,
    RewardConfig,
    Scenario,
    ShardedBatchedEnv,
    get_scenario,
)

__version__ = "0.1.0"

register_all()

__all__ = [
    "ENV_IDS", "PRESETS", "SCENARIOS", "AASOATTError", "AASOATTFilter", "AASOATTGymEnv", "AASOATTParallelEnv",
    "ActionError", "BatchedAASOATTEnv", "ConfigError", "DataFileError", "FilterConfig", "FilterReport", "FilterResult",
    "ResetNeeded", "RewardConfig", "RobotParams", "SafetyFilter", "Scenario", "ScenarioError", "ShardedBatchedEnv",
    "SolverError", "StateError", "Team", "UnknownKeywordError", "UsageError", "env", "get_scenario",
    "make_batched_env", "make_env", "make_team", "parallel_env",
]
