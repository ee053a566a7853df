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
``model.zip``              the Stable-Baselines3 PPO model (and its policy record)
``policy.json``            env keywords, filter configuration, policy class name,
                           whether observations are normalised (plain JSON)
``normalization.npz``      observation statistics ``mean``, ``var``, ``count``,
                           ``clip_obs``, ``epsilon`` (plain arrays)
=========================  =========================================================

Nothing is unpickled and nothing but the checked weights is set: ``policy.json`` is validated
field by field (:mod:`agents.run_spec`), the model zip is read by a fixed list of names and
shapes (:mod:`agents.sb3_model`), the statistics by their names and the observation's shape
(:func:`agents.run_files.read_npz`).  A ``vecnormalize.pkl`` or any other pickle in the folder
is never opened.  A run that was trained with observation normalisation but lacks
``normalization.npz`` is refused.  Every missing, oversized, crafted or non-finite file raises
:class:`~aasoatt_env.errors.DataFileError` naming it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env as make_aasoatt_env
from aasoatt_env.errors import ConfigError, DataFileError
from agents.rllib_agent import RLlibAgent
from agents.run_files import read_json, read_npz
from agents.run_spec import POLICY_ENV_KEYS, POLICY_FILE, check_record, check_spec, find_run_spec
from agents.sb3_model import MAX_LAYER_SIZE, MAX_LAYERS, check_layer_sizes, read_model

__all__ = ["MAX_LAYERS", "MAX_LAYER_SIZE", "POLICY_ENV_KEYS", "POLICY_FILE", "STATS_FILE", "LearnedAgent",
           "check_layer_sizes", "load_learned", "read_stats", "stats_path"]

STATS_FILE = "normalization.npz"
_LEGACY_PICKLE = "vecnormalize.pkl"
_SPEC_KEYS = ("format", "env", "filter", "policy", "normalize_obs", "backend")
_POLICIES = ("MlpPolicy", "TrackingPriorPolicy")
STATS_SCALARS = ("count", "clip_obs", "epsilon", "ret_mean", "ret_var", "ret_count")
"""Scalars a ``normalization.npz`` may hold besides the observation ``mean`` and ``var`` (``ret_*``: the
running return statistics of reward normalisation, read only to resume training)."""


def stats_path(model_zip: Path) -> Path:
    """The normalisation statistics beside ``model_zip``.

    ``model.zip`` -> ``normalization.npz``; a checkpoint ``ppo_<n>_steps.zip`` ->
    ``ppo_<n>_steps.normalization.npz``.
    """
    if model_zip.name == "model.zip":
        return model_zip.with_name(STATS_FILE)
    return model_zip.with_name(model_zip.stem + "." + STATS_FILE)


def read_stats(path: Path, obs_dim: int, need_obs: bool = True) -> dict[str, np.ndarray]:
    """The arrays of a ``normalization.npz``: ``mean`` and ``var`` of shape ``(obs_dim,)`` and scalars.

    Shapes are checked from the archive's headers before any data is read (a small file cannot
    make the loader allocate a huge array); values must be finite, ``var >= 0``, ``clip_obs > 0``,
    ``epsilon > 0``.
    """
    shapes: dict[str, tuple[int, ...] | None] = {"mean": (obs_dim,), "var": (obs_dim,)}
    scalars: dict[str, tuple[int, ...] | None] = dict.fromkeys(STATS_SCALARS)
    expected = {**shapes, "clip_obs": None, "epsilon": None} if need_obs else {}
    arrays = read_npz(path, expected, optional={**shapes, **scalars})
    bad = [k for k in ("var", "ret_var") if k in arrays and (arrays[k] < 0).any()]
    bad += [k for k in ("clip_obs", "epsilon", "count", "ret_count") if k in arrays and not arrays[k] > 0]
    if bad:
        raise DataFileError(f"{path}: {bad[0]} out of range, expected var >= 0 and clip_obs, epsilon, counts > 0")
    return arrays


def _obs_stats(p: Path, spec: dict[str, Any], obs_dim: int) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """``(mean, var, clip_obs, epsilon)`` beside the model when ``spec`` says observations are normalised."""
    if not spec["normalize_obs"]:
        return None
    stats = stats_path(p)
    if not stats.is_file():
        legacy = p.parent / _LEGACY_PICKLE
        hint = (f" ({legacy.name} is there, but pickles are never loaded: they can run arbitrary code; "
                "retrain, or write normalization.npz from the statistics of a trusted run)"
                if legacy.exists() else "")
        raise DataFileError(f"{stats}: missing; the policy was trained on normalised observations{hint}")
    a = read_stats(stats, obs_dim)
    return a["mean"], a["var"], float(a["clip_obs"]), float(a["epsilon"])


def _run_files(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``(model zip, policy.json)`` of a run folder, its ``model.zip`` or a checkpoint."""
    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError(f"path: got {type(path).__name__}, expected a run folder or a model .zip path")
    p = Path(path)
    if p.is_dir():
        p = p / "model.zip"
    if not p.is_file():
        raise DataFileError(f"{path}: no model here; expected a run folder holding model.zip, or a .zip file")
    checkpoint = p.parent.name == "checkpoints" and not (p.parent / POLICY_FILE).is_file()
    spec_file = (p.parent.parent if checkpoint else p.parent) / POLICY_FILE
    if not spec_file.is_file():
        raise DataFileError(f"{spec_file}: missing; LearnedAgent needs the run's policy.json (written by training)")
    return p, spec_file


class LearnedAgent:
    """A shared policy acting for every live robot (see the module docstring).

    Parameters
    ----------
    model : LoadedModel
        The policy read from the run (:func:`agents.sb3_model.read_model`), or anything with
        ``predict(obs, deterministic)`` and ``observation_space`` (an SB3 algorithm).
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
        """Load a run folder (or a ``.zip`` in one, e.g. a checkpoint) reading only what it expects.

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
            A file is missing, oversized, crafted or non-finite (the message names it).
        """
        p, spec_file = _run_files(path)
        spec = read_json(spec_file)
        probe = check_spec(spec, spec_file, keys=_SPEC_KEYS, policies=_POLICIES)
        if spec.get("backend", "sb3") != "sb3":
            raise DataFileError(f"{spec_file}: backend: got {str(spec['backend'])[:40]!r}, expected 'sb3'")
        agent0 = probe.possible_agents[0]
        obs_space, act_space = probe.observation_space(agent0), probe.action_space(agent0)
        probe.close()
        obs_stats = _obs_stats(p, spec, int(np.prod(obs_space.shape)))
        import torch

        torch.set_num_threads(1)
        model, record = read_model(p, _policy_class(spec["policy"]), obs_space, act_space, device)
        check_record(record, spec, spec_file, p)
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


def _policy_class(name: str) -> Any:
    """The SB3 policy class ``policy.json`` names (checked by :func:`agents.run_spec.check_spec`)."""
    if name == "TrackingPriorPolicy":
        from agents.prior import TrackingPriorPolicy

        return TrackingPriorPolicy
    from stable_baselines3.common.policies import ActorCriticPolicy

    return ActorCriticPolicy


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
