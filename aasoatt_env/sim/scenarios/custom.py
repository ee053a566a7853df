"""``custom``: your own team: start points, a reference (object, callable or waypoints) and obstacles."""

from __future__ import annotations

from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.model.portable import atan2
from aasoatt_env.sim.references import COORD_MAX, as_reference
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario

__all__ = ["Custom"]


class Custom(Scenario):
    """Your own team: start points, a reference (object, callable or waypoints) and obstacles.

    ``starts (N, 2)`` [m]; ``reference``: a :class:`~aasoatt_env.sim.references.Reference`, a callable ``t -> (N, 2)``
    with its ``duration`` [s], or ``{"waypoints": (N, K, 2), "times": (K,)}``; ``headings (N,)`` [rad] (default: along
    the reference velocity at ``t = 0``, else toward the goal); the horizon adds ``settle_time`` [s].
    """

    name = "custom"

    def __init__(self, starts: Any, reference: Any, duration: float | None = None, headings: Any = None,
                 obstacles: tuple[Any, Any] | None = None, robots: str | RobotParams | list = "paper",
                 settle_time: float = 3.0) -> None:
        st = check.real_array("starts", starts, lo=-COORD_MAX, hi=COORD_MAX, unit=" m")
        if st.ndim != 2 or st.shape[1] != 2 or not 1 <= st.shape[0] <= base.MAX_ROBOTS:
            raise ConfigError(f"starts: got shape {st.shape}, expected (N, 2) with 1 <= N <= {base.MAX_ROBOTS}")
        self.num_robots_ = st.shape[0]
        self._starts = st
        if duration is not None:
            duration = base.check_quantity("duration", duration)
            if not callable(reference) or (hasattr(reference, "goals") and hasattr(reference, "duration")):
                raise ConfigError(f"duration: got {duration:g} with a {type(reference).__name__} reference, which sets "
                                  "its own duration; duration is only for a callable reference t -> (N, 2)")
        self._reference = as_reference(reference, self.num_robots_, duration)
        self._team = make_team(robots, self.num_robots_)
        self._obstacles = base.check_obstacles(obstacles)
        base.check_clear_of_obstacles("obstacles", st, self._team.radius, self._obstacles)
        base.check_clear_of_obstacles("obstacles", np.asarray(self._reference.goals, float), self._team.radius,
                                      self._obstacles)
        self._headings = None if headings is None else check.real_array("headings", headings, lo=-1e6, hi=1e6,
                                                                         unit=" rad").reshape(-1)
        if self._headings is not None and self._headings.shape != (self.num_robots_,):
            raise ConfigError(f"headings: got shape {self._headings.shape}, expected ({self.num_robots_},)")
        self.settle_time = base.check_settle_time(settle_time)
        base.check_no_overlap("starts", st, self._team.radius)

    def build(self, rng: np.random.Generator) -> Layout:
        """Return the user's layout."""
        ref = self._reference
        _, v0, _ = ref(0.0)
        toward = atan2(*(ref.goals - self._starts).T[::-1])
        headings = self._headings if self._headings is not None else base.heading_of(v0, toward)
        pts = np.concatenate([self._starts, ref.goals, *(ref(t)[0] for t in np.linspace(0, ref.duration, 16)),
                              self._obstacles[0]])
        return Layout(team=self._team, starts=self._starts.copy(), headings=headings, reference=ref,
                      horizon=ref.duration + self.settle_time, obstacle_centers=self._obstacles[0],
                      obstacle_radii=self._obstacles[1], bounds=base.bounds_around(pts))
