"""Robot parameters: one validated :class:`RobotParams` per robot, stacked into ``(N,)`` arrays per :class:`Team`."""

from __future__ import annotations

import math
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, replace
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
_RANGES: dict[str, tuple[float, float]] = {  # SI units; beyond them the kinematics under- or overflow
    "radius": (1e-6, 1e6), "wheel_radius": (1e-6, 1e6), "half_track": (1e-6, 1e6), "offset": (1e-6, 1e6),
    "max_wheel_accel": (1e-6, 1e9), "max_wheel_speed": (1e-6, 1e9),
}


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of one robot.

    ``radius`` of the enclosing disc (a pair's safety distance is the sum), wheel radius ``rho``, half the wheel
    distance ``b`` and the control point's distance ``offset`` ``l > 0`` ahead of the axle centre [m]; bounds on
    each wheel's ``|du|`` [rad/s^2] and ``|u|`` [rad/s] (``inf``: none; double integrator: per component, SI);
    ``model``: ``"diff_drive"`` (feedback-linearised control point) or ``"double_integrator"`` (``A = I``).
    """

    radius: float = 0.48
    wheel_radius: float = 0.1
    half_track: float = 0.2
    offset: float = 0.2
    max_wheel_accel: float = 60.0
    max_wheel_speed: float = math.inf
    model: Model = "diff_drive"

    def __post_init__(self) -> None:
        for name, (lo, hi) in _RANGES.items():
            object.__setattr__(self, name, positive(f"RobotParams.{name}", getattr(self, name), lo=lo, hi=hi,
                                                    allow_inf=name == "max_wheel_speed"))
        choice("RobotParams.model", self.model, MODELS)

    @classmethod
    def preset(cls, name: str, **overrides: float | str) -> "RobotParams":
        """Return a preset of :data:`PRESETS`, optionally with fields overridden."""
        if not isinstance(name, str) or name not in PRESETS:
            raise ConfigError(f"robots: unknown robot preset {name!r}; known presets: {sorted(PRESETS)}")
        return replace(PRESETS[name], **overrides)

    @property
    def max_point_accel(self) -> float:
        """Largest control-point acceleration guaranteed in every direction at rest (eqn.n4's ``a_i^+``).

        The inscribed radius ``a rho k / sqrt(1 + k^2)`` (``k = l / b``) of ``{A du : |du|_inf <= a}``.
        """
        if self.model == "double_integrator":
            return self.max_wheel_accel
        k = self.offset / self.half_track
        return self.max_wheel_accel * self.wheel_radius * k / math.sqrt(1.0 + k * k)


PRESETS: dict[str, RobotParams] = {
    "paper": RobotParams(),
    "turtlebot3_burger": RobotParams(radius=0.105, wheel_radius=0.033, half_track=0.08, offset=0.05,
                                     max_wheel_accel=20.0, max_wheel_speed=0.22 / 0.033),
    "turtlebot3_waffle_pi": RobotParams(radius=0.22, wheel_radius=0.033, half_track=0.1435, offset=0.08,
                                        max_wheel_accel=20.0, max_wheel_speed=0.26 / 0.033),
    "paper_small": RobotParams(radius=0.3),
    "double_integrator": RobotParams(max_wheel_accel=6.0, model="double_integrator"),
}
"""Robot presets by name (the table: ``docs/env.md``); ``paper``: ``docs/technical_brief.md`` section 7."""


_PER_ROBOT = (*_RANGES, "max_point_accel")  # the Team fields with one value per robot


@dataclass(frozen=True)
class Team:
    """Parameters of N robots as ``(N,)`` arrays (:class:`RobotParams`) of one ``model``; not to be changed in place.

    Build with :func:`make_team`; ``group (N,)`` labels stacked independent teams (:func:`stack_teams`): no pair across.
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
        """The team of robots ``idx``; its :attr:`derived` holds ``(self, robot numbers)`` under :data:`SUBSET_OF`."""
        rows = np.arange(self.n)[idx]  # (the caller's index as robot numbers, a copy: masks and slices too)
        sub = Team(*(getattr(self, name)[rows] for name in _PER_ROBOT), self.model,
                   None if self.group is None else self.group[rows])
        sub.derived[SUBSET_OF] = (self, rows)
        return sub

    @property
    def is_diff_drive(self) -> bool:
        """False for double integrators."""
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
        """Columns of ``A`` at heading 0 as complex numbers ``(N, 2)``: ``A(theta)[:, j] = e^{i theta} columns[:, j]``.

        ``rho/2 (1 +- i k)`` (``k = l / b``) for differential drive, ``1`` and ``i`` for the double integrator.
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
        """Values other modules compute from these parameters, keyed by their maker and its arguments (not pickled)."""
        return {}

    def __getstate__(self) -> dict[str, Any]:
        """The parameters and cached arrays, without :attr:`derived` (a subset's whole team stays behind)."""
        return {k: v for k, v in self.__dict__.items() if k != "derived"}

    @cached_property
    def turn_gain(self) -> np.ndarray:
        """``rho / (2 b)``: yaw rate per unit wheel-speed difference, shape ``(N,)``."""
        return self.wheel_radius / (2.0 * self.half_track)


def make_team(robots: RobotParams | str | Sequence[RobotParams | str] | None, n: int) -> Team:
    """A :class:`Team` of ``n`` robots from one spec (preset name, :class:`RobotParams`, None: ``"paper"``) or ``n``."""
    robots = "paper" if robots is None else robots
    if isinstance(robots, (str, RobotParams)):
        specs: list[RobotParams | str] = [robots] * n
    elif isinstance(robots, (list, tuple)):
        specs = list(robots)
        if len(specs) != n:
            raise ConfigError(f"robots: got {len(specs)} robot specs, expected one or {n} (one per robot)")
    else:
        raise ConfigError(f"robots: got {type(robots).__name__}, expected a preset name {sorted(PRESETS)}, a "
                          "RobotParams, or a list of those (one per robot)")
    params = [RobotParams.preset(s) if isinstance(s, str) else s for s in specs]
    if not params:
        raise ConfigError("robots: got an empty list, expected one robot spec or one per robot")
    for i, p in enumerate(params):
        if not isinstance(p, RobotParams):
            raise ConfigError(f"robots[{i}]: got {type(p).__name__}, expected RobotParams or a preset name")
    models = {p.model for p in params}
    if len(models) > 1:
        raise ConfigError(f"robots: got mixed dynamics models {sorted(models)}, expected one model per team")
    return Team(**{name: np.array([getattr(p, name) for p in params], dtype=np.float64) for name in _PER_ROBOT},
                model=params[0].model)


def stack_teams(teams: Sequence[Team]) -> Team:
    """One :class:`Team` of all robots of ``teams`` (one dynamics model), ``group`` = each robot's team."""
    models = {t.model for t in teams}
    if len(models) != 1:
        raise ConfigError(f"teams: got dynamics models {sorted(models)}, expected one model for the whole stack")
    group = np.concatenate([np.full(t.n, k, dtype=np.int64) for k, t in enumerate(teams)])
    return Team(**{name: np.concatenate([getattr(t, name) for t in teams]) for name in _PER_ROBOT},
                model=teams[0].model, group=group)
