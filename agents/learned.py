"""``LearnedAgent``: a trained SB3 policy behind the same interface as the baselines.

>>> agent = LearnedAgent.load("runs/ppo_random_goals_6r_bare_s0/model.zip")
>>> env = agent.make_env()                  # the env settings it was trained with
>>> obs, _ = env.reset(seed=0); agent.reset(env)
>>> obs, *_ = env.step(agent.act(obs, env))

It reads only the observations (decentralised: one shared policy evaluated on
each live robot's observation, batched), so it runs unchanged on the bare env
or behind :class:`~aasoatt_env.safety.wrapper.AASOATTFilter`; behind the filter
its actions are the nominal.  The env must use the action mode, decision
interval and observation layout the policy was trained with: :meth:`make_env`
builds such an env from the run's ``config.json``.
"""

from __future__ import annotations

import json
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.errors import ConfigError

__all__ = ["LearnedAgent"]


class LearnedAgent:
    """A shared policy acting for every live robot (see the module docstring).

    Parameters
    ----------
    model : stable_baselines3 BaseAlgorithm
        The loaded model (any SB3 algorithm with ``predict``).
    obs_rms : RunningMeanStd, optional
        Observation statistics of ``VecNormalize`` (the policy was trained on
        ``clip((obs - mean) / sqrt(var + eps), -clip_obs, clip_obs)``).
    clip_obs, epsilon : float
        ``VecNormalize`` parameters.
    deterministic : bool
        Act with the mean action (True) or sample.
    config : dict, optional
        The training run's ``config.json``.
    """

    def __init__(
        self,
        model: Any,
        obs_rms: Any = None,
        clip_obs: float = 10.0,
        epsilon: float = 1e-8,
        deterministic: bool = True,
        config: dict[str, Any] | None = None,
    ) -> None:
        self.model = model
        self.obs_rms = obs_rms
        self.clip_obs = float(clip_obs)
        self.epsilon = float(epsilon)
        self.deterministic = bool(deterministic)
        self.config = dict(config or {})
        self._obs_shape = tuple(model.observation_space.shape)

    @classmethod
    def load(
        cls, path: str | os.PathLike[str], device: str = "cpu", deterministic: bool = True
    ) -> LearnedAgent:
        """Load ``model.zip`` (or a run folder holding it) with its normalisation and config.

        Parameters
        ----------
        path : str or PathLike
            A PPO ``.zip`` saved by :func:`train.train.train` (or a checkpoint),
            or the run folder.  ``vecnormalize.pkl`` and ``config.json`` next
            to it are used when present (for a checkpoint
            ``ppo_<n>_steps.zip``, ``ppo_vecnormalize_<n>_steps.pkl``).
        device : str
            Torch device.
        deterministic : bool
            Mean action (True) or sampled.
        """
        import torch
        from stable_baselines3 import PPO

        torch.set_num_threads(1)
        p = Path(path)
        if p.is_dir():
            p = p / "model.zip"
        if not p.is_file():
            raise ConfigError(
                f"LearnedAgent.load: got {str(path)!r}, expected a model .zip or a run folder holding model.zip"
            )
        model = PPO.load(p, device=device)
        stats = p.with_name("vecnormalize.pkl")
        if p.stem.startswith("ppo_") and p.stem.endswith("_steps"):
            stats = p.with_name(p.stem.replace("ppo_", "ppo_vecnormalize_", 1) + ".pkl")
        obs_rms, clip_obs, eps = None, 10.0, 1e-8
        if stats.is_file():
            with stats.open("rb") as fh:
                vn = pickle.load(fh)  # VecNormalize without its venv (its __getstate__ drops it)
            if getattr(vn, "norm_obs", False):
                obs_rms, clip_obs, eps = vn.obs_rms, vn.clip_obs, vn.epsilon
        cfg_path = p.parent / "config.json"
        if not cfg_path.is_file():
            cfg_path = p.parent.parent / "config.json"  # checkpoints/ppo_*.zip
        config = json.loads(cfg_path.read_text()) if cfg_path.is_file() else None
        return cls(model, obs_rms, clip_obs, eps, deterministic, config)

    # ------------------------------------------------------------------ env helpers
    def train_config(self) -> Any:
        """The run's :class:`~train.config.TrainConfig` (needs ``config.json``)."""
        if not self.config:
            raise ConfigError("LearnedAgent: got no config.json next to the model, expected the run's config")
        from train.config import TrainConfig

        return TrainConfig.from_dict(self.config)

    def make_env(self, filter: bool | None = None, **overrides: Any) -> Any:
        """An env with the training settings (``filter``: behind the filter or not; default as trained)."""
        from train.train import make_env

        return make_env(self.train_config(), filter=filter, **overrides)

    # ------------------------------------------------------------------ Agent interface
    def reset(self, env: Any) -> None:
        """Check that ``env``'s observations match the policy (stateless otherwise)."""
        base = env.unwrapped
        shape = tuple(base.observation_space(base.possible_agents[0]).shape)
        if shape != self._obs_shape:
            raise ConfigError(
                f"LearnedAgent: got an env with observation shape {shape}, expected {self._obs_shape} "
                "(same num_neighbors/num_obstacles as in training)"
            )
        mode = self.config.get("action_mode")
        if mode is not None and mode != base.action_mode:
            raise ConfigError(
                f"LearnedAgent: got an env with action_mode={base.action_mode!r}, expected {mode!r} (as trained)"
            )

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """Apply the training observation normalisation to a batch ``(n, obs_dim)``."""
        if self.obs_rms is None:
            return obs
        out = (obs - self.obs_rms.mean) / np.sqrt(self.obs_rms.var + self.epsilon)
        return np.clip(out, -self.clip_obs, self.clip_obs).astype(np.float32)

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """One action per live agent of ``env`` from its observation (batched)."""
        agents = list(env.agents)
        if not agents:
            return {}
        batch = np.stack([np.asarray(observations[a], dtype=np.float32) for a in agents])
        actions, _ = self.model.predict(self.normalize(batch), deterministic=self.deterministic)
        actions = np.asarray(actions, dtype=np.float32)
        return {a: actions[i] for i, a in enumerate(agents)}
