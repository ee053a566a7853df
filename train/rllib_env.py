"""The env of the RLlib backend: every robot of many teams is one sub-env of one Gymnasium vector env.

RLlib's env runner steps a Gymnasium vector env and keeps one single-agent episode per sub-env.
:class:`SlotVectorEnv` makes each robot of ``K`` teams such a sub-env (``K * N`` slots, one shared
policy: parameter sharing, as the Stable-Baselines3 backend does) and steps all teams with one
vectorised call of :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv` (behind the filter: one
filter call for all teams, with the compiled kernels where numba is installed).  So an env
runner does one batched physics step, one policy forward pass and one filter call per decision
for all its robots.

Episode boundaries follow Gymnasium's next-step autoreset, which RLlib expects: the step at
which a team's episode ends returns its last observation with ``truncated`` (or ``terminated``)
for its robots; the next step hands out the new episode's first observation, with reward 0 and
no flags, and the actions RLlib sends for that team at that step are ignored.  The batch has
already reset the team, and all teams advance together, so the team spends that step at rest
(zero nominal acceleration): each episode RLlib sees starts after one decision at rest from the
scenario's initial state, and is one decision shorter than the horizon.  Robots of a team end
their episodes together, so ``terminate_on_collision`` is not supported here (a robot that
collides would have no episode to continue until its team resets).

Actions are clipped to ``[-1, 1]`` here, for all robots at once (what RLlib's per-robot action
normalisation does for this action space; :class:`agents.rllib_agent.RLlibAgent` acts the same).

At the end of each robot-episode ``infos["is_success"]`` says whether the robot is within
``goal_tolerance`` of its goal; :func:`log_success` makes it RLlib's ``success`` metric.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector.utils import batch_space

__all__ = ["SlotVectorEnv", "log_success", "make_rllib_env", "slots_per_team"]


def slots_per_team(env_kwargs: dict[str, Any]) -> int:
    """Robots of one team of ``env_kwargs`` (built once to ask: a scenario may fix its team)."""
    from aasoatt_env.api.factory import make_env

    probe = make_env(**env_kwargs)
    n = len(probe.possible_agents)
    probe.close()
    return n


class SlotVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` robot slots: ``num_envs / N`` teams of ``N`` robots stepped together (module docstring).

    Parameters
    ----------
    env_config : dict
        ``{"env": env keywords, "filter": filter configuration or None}`` (:meth:`RLlibConfig.env_config`).
    num_envs : int
        Slots: a multiple of the team size ``N``.
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP}

    def __init__(self, env_config: dict[str, Any], num_envs: int) -> None:
        from aasoatt_env.api.factory import make_batched_env

        env = dict(env_config["env"])
        if env.get("terminate_on_collision"):
            raise ValueError("SlotVectorEnv: terminate_on_collision is not supported (teams end their episodes "
                             "together)")
        n = slots_per_team(env)
        if num_envs % n:
            raise ValueError(f"num_envs: got {num_envs}, expected a multiple of the team size {n}")
        self.teams, self.robots = num_envs // n, n
        self.batch = make_batched_env(self.teams, filter=env_config.get("filter"), **env)
        self.num_envs = num_envs
        self.single_observation_space = self.batch.agent_observation_space
        self.single_action_space = self.batch.agent_action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._tolerance = float((env.get("reward") or {}).get("goal_tolerance", 0.1))
        self._restart = np.zeros(self.teams, dtype=bool)
        self._dim = int(np.prod(self.single_observation_space.shape))

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Reset every team (team ``k`` with ``seed + k``)."""
        obs, _ = self.batch.reset(seed=seed, options=options)
        self._restart[:] = False
        return obs.reshape(self.num_envs, self._dim), {}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        """One decision of every team (module docstring: episode ends and restarts)."""
        act = np.clip(np.asarray(actions, dtype=np.float32), -1.0, 1.0).reshape(self.teams, self.robots, -1)
        restart = self._restart
        act[restart] = 0.0
        obs, rew, term, trunc, info = self.batch.step(act)
        ended = info.get("_final_obs")
        if ended is not None:
            obs = np.where(ended[:, None, None], info["final_obs"], obs)
        rew, term, trunc = rew.astype(np.float32), term.copy(), trunc.copy()
        rew[restart], term[restart], trunc[restart] = 0.0, False, False
        done = term | trunc
        infos: dict[str, Any] = {}
        if done.any():
            success = (info["goal_distance"] <= self._tolerance) & ~term
            infos = {"is_success": success.ravel(), "_is_success": done.ravel()}
        self._restart = ended.copy() if ended is not None else np.zeros(self.teams, dtype=bool)
        return obs.reshape(self.num_envs, self._dim), rew.ravel(), term.ravel(), trunc.ravel(), infos

    def close_extras(self, **kwargs: Any) -> None:
        """Close the teams (if they were built)."""
        batch = getattr(self, "batch", None)
        if batch is not None:
            batch.close()


def make_rllib_env(env_config: dict[str, Any]) -> SlotVectorEnv:
    """RLlib's env creator: the vector env of ``env_config["num_envs"]`` slots (runs in every env runner)."""
    return SlotVectorEnv(dict(env_config), int(env_config["num_envs"]))


def log_success(episode: Any, metrics_logger: Any = None, **kwargs: Any) -> None:
    """RLlib ``on_episode_end`` callback: log whether the robot ended within the goal tolerance."""
    if metrics_logger is not None:
        info = episode.get_infos(-1) or {}
        metrics_logger.log_value("success", float(bool(info.get("is_success", False))), reduce="mean", window=1000)
