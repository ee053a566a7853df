"""``LearnedAgent``: a trained SB3 policy behind the same interface as the baselines.

>>> agent = LearnedAgent.load("runs/ppo_random_goals_6r_bare_s0")   # doctest: +SKIP
>>> env = agent.make_env()                  # the env settings it was trained with
>>> obs, _ = env.reset(seed=0); agent.reset(env)
>>> obs, *_ = env.step(agent.act(obs, env))

It reads only the observations (decentralised: one shared policy evaluated on
each live robot's observation, batched), so it runs unchanged on the bare env
or behind :class:`~aasoatt_env.safety.wrapper.AASOATTFilter`; behind the filter
its actions are the nominal.  The env must use the action mode, decision
interval and observation layout the policy was trained with: :meth:`make_env`
builds such an env from the run's ``policy.json``.

Files of a run folder (written by :func:`train.train.train`):

=========================  =========================================================
file                       content
=========================  =========================================================
``model.zip``              the Stable-Baselines3 PPO model
``policy.json``            env keywords, filter configuration, policy class name,
                           whether observations are normalised (plain JSON)
``normalization.npz``      observation statistics ``mean``, ``var``, ``clip_obs``,
                           ``epsilon`` (plain arrays)
=========================  =========================================================

Nothing is unpickled: the statistics are plain arrays, and the SB3 zip is read
with every cloudpickled entry of its ``data`` replaced (``custom_objects``), its
tensors by ``torch.load(weights_only=True)``.  A run that was trained with
observation normalisation but lacks ``normalization.npz`` is refused (the policy
would act on unnormalised observations).
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env as make_aasoatt_env
from aasoatt_env.errors import ConfigError, DataFileError
from agents.rllib_agent import RLlibAgent, find_run_spec

__all__ = ["POLICY_FILE", "STATS_FILE", "LearnedAgent", "load_learned", "stats_path"]

POLICY_FILE = "policy.json"
STATS_FILE = "normalization.npz"
_FORMAT = 1


def stats_path(model_zip: Path) -> Path:
    """The normalisation statistics beside ``model_zip``.

    ``model.zip`` -> ``normalization.npz``; a checkpoint ``ppo_<n>_steps.zip`` ->
    ``ppo_<n>_steps.normalization.npz``.
    """
    if model_zip.name == "model.zip":
        return model_zip.with_name(STATS_FILE)
    return model_zip.with_name(model_zip.stem + "." + STATS_FILE)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataFileError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(data, dict):
        raise DataFileError(f"{path}: got a JSON {type(data).__name__}, expected an object")
    return data


def _read_stats(path: Path) -> tuple[np.ndarray, np.ndarray, float, float]:
    try:
        with np.load(path, allow_pickle=False) as z:
            mean, var = np.asarray(z["mean"], np.float64), np.asarray(z["var"], np.float64)
            clip_obs, eps = float(z["clip_obs"]), float(z["epsilon"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFileError(f"{path}: not a readable normalisation file ({type(exc).__name__}: {exc})") from None
    if mean.shape != var.shape or mean.ndim != 1 or not (np.isfinite(mean).all() and np.isfinite(var).all()) \
            or np.any(var < 0) or not (clip_obs > 0 and eps > 0):
        raise DataFileError(f"{path}: expected finite mean and var of one shape, var >= 0, clip_obs > 0, epsilon > 0")
    return mean, var, clip_obs, eps


def _serialized_keys(model_zip: Path) -> list[str]:
    """Keys of the zip's ``data`` that SB3 would cloudpickle-load."""
    try:
        with zipfile.ZipFile(model_zip) as archive:
            data = json.loads(archive.read("data").decode())
    except (OSError, KeyError, UnicodeDecodeError, json.JSONDecodeError, zipfile.BadZipFile) as exc:
        raise DataFileError(f"{model_zip}: not a readable Stable-Baselines3 model zip ({exc})") from None
    if not isinstance(data, dict):
        raise DataFileError(f"{model_zip}: its 'data' entry is not a JSON object")
    return [k for k, v in data.items() if isinstance(v, dict) and ":serialized:" in v]


class LearnedAgent:
    """A shared policy acting for every live robot (see the module docstring).

    Parameters
    ----------
    model : stable_baselines3 BaseAlgorithm
        The loaded model (any SB3 algorithm with ``predict``).
    spec : dict
        The run's ``policy.json`` (``env``, ``filter``, ``policy``, ``normalize_obs``).
    obs_stats : tuple, optional
        ``(mean, var, clip_obs, epsilon)`` of the training's observation normalisation.
    deterministic : bool
        Act with the mean action (True) or sample.
    """

    def __init__(
        self,
        model: Any,
        spec: dict[str, Any],
        obs_stats: tuple[np.ndarray, np.ndarray, float, float] | None = None,
        deterministic: bool = True,
    ) -> None:
        self.model = model
        self.spec = dict(spec)
        self.obs_stats = obs_stats
        self.deterministic = bool(deterministic)
        self._obs_shape = tuple(model.observation_space.shape)

    @classmethod
    def load(cls, path: str | os.PathLike[str], device: str = "cpu", deterministic: bool = True) -> LearnedAgent:
        """Load a run folder (or a ``.zip`` in one, e.g. a checkpoint) without unpickling anything.

        Parameters
        ----------
        path : str or PathLike
            The run folder, its ``model.zip``, or a checkpoint ``checkpoints/ppo_<n>_steps.zip``.
        device : str
            Torch device.
        deterministic : bool
            Mean action (True) or sampled.

        Raises
        ------
        DataFileError
            A file is missing or corrupted (the message names it).
        """
        import torch
        from stable_baselines3 import PPO

        torch.set_num_threads(1)
        p = Path(path)
        if p.is_dir():
            p = p / "model.zip"
        if not p.is_file():
            raise DataFileError(f"{path}: no model here; expected a run folder holding model.zip, or a .zip file")
        run = p.parent if (p.parent / POLICY_FILE).is_file() else p.parent.parent
        spec_file = run / POLICY_FILE
        if not spec_file.is_file():
            raise DataFileError(f"{spec_file}: missing; LearnedAgent needs the run's policy.json (written by training)")
        spec = _read_json(spec_file)
        for key in ("env", "policy", "normalize_obs"):
            if key not in spec:
                raise DataFileError(f"{spec_file}: missing key {key!r}")
        if not isinstance(spec["env"], dict):
            raise DataFileError(f"{spec_file}: 'env' must be an object of env keywords")
        obs_stats = None
        if spec["normalize_obs"]:
            stats = stats_path(p)
            if not stats.is_file():
                raise DataFileError(f"{stats}: missing; the policy was trained on normalised observations")
            obs_stats = _read_stats(stats)
        try:
            probe = make_aasoatt_env(**spec["env"])
        except (ConfigError, TypeError) as exc:
            raise DataFileError(f"{spec_file}: its env settings are invalid ({exc})") from None
        agent0 = probe.possible_agents[0]
        custom = dict.fromkeys(_serialized_keys(p))
        custom.update(observation_space=probe.observation_space(agent0), action_space=probe.action_space(agent0),
                      policy_class=_policy_class(spec["policy"], spec_file), lr_schedule=lambda _: 0.0,
                      clip_range=0.2, clip_range_vf=None)
        probe.close()
        try:
            model = PPO.load(p, device=device, custom_objects=custom)
        except (OSError, ValueError, KeyError, RuntimeError, zipfile.BadZipFile, EOFError) as exc:
            raise DataFileError(f"{p}: cannot load the model ({type(exc).__name__}: {exc})") from None
        if obs_stats is not None and obs_stats[0].shape != tuple(model.observation_space.shape):
            raise DataFileError(f"{stats_path(p)}: statistics of shape {obs_stats[0].shape}, expected "
                                f"{tuple(model.observation_space.shape)}")
        return cls(model, spec, obs_stats, deterministic)

    # ------------------------------------------------------------------ env helpers
    def make_env(self, filter: bool | None = None, **overrides: Any) -> Any:
        """An env with the training settings; ``filter``: behind the filter or not (default: as trained)."""
        use = self.spec.get("filter") is not None if filter is None else filter
        cfg = (self.spec.get("filter") or {}) if use else None
        return make_aasoatt_env(**{**self.spec["env"], **overrides}, filter=cfg)

    # ------------------------------------------------------------------ Agent interface
    def reset(self, env: Any) -> None:
        """Check that ``env``'s observations and action mode match the policy (stateless otherwise)."""
        base = env.unwrapped
        shape = tuple(base.observation_space(base.possible_agents[0]).shape)
        if shape != self._obs_shape:
            raise ConfigError(
                f"LearnedAgent: got an env with observation shape {shape}, expected {self._obs_shape} "
                "(same num_neighbors/num_obstacles as in training)"
            )
        mode = self.spec["env"].get("action_mode")
        if mode is not None and mode != base.action_mode:
            raise ConfigError(
                f"LearnedAgent: got an env with action_mode={base.action_mode!r}, expected {mode!r} (as trained)"
            )

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """Apply the training observation normalisation to a batch ``(n, obs_dim)``."""
        if self.obs_stats is None:
            return obs
        mean, var, clip_obs, eps = self.obs_stats
        return np.clip((obs - mean) / np.sqrt(var + eps), -clip_obs, clip_obs).astype(np.float32)

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """One action per live agent of ``env`` from its observation (batched)."""
        agents = list(env.agents)
        if not agents:
            return {}
        batch = np.stack([np.asarray(observations[a], dtype=np.float32) for a in agents])
        actions, _ = self.model.predict(self.normalize(batch), deterministic=self.deterministic)
        actions = np.asarray(actions, dtype=np.float32)
        return {a: actions[i] for i, a in enumerate(agents)}


def _policy_class(name: Any, spec_file: Path) -> Any:
    if name == "MlpPolicy":
        from stable_baselines3.common.policies import ActorCriticPolicy

        return ActorCriticPolicy
    if name == "TrackingPriorPolicy":
        from agents.prior import TrackingPriorPolicy

        return TrackingPriorPolicy
    raise DataFileError(f"{spec_file}: policy {name!r} is unknown, expected 'MlpPolicy' or 'TrackingPriorPolicy'")


def load_learned(path: str | os.PathLike[str], device: str = "cpu", deterministic: bool = True) -> Any:
    """Load a trained policy of either backend: Stable-Baselines3 or Ray RLlib.

    :class:`LearnedAgent` for a run of :mod:`train.train`; :class:`agents.rllib_agent.RLlibAgent`
    for a run of :mod:`train.rllib` (``"backend": "rllib"`` in its ``policy.json``).  Both act
    through ``reset(env)`` / ``act(observations, env)`` and carry the run's ``spec``.
    """
    found = find_run_spec(path)
    if found is not None and found[1].get("backend") == "rllib":
        return RLlibAgent.load(path, device=device, deterministic=deterministic)
    return LearnedAgent.load(path, device=device, deterministic=deterministic)
