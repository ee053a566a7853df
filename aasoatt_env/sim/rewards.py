"""The per-agent reward of one env step.

``r_i = -tracking |p_i - p_d_i| - collision [clearance_i < -tol] - effort |action_i|^2 / 2
- correction c_i + goal_bonus [|p_i - goal_i| < goal_tolerance]``, where ``c_i`` is the largest
``|du_safe - du_nominal| / max_wheel_accel`` of the step's control filter (0 without one).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError

__all__ = ["RewardConfig", "rewards"]


@dataclass(frozen=True)
class RewardConfig:
    """Weights of the reward terms (module docstring); all finite and ``>= 0``."""

    tracking: float = 1.0
    collision: float = 10.0
    effort: float = 0.01
    correction: float = 0.0
    goal_bonus: float = 0.0
    goal_tolerance: float = 0.05

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name, check.real(f"RewardConfig.{f.name}", getattr(self, f.name), lo=0.0))

    @classmethod
    def coerce(cls, value: RewardConfig | Mapping[str, Any] | None) -> RewardConfig:
        """A :class:`RewardConfig` from itself, a mapping of its fields (unknown keys: ``TypeError``) or None."""
        if value is None:
            return cls()
        if isinstance(value, RewardConfig):
            return value
        if isinstance(value, Mapping):
            check.reject_unknown("RewardConfig", value, [f.name for f in fields(cls)])
            return cls(**dict(value))
        raise ConfigError(f"reward: got {value!r}, expected a RewardConfig, a mapping of its weights or None")


def rewards(cfg: RewardConfig, tracking_error: np.ndarray, collided: np.ndarray, action: np.ndarray,
            goal_distance: np.ndarray | None, correction: np.ndarray | None) -> np.ndarray:
    """Rewards ``(N,)`` of one env step (module docstring); ``correction`` ``c_i`` (None without a filter)."""
    r = -cfg.tracking * tracking_error - cfg.collision * collided - cfg.effort * 0.5 * np.add.reduce(action * action,
                                                                                                   axis=1)
    if cfg.goal_bonus and goal_distance is not None:
        r = r + cfg.goal_bonus * (goal_distance < cfg.goal_tolerance)
    if cfg.correction and correction is not None:
        r = r - cfg.correction * correction
    return r
