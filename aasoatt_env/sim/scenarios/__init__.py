"""Scenarios: who starts where, which reference each robot tracks, which obstacles.

A scenario is the middle layer between the physics (:mod:`aasoatt_env.model`)
and the environment plumbing (:mod:`aasoatt_env.sim.env`): it validates its own
parameters once, then :meth:`Scenario.build` returns a
:class:`~aasoatt_env.sim.scenarios.base.Layout` for a given random generator.
One file per scenario (as in PettingZoo's MPE2 and VMAS), each with its table:

=======================  ===============  ==================================================
name                     paper            layout
=======================  ===============  ==================================================
``circle_swap``          Tab. II, III     N robots evenly on a circle, each tracks the
                                          straight line to its antipode
``circle_obstacles``     Fig. 5           circle swap with static disc obstacles
                                          (default: 20 robots, 3 obstacles)
``tracking``             Tab. I           one robot on a straight / sine / circle reference
``position_swap``        Fig. 6           4 TurtleBot3 Burgers swap corners, 2.24 m at 0.1 m/s
``random_goals``         (learning)       random starts and goals, spacing guaranteed
``custom``               (yours)          your starts, reference (callable / waypoints)
                                          and obstacles
=======================  ===============  ==================================================

Adding a scenario: one file with a :class:`Scenario` subclass, and one line in
:data:`SCENARIOS`.
"""

from __future__ import annotations

import inspect
from typing import Any

from aasoatt_env.errors import ScenarioError, UnknownKeywordError
from aasoatt_env.sim.scenarios.base import Layout, Scenario, max_robots_on_circle
from aasoatt_env.sim.scenarios.circle_obstacles import FIG5_OBSTACLES, CircleSwapObstacles
from aasoatt_env.sim.scenarios.circle_swap import CircleSwap
from aasoatt_env.sim.scenarios.custom import Custom
from aasoatt_env.sim.scenarios.position_swap import PositionSwap
from aasoatt_env.sim.scenarios.random_goals import RandomGoals
from aasoatt_env.sim.scenarios.tracking import Tracking
from aasoatt_env.validation import reject_unknown

__all__ = [
    "FIG5_OBSTACLES",
    "SCENARIOS",
    "CircleSwap",
    "CircleSwapObstacles",
    "Custom",
    "Layout",
    "PositionSwap",
    "RandomGoals",
    "Scenario",
    "Tracking",
    "get_scenario",
    "max_robots_on_circle",
]

SCENARIOS: dict[str, type[Scenario]] = {
    cls.name: cls for cls in (CircleSwap, CircleSwapObstacles, Tracking, PositionSwap, RandomGoals, Custom)
}
"""Scenario registry: name -> class."""


def get_scenario(scenario: str | Scenario, **kwargs: Any) -> Scenario:
    """A scenario instance from a name (with parameters) or an instance passed through.

    Unknown parameter names raise ``TypeError`` (Python's convention) naming the
    scenario and listing its parameters.
    """
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
