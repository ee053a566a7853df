"""``corridor``: two groups cross a straight corridor walled by discs, in opposite directions."""

from __future__ import annotations

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ScenarioError
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.model.portable import atan2
from aasoatt_env.sim.references import WaypointReference
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario

__all__ = ["Corridor", "disc_wall", "passage_layout"]


def disc_wall(a: np.ndarray, b: np.ndarray, radius: float, pitch: float) -> np.ndarray:
    """Centres ``(M, 2)`` of discs every ``pitch`` [m] (at most) from ``a`` to ``b``, both ends included."""
    count = max(1, int(np.ceil(float(np.hypot(*(b - a))) / pitch)))
    return a + np.linspace(0.0, 1.0, count + 1)[:, None] * (b - a)


def passage_layout(scenario: Scenario, starts: np.ndarray, goals: np.ndarray, gate: float,
                   obstacles: tuple[np.ndarray, np.ndarray], duration: float) -> Layout:
    """A layout whose robots go start -> ``(-+gate, 0)`` -> ``(+-gate, 0)`` -> goal along straight lines.

    Robots starting at ``x < 0`` pass the gate points left to right, the others right to left; the waypoint times
    split ``duration`` in proportion to the longest leg of each kind.
    """
    side = np.where(starts[:, :1] < 0.0, -1.0, 1.0)
    enter = np.concatenate((side * gate, np.zeros_like(side)), axis=1)
    wp = np.stack((starts, enter, -enter, goals), axis=1)
    legs = np.hypot(*np.diff(wp, axis=1).transpose(2, 0, 1)).max(axis=0)
    times = np.concatenate(([0.0], np.cumsum(legs) / legs.sum() * duration))
    ref = WaypointReference(wp, times)
    team = scenario._team  # type: ignore[attr-defined]
    base.check_no_overlap("starts", starts, team.radius)
    base.check_clear_of_obstacles("obstacles", starts, team.radius, obstacles)
    base.check_clear_of_obstacles("obstacles", goals, team.radius, obstacles)
    pts = np.concatenate((starts, goals, obstacles[0]))
    return Layout(team=team, starts=starts, headings=atan2(*(enter - starts).T[::-1]), reference=ref,
                  horizon=duration + scenario.settle_time,  # type: ignore[attr-defined]
                  obstacle_centers=obstacles[0], obstacle_radii=obstacles[1], bounds=base.bounds_around(pts))


class Corridor(Scenario):
    """Two groups swap ends through a corridor of clear ``width`` [m] and ``length`` [m] along the x axis.

    ``left`` robots start in a line across the axis (``spacing`` [m] apart) ``approach`` [m] before the left mouth
    and end at the mirror points beyond the right mouth; ``right`` robots do the reverse.  Each wall is a row of discs
    of radius ``wall_radius`` every ``wall_pitch`` [m] or closer, their surfaces ``width`` apart; at each mouth a cross
    wall reaches ``flange`` [m] beyond the corridor on both sides (0: none).  References: straight lines through the
    axis points 0.5 m outside each mouth, done at ``duration`` [s]; the horizon adds ``settle_time`` [s].  The layout
    is the same for every seed.
    """

    name = "corridor"

    def __init__(self, width: float = 2.2, length: float = 10.0, left: int = 4, right: int = 4,
                 robots: str | RobotParams | list = "paper", spacing: float = 1.2, approach: float = 4.0,
                 wall_radius: float = 0.3, wall_pitch: float = 0.5, flange: float = 6.0, duration: float = 40.0,
                 settle_time: float = 20.0) -> None:
        self.width, self.length, self.spacing, self.approach, self.wall_radius, self.wall_pitch, self.duration = (
            base.check_quantity(k, v) for k, v in (("width", width), ("length", length), ("spacing", spacing),
                                                   ("approach", approach), ("wall_radius", wall_radius),
                                                   ("wall_pitch", wall_pitch), ("duration", duration)))
        self.flange = check.real("flange", flange, lo=0.0, hi=base.QUANTITY_RANGE[1])
        self.left, self.right = base.check_groups(left, right)
        self.num_robots_ = self.left + self.right
        self.settle_time = base.check_settle_time(settle_time)
        self._team = make_team(robots, self.num_robots_)
        if float(2 * self._team.radius.max()) >= self.width:
            raise ScenarioError(f"width: got {self.width:g} m, but a robot is {2 * self._team.radius.max():g} m "
                                "across; expected a wider corridor")
        self._starts_goals()  # (the checks of the layout, at construction)

    def _starts_goals(self) -> tuple[np.ndarray, np.ndarray]:
        x = self.length / 2.0 + self.approach
        lines = [self.spacing * (np.arange(n) - (n - 1) / 2.0) for n in (self.left, self.right)]
        starts = np.concatenate([np.stack((np.full(n, s * x), y), axis=1)
                                 for n, s, y in ((self.left, -1.0, lines[0]), (self.right, 1.0, lines[1]))])
        return starts, starts * np.array([-1.0, 1.0])

    def obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        """The walls: ``(centres (M, 2), radii (M,))``."""
        h, y = self.length / 2.0, self.width / 2.0 + self.wall_radius
        f = y + self.flange
        c = np.concatenate([disc_wall(np.array([-h, s * y]), np.array([h, s * y]), self.wall_radius, self.wall_pitch)
                            for s in (-1.0, 1.0)]
                           + [disc_wall(np.array([x, s * y]), np.array([x, s * f]), self.wall_radius,
                                        self.wall_pitch)[1:] for s in (-1.0, 1.0) for x in (-h, h) if self.flange])
        return c, np.full(c.shape[0], self.wall_radius)

    def build(self, rng: np.random.Generator) -> Layout:
        """Return the corridor layout (deterministic)."""
        starts, goals = self._starts_goals()
        return passage_layout(self, starts, goals, self.length / 2.0 + 0.5, self.obstacles(), self.duration)
