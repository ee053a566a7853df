"""Robot parameters: one validated dataclass per robot, vectorised per team.

:class:`RobotParams` describes one robot (disc radius, wheel geometry, control
point offset, input bounds).  :class:`Team` stacks N of them into arrays of
shape ``(N,)`` so the dynamics, the barriers and the QP never loop over robots.

Presets
-------
``"paper"``
    The defaults of ``docs/technical_brief.md`` section 7: disc radius 0.48 m (so ``d_s = 0.96``),
    wheel radius 0.1 m, half track 0.2 m, control-point offset 0.2 m,
    ``|du| <= 60 rad/s^2`` and no wheel-speed limit.  The paper does not state
    its wheel geometry or bounds; these values reproduce its N = 10 results.
``"turtlebot3_waffle_pi"``
    ROBOTIS TurtleBot3 Waffle Pi: wheel radius 0.033 m, track 0.287 m, top
    speed 0.26 m/s (a wheel-speed limit of 7.88 rad/s); enclosing radius 0.22 m;
    offset 0.08 m; wheel-acceleration bound 20 rad/s^2 (our choice).
``"paper_small"``
    The paper robot with a disc radius of 0.3 m: 100 robots of radius 0.48 do not
    fit on the radius-10 circle of the paper's 100-robot experiment, these do.
``"double_integrator"``
    A holonomic point robot (``A = I``) of radius 0.48 with ``|a| <= 6 m/s^2`` per axis.
``"turtlebot3_burger"``
    ROBOTIS TurtleBot3 Burger: wheel radius 0.033 m, track 0.160 m (half track
    0.08 m), top speed 0.22 m/s, i.e. a wheel-speed limit of 0.22 / 0.033 =
    6.67 rad/s; enclosing radius 0.105 m; offset 0.05 m; wheel-acceleration
    bound 20 rad/s^2 (about 0.66 m/s^2 at the rim; our choice, not ROBOTIS').
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, fields, replace
from functools import cached_property
from typing import Any, Literal

import numpy as np

from aasoatt_env.errors import ConfigError
from aasoatt_env.validation import choice, positive

__all__ = ["PRESETS", "SUBSET_OF", "RobotParams", "Team", "make_team", "stack_teams"]

SUBSET_OF = "subset_of"
"""The :attr:`Team.derived` key of a :meth:`Team.subset`'s ``(whole team, robot numbers)``."""

Model = Literal["diff_drive", "double_integrator"]
MODELS: tuple[str, ...] = ("diff_drive", "double_integrator")


_RANGES: dict[str, tuple[float, float]] = {
    "radius": (1e-6, 1e6),
    "wheel_radius": (1e-6, 1e6),
    "half_track": (1e-6, 1e6),
    "offset": (1e-6, 1e6),
    "max_wheel_accel": (1e-6, 1e9),
    "max_wheel_speed": (1e-6, 1e9),
}
"""Valid range of each :class:`RobotParams` field (SI units; ``max_wheel_speed`` may also be ``inf``).
Beyond them the kinematics under- or overflow (a radius of 5e-324 divides by zero)."""


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of one robot.

    Parameters
    ----------
    radius : float
        Radius of the robot's enclosing disc [m]; the safety distance of a pair
        is the sum of their radii.
    wheel_radius : float
        Wheel radius ``rho`` [m].
    half_track : float
        Half the distance between the wheels ``b`` [m].
    offset : float
        Distance ``l`` of the controlled point ahead of the axle centre [m];
        must be positive (``l = 0`` makes ``A`` singular).
    max_wheel_accel : float
        Bound on each wheel's angular acceleration, ``|du| <= max_wheel_accel``
        [rad/s^2].  For the double integrator: bound on each acceleration
        component [m/s^2].
    max_wheel_speed : float
        Bound on each wheel's angular speed [rad/s] (``inf`` for none).  It is
        enforced by tightening the acceleration bounds of the step, never by
        clipping the state.  For the double integrator: bound on each velocity
        component [m/s].
    model : {"diff_drive", "double_integrator"}
        Differential drive (feedback-linearised control point) or holonomic
        double integrator (``A = I``, ``A_dot = 0``).
    """

    radius: float = 0.48
    wheel_radius: float = 0.1
    half_track: float = 0.2
    offset: float = 0.2
    max_wheel_accel: float = 60.0
    max_wheel_speed: float = math.inf
    model: Model = "diff_drive"

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name == "model":
                continue
            lo, hi = _RANGES[f.name]
            value = positive(f"RobotParams.{f.name}", getattr(self, f.name), allow_inf=f.name == "max_wheel_speed",
                             lo=lo, hi=hi)
            object.__setattr__(self, f.name, value)
        choice("RobotParams.model", self.model, MODELS)

    @classmethod
    def preset(cls, name: str, **overrides: float | str) -> "RobotParams":
        """Return a preset (see module docstring), optionally with fields overridden."""
        if not isinstance(name, str) or name not in PRESETS:
            raise ConfigError(f"robots: unknown robot preset {name!r}; known presets: {sorted(PRESETS)}")
        return replace(PRESETS[name], **overrides)

    @property
    def max_point_accel(self) -> float:
        """Largest control-point acceleration guaranteed in every direction at rest.

        The reachable set ``{A du : |du|_inf <= a}`` is a parallelogram whose
        two columns both have length ``rho/2 sqrt(1 + k^2)`` (``k = l / b``) and
        whose determinant is ``-rho^2 k / 2``; its inscribed-circle radius is
        ``a |det A| / |column| = a rho k / sqrt(1 + k^2)``.  The braking SBC
        (eqn.n4) uses this as ``a_i^+``.
        """
        if self.model == "double_integrator":
            return self.max_wheel_accel
        k = self.offset / self.half_track
        return self.max_wheel_accel * self.wheel_radius * k / math.sqrt(1.0 + k * k)


PRESETS: dict[str, RobotParams] = {
    "paper": RobotParams(),
    "turtlebot3_burger": RobotParams(
        radius=0.105,
        wheel_radius=0.033,
        half_track=0.08,
        offset=0.05,
        max_wheel_accel=20.0,
        max_wheel_speed=0.22 / 0.033,
    ),
    "turtlebot3_waffle_pi": RobotParams(
        radius=0.22,
        wheel_radius=0.033,
        half_track=0.1435,
        offset=0.08,
        max_wheel_accel=20.0,
        max_wheel_speed=0.26 / 0.033,
    ),
    "paper_small": RobotParams(radius=0.3),
    "double_integrator": RobotParams(max_wheel_accel=6.0, model="double_integrator"),
}


@dataclass(frozen=True)
class Team:
    """Parameters of N robots as arrays of shape ``(N,)`` (see :class:`RobotParams`).

    All robots share one dynamics ``model``.  Build with :func:`make_team`.

    ``group`` (optional, ``(N,)`` int) stacks several independent teams into one:
    robots of different groups live in separate worlds, so the safety filter
    forms no pair between them (one filter call for many teams, e.g.
    :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`).  ``None``: one team.
    """

    radius: np.ndarray
    wheel_radius: np.ndarray
    half_track: np.ndarray
    offset: np.ndarray
    max_wheel_accel: np.ndarray
    max_wheel_speed: np.ndarray
    max_point_accel: np.ndarray
    model: Model
    group: np.ndarray | None = None

    @property
    def n(self) -> int:
        """Number of robots."""
        return int(self.radius.shape[0])

    def subset(self, idx: np.ndarray) -> Team:
        """The team of robots ``idx`` (same order).

        It keeps ``(self, its robot numbers)`` in its :attr:`derived` under :data:`SUBSET_OF`: per-robot values
        made for this team can be indexed for it instead of made again (the backup layer's checks
        of a group of robots, several times per step).
        """
        rows = np.arange(self.n)[idx]  # (the caller's index as robot numbers, a copy: masks and slices too)
        sub = Team(self.radius[rows], self.wheel_radius[rows], self.half_track[rows], self.offset[rows],
                   self.max_wheel_accel[rows], self.max_wheel_speed[rows], self.max_point_accel[rows], self.model,
                   None if self.group is None else self.group[rows])
        sub.derived[SUBSET_OF] = (self, rows)
        return sub

    @property
    def is_diff_drive(self) -> bool:
        """True for differential-drive robots, False for double integrators."""
        return self.model == "diff_drive"

    @cached_property
    def du_max(self) -> np.ndarray:
        """Symmetric input bound per robot and input, shape ``(N, 2)`` (read-only)."""
        out = np.repeat(self.max_wheel_accel[:, None], 2, axis=1)
        out.flags.writeable = False
        return out

    @cached_property
    def speed_limited(self) -> bool:
        """True when some robot has a finite wheel-speed limit."""
        return bool(np.isfinite(self.max_wheel_speed).any())

    @cached_property
    def input_columns(self) -> np.ndarray:
        """Columns of ``A`` at heading 0 as complex numbers, shape ``(N, 2)``.

        ``A(theta)[:, j] = e^{i theta} * input_columns[:, j]`` (real part: row 0,
        imaginary part: row 1), i.e. ``rho/2 (1 + i k)`` and ``rho/2 (1 - i k)``
        with ``k = l / b`` for differential drive, ``1`` and ``i`` for the double
        integrator.  Cached; the dynamics use it to build ``A`` with one rotation.
        """
        if not self.is_diff_drive:
            return np.tile(np.array([1.0 + 0.0j, 1.0j]), (self.n, 1))
        h = 0.5 * self.wheel_radius
        k = self.offset / self.half_track
        return np.stack((h * (1.0 + 1j * k), h * (1.0 - 1j * k)), axis=1)

    @cached_property
    def wheel_map(self) -> np.ndarray:
        """Wheel speeds -> (forward speed, yaw rate) of the axle, shape ``(N, 2, 2)``."""
        h, g = 0.5 * self.wheel_radius, self.turn_gain
        return np.stack((np.stack((h, h), axis=1), np.stack((g, -g), axis=1)), axis=1)

    @cached_property
    def derived(self) -> dict[Hashable, Any]:
        """Values other modules compute from these parameters, kept for the team's life.

        As with the other cached properties, a team's arrays are not to be changed in place.

        Keyed by their maker and its arguments, e.g. the backup layer's per-robot constants
        for one braking fraction and sensing range (:mod:`aasoatt_env.safety.gatekeeper`);
        a :meth:`subset` holds its whole team and robot numbers under :data:`SUBSET_OF`.
        Not pickled (a copy makes them again on first use).
        """
        return {}

    def __getstate__(self) -> dict[str, Any]:
        """The parameters and cached arrays, without :attr:`derived` (a subset's whole team stays behind)."""
        return {k: v for k, v in self.__dict__.items() if k != "derived"}

    @cached_property
    def turn_gain(self) -> np.ndarray:
        """``rho / (2 b)``: yaw rate per unit wheel-speed difference, shape ``(N,)``."""
        return self.wheel_radius / (2.0 * self.half_track)


def make_team(robots: RobotParams | str | Sequence[RobotParams | str] | None, n: int) -> Team:
    """Build a :class:`Team` of ``n`` robots.

    Parameters
    ----------
    robots : RobotParams, str, sequence of those, or None
        One spec (preset name or :class:`RobotParams`) shared by all robots, or
        one per robot (heterogeneous team).  ``None`` means the ``"paper"`` preset.
    n : int
        Number of robots.
    """
    if robots is None:
        robots = "paper"
    if isinstance(robots, (str, RobotParams)):
        specs: list[RobotParams | str] = [robots] * n
    elif isinstance(robots, (list, tuple)):
        specs = list(robots)
        if len(specs) != n:
            raise ConfigError(f"robots: got {len(specs)} robot specs, expected one or {n} (one per robot)")
    else:
        raise ConfigError(
            f"robots: got {type(robots).__name__}, expected a preset name {sorted(PRESETS)}, a RobotParams, "
            "or a list of those (one per robot)"
        )
    params = [RobotParams.preset(s) if isinstance(s, str) else s for s in specs]
    if not params:
        raise ConfigError("robots: got an empty list, expected one robot spec or one per robot")
    for i, p in enumerate(params):
        if not isinstance(p, RobotParams):
            raise ConfigError(f"robots[{i}]: got {type(p).__name__}, expected RobotParams or a preset name")
    models = {p.model for p in params}
    if len(models) > 1:
        raise ConfigError(f"robots: got mixed dynamics models {sorted(models)}, expected one model per team")

    def col(name: str) -> np.ndarray:
        return np.array([getattr(p, name) for p in params], dtype=np.float64)

    return Team(
        radius=col("radius"),
        wheel_radius=col("wheel_radius"),
        half_track=col("half_track"),
        offset=col("offset"),
        max_wheel_accel=col("max_wheel_accel"),
        max_wheel_speed=col("max_wheel_speed"),
        max_point_accel=col("max_point_accel"),
        model=params[0].model if params else "diff_drive",
    )


def stack_teams(teams: Sequence[Team]) -> Team:
    """One :class:`Team` of all robots of ``teams``, in order, with ``group`` = the index of each robot's team.

    The teams must share one dynamics model.  The filter keeps the groups apart
    (:attr:`Team.group`), so the stack can be filtered in one call.
    """
    models = {t.model for t in teams}
    if len(models) != 1:
        raise ConfigError(f"teams: got dynamics models {sorted(models)}, expected one model for the whole stack")
    names = [f.name for f in fields(Team) if f.name not in ("model", "group")]
    group = np.concatenate([np.full(t.n, k, dtype=np.int64) for k, t in enumerate(teams)])
    return Team(**{name: np.concatenate([getattr(t, name) for t in teams]) for name in names}, model=teams[0].model,
                group=group)
