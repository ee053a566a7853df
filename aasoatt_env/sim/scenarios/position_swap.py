"""``position_swap``: 4 TurtleBot3 Burgers swap corners, 2.24 m at 0.1 m/s (the paper's Fig. 6 experiment)."""

from __future__ import annotations

import numpy as np

from aasoatt_env.errors import ConfigError
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.sim.references import LinearReference
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario

__all__ = ["PositionSwap"]


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
