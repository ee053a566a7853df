"""Scenarios, one file each (``docs/env.md``); a new one: a :class:`Scenario` subclass, a line in :data:`SCENARIOS`."""

from __future__ import annotations

import inspect
from typing import Any

from aasoatt_env.errors import ScenarioError, UnknownKeywordError
from aasoatt_env.sim.scenarios.base import Layout, Scenario, max_robots_on_circle
from aasoatt_env.sim.scenarios.circle_obstacles import FIG5_OBSTACLES, CircleSwapObstacles
from aasoatt_env.sim.scenarios.circle_swap import CircleSwap
from aasoatt_env.sim.scenarios.corridor import Corridor
from aasoatt_env.sim.scenarios.custom import Custom
from aasoatt_env.sim.scenarios.doorway import Doorway
from aasoatt_env.sim.scenarios.obstacle_field import ObstacleField
from aasoatt_env.sim.scenarios.position_swap import PositionSwap
from aasoatt_env.sim.scenarios.random_goals import RandomGoals
from aasoatt_env.sim.scenarios.tracking import Tracking
from aasoatt_env.validation import reject_unknown

__all__ = ["FIG5_OBSTACLES", "SCENARIOS", "CircleSwap", "CircleSwapObstacles", "Corridor", "Custom", "Doorway",
           "Layout", "ObstacleField", "PositionSwap", "RandomGoals", "Scenario", "Tracking", "get_scenario",
           "max_robots_on_circle"]

SCENARIOS: dict[str, type[Scenario]] = {
    cls.name: cls for cls in (CircleSwap, CircleSwapObstacles, Tracking, PositionSwap, RandomGoals, Custom, Corridor,
                              Doorway, ObstacleField)
}
"""Scenario registry: name -> class."""


def get_scenario(scenario: str | Scenario, **kwargs: Any) -> Scenario:
    """A scenario from a name and its parameters (unknown names: ``TypeError`` listing them), or an instance."""
    if isinstance(scenario, Scenario):
        if kwargs:
            raise UnknownKeywordError(f"scenario parameters {sorted(kwargs)} given with a Scenario instance; "
                                      "pass them to its constructor instead")
        return scenario
    if not isinstance(scenario, str) or scenario not in SCENARIOS:
        raise ScenarioError(f"unknown scenario {scenario!r}; known scenarios: {sorted(SCENARIOS)}")
    cls = SCENARIOS[scenario]
    params = [p for c in cls.__mro__ if "__init__" in vars(c) and issubclass(c, Scenario) and c is not Scenario
              for p in inspect.signature(c.__init__).parameters if p not in ("self", "kwargs")]
    reject_unknown(f"scenario {scenario!r}: {cls.__name__}", kwargs, params)
    return cls(**kwargs)
