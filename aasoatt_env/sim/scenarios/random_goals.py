"""``random_goals``: seeded random starts and goals in a square arena, spacing guaranteed (for learning)."""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError, ScenarioError
from aasoatt_env.model.geometry import kdtree
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.model.portable import atan2
from aasoatt_env.sim.references import LinearReference
from aasoatt_env.sim.scenarios import base
from aasoatt_env.sim.scenarios.base import Layout, Scenario

__all__ = ["MAX_OBSTACLES", "RandomGoals"]

MAX_OBSTACLES: int = 1000
"""Largest ``random_obstacles``."""
_SEQUENTIAL_MAX = 2000  # up to this many robots points are placed one by one, else in vectorised batches
_SEQUENTIAL_TRIES = 50  # whole-set tries of the one-by-one sampler


class RandomGoals(Scenario):
    """Random starts and goals in a square arena, for learning.

    Starts (and goals) are ``min_spacing`` [m] apart or more (default: the robots' diameter + 0.2 m) in an arena of
    side ``arena_size`` [m] (default grows with ``sqrt(N)``); each robot tracks the straight line to its goal at
    ``speed`` [m/s], the horizon adds ``settle_time`` [s]; ``random_obstacles`` discs (radius 0.3-0.8 m) lie clear of
    every start and goal by the robots' radius + 0.1 m.
    """

    name = "random_goals"
    radii: tuple[float, float] = (0.3, 0.8)  # of the random discs [m]
    _pad, _tries = 0, 100  # extra draws per batch of 4 random_obstacles; batches
    _crowded = "random_obstacles: could not place {m} obstacles clear of the robots; enlarge arena_size"

    def __init__(self, num_robots: int = 6, arena_size: float | None = None, min_spacing: float | None = None,
                 speed: float = 0.8, settle_time: float = 3.0, robots: str | RobotParams | list = "paper",
                 random_obstacles: int = 0) -> None:
        self.num_robots_ = base.check_num_robots(num_robots)
        self.random_obstacles = check.integer("random_obstacles", random_obstacles, lo=0, hi=MAX_OBSTACLES)
        self._team = make_team(robots, self.num_robots_)
        d = 2.0 * float(self._team.radius.max())
        self.min_spacing = d + 0.2 if min_spacing is None else base.check_quantity("min_spacing", min_spacing)
        if self.min_spacing < d:
            raise ConfigError(f"min_spacing: got {self.min_spacing:g}, expected >= robot diameter {d:g}")
        default_arena = max(6.0, 2.2 * self.min_spacing * math.sqrt(self.num_robots_))
        self.arena_size = default_arena if arena_size is None else base.check_quantity("arena_size", arena_size)
        self.speed = base.check_quantity("speed", speed)
        self.settle_time = base.check_settle_time(settle_time)
        self.robots = robots
        longest = math.sqrt(2.0) * self.arena_size / self.speed
        if longest > base.QUANTITY_RANGE[1]:
            raise ConfigError(f"speed: got {self.speed:g}, so a robot may need {longest:.3g} s to cross the arena of "
                              f"size {self.arena_size:g}; expected a travel time <= {base.QUANTITY_RANGE[1]:g} s")
        cover = self.num_robots_ * math.pi * (self.min_spacing / 2) ** 2 / self.arena_size**2
        if cover > 0.45:
            raise ScenarioError(f"num_robots / arena_size / min_spacing: {self.num_robots_} robots with spacing "
                                f"{self.min_spacing:g} do not fit reliably in an arena of size {self.arena_size:g} "
                                f"(cover {cover:.2f}, expected <= 0.45)")

    def _sample(self, rng: np.random.Generator) -> np.ndarray:
        """Points ``min_spacing`` apart: one by one (a whole new try where one finds no room in 10,000 draws)."""
        if self.num_robots_ > _SEQUENTIAL_MAX:
            return self._sample_batched(rng)
        n, half = self.num_robots_, self.arena_size / 2.0 - self.min_spacing / 2.0
        for _ in range(_SEQUENTIAL_TRIES):
            pts = np.empty((n, 2))
            for i in range(n):
                for _ in range(10_000):
                    cand = rng.uniform(-half, half, size=2)
                    if i == 0 or np.min(np.hypot(*(pts[:i] - cand).T)) >= self.min_spacing:
                        pts[i] = cand
                        break
                else:
                    break  # no room: a new try
            else:
                return pts
        raise ScenarioError(f"random_goals: could not place {n} robots {self.min_spacing:g} m apart in an arena of "
                            f"size {self.arena_size:g} in {_SEQUENTIAL_TRIES} tries; enlarge arena_size")

    def _sample_batched(self, rng: np.random.Generator) -> np.ndarray:
        """Dart throwing in vectorised batches (large teams): candidates clear of the points and earlier candidates."""
        n, half, s = self.num_robots_, self.arena_size / 2.0 - self.min_spacing / 2.0, self.min_spacing
        pts = np.empty((0, 2))
        for _ in range(200):
            need = n - pts.shape[0]
            cand = rng.uniform(-half, half, size=(max(2 * need, 64), 2))
            if pts.shape[0]:
                d, _ = kdtree(pts).query(cand, k=1)
                cand = cand[d >= s]
            clash = kdtree(cand).query_pairs(s, output_type="ndarray")
            if clash.shape[0]:
                drop = np.zeros(cand.shape[0], dtype=bool)
                for i, j in clash[np.argsort(clash.max(axis=1), kind="stable")]:  # keep the earlier of each pair
                    if not drop[min(i, j)]:
                        drop[max(i, j)] = True
                cand = cand[~drop]
            pts = np.concatenate((pts, cand[:need]))
            if pts.shape[0] == n:
                return pts
        raise ScenarioError(f"random_goals: could not place {n} robots {s:g} m apart in the arena; enlarge arena_size")

    def build(self, rng: np.random.Generator) -> Layout:
        """Sample starts and goals from ``rng``."""
        starts, goals = self._sample(rng), self._sample(rng)
        dist = np.hypot(*(goals - starts).T)
        durations = np.maximum(dist / self.speed, 1e-3)
        ref = LinearReference(starts, goals, durations)  # every robot at the same speed: its own duration
        b = self.arena_size / 2.0 + 0.5
        centers, radii = self._obstacles(rng, np.concatenate((starts, goals)))
        return Layout(team=self._team, starts=starts, reference=ref, horizon=ref.duration + self.settle_time,
                      headings=atan2(goals[:, 1] - starts[:, 1], goals[:, 0] - starts[:, 0]),
                      obstacle_centers=centers, obstacle_radii=radii, bounds=(-b, b, -b, b))

    def _obstacles(self, rng: np.random.Generator, keep_clear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``random_obstacles`` discs (radii uniform in ``radii``) clear of the starts and goals (rejection)."""
        m = self.random_obstacles
        size, clear, half = 4 * m + self._pad, float(self._team.radius.max()) + 0.1, self.arena_size / 2.0
        centers, radii = np.zeros((0, 2)), np.zeros(0)
        for _ in range(self._tries if m else 0):
            c = rng.uniform(-half, half, size=(size, 2))
            r = rng.uniform(*self.radii, size=size)
            d = np.hypot(*(c[:, None, :] - keep_clear[None, :, :]).transpose(2, 0, 1)).min(axis=1)
            ok = d >= r + clear
            centers, radii = np.concatenate((centers, c[ok]))[:m], np.concatenate((radii, r[ok]))[:m]
            if radii.size == m:
                break
        if radii.size < m:
            raise ScenarioError(self._crowded.format(m=m))
        return centers, radii
