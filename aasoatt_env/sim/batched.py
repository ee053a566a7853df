"""``BatchedAASOATTEnv``: ``K`` teams in one vectorised physics call, as ``K`` separate envs (``docs/env.md``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces

from aasoatt_env.errors import ConfigError, ResetNeeded
from aasoatt_env.sim.env import AASOATTParallelEnv, parse_actions
from aasoatt_env.sim.protocol import GroupedControlFilter
from aasoatt_env.sim.stack import TeamStack

__all__ = ["BatchedAASOATTEnv"]


class TeamsAPI:
    """What :class:`BatchedAASOATTEnv` and :class:`~aasoatt_env.sim.sharded.ShardedBatchedEnv` share."""

    metadata = {"autoreset_mode": "same_step"}
    shared_settings: dict[str, Any]  # the teams' SHARED_SETTINGS and `filtered`
    num_envs: int
    _started: bool  # reset() was called

    def _take_settings(self, settings: dict[str, Any], agent_obs: spaces.Box, agent_act: spaces.Box) -> None:
        self.shared_settings = settings
        self.possible_agents: list[str] = list(settings["possible_agents"])
        self.num_agents = n = len(self.possible_agents)
        for name in SHARED_SETTINGS[1:]:
            setattr(self, name, settings[name])
        self.agent_observation_space, self.agent_action_space = agent_obs, agent_act  # one robot's
        leads = ((n,), (self.num_envs, n))  # a team's, the batch's
        self.single_observation_space, self.observation_space = (
            spaces.Box(np.broadcast_to(agent_obs.low, (*lead, *agent_obs.shape)),
                       np.broadcast_to(agent_obs.high, (*lead, *agent_obs.shape)), dtype=agent_obs.dtype)
            for lead in leads)
        self.single_action_space, self.action_space = (spaces.Box(-1.0, 1.0, (*lead, 2), np.float32) for lead in leads)

    def _check_step(self, finished: np.ndarray) -> None:
        """Before a ``step``: :class:`ResetNeeded` until the first ``reset``, or naming the teams ``finished``."""
        if not self._started:
            raise ResetNeeded("step(): call reset() first")
        if finished.size:  # (autoreset=False)
            raise ResetNeeded(f"step(): team(s) {finished.tolist()} finished their episode (autoreset=False); "
                              "call reset() first")

    @property
    def filtered(self) -> bool:
        """Whether the teams are filtered."""
        return bool(self.shared_settings["filtered"])

    def _on_team(self, k: int, what: str, args: tuple) -> Any:
        """``what`` (``get``, ``set``, ``call``, ``wrapped``) with ``args`` on team ``k``'s own env."""
        raise NotImplementedError

    def env_get(self, k: int, name: str) -> Any:
        """Attribute ``name`` of team ``k``'s own env (``k`` as a sequence index: ``-1`` is the last team)."""
        return self._on_team(k, "get", (name,))

    def env_set(self, k: int, name: str, value: Any) -> None:
        """Set attribute ``name`` of team ``k``'s own env."""
        self._on_team(k, "set", (name, value))

    def env_call(self, k: int, name: str, *args: Any, **kwargs: Any) -> Any:
        """Call method ``name`` of team ``k``'s own env, after a ``sync`` (its state is the batch's)."""
        return self._on_team(k, "call", (name, args, kwargs))

    def env_is_wrapped(self, k: int, wrapper_class: type) -> bool:
        """Whether team ``k``'s own env is (PettingZoo-)wrapped by ``wrapper_class``."""
        return bool(self._on_team(k, "wrapped", (wrapper_class,)))


class BatchedAASOATTEnv(TeamsAPI, TeamStack):
    """``K`` teams of one scenario stepped together.

    ``env_fns`` each return an :class:`~aasoatt_env.sim.env.AASOATTParallelEnv` or a wrapper of one (its filter
    is used, its ``step`` is not) with the same :data:`SHARED_SETTINGS`.  ``group_filter``: one filter call for
    all teams where their filters allow it; ``team_offset``: the first team's number in messages (a shard).
    """

    def __init__(self, env_fns: Sequence[Callable[[], Any]], *, autoreset: bool = True,
                 group_filter: bool = True, team_offset: int = 0) -> None:
        if len(env_fns) < 1:
            raise ConfigError(f"env_fns: got {len(env_fns)} callables, expected at least 1")
        self.envs: list[Any] = [fn() for fn in env_fns]
        bases = [getattr(e, "unwrapped", e) for e in self.envs]
        for k, b in enumerate(bases):
            if not isinstance(b, AASOATTParallelEnv):
                raise ConfigError(f"env_fns[{k}]: got {type(b).__name__}, expected an AASOATTParallelEnv (or a "
                                  "wrapper of one)")
        self._bases: list[AASOATTParallelEnv] = bases
        first = bases[0]
        settings = shared_settings(first)
        for k, b in enumerate(bases[1:], 1):
            check_shared(shared_settings(b), settings, int(team_offset) + k)
        self.autoreset = bool(autoreset)
        self._offset = int(team_offset)
        self.num_envs = len(bases)
        agent = first.possible_agents[0]
        self._take_settings(settings, first.observation_space(agent), first.action_space(agent))
        self.nominal_actions = first._nominal_actions  # a nominal for a filter that keeps the bounds (up to 1e6)
        self._grouped: GroupedControlFilter | None = None
        if self.filtered and group_filter:
            make = getattr(first.control_filter, "grouped", None)
            self._grouped = make([b.control_filter for b in bases]) if callable(make) else None
        self._started = False
        self._done = np.zeros(self.num_envs, dtype=bool)
        self._init_stack(self.num_envs, self.num_agents)

    @property
    def live(self) -> np.ndarray:
        """``(K, N)`` bool: agents that act at the next ``step`` (a copy)."""
        return (self._active & ~np.repeat(self._done, self.num_agents)).reshape(self.num_envs, self.num_agents)

    @property
    def grouped_filter(self) -> GroupedControlFilter | None:
        """The one filter of all teams, or None (one per team)."""
        return self._grouped

    @property
    def max_steps(self) -> np.ndarray:
        """Each team's episode horizon in env steps ``(K,)``."""
        return self._max_steps.copy()

    @property
    def elapsed_steps(self) -> np.ndarray:
        """Env steps taken in each team's episode ``(K,)``."""
        return self._steps.copy()

    def reset(self, seed: int | Sequence[int | None] | None = None,
              options: dict | Sequence[dict | None] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every team; ``seed``/``options``: None, one (team ``k`` gets ``seed + k``) or one per team."""
        seeds, opts = per_team_reset_args(seed, options, self.num_envs)
        obs = np.stack([self._reset_team(k, seeds[k], opts[k]) for k in range(self.num_envs)])
        self._restack()
        self._started = True
        return obs, {}

    def _reset_team(self, k: int, seed: int | None, options: dict | None) -> np.ndarray:
        obs, _ = self.envs[k].reset(seed=seed, options=options)
        self._take_team(k, self._bases[k], 0)
        self._done[k] = False
        self._filter_resets.append(k)
        return np.stack([obs[a] for a in self.possible_agents])

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Hold each team's actions ``(K, N, 2)`` for ``decision_interval`` physics steps."""
        self._check_step(np.flatnonzero(self._done) + self._offset)
        act = parse_actions(actions, self.live, self.nominal_actions, self.clip_actions, self._offset)
        live_before = self._active
        saturated, between, outputs = self._physics(act)
        obs, rew, collided, terminated, finished, corr, goal = self._decide(act, saturated, between, outputs)
        shape = (self.num_envs, self.num_agents)
        infos: dict[str, Any] = {}
        if outputs:
            intervened, avoiding = self._filter_flags(outputs)
            infos.update(filter_correction=corr.reshape(shape), filter_intervened=intervened.reshape(shape),
                         filter_avoiding=avoiding.reshape(shape))
        goal = np.hypot(*(self._kin.p - self._goals).T) if goal is None else goal  # type: ignore[union-attr]
        infos.update(tracking_error=self._err.reshape(shape), clearance=self._clearance.reshape(shape).copy(),
                     collision=collided.reshape(shape), saturated=saturated.reshape(shape).copy(),
                     goal_distance=goal.reshape(shape), time=self._times.copy())
        truncated = np.repeat(finished, self.num_agents) & live_before
        terminated = np.zeros(shape, dtype=bool) if terminated is None else terminated.reshape(shape)
        self._done = finished | ~self._active.reshape(shape).any(axis=1)
        obs = obs.reshape(*shape, -1)
        if self.autoreset and self._done.any():
            infos["final_obs"], infos["_final_obs"] = obs.copy(), self._done.copy()
            for k in np.flatnonzero(self._done):
                obs[k] = self._reset_team(int(k), None, None)
            self._restack()
        return obs, rew.reshape(shape), terminated, truncated.reshape(shape), infos

    def sync(self) -> None:
        """Write the batch's state into the teams' own envs (``envs``), e.g. before rendering them."""
        if not self._started:
            raise ResetNeeded("sync(): call reset() first")
        for k, base in enumerate(self._bases):
            base._load_state(self, k, bool(self._steps[k] >= self._max_steps[k]))

    def render(self) -> tuple[Any, ...]:
        """One frame per team (their envs' ``render()``; needs a ``render_mode``)."""
        self.sync()
        return tuple(env.render() for env in self.envs)

    def _on_team(self, k: int, what: str, args: tuple) -> Any:
        env = self.envs[team_index(k, self.num_envs)]
        if what == "get":
            return getattr(env, args[0])
        if what == "set":
            return setattr(env, *args)
        if what == "call":
            self.sync()
            return getattr(env, args[0])(*args[1], **args[2])
        while env is not None and not isinstance(env, args[0]):  # "wrapped"
            env = getattr(env, "env", None)
        return env is not None

    def close(self) -> None:
        """Close the teams' envs."""
        for env in self.envs:
            env.close()


SHARED_SETTINGS = ("possible_agents", "dt", "decision_interval", "action_mode", "num_neighbors", "num_obstacles",
                   "sensing_range", "reward_config", "terminate_on_collision", "collision_tolerance", "clip_actions")
"""Settings every team of a batch shares (attributes of :class:`~aasoatt_env.sim.env.AASOATTParallelEnv`)."""


def shared_settings(env: AASOATTParallelEnv) -> dict[str, Any]:
    """The :data:`SHARED_SETTINGS` of a team's env, and whether it is behind a filter (``filtered``)."""
    return {**{name: getattr(env, name) for name in SHARED_SETTINGS}, "filtered": env.control_filter is not None}


def check_shared(got: dict[str, Any], want: dict[str, Any], k: int) -> None:
    """Raise :class:`ConfigError` naming ``env_fns[k]`` if its shared settings differ from env 0's."""
    if got["filtered"] != want["filtered"]:
        raise ConfigError(f"env_fns[{k}]: behind a filter or not, unlike env 0; a batch is one or the other")
    for name in SHARED_SETTINGS:
        if got[name] != want[name]:
            raise ConfigError(f"env_fns[{k}]: {name} differs from env 0's ({got[name]!r} vs {want[name]!r}); a "
                              "batch shares one setting")


def team_index(k: Any, num_envs: int) -> int:
    """Team number ``k`` in ``[0, num_envs)`` (negative ``k`` counts from the end), or :class:`ConfigError`."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not -num_envs <= k < num_envs:
        raise ConfigError(f"k: got {k!r}, expected a team number in [0, {num_envs}) (or from -{num_envs})")
    return int(k) % num_envs


def per_team_reset_args(seed: int | Sequence[int | None] | None, options: dict | Sequence[dict | None] | None,
                        k_all: int) -> tuple[list[int | None], list[dict | None]]:
    """``reset``'s ``seed`` and ``options`` as one entry per team (validated; see :meth:`BatchedAASOATTEnv.reset`)."""
    if seed is None or isinstance(seed, (int, np.integer)):
        seeds: list[int | None] = [None if seed is None else int(seed) + k for k in range(k_all)]
    else:
        seeds = list(seed)
        if len(seeds) != k_all:
            raise ConfigError(f"seed: got {len(seeds)} seeds, expected one per team ({k_all})")
    if options is None or isinstance(options, dict):
        opts: list[dict | None] = [options] * k_all
    else:
        opts = list(options)
        if len(opts) != k_all or not all(o is None or isinstance(o, dict) for o in opts):
            raise ConfigError(f"options: got a sequence of {len(opts)} entries, expected None, one dict, or one "
                              f"dict/None per team ({k_all})")
    return seeds, opts
