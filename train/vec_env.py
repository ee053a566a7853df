"""SB3 :class:`~stable_baselines3.common.vec_env.VecEnv` adapters: one slot per robot (parameter sharing).

Every robot of every env is one *slot*, so one policy acts for all of them:
``num_envs = n_envs * n_agents`` with slot ``k * n_agents + i`` = robot ``i`` of
env ``k``.  This replaces SuperSuit (``docs/technical_brief.md`` section 8: its ``seed=``
crashes with SB3 2.9, ``black_death_v3`` ends episodes a step late and
time-limit truncation is lost).

* :class:`BatchedVecEnv` (what ``aasoatt train`` uses): over a
  :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`, all teams stepped by one
  vectorised physics call per physics step.
* :class:`ParallelVecEnv`: over any PettingZoo parallel envs, stepped one by one.

Contract (both)
---------------
* **Seeding** goes through SB3: ``VecEnv.seed(s)`` (PPO calls it with its
  ``seed``) makes the next ``reset`` seed env ``k`` with ``s + k * n_agents``
  (the seed of its first slot); later auto-resets pass no seed, so they draw
  from each env's generator and a run is reproducible from ``s`` alone.
* **Auto-reset**: when an env has no live agent left (all terminated or the
  horizon reached) it is reset inside ``step_wait``; the returned observation
  of its slots is the first of the new episode and the last one is in
  ``infos[slot]["terminal_observation"]``.
* **Truncation**: ``infos[slot]["TimeLimit.truncated"]`` is True when the slot
  ended by the horizon and not by termination (so SB3 bootstraps its value).
* **Agents that terminate early** (``terminate_on_collision=True``): the slot
  reports ``done=True`` exactly once, at the step its robot terminates (with
  its ``terminal_observation``, ``TimeLimit.truncated=False``).  Until its env
  resets the slot is *dead*: its observation is zeros, its reward 0, ``done``
  False, ``infos[slot] == {"dead": True}``, and whatever action the policy
  gives for it is ignored.  These padding transitions belong to no episode:
  ``acted_slots`` (slots whose robot acted at the last step) and
  ``live_slots`` (slots whose current observation is real) say which rows are
  real, and :class:`SlotMonitor` (episode lengths and returns),
  :class:`SlotNormalize` (running statistics) and :class:`train.ppo.SlotPPO`
  (the PPO loss) use only those.
* Per-slot infos carry the env's per-agent values (``tracking_error``,
  ``collision``, ...; see each class).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize
from stable_baselines3.common.vec_env.base_vec_env import (
    VecEnv,
    VecEnvIndices,
    VecEnvObs,
    VecEnvStepReturn,
    VecEnvWrapper,
)

from aasoatt_env.errors import ActionError

__all__ = ["BatchedVecEnv", "ParallelVecEnv", "SlotMonitor", "SlotNormalize", "VelocityTrackingShaping"]


class _SlotMasks:
    """The slot masks SlotMonitor, SlotNormalize and SlotPPO read (``_live``, ``_acted`` kept by the VecEnv)."""

    _live: np.ndarray
    _acted: np.ndarray

    @property
    def live_slots(self) -> np.ndarray:
        """Boolean mask of slots whose robot is alive (a copy): their current observation is a real one."""
        return self._live.copy()

    @property
    def acted_slots(self) -> np.ndarray:
        """Slots whose robot acted at the last step (a copy): the others' transitions were padding."""
        return self._acted.copy()

    def _slot_actions(self, actions: Any) -> np.ndarray:
        """``actions`` as an array ``(num_envs, *action shape)``; any other shape is an :class:`ActionError`."""
        arr = np.asarray(actions)
        want = (self.num_envs, *self.action_space.shape)
        if arr.shape != want:
            raise ActionError(f"actions: got shape {arr.shape}, expected {want} (one row per slot: "
                              f"{self.num_envs // self.n_agents} teams x {self.n_agents} robots)")
        return arr


class ParallelVecEnv(_SlotMasks, VecEnv):
    """Vectorise ``n_envs`` PettingZoo parallel envs with one slot per agent.

    Parameters
    ----------
    env_fns : sequence of callables
        Each returns a parallel env (bare or wrapped, e.g. behind
        :class:`~aasoatt_env.safety.wrapper.AASOATTFilter`).  All must have the
        same ``possible_agents`` and the same observation and action spaces.

    Notes
    -----
    See the module docstring for seeding, auto-reset, truncation and dead slots.
    """

    def __init__(self, env_fns: Sequence[Callable[[], Any]]) -> None:
        if len(env_fns) < 1:
            raise ValueError(f"env_fns: got {len(env_fns)} callables, expected at least 1")
        self.envs = [fn() for fn in env_fns]
        first = self.envs[0]
        self.agents: list[str] = list(first.possible_agents)
        self.n_agents = len(self.agents)
        self.n_envs = len(self.envs)
        obs_space = first.observation_space(self.agents[0])
        act_space = first.action_space(self.agents[0])
        for k, env in enumerate(self.envs):
            if list(env.possible_agents) != self.agents:
                raise ValueError(f"env {k}: got agents {env.possible_agents}, expected {self.agents}")
            for a in self.agents:
                if env.observation_space(a) != obs_space or env.action_space(a) != act_space:
                    raise ValueError(f"env {k} agent {a}: spaces differ from {self.agents[0]}'s (parameter sharing)")
        super().__init__(self.n_envs * self.n_agents, obs_space, act_space)
        self._obs_shape = obs_space.shape
        self._obs = np.zeros((self.num_envs, *self._obs_shape), dtype=obs_space.dtype)
        self._live = np.zeros(self.num_envs, dtype=bool)
        self._acted = np.ones(self.num_envs, dtype=bool)
        self._actions: np.ndarray | None = None

    # ------------------------------------------------------------------ helpers
    def _slot(self, k: int, i: int) -> int:
        return k * self.n_agents + i

    def _reset_env(self, k: int, seed: int | None, options: dict | None) -> tuple[np.ndarray, list[dict]]:
        """Reset env ``k``; write its slots' observations and return them with reset infos."""
        obs, infos = self.envs[k].reset(seed=seed, options=options or None)
        block = np.zeros((self.n_agents, *self._obs_shape), dtype=self._obs.dtype)
        out_infos: list[dict] = []
        for i, a in enumerate(self.agents):
            if a in obs:
                block[i] = obs[a]
            self._live[self._slot(k, i)] = a in obs
            out_infos.append(dict(infos.get(a, {})))
        self._obs[k * self.n_agents : (k + 1) * self.n_agents] = block
        return block, out_infos

    # ------------------------------------------------------------------ VecEnv API
    def reset(self) -> VecEnvObs:
        """Reset every env with the seeds/options set by ``seed()``/``set_options()`` (then cleared)."""
        for k in range(self.n_envs):
            seed = self._seeds[self._slot(k, 0)]
            opts = self._options[self._slot(k, 0)]
            _, infos = self._reset_env(k, seed, opts)
            for i in range(self.n_agents):
                self.reset_infos[self._slot(k, i)] = infos[i]
        self._reset_seeds()
        self._reset_options()
        return self._obs.copy()

    def step_async(self, actions: np.ndarray) -> None:
        """Store the actions ``(num_envs, *action_shape)``; dead slots' rows are ignored."""
        self._actions = self._slot_actions(actions)

    def step_wait(self) -> VecEnvStepReturn:
        """Step every env once and auto-reset those whose episode ended."""
        assert self._actions is not None, "step_async() must be called first"
        acts = self._actions.reshape(self.num_envs, -1)
        self._acted = self._live.copy()
        rewards = np.zeros(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for k, env in enumerate(self.envs):
            base = k * self.n_agents
            live = list(env.agents)
            action_dict = {a: acts[base + self.agents.index(a)] for a in live}
            try:
                obs, rew, term, trunc, inf = env.step(action_dict)
            except ActionError as exc:  # the env names the robot; the slots say where it is in the batch
                raise ActionError(f"team {k} (slots {base}..{base + self.n_agents - 1}): {exc}") from None
            for i, a in enumerate(self.agents):
                s = base + i
                if not self._live[s]:
                    self._obs[s] = 0
                    infos[s] = {"dead": True}
                    continue
                o = np.asarray(obs[a], dtype=self._obs.dtype)
                rewards[s] = rew[a]
                info = dict(inf.get(a, {}))
                t, tr = bool(term[a]), bool(trunc[a])
                if t or tr:
                    dones[s] = True
                    info["terminal_observation"] = o
                    info["TimeLimit.truncated"] = tr and not t
                    self._live[s] = False
                    self._obs[s] = 0
                else:
                    self._obs[s] = o
                infos[s] = info
            if not env.agents:  # episode over: auto-reset (seedless: the env's generator continues)
                _, rinfos = self._reset_env(k, None, None)
                for i in range(self.n_agents):
                    self.reset_infos[base + i] = rinfos[i]
        self._actions = None
        return self._obs.copy(), rewards, dones, infos

    def close(self) -> None:
        """Close every env."""
        for env in self.envs:
            env.close()

    def _env_of_slots(self, indices: VecEnvIndices) -> list[Any]:
        return [self.envs[s // self.n_agents] for s in self._get_indices(indices)]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute of the env behind each slot."""
        return [getattr(env, attr_name) for env in self._env_of_slots(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute on the envs behind the slots (each env once)."""
        for env in {id(e): e for e in self._env_of_slots(indices)}.values():
            setattr(env, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        """Call a method of the env behind each slot."""
        return [getattr(env, method_name)(*method_args, **method_kwargs) for env in self._env_of_slots(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        """Whether the env behind each slot is (PettingZoo-)wrapped by ``wrapper_class``."""
        out = []
        for env in self._env_of_slots(indices):
            e, found = env, False
            while e is not None:
                if isinstance(e, wrapper_class):
                    found = True
                    break
                e = getattr(e, "env", None)
            out.append(found)
        return out

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One rendered frame per env (not per slot)."""
        return [env.render() for env in self.envs]



class VelocityTrackingShaping(VecEnvWrapper):
    """Add ``-weight * |v_i - v_d_i|`` to each slot's reward (velocity-tracking error).

    The env's tracking reward ``-|p_i - p_d_i|`` reacts to an acceleration
    only after several decisions (position is its double integral), so its
    credit assignment is slow and noisy; the velocity error ``v_i - v_d_i``
    (observation entries 4:6 and 10:12, see :mod:`aasoatt_env.sim.observations`)
    responds within one decision.  Penalising both is the reward counterpart of
    the tracking law's PD feedback on ``(p - p_d, v - v_d)``.  The error is read
    from the observation *after* the step (``terminal_observation`` for slots
    whose episode ended); dead slots (``infos[slot]["dead"]``) get nothing.
    """

    def __init__(self, venv: VecEnv, weight: float) -> None:
        super().__init__(venv)
        self.weight = float(weight)

    def reset(self) -> VecEnvObs:
        """Reset the wrapped VecEnv."""
        return self.venv.reset()

    def step_wait(self) -> VecEnvStepReturn:
        """Step and subtract the velocity-tracking penalty."""
        obs, rewards, dones, infos = self.venv.step_wait()
        o = np.array(obs, dtype=np.float64, copy=True)
        for s in np.flatnonzero(dones):
            term = infos[s].get("terminal_observation")
            if term is not None:
                o[s] = term
        err = np.linalg.norm(o[:, 4:6] - o[:, 10:12], axis=1)
        dead = np.array([bool(info.get("dead", False)) for info in infos])
        rewards = rewards - (self.weight * err * ~dead).astype(rewards.dtype)
        return obs, rewards, dones, infos


class BatchedVecEnv(_SlotMasks, VecEnv):
    """The SB3 adapter of :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`: one slot per robot of every team.

    Same contract as :class:`ParallelVecEnv` (slots ``k * N + i``, seeding, auto-reset,
    ``terminal_observation``, ``TimeLimit.truncated``, dead slots), but all teams are
    stepped by one vectorised call.  Per-slot infos hold ``tracking_error``,
    ``clearance``, ``collision``, ``goal_distance`` (and behind a filter
    ``filter_intervened``, ``filter_correction``); a slot whose episode ends also
    gets ``is_success``: not terminated and within ``success_radius`` of its goal
    (SB3 logs ``rollout/success_rate`` from it).  The batch's infos arrays of the
    last step are in :attr:`last_infos`.

    Parameters
    ----------
    batch : BatchedAASOATTEnv
        The teams (``autoreset=True``).
    success_radius : float
        Goal distance [m] that counts as success (the evaluation's 0.1 m).
    """

    def __init__(self, batch: Any, success_radius: float = 0.1) -> None:
        if not batch.autoreset:
            raise ValueError("batch: expected a BatchedAASOATTEnv with autoreset=True")
        self.batch = batch
        self.n_envs, self.n_agents = batch.num_envs, batch.num_agents
        self.agents = list(batch.possible_agents)
        self.success_radius = float(success_radius)
        super().__init__(self.n_envs * self.n_agents, batch.agent_observation_space, batch.agent_action_space)
        self._obs_dim = int(np.prod(batch.agent_observation_space.shape))
        self._live = np.zeros(self.num_envs, dtype=bool)
        self._acted = np.ones(self.num_envs, dtype=bool)
        self._actions: np.ndarray | None = None
        self.last_infos: dict[str, Any] = {}
        """The batch's infos arrays ``(K, N)`` of the last step (see :class:`BatchedAASOATTEnv`)."""
        self.last_dones = np.zeros(self.num_envs, dtype=bool)

    @property
    def envs(self) -> list[Any]:
        """The teams' own envs."""
        return self.batch.envs

    def reset(self) -> VecEnvObs:
        """Reset every team with the seeds/options set by ``seed()``/``set_options()`` (then cleared)."""
        seeds = [self._seeds[k * self.n_agents] for k in range(self.n_envs)]
        opts = [self._options[k * self.n_agents] or None for k in range(self.n_envs)]
        obs, _ = self.batch.reset(seed=seeds, options=opts)
        for s in range(self.num_envs):
            self.reset_infos[s] = {}
        self._reset_seeds()
        self._reset_options()
        self._live = self.batch.live.ravel()
        self._acted = np.ones(self.num_envs, dtype=bool)
        return obs.reshape(self.num_envs, self._obs_dim).copy()

    def step_async(self, actions: np.ndarray) -> None:
        """Store the actions ``(num_envs, 2)``; dead slots' rows are ignored."""
        self._actions = self._slot_actions(actions)

    def step_wait(self) -> VecEnvStepReturn:
        """Step all teams once (auto-reset inside the batch)."""
        assert self._actions is not None, "step_async() must be called first"
        acted = self._live
        obs3, rew, term, trunc, binfo = self.batch.step(self._actions.reshape(self.n_envs, self.n_agents, 2))
        self._actions = None
        obs = obs3.reshape(self.num_envs, self._obs_dim)
        final = binfo.get("_final_obs")
        final_obs = binfo["final_obs"].reshape(self.num_envs, self._obs_dim) if final is not None else None
        reset_slots = np.repeat(final, self.n_agents) if final is not None else np.zeros(self.num_envs, dtype=bool)
        t, tr = term.ravel(), trunc.ravel()
        dones = (t | tr) & acted
        live_after = self.batch.live.ravel()
        rewards = np.where(acted, rew.ravel(), 0.0).astype(np.float32)
        out = obs.copy()
        out[~live_after] = 0.0
        err, clr = binfo["tracking_error"].ravel().tolist(), binfo["clearance"].ravel().tolist()
        col, gd = binfo["collision"].ravel().tolist(), binfo["goal_distance"].ravel()
        filtered = "filter_correction" in binfo
        if filtered:
            fi = binfo["filter_intervened"].ravel().tolist()
            fc = binfo["filter_correction"].ravel().tolist()
        infos: list[dict[str, Any]] = []
        for s in range(self.num_envs):
            if not acted[s]:
                infos.append({"dead": True})
                continue
            info: dict[str, Any] = {"tracking_error": err[s], "clearance": clr[s], "collision": col[s],
                                    "goal_distance": float(gd[s])}
            if filtered:
                info["filter_intervened"], info["filter_correction"] = fi[s], fc[s]
            if dones[s]:
                info["terminal_observation"] = (final_obs[s] if reset_slots[s] else obs[s]).copy()  # type: ignore
                info["TimeLimit.truncated"] = bool(tr[s] and not t[s])
                info["is_success"] = bool(not t[s] and gd[s] <= self.success_radius)
            infos.append(info)
        self._acted = acted
        self._live = live_after
        self.last_infos = binfo
        self.last_dones = dones
        return out, rewards, dones, infos

    def close(self) -> None:
        """Close the teams."""
        self.batch.close()

    def _teams_of(self, indices: VecEnvIndices) -> list[int]:
        return [s // self.n_agents for s in self._get_indices(indices)]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute of the team env behind each slot."""
        return [self.batch.env_get(k, attr_name) for k in self._teams_of(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute on the team envs behind the slots (each once)."""
        for k in sorted(set(self._teams_of(indices))):
            self.batch.env_set(k, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        """Call a method of the team env behind each slot (after :meth:`BatchedAASOATTEnv.sync`)."""
        return [self.batch.env_call(k, method_name, *method_args, **method_kwargs) for k in self._teams_of(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        """Whether the team env behind each slot is (PettingZoo-)wrapped by ``wrapper_class``."""
        return [self.batch.env_is_wrapped(k, wrapper_class) for k in self._teams_of(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One rendered frame per team (not per slot)."""
        return list(self.batch.render())



def _slot_masks(venv: VecEnv) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(acted_slots, live_slots)`` of the adapter under ``venv`` (None, None for other VecEnvs)."""
    base = venv.unwrapped
    acted, live = getattr(base, "acted_slots", None), getattr(base, "live_slots", None)
    return acted, live


class SlotMonitor(VecMonitor):
    """:class:`~stable_baselines3.common.vec_env.VecMonitor` that counts only the steps a slot's robot acted.

    Dead-slot padding (``terminate_on_collision``) is not part of any episode, so
    ``infos[slot]["episode"]["l"]`` never exceeds the horizon.
    """

    def step_wait(self) -> VecEnvStepReturn:
        """Step; add ``infos[slot]["episode"]`` to the slots whose episode ended."""
        obs, rewards, dones, infos = self.venv.step_wait()
        acted, _ = _slot_masks(self.venv)
        self.episode_returns += rewards
        self.episode_lengths += 1 if acted is None else acted.astype(self.episode_lengths.dtype)
        new_infos = list(infos[:])
        for i in np.flatnonzero(dones):
            info = infos[i].copy()
            episode_info = {"r": self.episode_returns[i], "l": self.episode_lengths[i],
                            "t": round(time.time() - self.t_start, 6)}
            for key in self.info_keywords:
                episode_info[key] = info[key]
            info["episode"] = episode_info
            self.episode_count += 1
            self.episode_returns[i] = 0
            self.episode_lengths[i] = 0
            if self.results_writer:
                self.results_writer.write_row(episode_info)
            new_infos[i] = info
        return obs, rewards, dones, new_infos


class SlotNormalize(VecNormalize):
    """:class:`~stable_baselines3.common.vec_env.VecNormalize` whose statistics skip dead-slot padding.

    The running observation statistics are updated with real observations only
    (not the zeros of dead slots), the return statistics with the slots whose
    robot acted.  Without dead slots it is exactly ``VecNormalize``.
    """

    def step_wait(self) -> VecEnvStepReturn:
        """Step, update the statistics with the real rows, normalise."""
        obs, rewards, dones, infos = self.venv.step_wait()
        assert isinstance(obs, np.ndarray)
        acted, live = _slot_masks(self.venv)
        self.old_obs = obs
        self.old_reward = rewards
        if self.training and self.norm_obs:
            self.obs_rms.update(obs if live is None or live.all() else obs[live])
        obs = self.normalize_obs(obs)
        if self.training:
            self.returns = self.returns * self.gamma + rewards
            self.ret_rms.update(self.returns if acted is None or acted.all() else self.returns[acted])
        rewards = self.normalize_reward(rewards)
        for idx in np.flatnonzero(dones):
            if "terminal_observation" in infos[idx]:
                infos[idx]["terminal_observation"] = self.normalize_obs(infos[idx]["terminal_observation"])
        self.returns[dones] = 0
        return obs, rewards, dones, infos
