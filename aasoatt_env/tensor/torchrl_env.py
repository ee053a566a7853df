"""TorchRL ``EnvBase`` over :class:`~aasoatt_env.tensor.env.TensorEnv` (needs ``torchrl``, the dev extra).

Batch size ``(B,)``; keys per team: ``observation`` ``(N, obs_dim)`` float32, ``action`` ``(N, 2)`` in ``[-1, 1]``
(behind the filter a nominal; the spec says the task's range), ``reward``, ``done``, ``terminated``, ``truncated``
``(N, 1)``, and the filter's ``correction``, ``intervened`` and ``status`` ``(N,)``.  Finished teams are reset
by TorchRL's partial ``_reset`` (the wrapped env's same-step auto-reset is off).
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.data import Categorical as Discrete
from torchrl.envs import EnvBase

from aasoatt_env.tensor.env import TensorEnv, make_tensor_env

__all__ = ["TorchRLTensorEnv"]


class TorchRLTensorEnv(EnvBase):
    """``make_tensor_env(*args, **kwargs)`` as a TorchRL environment (module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        env: TensorEnv = make_tensor_env(*args, **kwargs)
        env.autoreset = False
        self.env = env
        B, N = env.num_envs, env.num_robots
        super().__init__(device=env.device, batch_size=torch.Size([B]))
        self.observation_spec = Composite(
            observation=Unbounded((B, N, env.obs_dim), dtype=torch.float32, device=env.device),
            correction=Unbounded((B, N), dtype=env.dtype, device=env.device),
            intervened=Discrete(2, (B, N), dtype=torch.bool, device=env.device),
            status=Unbounded((B, N), dtype=torch.int64, device=env.device), shape=(B,))
        self.action_spec = Bounded(-1.0, 1.0, (B, N, 2), dtype=env.dtype, device=env.device)
        self.reward_spec = Unbounded((B, N, 1), dtype=env.dtype, device=env.device)
        self.done_spec = Composite(**{k: Discrete(2, (B, N, 1), dtype=torch.bool, device=env.device)
                                      for k in ("done", "terminated", "truncated")}, shape=(B,))
        self._seed: int | None = None
        self._started = False

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed

    def _td(self, obs: torch.Tensor, info: dict, extra: dict | None = None) -> TensorDict:
        B = self.env.num_envs
        out = {"observation": obs, "correction": info["correction"], "intervened": info["intervened"],
               "status": info["status"]}
        return TensorDict({**out, **(extra or {})}, batch_size=[B], device=self.env.device)

    def _reset(self, tensordict: TensorDict | None = None, **kwargs: Any) -> TensorDict:
        env, B, N = self.env, self.env.num_envs, self.env.num_robots
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if not self._started or mask is None:
            obs, info = env.reset(seed=self._seed)
            self._started = True
        else:
            obs, info = env.reset_done(mask.reshape(B, -1).any(-1))
        zeros = torch.zeros(B, N, 1, dtype=torch.bool, device=env.device)
        return self._td(obs, info, {"done": zeros, "terminated": zeros.clone(), "truncated": zeros.clone()})

    def _step(self, tensordict: TensorDict) -> TensorDict:
        obs, rew, term, trunc, info = self.env.step(tensordict.get("action"))
        return self._td(obs, info, {"reward": rew[..., None], "terminated": term[..., None],
                                    "truncated": trunc[..., None], "done": (term | trunc)[..., None]})
