"""TorchRL ``EnvBase`` over :class:`~aasoatt_env.tensor.env.TensorEnv` (needs ``torchrl``, the dev extra).

Batch size ``(B,)``; the robots are one agent group (TorchRL's MARL layout): under ``group`` (default ``"agents"``)
``observation`` ``(B, N, obs_dim)`` float32, ``action`` ``(B, N, 2)`` in ``[-1, 1]``, ``reward`` ``(B, N, 1)``, the
filter's ``correction``, ``intervened``, ``status`` and the surface ``clearance`` ``(B, N)``; ``done``, ``terminated``
and ``truncated`` ``(B, 1)`` per team at the root. Finished teams are reset by TorchRL's partial ``_reset``.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.data import Categorical as Discrete
from torchrl.envs import EnvBase

from aasoatt_env import validation as check
from aasoatt_env.tensor.env import TensorEnv, make_tensor_env

__all__ = ["TorchRLTensorEnv"]

_INFOS = ("correction", "intervened", "status", "clearance")


class TorchRLTensorEnv(EnvBase):
    """``make_tensor_env(*args, **kwargs)`` as a TorchRL environment with one group of agents (module docstring)."""

    def __init__(self, *args: Any, group: str = "agents", **kwargs: Any) -> None:
        env: TensorEnv = make_tensor_env(*args, **kwargs)
        env.autoreset = False  # finished teams wait for TorchRL's partial _reset
        self.env, self.group = env, group
        B, N, dev, dt = env.num_envs, env.num_robots, env.device, env.dtype
        super().__init__(device=dev, batch_size=torch.Size([B]))
        self.observation_spec = Composite({group: Composite(
            observation=Unbounded((B, N, env.obs_dim), dtype=torch.float32, device=dev),
            correction=Unbounded((B, N), dtype=dt, device=dev),
            intervened=Discrete(2, (B, N), dtype=torch.bool, device=dev),
            status=Unbounded((B, N), dtype=torch.int64, device=dev),
            clearance=Unbounded((B, N), dtype=dt, device=dev), shape=(B, N))}, shape=(B,))
        self.action_spec = Composite({group: Composite(action=Bounded(-1.0, 1.0, (B, N, 2), dtype=dt, device=dev),
                                                       shape=(B, N))}, shape=(B,))
        self.reward_spec = Composite({group: Composite(reward=Unbounded((B, N, 1), dtype=dt, device=dev),
                                                       shape=(B, N))}, shape=(B,))
        self.done_spec = Composite(**{k: Discrete(2, (B, 1), dtype=torch.bool, device=dev)
                                      for k in ("done", "terminated", "truncated")}, shape=(B,))
        self._seed: int | None = None
        self._started = False

    def _set_seed(self, seed: int | None) -> None:
        """The next full reset's seed (used once, as TorchRL's envs do; later full resets continue the generators)."""
        self._seed = None if seed is None else check.integer("seed", seed, lo=0)

    def _td(self, obs: torch.Tensor, info: dict, root: dict[str, torch.Tensor],
            reward: torch.Tensor | None = None) -> TensorDict:
        B, N = self.env.num_envs, self.env.num_robots
        agents = {"observation": obs, **{k: info[k] for k in _INFOS}}
        if reward is not None:
            agents["reward"] = reward[..., None]
        return TensorDict({self.group: TensorDict(agents, batch_size=[B, N], device=self.env.device), **root},
                          batch_size=[B], device=self.env.device)

    def _reset(self, tensordict: TensorDict | None = None, **kwargs: Any) -> TensorDict:
        env, B = self.env, self.env.num_envs
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if not self._started or mask is None:
            obs, info = env.reset(seed=self._seed)
            self._started, self._seed = True, None
        else:
            obs, info = env.reset_done(mask.reshape(B, -1).any(-1))
        zeros = torch.zeros(B, 1, dtype=torch.bool, device=env.device)
        return self._td(obs, info, {"done": zeros, "terminated": zeros.clone(), "truncated": zeros.clone()})

    def _step(self, tensordict: TensorDict) -> TensorDict:
        obs, rew, term, trunc, info = self.env.step(tensordict.get((self.group, "action")))
        term, trunc = term.all(-1, keepdim=True), trunc.all(-1, keepdim=True)
        return self._td(obs, info, {"terminated": term, "truncated": trunc, "done": term | trunc}, rew)
