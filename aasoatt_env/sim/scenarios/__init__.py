"""Scenarios: who starts where, which reference each robot tracks, which obstacles.

A scenario is the middle layer between the physics (:mod:`aasoatt_env.model.dynamics`)
and the environment plumbing (:mod:`aasoatt_env.sim.env`): it validates its own
parameters once, then :meth:`Scenario.build` returns a :class:`Layout` for a
given random generator.

=======================  ===============  ==================================================
name                     paper            layout
=======================  ===============  ==================================================
``circle_swap``          Tab. II, III     N robots evenly on a circle, each tracks the
                                          straight line to its antipode
``circle_obstacles``     Fig. 5           circle swap with static disc obstacles
                                          (default: 20 robots, 3 obstacles)
``tracking``             Tab. I           one robot on a straight / sine / circle reference
``position_swap``        Fig. 6           4 TurtleBot3 Burgers swap corners, 2.24 m at 0.1 m/s
``random_goals``         (learning)       random starts and goals, spacing guaranteed
``custom``               (yours)          your starts, reference (callable / waypoints)
                                          and obstacles
=======================  ===============  ==================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from aasoatt_env.errors import ConfigError, ScenarioError
from aasoatt_env.model.params import RobotParams, Team, check_positive, make_team
from aasoatt_env.sim.references import FunctionReference, LinearReference, Reference, as_reference

__all__ = [
    "SCENARIOS",
    "CircleSwap",
    "CircleSwapObstacles",
    "Custom",
    "Layout",
    "PositionSwap",
    "RandomGoals",
    "Scenario",
    "Tracking",
    "get_scenario",
    "max_robots_on_circle",
]


@dataclass
class Layout:
    """Everything the environment needs to start an episode."""

    team: Team
    starts: np.ndarray
    """Initial control-point positions, ``(N, 2)``."""
    headings: np.ndarray
    """Initial headings, ``(N,)``."""
    reference: Reference
    horizon: float
    """Episode length [s] (reference duration plus settling time)."""
    obstacle_centers: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    obstacle_radii: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bounds: tuple[float, float, float, float] = (-7.0, 7.0, -7.0, 7.0)


def max_robots_on_circle(circle_radius: float, robot_radius: float) -> int:
    """Most robots of ``robot_radius`` that fit evenly, non-overlapping, on the circle."""
    ratio = robot_radius / circle_radius  # chord 2 R sin(pi/N) >= 2 r
    if ratio >= 1.0:
        return 1
    return int(math.floor(math.pi / math.asin(ratio) + 1e-9))


def _check_obstacles(centers: Any, radii: Any) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 2) if np.size(centers) else np.zeros((0, 2))
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    if r.shape[0] != c.shape[0]:
        raise ConfigError(f"obstacles: got {c.shape[0]} centres and {r.shape[0]} radii, expected as many")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r)) and np.all(r > 0)):
        raise ConfigError("obstacles: expected finite centres and positive finite radii")
    return c, r


def _heading_of(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    speed = np.hypot(v[:, 0], v[:, 1])
    return np.where(speed > 1e-12, np.arctan2(v[:, 1], v[:, 0]), fallback)


class Scenario:
    """Base class: subclasses set ``name``, validate in ``__init__`` and implement ``build``."""

    name: ClassVar[str] = ""
    random: ClassVar[bool] = False
    """True when the layout depends on the seed."""

    def build(self, rng: np.random.Generator) -> Layout:  # pragma: no cover - abstract
        """Return the layout of a new episode."""
        raise NotImplementedError

    @property
    def params(self) -> dict[str, Any]:
        """The scenario's parameters (for ``aasoatt list`` and metadata)."""
        return {k: v for k, v in vars(self).items() if not k.startswith("_")}

    @property
    def num_robots(self) -> int:
        """Number of robots."""
        return int(getattr(self, "num_robots_", 1))


class CircleSwap(Scenario):
    """N robots evenly on a circle; each tracks the straight line to its antipode.

    Parameters
    ----------
    num_robots : int
        N >= 1; at most as many as fit on the circle without overlap.
    radius : float
        Circle radius [m] (paper: 6 with 12 s, 10 with 20 s).
    duration : float
        Travel time of the reference [s].
    settle_time : float
        Extra time after the reference ends [s] (episode horizon = duration + settle_time).
    robots : str, RobotParams or sequence
        Robot preset(s), see :func:`aasoatt_env.model.params.make_team`.
    profile : {"linear", "smooth"}
        Timing of the straight-line reference.
    obstacles : tuple (centres (M, 2), radii (M,)), optional
        Static disc obstacles.
    """

    name = "circle_swap"

    def __init__(
        self,
        num_robots: int = 10,
        radius: float = 6.0,
        duration: float = 12.0,
        settle_time: float = 3.0,
        robots: str | RobotParams | list = "paper",
        profile: str = "linear",
        obstacles: tuple[Any, Any] | None = None,
    ) -> None:
        if int(num_robots) != num_robots or num_robots < 1:
            raise ConfigError(f"num_robots: got {num_robots!r}, expected an integer >= 1")
        self.num_robots_ = int(num_robots)
        self.radius = check_positive("radius", radius)
        self.duration = check_positive("duration", duration)
        if settle_time < 0:
            raise ConfigError(f"settle_time: got {settle_time!r}, expected >= 0")
        self.settle_time = float(settle_time)
        self.robots = robots
        self.profile = profile
        self._team = make_team(robots, self.num_robots_)
        rmax = float(self._team.radius.max())
        fit = max_robots_on_circle(self.radius, rmax) if self.num_robots_ > 1 else 1
        if self.num_robots_ > fit:
            raise ScenarioError(
                f"num_robots: got {self.num_robots_}, but at most {fit} robots of radius {rmax:g} "
                f"fit on a circle of radius {self.radius:g}"
            )
        self._obstacles = _check_obstacles(*(obstacles if obstacles is not None else ((), ())))

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
        return Layout(
            team=self._team,
            starts=starts,
            headings=headings,
            reference=ref,
            horizon=self.duration + self.settle_time,
            obstacle_centers=self._obstacles[0],
            obstacle_radii=self._obstacles[1],
            bounds=(-b, b, -b, b),
        )


#: The three obstacles of our Fig. 5 preset: (x, y, radius); different sizes,
#: one at the centre where every reference crosses.
FIG5_OBSTACLES: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.6),
    (2.8, 1.6, 0.4),
    (-2.2, -2.6, 0.8),
)


class CircleSwapObstacles(CircleSwap):
    """Circle swap among static disc obstacles (the paper's Fig. 5 by default).

    Same parameters as :class:`CircleSwap` (default 20 robots); ``obstacles``
    defaults to :data:`FIG5_OBSTACLES`.
    """

    name = "circle_obstacles"

    def __init__(self, num_robots: int = 20, obstacles: tuple[Any, Any] | None = None, **kwargs: Any):
        if obstacles is None:
            arr = np.array(FIG5_OBSTACLES)
            obstacles = (arr[:, :2], arr[:, 2])
        super().__init__(num_robots=num_robots, obstacles=obstacles, **kwargs)


class Tracking(Scenario):
    """One robot tracking a straight, sine or circle reference (Table I).

    Parameters
    ----------
    trajectory : {"straight", "sine", "circle"}
        ``straight``: ``p_d = (v t, v t / 2)``; ``sine``: ``p_d = (v t, A sin(w t))``;
        ``circle``: ``p_d = R (cos(w t), sin(w t))`` with ``w = v / R``.
    speed : float
        Nominal speed ``v`` [m/s].
    amplitude, frequency : float
        Sine amplitude ``A`` [m] and angular frequency ``w`` [rad/s].
    circle_radius : float
        ``R`` [m] for the circle.
    duration : float
        Episode length [s].
    robots : str or RobotParams
        Robot preset.
    reference : Reference or callable, optional
        A user reference instead of the three built-ins.
    """

    name = "tracking"
    TRAJECTORIES: ClassVar[tuple[str, ...]] = ("straight", "sine", "circle")

    def __init__(
        self,
        trajectory: str = "circle",
        speed: float = 0.5,
        amplitude: float = 1.0,
        frequency: float = 0.5,
        circle_radius: float = 2.0,
        duration: float = 12.0,
        robots: str | RobotParams = "paper",
        reference: Any = None,
    ) -> None:
        if reference is None and trajectory not in self.TRAJECTORIES:
            raise ConfigError(f"trajectory: got {trajectory!r}, expected one of {list(self.TRAJECTORIES)}")
        self.trajectory = trajectory
        self.speed = check_positive("speed", speed)
        self.amplitude = check_positive("amplitude", amplitude)
        self.frequency = check_positive("frequency", frequency)
        self.circle_radius = check_positive("circle_radius", circle_radius)
        self.duration = check_positive("duration", duration)
        self.robots = robots
        self._team = make_team(robots, 1)
        self._user_reference = reference
        self.num_robots_ = 1

    def _reference(self) -> Reference:
        if self._user_reference is not None:
            return as_reference(self._user_reference, 1, self.duration)
        v, A, w, R = self.speed, self.amplitude, self.frequency, self.circle_radius
        if self.trajectory == "straight":

            def p(t: float) -> np.ndarray:
                return np.array([[v * t, 0.5 * v * t]])

            def dp(t: float) -> np.ndarray:
                return np.array([[v, 0.5 * v]])

            def ddp(t: float) -> np.ndarray:
                return np.zeros((1, 2))
        elif self.trajectory == "sine":

            def p(t: float) -> np.ndarray:
                return np.array([[v * t, A * math.sin(w * t)]])

            def dp(t: float) -> np.ndarray:
                return np.array([[v, A * w * math.cos(w * t)]])

            def ddp(t: float) -> np.ndarray:
                return np.array([[0.0, -A * w * w * math.sin(w * t)]])
        else:
            om = v / R

            def p(t: float) -> np.ndarray:
                return R * np.array([[math.cos(om * t), math.sin(om * t)]])

            def dp(t: float) -> np.ndarray:
                return R * om * np.array([[-math.sin(om * t), math.cos(om * t)]])

            def ddp(t: float) -> np.ndarray:
                return -R * om * om * np.array([[math.cos(om * t), math.sin(om * t)]])

        return FunctionReference(p, self.duration, velocity=dp, acceleration=ddp)

    def build(self, rng: np.random.Generator) -> Layout:
        """Start on the reference, at rest, heading along the reference velocity."""
        ref = self._reference()
        p0, v0, _ = ref(0.0)
        pts = np.concatenate([ref(t)[0] for t in np.linspace(0.0, self.duration, 64)])
        lo, hi = pts.min(axis=0) - 1.5, pts.max(axis=0) + 1.5
        return Layout(
            team=self._team,
            starts=p0,
            headings=_heading_of(v0, np.zeros(1)),
            reference=ref,
            horizon=self.duration,
            bounds=(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])),
        )


class PositionSwap(Scenario):
    """Four robots on the corners of a square swap with the opposite corner.

    The paper's TurtleBot3 experiment: each robot travels ``distance`` = 2.24 m
    at ``speed`` = 0.1 m/s (22.4 s), so the square's diagonal is 2.24 m.

    Parameters
    ----------
    distance, speed : float
        Travel distance [m] and reference speed [m/s].
    settle_time : float
        Extra time after the reference ends [s].
    robots : str or RobotParams
        Robot preset (default ``"turtlebot3_burger"``).
    """

    name = "position_swap"

    def __init__(
        self,
        distance: float = 2.24,
        speed: float = 0.1,
        settle_time: float = 5.0,
        robots: str | RobotParams = "turtlebot3_burger",
    ) -> None:
        self.distance = check_positive("distance", distance)
        self.speed = check_positive("speed", speed)
        if settle_time < 0:
            raise ConfigError(f"settle_time: got {settle_time!r}, expected >= 0")
        self.settle_time = float(settle_time)
        self.robots = robots
        self.num_robots_ = 4
        self._team = make_team(robots, 4)

    def build(self, rng: np.random.Generator) -> Layout:
        """Return the (deterministic) corner-swap layout."""
        h = self.distance / 2.0
        ang = np.pi / 4 + np.pi / 2 * np.arange(4)
        starts = h * np.stack((np.cos(ang), np.sin(ang)), axis=1)
        goals = -starts
        duration = self.distance / self.speed
        b = h + 0.5
        return Layout(
            team=self._team,
            starts=starts,
            headings=ang + np.pi,
            reference=LinearReference(starts, goals, duration),
            horizon=duration + self.settle_time,
            bounds=(-b, b, -b, b),
        )


class RandomGoals(Scenario):
    """Random starts and goals in a square arena, for learning.

    Starts (and, separately, goals) are at least ``min_spacing`` apart, centre
    to centre (default: the robots' diameter plus 0.2 m), drawn by rejection
    sampling from the episode's seeded generator.  Each robot tracks a straight
    line to its goal at ``speed`` (so the reference durations differ; the
    episode horizon is the longest plus ``settle_time``).

    Parameters
    ----------
    num_robots : int
        N >= 1.
    arena_size : float, optional
        Side of the square arena [m]; default grows with ``sqrt(N)``.
    min_spacing : float, optional
        Minimum centre distance between starts and between goals [m].
    speed : float
        Reference speed [m/s].
    settle_time : float
        Extra time after the longest reference ends [s].
    robots : str, RobotParams or sequence
        Robot preset(s).
    """

    name = "random_goals"
    random = True

    def __init__(
        self,
        num_robots: int = 6,
        arena_size: float | None = None,
        min_spacing: float | None = None,
        speed: float = 0.8,
        settle_time: float = 3.0,
        robots: str | RobotParams | list = "paper",
    ) -> None:
        if int(num_robots) != num_robots or num_robots < 1:
            raise ConfigError(f"num_robots: got {num_robots!r}, expected an integer >= 1")
        self.num_robots_ = int(num_robots)
        self._team = make_team(robots, self.num_robots_)
        d = 2.0 * float(self._team.radius.max())
        self.min_spacing = d + 0.2 if min_spacing is None else check_positive("min_spacing", min_spacing)
        if self.min_spacing < d:
            raise ConfigError(f"min_spacing: got {self.min_spacing:g}, expected >= robot diameter {d:g}")
        default_arena = max(6.0, 2.2 * self.min_spacing * math.sqrt(self.num_robots_))
        self.arena_size = default_arena if arena_size is None else check_positive("arena_size", arena_size)
        self.speed = check_positive("speed", speed)
        self.settle_time = float(settle_time)
        self.robots = robots
        # packing sanity check: fraction of the arena the spacing discs would cover
        cover = self.num_robots_ * math.pi * (self.min_spacing / 2) ** 2 / self.arena_size**2
        if cover > 0.45:
            raise ScenarioError(
                f"num_robots: {self.num_robots_} robots with spacing {self.min_spacing:g} do not fit "
                f"reliably in an arena of size {self.arena_size:g} (cover {cover:.2f}, expected <= 0.45)"
            )

    def _sample(self, rng: np.random.Generator) -> np.ndarray:
        n, half = self.num_robots_, self.arena_size / 2.0 - self.min_spacing / 2.0
        pts = np.empty((n, 2))
        for i in range(n):
            for _ in range(10_000):
                cand = rng.uniform(-half, half, size=2)
                if i == 0 or np.min(np.hypot(*(pts[:i] - cand).T)) >= self.min_spacing:
                    pts[i] = cand
                    break
            else:  # pragma: no cover - guarded by the cover check
                raise ScenarioError("random_goals: could not place robots with the requested spacing")
        return pts

    def build(self, rng: np.random.Generator) -> Layout:
        """Sample starts and goals from ``rng``."""
        starts, goals = self._sample(rng), self._sample(rng)
        dist = np.hypot(*(goals - starts).T)
        durations = np.maximum(dist / self.speed, 1e-3)
        T = float(durations.max())
        ref = FunctionReference(
            lambda t: starts + (goals - starts) * np.clip(t / durations, 0.0, 1.0)[:, None],
            T,
            velocity=lambda t: ((goals - starts) / durations[:, None]) * (t < durations)[:, None],
            acceleration=lambda t: np.zeros_like(starts),
        )
        b = self.arena_size / 2.0 + 0.5
        return Layout(
            team=self._team,
            starts=starts,
            headings=np.arctan2(goals[:, 1] - starts[:, 1], goals[:, 0] - starts[:, 0]),
            reference=ref,
            horizon=T + self.settle_time,
            bounds=(-b, b, -b, b),
        )


class Custom(Scenario):
    """Your own team: start points, a reference (object, callable or waypoints) and obstacles.

    Parameters
    ----------
    starts : array_like, shape (N, 2)
        Initial control-point positions.
    reference : Reference, callable or dict
        A :class:`~aasoatt_env.sim.references.Reference`, a callable ``t -> (N, 2)``
        (with ``duration``) or ``{"waypoints": (N, K, 2), "times": (K,)}``.
    duration : float, optional
        Reference duration (needed for a callable).
    headings : array_like, shape (N,), optional
        Initial headings; default: along the reference velocity at ``t = 0``
        (or toward the goal when it is zero).
    obstacles : tuple (centres (M, 2), radii (M,)), optional
        Static disc obstacles.
    robots : str, RobotParams or sequence
        Robot preset(s).
    settle_time : float
        Extra time after the reference ends [s].
    """

    name = "custom"

    def __init__(
        self,
        starts: Any,
        reference: Any,
        duration: float | None = None,
        headings: Any = None,
        obstacles: tuple[Any, Any] | None = None,
        robots: str | RobotParams | list = "paper",
        settle_time: float = 3.0,
    ) -> None:
        st = np.asarray(starts, dtype=np.float64)
        if st.ndim != 2 or st.shape[1] != 2 or not np.all(np.isfinite(st)):
            raise ConfigError(f"starts: got shape {st.shape}, expected finite (N, 2)")
        self.num_robots_ = st.shape[0]
        self._starts = st
        self._reference = as_reference(reference, self.num_robots_, duration)
        self._team = make_team(robots, self.num_robots_)
        self._obstacles = _check_obstacles(*(obstacles if obstacles is not None else ((), ())))
        if headings is not None:
            h = np.asarray(headings, dtype=np.float64).reshape(-1)
            if h.shape != (self.num_robots_,) or not np.all(np.isfinite(h)):
                raise ConfigError(f"headings: got shape {h.shape}, expected finite ({self.num_robots_},)")
            self._headings = h
        else:
            self._headings = None
        if settle_time < 0:
            raise ConfigError(f"settle_time: got {settle_time!r}, expected >= 0")
        self.settle_time = float(settle_time)
        d = np.hypot(*(st[:, None] - st[None]).transpose(2, 0, 1)) + np.diag(np.full(self.num_robots_, np.inf))
        rs = self._team.radius[:, None] + self._team.radius[None, :]
        if np.any(d < rs):
            i, j = np.argwhere(d < rs)[0]
            raise ScenarioError(f"starts: robots {i} and {j} overlap ({d[i, j]:.3f} < {rs[i, j]:.3f})")

    def build(self, rng: np.random.Generator) -> Layout:
        """Return the user's layout."""
        ref = self._reference
        _, v0, _ = ref(0.0)
        toward = np.arctan2(*(ref.goals - self._starts).T[::-1])
        headings = self._headings if self._headings is not None else _heading_of(v0, toward)
        pts = np.concatenate([self._starts, ref.goals, *(ref(t)[0] for t in np.linspace(0, ref.duration, 16))])
        if self._obstacles[0].shape[0]:
            pts = np.concatenate([pts, self._obstacles[0]])
        lo, hi = pts.min(axis=0) - 1.5, pts.max(axis=0) + 1.5
        return Layout(
            team=self._team,
            starts=self._starts.copy(),
            headings=headings,
            reference=ref,
            horizon=ref.duration + self.settle_time,
            obstacle_centers=self._obstacles[0],
            obstacle_radii=self._obstacles[1],
            bounds=(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])),
        )


SCENARIOS: dict[str, type[Scenario]] = {
    cls.name: cls for cls in (CircleSwap, CircleSwapObstacles, Tracking, PositionSwap, RandomGoals, Custom)
}


def get_scenario(scenario: str | Scenario, **kwargs: Any) -> Scenario:
    """Return a scenario instance from a name (with parameters) or pass one through."""
    if isinstance(scenario, Scenario):
        if kwargs:
            raise ConfigError(f"scenario parameters {sorted(kwargs)} given with a Scenario instance")
        return scenario
    if scenario not in SCENARIOS:
        raise ScenarioError(f"unknown scenario {scenario!r}; known scenarios: {sorted(SCENARIOS)}")
    try:
        return SCENARIOS[scenario](**kwargs)
    except TypeError as exc:
        raise ConfigError(f"scenario {scenario!r}: {exc}") from None
