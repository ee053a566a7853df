"""``doorway``: two rooms joined by a door in a wall of discs; seeded groups swap rooms through it."""

from __future__ import annotations

import numpy as np

from aasoatt_env.errors import ScenarioError
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario
from aasoatt_env.sim.scenarios.corridor import disc_wall, passage_layout

__all__ = ["Doorway", "grid_points"]


def grid_points(rng: np.random.Generator, n: int, lo: np.ndarray, hi: np.ndarray, pitch: float) -> np.ndarray:
    """``n`` points in the box ``[lo, hi]``, in distinct cells of a grid of ``pitch`` [m] drawn by ``rng``."""
    cells = np.floor((hi - lo) / pitch).astype(int)
    if n > cells.prod():
        raise ScenarioError(f"{n} robots do not fit in a room of {cells[0]} x {cells[1]} places {pitch:g} m apart; "
                            "enlarge the room")
    pick = rng.choice(int(cells.prod()), size=n, replace=False)
    return lo + pitch * (np.stack((pick % cells[0], pick // cells[0]), axis=1) + 0.5)


class Doorway(Scenario):
    """Two square rooms of side ``room`` [m] either side of a wall on the y axis, joined by a door ``door`` [m] wide.

    The wall is a row of discs of radius ``wall_radius`` every ``wall_pitch`` [m] or closer, ``room`` long each side
    of the door.  ``left`` robots start at seeded places of the left room (a grid of the robots' diameter + 0.3 m)
    and end at seeded places of the right room, ``right`` robots the reverse; each tracks the straight lines through
    the points 1 m either side of the door, done at ``duration`` [s]; the horizon adds ``settle_time`` [s].
    """

    name = "doorway"

    def __init__(self, door: float = 1.6, room: float = 8.0, left: int = 4, right: int = 4,
                 robots: str | RobotParams | list = "paper", wall_radius: float = 0.3, wall_pitch: float = 0.5,
                 duration: float = 30.0, settle_time: float = 30.0) -> None:
        self.door, self.room, self.wall_radius, self.wall_pitch, self.duration = (
            base.check_quantity(k, v) for k, v in (("door", door), ("room", room), ("wall_radius", wall_radius),
                                                   ("wall_pitch", wall_pitch), ("duration", duration)))
        self.left, self.right = base.check_groups(left, right)
        self.num_robots_ = self.left + self.right
        self.settle_time = base.check_settle_time(settle_time)
        self._team = make_team(robots, self.num_robots_)
        self._pitch = 2.0 * float(self._team.radius.max()) + 0.3
        if self._pitch - 0.3 >= self.door:
            raise ScenarioError(f"door: got {self.door:g} m, but a robot is {self._pitch - 0.3:g} m across; expected "
                                "a wider door")
        self.build(np.random.default_rng(0))  # (the checks of the layout, at construction)

    def obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        """The wall: ``(centres (M, 2), radii (M,))``."""
        y0 = self.door / 2.0 + self.wall_radius
        c = np.concatenate([disc_wall(np.array([0.0, s * y0]), np.array([0.0, s * (y0 + self.room)]),
                                      self.wall_radius, self.wall_pitch) for s in (-1.0, 1.0)])
        return c, np.full(c.shape[0], self.wall_radius)

    def build(self, rng: np.random.Generator) -> Layout:
        """Places drawn from ``rng``: starts, then goals, of the left group, then of the right group."""
        near = self.wall_radius + float(self._team.radius.max()) + 0.2
        boxes = [(np.array([-self.room, -self.room / 2.0]), np.array([-near, self.room / 2.0])),
                 (np.array([near, -self.room / 2.0]), np.array([self.room, self.room / 2.0]))]
        pts = [grid_points(rng, n, *boxes[k], self._pitch) for n, k in ((self.left, 0), (self.left, 1),
                                                                        (self.right, 1), (self.right, 0))]
        starts, goals = np.concatenate((pts[0], pts[2])), np.concatenate((pts[1], pts[3]))
        return passage_layout(self, starts, goals, 1.0, self.obstacles(), self.duration)
