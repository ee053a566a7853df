"""``obstacle_field``: seeded random starts and goals among seeded random disc obstacles of a given density."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ScenarioError
from aasoatt_env.sim.scenarios.random_goals import RandomGoals

__all__ = ["ObstacleField"]


class ObstacleField(RandomGoals):
    """Random starts and goals (as :class:`.RandomGoals`) among random discs covering ``density`` of the arena.

    Disc radii are uniform in ``radii = (low, high)`` [m]; their count is ``density`` times the arena's area over
    a disc's mean area; centres are uniform, each disc clear of every start and goal by the robots' radius + 0.1 m
    (discs may overlap one another, so a goal can be walled off: a geometry with no solution).  Straight-line
    references; ``settle_time`` [s] defaults to 30.
    """

    name = "obstacle_field"
    _pad, _tries = 4, 200
    _crowded = "density: could not place {m} obstacles clear of the robots; lower the density or enlarge arena_size"

    def __init__(self, num_robots: int = 8, density: float = 0.1, radii: Any = (0.3, 0.8), settle_time: float = 30.0,
                 **kwargs: Any) -> None:
        self.density = check.real("density", density, lo=0.0, hi=0.5)
        r = check.real_array("radii", radii, lo=1e-3, hi=1e3, unit=" m").reshape(-1)
        if r.shape != (2,) or r[0] > r[1]:
            raise ScenarioError(f"radii: got {check.short_repr(np.asarray(radii).tolist())}, expected (low, high) "
                                "with 0 < low <= high")
        self.radii = (float(r[0]), float(r[1]))
        super().__init__(num_robots=num_robots, settle_time=settle_time, **kwargs)
        mean_area = math.pi * (r[0] ** 2 + r[0] * r[1] + r[1] ** 2) / 3.0
        self.random_obstacles = int(round(self.density * self.arena_size**2 / mean_area))
