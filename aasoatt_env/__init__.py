"""aasoatt_env: acceleration-actuated multi-robot environment and CBF-QP safety filter."""

from aasoatt_env.errors import AASOATTError, ActionError, ConfigError, ScenarioError, SolverError
from aasoatt_env.params import PRESETS, RobotParams, Team, make_team

__all__ = [
    "PRESETS",
    "AASOATTError",
    "ActionError",
    "ConfigError",
    "RobotParams",
    "ScenarioError",
    "SolverError",
    "Team",
    "make_team",
]
