"""Centralised single-agent Gymnasium view of the multi-robot env (spaces, reward, ``info``: ``docs/env.md``)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from aasoatt_env import validation as check
from aasoatt_env.api.factory import make_env
from aasoatt_env.errors import ConfigError
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.sim.env import real_actions

__all__ = ["AASOATTGymEnv"]


class AASOATTGymEnv(gym.Env):
    """Joint-action view of :class:`~aasoatt_env.sim.env.AASOATTParallelEnv` (``**kwargs``: its keywords).

    ``parallel_env``: wrap this (possibly filtered) env instead; ``safety_filter``: a :class:`FilterConfig` or a
    dict of its fields (``{}``: the defaults) puts the safety filter between the joint action and the robots.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 20}

    def __init__(self, scenario: str = "circle_swap", parallel_env: Any = None,
                 safety_filter: FilterConfig | dict[str, Any] | None = None, **kwargs: Any) -> None:
        if parallel_env is not None:
            if safety_filter is not None or kwargs:
                raise ConfigError("parallel_env: given together with safety_filter/env keywords; "
                                  "build the parallel env with them instead (aasoatt_env.make_env)")
            self.par = parallel_env
        else:
            if safety_filter is not None and not isinstance(safety_filter, (FilterConfig, dict)):
                raise ConfigError(f"safety_filter: got {safety_filter!r}, expected a FilterConfig, a dict of its "
                                  "fields ({} for the defaults) or None")
            self.par = make_env(scenario, filter=safety_filter, infos="flat", **kwargs)
        self.render_mode = self.par.unwrapped.render_mode
        self._agents = list(self.par.possible_agents)
        self._obs_dim = self.par.observation_space(self._agents[0]).shape[0]
        self.observation_space = spaces.Box(-100.0, 100.0, (self._obs_dim * len(self._agents),), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (2 * len(self._agents),), np.float32)

    def _flat(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        missing = np.zeros(self._obs_dim, dtype=np.float32)  # an agent gone from the episode
        return np.concatenate([np.asarray(obs.get(a, missing), dtype=np.float32) for a in self._agents])

    @staticmethod
    def _team_info(infos: dict[str, dict]) -> dict[str, Any]:
        vals = list(infos.values())
        return {
            "agents": infos,
            "min_clearance": min((v["clearance"] for v in vals), default=float("inf")),
            "collision": any(v["collision"] for v in vals),
            "mean_tracking_error": float(np.mean([v["tracking_error"] for v in vals])) if vals else 0.0,
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Reset the team; ``seed`` (an integer >= 0) seeds the scenario."""
        if seed is not None:
            seed = check.integer("seed", seed, lo=0)  # before Gymnasium's own check, which raises its own error type
        super().reset(seed=seed)
        obs, infos = self.par.reset(seed=seed, options=options)
        return self._flat(obs), self._team_info(infos)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Apply the joint action."""
        a = real_actions(action, lambda at: "action" + (f"[{at[0]}]" if at else ""),  # no strings, complex, bools
                         f"{self.action_space.shape} real numbers", self.action_space.shape).astype(np.float64)
        idx = self.par.unwrapped.agent_index
        acts = {ag: a[2 * idx[ag] : 2 * idx[ag] + 2] for ag in self.par.agents}
        obs, rew, term, trunc, infos = self.par.step(acts)
        reward = float(np.mean(list(rew.values()))) if rew else 0.0
        return self._flat(obs), reward, any(term.values()), any(trunc.values()), self._team_info(infos)

    def render(self) -> np.ndarray | None:
        """Render through the parallel env."""
        return self.par.render()

    def close(self) -> None:
        """Close the parallel env."""
        self.par.close()
