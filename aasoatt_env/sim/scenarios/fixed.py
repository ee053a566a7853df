"""Fixed layouts: ``circle_swap``, ``circle_obstacles``, ``position_swap``, ``tracking`` (the paper's), ``custom``."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError, ScenarioError
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.sim.references import COORD_MAX, FunctionReference, LinearReference, Reference, as_reference
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario, bounds_around, check_quantity, heading_of

__all__ = ["FIG5_OBSTACLES", "CircleSwap", "CircleSwapObstacles", "Custom", "PositionSwap", "Tracking"]

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
