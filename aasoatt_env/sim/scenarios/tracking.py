"""``tracking``: one robot on a straight, sine or circle reference (Table I); ``custom``: your own team."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.sim.references import COORD_MAX, FunctionReference, Reference, as_reference
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario, bounds_around, check_quantity, heading_of

__all__ = ["Custom", "Tracking"]


class Tracking(Scenario):
    """One robot tracking a straight, sine or circle reference (Table I).

    ``trajectory``: ``"straight"``, ``p_d = (v t, v t / 2)``; ``"sine"``, ``p_d = (v t, A sin(w t))``; ``"circle"``,
    ``p_d = R (cos(v t / R), sin(v t / R))``, with ``speed`` ``v`` [m/s], ``amplitude`` ``A`` [m], ``frequency`` ``w``
    [rad/s], ``circle_radius`` ``R`` [m]; ``reference``: a user reference (object or callable) instead.
    """

    name = "tracking"
    TRAJECTORIES: ClassVar[tuple[str, ...]] = ("straight", "sine", "circle")

    def __init__(self, trajectory: str = "circle", speed: float = 0.5, amplitude: float = 1.0, frequency: float = 0.5,
                 circle_radius: float = 2.0, duration: float = 12.0, robots: str | RobotParams = "paper",
                 reference: Any = None) -> None:
        check.choice("trajectory", trajectory, self.TRAJECTORIES)  # checked even when `reference` replaces it
        self.trajectory = trajectory
        self.speed = check_quantity("speed", speed)
        self.amplitude = check_quantity("amplitude", amplitude)
        self.frequency = check_quantity("frequency", frequency)
        self.circle_radius = check_quantity("circle_radius", circle_radius)
        self.duration = check_quantity("duration", duration)
        self.robots = robots
        self._team = make_team(robots, 1)
        self._user_reference = reference

    def _reference(self) -> Reference:
        if self._user_reference is not None:
            return as_reference(self._user_reference, 1, self.duration)
        v, A, w, R = self.speed, self.amplitude, self.frequency, self.circle_radius
        om = v / R
        p, dp, ddp = {  # position, velocity and acceleration of each trajectory
            "straight": (lambda t: np.array([[v * t, 0.5 * v * t]]), lambda t: np.array([[v, 0.5 * v]]),
                         lambda t: np.zeros((1, 2))),
            "sine": (lambda t: np.array([[v * t, A * math.sin(w * t)]]),
                     lambda t: np.array([[v, A * w * math.cos(w * t)]]),
                     lambda t: np.array([[0.0, -A * w * w * math.sin(w * t)]])),
            "circle": (lambda t: R * np.array([[math.cos(om * t), math.sin(om * t)]]),
                       lambda t: R * om * np.array([[-math.sin(om * t), math.cos(om * t)]]),
                       lambda t: -R * om * om * np.array([[math.cos(om * t), math.sin(om * t)]])),
        }[self.trajectory]
        return FunctionReference(p, self.duration, velocity=dp, acceleration=ddp)

    def build(self, rng: np.random.Generator) -> Layout:
        """Start on the reference, at rest, heading along the reference velocity."""
        ref = self._reference()
        p0, v0, _ = ref(0.0)
        pts = np.concatenate([ref(t)[0] for t in np.linspace(0.0, self.duration, 64)])
        return Layout(team=self._team, starts=p0, headings=heading_of(v0, np.zeros(1)), reference=ref,
                      horizon=self.duration, bounds=bounds_around(pts))


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
        toward = np.arctan2(*(ref.goals - self._starts).T[::-1])
        headings = self._headings if self._headings is not None else base.heading_of(v0, toward)
        pts = np.concatenate([self._starts, ref.goals, *(ref(t)[0] for t in np.linspace(0, ref.duration, 16))])
        if self._obstacles[0].shape[0]:
            pts = np.concatenate([pts, self._obstacles[0]])
        return Layout(team=self._team, starts=self._starts.copy(), headings=headings, reference=ref,
                      horizon=ref.duration + self.settle_time, obstacle_centers=self._obstacles[0],
                      obstacle_radii=self._obstacles[1], bounds=base.bounds_around(pts))
