"""Swaps: ``circle_swap`` (Tables II, III), ``circle_obstacles`` (Fig. 5) and ``position_swap`` (Fig. 6)."""

from __future__ import annotations

from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError, ScenarioError
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.sim.references import LinearReference
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario

__all__ = ["FIG5_OBSTACLES", "CircleSwap", "CircleSwapObstacles", "PositionSwap"]

FIG5_OBSTACLES: tuple[tuple[float, float, float], ...] = ((0.0, 0.0, 0.6), (2.8, 1.6, 0.4), (-2.2, -2.6, 0.8))
"""The three obstacles of our Fig. 5 preset: ``(x, y, radius)``."""


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
        headings = np.arctan2(goals[:, 1] - starts[:, 1], goals[:, 0] - starts[:, 0])
        b = self.radius + 1.0
        return Layout(team=self._team, starts=starts, headings=headings, reference=ref,
                      horizon=self.duration + self.settle_time, obstacle_centers=self._obstacles[0],
                      obstacle_radii=self._obstacles[1], bounds=(-b, b, -b, b))


class CircleSwapObstacles(CircleSwap):
    """Circle swap among static disc obstacles (default: 20 robots, :data:`FIG5_OBSTACLES`), as :class:`CircleSwap`."""

    name = "circle_obstacles"

    def __init__(self, num_robots: int = 20, obstacles: tuple[Any, Any] | None = None, **kwargs: Any) -> None:
        if obstacles is None:
            arr = np.array(FIG5_OBSTACLES)
            obstacles = (arr[:, :2], arr[:, 2])
        super().__init__(num_robots=num_robots, obstacles=obstacles, **kwargs)


class PositionSwap(Scenario):
    """Four robots on the corners of a square swap with the opposite corner.

    Each travels the diagonal ``distance`` [m] at ``speed`` [m/s] (the paper's TurtleBot3 experiment:
    2.24 m at 0.1 m/s); the horizon is the travel time plus ``settle_time`` [s].
    """

    name = "position_swap"

    def __init__(self, distance: float = 2.24, speed: float = 0.1, settle_time: float = 5.0,
                 robots: str | RobotParams = "turtlebot3_burger") -> None:
        self.distance = base.check_quantity("distance", distance)
        self.speed = base.check_quantity("speed", speed)
        self.settle_time = base.check_settle_time(settle_time)
        if self.distance / self.speed > base.QUANTITY_RANGE[1]:
            raise ConfigError(f"speed: got {self.speed:g}, which takes {self.distance / self.speed:.3g} s for distance "
                              f"{self.distance:g}; expected a travel time <= {base.QUANTITY_RANGE[1]:g} s")
        self.robots = robots
        self.num_robots_ = 4
        self._team = make_team(robots, 4)
        # the square's corners must hold the robots (neighbouring corners are distance / sqrt(2) apart)
        base.check_no_overlap(f"distance: got {self.distance:g} m, whose start corners do not hold the robots",
                              PositionSwap.build(self, np.random.default_rng(0)).starts, self._team.radius)

    def build(self, rng: np.random.Generator) -> Layout:
        """Return the (deterministic) corner-swap layout."""
        h = self.distance / 2.0
        ang = np.pi / 4 + np.pi / 2 * np.arange(4)
        starts = h * np.stack((np.cos(ang), np.sin(ang)), axis=1)
        goals = -starts
        duration = self.distance / self.speed
        b = h + 0.5
        return Layout(team=self._team, starts=starts, headings=ang + np.pi, horizon=duration + self.settle_time,
                      reference=LinearReference(starts, goals, duration), bounds=(-b, b, -b, b))
