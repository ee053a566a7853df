"""``circle_swap``: N robots evenly on a circle, each tracks the straight line to its antipode (Tables II, III)."""

from __future__ import annotations

from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ScenarioError
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.model.portable import atan2
from aasoatt_env.sim.references import LinearReference
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario

__all__ = ["CircleSwap"]


class CircleSwap(Scenario):
    """N robots evenly on a circle; each tracks the straight line to its antipode.

    ``radius`` [m] and travel time ``duration`` [s] (paper: 6 m in 12 s, 10 m in 20 s); the horizon adds
    ``settle_time`` [s].  ``robots``: :func:`~aasoatt_env.model.params.make_team`'s; ``profile``:
    :class:`~aasoatt_env.sim.references.LinearReference`'s; ``obstacles``: ``(centres (M, 2), radii (M,))``.
    """

    name = "circle_swap"

    def __init__(self, num_robots: int = 10, radius: float = 6.0, duration: float = 12.0, settle_time: float = 3.0,
                 robots: str | RobotParams | list = "paper", profile: str = "linear",
                 obstacles: tuple[Any, Any] | None = None) -> None:
        self.num_robots_ = base.check_num_robots(num_robots)
        self.radius = base.check_quantity("radius", radius)
        self.duration = base.check_quantity("duration", duration)
        self.settle_time = base.check_settle_time(settle_time)
        self.robots = robots
        self.profile = check.choice("profile", profile, ("linear", "smooth"))
        self._team = make_team(robots, self.num_robots_)
        rmax = float(self._team.radius.max())
        fit = base.max_robots_on_circle(self.radius, rmax) if self.num_robots_ > 1 else 1
        if self.num_robots_ > fit:
            raise ScenarioError(f"num_robots: got {self.num_robots_}, but at most {fit} robots of radius {rmax:g} "
                                f"fit on a circle of radius {self.radius:g}")
        self._obstacles = base.check_obstacles(obstacles)
        starts, goals = self._starts_goals()
        base.check_clear_of_obstacles("obstacles", starts, self._team.radius, self._obstacles)
        base.check_clear_of_obstacles("obstacles", goals, self._team.radius, self._obstacles)

    def _starts_goals(self) -> tuple[np.ndarray, np.ndarray]:
        n = self.num_robots_
        ang = 2.0 * np.pi * np.arange(n) / n
        starts = self.radius * np.stack((np.cos(ang), np.sin(ang)), axis=1)
        return starts, -starts

    def build(self, rng: np.random.Generator) -> Layout:
        """Return the (deterministic) circle-swap layout."""
        starts, goals = self._starts_goals()
        ref = LinearReference(starts, goals, self.duration, profile=self.profile)  # type: ignore[arg-type]
        headings = atan2(goals[:, 1] - starts[:, 1], goals[:, 0] - starts[:, 0])
        b = self.radius + 1.0
        return Layout(team=self._team, starts=starts, headings=headings, reference=ref,
                      horizon=self.duration + self.settle_time, obstacle_centers=self._obstacles[0],
                      obstacle_radii=self._obstacles[1], bounds=(-b, b, -b, b))
