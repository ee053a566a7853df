"""PPO that never trains on dead-slot padding.

With ``terminate_on_collision`` a robot that collides leaves its episode while
its team goes on; its slot of the VecEnv (:mod:`train.vec_env`) is *dead* until
the team resets and returns padding (zero observation, reward 0).  SB3's PPO
stores every slot at every step.  :class:`SlotPPO` records, at each step, which
slots' robots acted (the adapter's ``acted_slots``) and
:class:`MaskedRolloutBuffer` draws the minibatches from those transitions only.
The advantages of real transitions never reach across padding: a robot's last
real step ends with ``done`` (no bootstrap), and padding is never a real
transition's successor.  Without dead slots both classes behave exactly like
SB3's (same minibatches, seed for seed).
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.type_aliases import RolloutBufferSamples

__all__ = ["MaskedRolloutBuffer", "SlotPPO"]


class MaskedRolloutBuffer(RolloutBuffer):
    """A :class:`~stable_baselines3.common.buffers.RolloutBuffer` with a per-transition ``valid`` mask.

    Set :attr:`next_valid` (``(n_envs,)`` bool) before each ``add``; ``get``
    yields minibatches of the valid transitions only.
    """

    next_valid: np.ndarray | None = None

    def reset(self) -> None:
        """Empty the buffer (every transition valid until told otherwise)."""
        super().reset()
        self.valid = np.ones((self.buffer_size, self.n_envs), dtype=bool)
        self.next_valid = None

    def add(self, *args: Any, **kwargs: Any) -> None:
        """Store one step of every slot, with :attr:`next_valid` as its mask."""
        if self.next_valid is not None:
            self.valid[self.pos] = self.next_valid
            self.next_valid = None
        super().add(*args, **kwargs)

    @property
    def n_valid(self) -> int:
        """Number of valid transitions stored."""
        return int(self.valid.sum())

    def get(self, batch_size: int | None = None) -> Generator[RolloutBufferSamples, None, None]:
        """Minibatches of the valid transitions (SB3's permutation, padding dropped)."""
        assert self.full, ""
        total = self.buffer_size * self.n_envs
        indices = np.random.permutation(total)  # noqa: NPY002 - SB3 draws from the global generator it seeds
        valid = self.valid.swapaxes(0, 1).reshape(total)  # the order of swap_and_flatten
        if not valid.all():
            indices = indices[valid[indices]]
        if not self.generator_ready:
            for name in ("observations", "actions", "values", "log_probs", "advantages", "returns"):
                self.__dict__[name] = self.swap_and_flatten(self.__dict__[name])
            self.generator_ready = True
        if batch_size is None:
            batch_size = indices.shape[0]
        start = 0
        while start < indices.shape[0]:
            yield self._get_samples(indices[start:start + batch_size])
            start += batch_size


class SlotPPO(PPO):
    """SB3 PPO that trains only on the transitions of slots whose robot acted (module docstring).

    Takes the arguments of :class:`~stable_baselines3.PPO`; the rollout buffer
    defaults to :class:`MaskedRolloutBuffer`.  The mask comes from the VecEnv's
    ``acted_slots`` (:class:`train.vec_env.BatchedVecEnv`,
    :class:`train.vec_env.ParallelVecEnv`); other VecEnvs train on everything.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("rollout_buffer_class", MaskedRolloutBuffer)
        super().__init__(*args, **kwargs)

    def _update_info_buffer(self, infos: list[dict[str, Any]], dones: np.ndarray | None = None) -> None:
        # called by collect_rollouts after env.step and right before rollout_buffer.add: mark the step's padding
        env = getattr(self, "env", None)
        acted = getattr(env.unwrapped, "acted_slots", None) if env is not None else None
        if acted is not None and isinstance(self.rollout_buffer, MaskedRolloutBuffer):
            self.rollout_buffer.next_valid = acted
        super()._update_info_buffer(infos, dones)
