"""Analytic baseline controllers: the paper's tracking law, SBC's PD law, random."""

from __future__ import annotations

from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError
from aasoatt_env.model.tracking import PAPER_K3, PAPER_K4, point_accel_to_du, tracking_accel
from agents.base import register_agent
from agents.learned import load_learned

__all__ = ["PDController", "RandomAgent", "TrackingController", "point_accel_to_action"]


def point_accel_to_action(env: Any, accel: np.ndarray, saturate: bool) -> dict[str, np.ndarray]:
    """Map desired control-point accelerations ``(N, 2)`` to normalised wheel actions.

    ``du = A^{-1} (accel - A_dot u)`` divided by ``max_wheel_accel``.  With
    ``saturate=False`` the action may leave ``[-1, 1]``: behind
    :class:`~aasoatt_env.safety.wrapper.AASOATTFilter` that is the nominal the QP
    projects (the bounds stay hard there); a bare env needs ``saturate=True``,
    which clips each wheel to its bound.
    """
    base = env.unwrapped
    act = point_accel_to_du(base.kinematics, accel) / base.team.max_wheel_accel[:, None]
    if saturate:
        act = np.clip(act, -1.0, 1.0)
    act = act.astype(np.float32)
    idx = base.agent_index
    return {a: act[idx[a]] for a in env.agents}


class TrackingController:
    """The paper's trajectory-tracking law (eqn.11-12), as a nominal controller.

    ``a = a_d - (k3 + k4)(v - v_d) - k3 k4 (p - p_d)``, i.e. ``A du = dzr`` with
    ``dzr = a - A_dot u``.  It reads the state and reference from the env
    (full-state feedback), not from the observations.

    Parameters
    ----------
    k3, k4 : float
        Positive gains (paper: 1 and 4).
    saturate : bool
        Clip actions to ``[-1, 1]`` (needed on a bare env; behind the filter
        leave False so the QP sees the unclipped target).
    """

    def __init__(self, k3: float = PAPER_K3, k4: float = PAPER_K4, saturate: bool = False) -> None:
        self.k3 = check.positive("k3", k3, hi=1e3)
        self.k4 = check.positive("k4", k4, hi=1e3)
        self.saturate = check.boolean("saturate", saturate)

    def reset(self, env: Any) -> None:
        """Nothing to reset (stateless)."""

    def point_accel(self, env: Any) -> np.ndarray:
        """Desired control-point accelerations ``(N, 2)``."""
        base = env.unwrapped
        kin = base.kinematics
        p_d, v_d, a_d = base.reference
        return tracking_accel(kin.p, kin.v, p_d, v_d, a_d, self.k3, self.k4)

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """Actions for every live agent."""
        return point_accel_to_action(env, self.point_accel(env), self.saturate)


class PDController(TrackingController):
    """SBC's nominal controller ``a = -k3 (p - p_d) - k4 v`` (Table I; paper k3 = 10 or 80, k4 = 4)."""

    def __init__(self, k3: float = 10.0, k4: float = 4.0, saturate: bool = False) -> None:
        super().__init__(k3, k4, saturate)

    def point_accel(self, env: Any) -> np.ndarray:
        """Desired control-point accelerations ``(N, 2)``."""
        base = env.unwrapped
        kin = base.kinematics
        return -self.k3 * (kin.p - base.reference[0]) - self.k4 * kin.v


class RandomAgent:
    """Uniform random actions in each agent's action space (seeded)."""

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self, env: Any) -> None:
        """Nothing to reset."""

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """One uniform sample per live agent."""
        out = {}
        for a in env.agents:
            space = env.action_space(a)
            out[a] = self.rng.uniform(space.low, space.high).astype(np.float32)
        return out


def _load_learned(path: str | None = None, **kwargs: Any) -> Any:
    """Factory for ``--controller learned``: an SB3 or RLlib run (imports SB3 or Ray lazily: their extras)."""
    if path is None:
        raise ConfigError("controller 'learned': got no model path, expected --model PATH (a run folder or .zip)")
    return load_learned(path, **kwargs)


register_agent("tracking", TrackingController)
register_agent("learned", _load_learned)  # type: ignore[arg-type]
register_agent("pd", PDController)
register_agent("random", RandomAgent)
