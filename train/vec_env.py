"""An SB3 :class:`~stable_baselines3.common.vec_env.VecEnv` over PettingZoo parallel envs.

Parameter sharing: every robot of every env is one *slot* of the vectorised
env, so one policy acts for all of them.  ``num_envs = n_envs * n_agents``
with slot ``k * n_agents + i`` = robot ``i`` of env ``k``.  This replaces
SuperSuit (``SPEC.md`` section 8: its ``seed=`` crashes with SB3 2.9,
``black_death_v3`` ends episodes a step late and time-limit truncation is
lost).

Contract
--------
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
  False, ``infos[slot]["dead"] = True``, and whatever action the policy gives
  for it is ignored (not sent to the env, which would reject it).  The
  padding transitions carry no reward; they only bias the value of the zero
  observation slightly, so training defaults to ``terminate_on_collision=False``
  (the collision is then a penalty, see :mod:`train.train`).
* The per-agent ``infos`` of the env (``tracking_error``, ``collision``,
  ``filter``, ...) are passed through in each slot's info dict.

Works under :class:`~stable_baselines3.common.vec_env.VecMonitor` and
:class:`~stable_baselines3.common.vec_env.VecNormalize`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import (
    VecEnv,
    VecEnvIndices,
    VecEnvObs,
    VecEnvStepReturn,
    VecEnvWrapper,
)

__all__ = ["ParallelVecEnv"]


class ParallelVecEnv(VecEnv):
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
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        """Step every env once and auto-reset those whose episode ended."""
        assert self._actions is not None, "step_async() must be called first"
        acts = self._actions.reshape(self.num_envs, -1)
        rewards = np.zeros(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for k, env in enumerate(self.envs):
            base = k * self.n_agents
            live = list(env.agents)
            action_dict = {a: acts[base + self.agents.index(a)] for a in live}
            obs, rew, term, trunc, inf = env.step(action_dict)
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

    @property
    def live_slots(self) -> np.ndarray:
        """Boolean mask of slots whose robot is alive (a copy)."""
        return self._live.copy()


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
        return self.venv.reset()

    def step_wait(self) -> VecEnvStepReturn:
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
