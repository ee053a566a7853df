"""What every scenario shares: the :class:`Layout` of an episode, the :class:`Scenario` base and its checks."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError, ScenarioError
from aasoatt_env.model.geometry import robot_pairs
from aasoatt_env.model.params import Team
from aasoatt_env.model.portable import atan2
from aasoatt_env.sim.references import Reference

__all__ = ["MAX_ROBOTS", "Layout", "Scenario", "bounds_around", "check_clear_of_obstacles", "check_groups",
           "check_no_overlap", "check_num_robots", "check_obstacles", "check_quantity", "check_settle_time",
           "check_starts", "heading_of", "max_robots_on_circle"]

MAX_ROBOTS: int = 100_000
"""Largest team a scenario builds."""
QUANTITY_RANGE: tuple[float, float] = (1e-6, 1e6)
"""Valid range of a scenario's lengths [m], durations [s] and speeds [m/s] (beyond it a layout under- or overflows)."""
TOUCH_TOL: float = 2.5e-10
"""How far inside contact [m] a start still counts as touching (rounding); half the backup check's tolerance."""


@dataclass
class Layout:
    """What the env needs to start an episode: control-point ``starts (N, 2)``, ``headings (N,)``, ``horizon`` [s]."""

    team: Team
    starts: np.ndarray
    headings: np.ndarray
    reference: Reference
    horizon: float
    obstacle_centers: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    obstacle_radii: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bounds: tuple[float, float, float, float] = (-7.0, 7.0, -7.0, 7.0)


class Scenario:
    """Base class: subclasses set ``name``, validate in ``__init__`` and implement ``build``."""

    name: ClassVar[str] = ""
    num_robots_: int = 1

    def build(self, rng: np.random.Generator) -> Layout:  # pragma: no cover - abstract
        """Return the layout of a new episode."""
        raise NotImplementedError

    @property
    def num_robots(self) -> int:
        """Number of robots."""
        return int(self.num_robots_)


def check_num_robots(value: Any) -> int:
    """``num_robots``: an integer in ``[1, MAX_ROBOTS]``."""
    return check.integer("num_robots", value, lo=1, hi=MAX_ROBOTS)


def check_quantity(name: str, value: Any) -> float:
    """A scenario length, duration or speed: a finite number in :data:`QUANTITY_RANGE`."""
    return check.real(name, value, lo=QUANTITY_RANGE[0], hi=QUANTITY_RANGE[1])


def check_groups(left: Any, right: Any) -> tuple[int, int]:
    """``left``, ``right``: the robot counts of two groups, integers in ``[0, MAX_ROBOTS]``, at least one in all."""
    counts = tuple(check.integer(k, v, lo=0, hi=MAX_ROBOTS) for k, v in (("left", left), ("right", right)))
    if sum(counts) < 1:
        raise ScenarioError(f"left, right: got {left} and {right} robots, expected at least one in all")
    return counts  # type: ignore[return-value]


def check_settle_time(value: Any) -> float:
    """``settle_time``: a finite number of seconds in ``[0, 1e6]``."""
    return check.real("settle_time", value, lo=0.0, hi=1e6)


def max_robots_on_circle(circle_radius: float, robot_radius: float) -> int:
    """Most robots of ``robot_radius`` that fit evenly on the circle without overlap (``R sin(pi/N) >= r``)."""
    ratio = robot_radius / circle_radius
    if ratio >= 1.0:
        return 1
    return int(math.floor(math.pi / math.asin(ratio) + 1e-9))


def check_obstacles(obstacles: Any) -> tuple[np.ndarray, np.ndarray]:
    """``obstacles``: None or a pair ``(centres (M, 2), radii (M,))`` of finite values, radii > 0."""
    if obstacles is None:
        return np.zeros((0, 2)), np.zeros(0)
    if not (isinstance(obstacles, (tuple, list)) and len(obstacles) == 2):
        raise ConfigError(f"obstacles: got {obstacles!r}, expected a pair (centres (M, 2), radii (M,)) or None")
    centers, radii = obstacles
    c = check.real_array("obstacles (centres)", centers, lo=-QUANTITY_RANGE[1], hi=QUANTITY_RANGE[1], unit=" m")
    r = check.real_array("obstacles (radii)", radii, lo=QUANTITY_RANGE[0], hi=QUANTITY_RANGE[1], unit=" m").reshape(-1)
    if c.size == 0 or c.shape == (2,):  # no obstacle, or one centre
        c = c.reshape(-1, 2)
    if c.ndim != 2 or c.shape[1] != 2:
        raise ConfigError(f"obstacles: got centres of shape {np.shape(centers)}, expected (M, 2)")
    if r.shape[0] != c.shape[0]:
        raise ConfigError(f"obstacles: got {c.shape[0]} centres and {r.shape[0]} radii, expected as many")
    return c, r


def check_clear_of_obstacles(name: str, points: np.ndarray, radii: np.ndarray, obstacles: tuple[np.ndarray, np.ndarray]
                             ) -> None:
    """Raise :class:`ScenarioError` if a robot of radius ``radii`` at ``points`` overlaps an obstacle."""
    centers, orad = obstacles
    if centers.shape[0] == 0:
        return
    reach = radii[:, None] + orad[None, :]
    gap = np.hypot(*(points[:, None, :] - centers[None, :, :]).transpose(2, 0, 1)) - reach
    over = gap < -_touching(reach)
    if np.any(over):
        i, k = np.argwhere(over)[0]
        raise ScenarioError(f"{name}: robot {i} at {points[i].round(3).tolist()} overlaps obstacle {k} "
                            f"(gap {gap[i, k]:.3f} m); move the obstacle or the robot")


def check_starts(scenario: Scenario, layout: Layout) -> None:
    """Raise :class:`ScenarioError` if the starts of ``layout`` overlap each other or an obstacle.

    Every env checks every layout, a user's scenario's too: the filter's guarantee starts from a safe state.
    """
    where = f"scenario {scenario.name or type(scenario).__name__!r}: starts"
    check_no_overlap(where, layout.starts, layout.team.radius, layout.team.group)
    check_clear_of_obstacles(where, layout.starts, layout.team.radius, (layout.obstacle_centers,
                                                                        layout.obstacle_radii))


def _touching(contact: np.ndarray) -> np.ndarray:
    """How far inside ``contact`` (the sum of two radii) a start still counts as touching: ``1e-9`` of it at most."""
    return np.minimum(1e-9 * contact, TOUCH_TOL)


def check_no_overlap(name: str, points: np.ndarray, radii: np.ndarray, groups: np.ndarray | None = None) -> None:
    """Raise :class:`ScenarioError` if a start is not finite or two robots of one of ``groups`` overlap (not touch)."""
    points = np.asarray(points, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        raise ScenarioError(f"{name}: robot {bad[0]} at {points[bad[0]].tolist()}, expected finite coordinates")
    if points.shape[0] < 2:
        return
    pr = robot_pairs(points, 2.0 * float(np.max(radii)), groups=groups)
    d = np.hypot(*(points[pr[:, 0]] - points[pr[:, 1]]).T)
    rs = radii[pr[:, 0]] + radii[pr[:, 1]]
    hit = np.flatnonzero(d < rs - _touching(rs))
    if hit.size:
        k = hit[0]
        raise ScenarioError(f"{name}: robots {pr[k, 0]} and {pr[k, 1]} overlap ({d[k]:.9g} m apart < {rs[k]:.9g} m, "
                            "the sum of their radii)")


def bounds_around(points: np.ndarray, margin: float = 1.5) -> tuple[float, float, float, float]:
    """``(xmin, xmax, ymin, ymax)`` of ``points`` ``(P, 2)``, widened by ``margin`` [m] (a layout's view)."""
    lo, hi = points.min(axis=0) - margin, points.max(axis=0) + margin
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def heading_of(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Headings along ``v`` ``(N, 2)``; ``fallback`` where ``v`` is zero."""
    speed = np.hypot(v[:, 0], v[:, 1])
    return np.where(speed > 1e-12, atan2(v[:, 1], v[:, 0]), fallback)
