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
tensors by ``torch.load(weights_only=True)``; its ``policy_kwargs`` must be the
plain ones training writes (bounded layer sizes).  A ``vecnormalize.pkl`` or any
other pickle in the folder is never opened.  A run that was trained with
observation normalisation but lacks ``normalization.npz`` is refused (the policy
would act on unnormalised observations).  Every missing or corrupted file raises
:class:`~aasoatt_env.errors.DataFileError` naming it.

Loading a Stable-Baselines3 zip with SB3's own ``PPO.load`` unpickles its
``data`` entries: do that only with files from a trusted source.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env as make_aasoatt_env
from aasoatt_env.errors import ConfigError, DataFileError
from aasoatt_env.safety.config import FilterConfig
from agents.rllib_agent import RLlibAgent, find_run_spec

__all__ = ["MAX_LAYERS", "MAX_LAYER_SIZE", "POLICY_ENV_KEYS", "POLICY_FILE", "STATS_FILE", "LearnedAgent",
           "check_layer_sizes", "load_learned", "stats_path"]

POLICY_FILE = "policy.json"
STATS_FILE = "normalization.npz"
_FORMAT = 1
_LEGACY_PICKLE = "vecnormalize.pkl"

_READ_ERRORS: tuple[type[BaseException], ...] = (
    OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError,
    RecursionError, MemoryError, UnicodeDecodeError,
)
"""What reading a corrupted or crafted file can raise (bad zip or deflate data, an unsupported zip
feature, JSON nested beyond the recursion limit, a header claiming a huge array)."""

MAX_LAYER_SIZE: int = 4096
"""Largest hidden layer a run may have (training refuses more; the loaders refuse a file with more)."""
MAX_LAYERS: int = 16
"""Most hidden layers a run may have (as :data:`MAX_LAYER_SIZE`)."""
POLICY_ENV_KEYS: tuple[str, ...] = ("dt", "decision_interval", "action_mode", "sensing_range", "num_neighbors",
                                    "num_obstacles")
"""Env settings a trained policy depends on: its decision period, what its actions mean and its
observation layout (a run's ``policy.json`` records them; an env for the policy must have them)."""
_POLICY_KWARGS = ("net_arch", "log_std_init", "prior_matrix")
"""``policy_kwargs`` that ``aasoatt train`` writes; anything else in a model zip is refused."""


def stats_path(model_zip: Path) -> Path:
    """The normalisation statistics beside ``model_zip``.

    ``model.zip`` -> ``normalization.npz``; a checkpoint ``ppo_<n>_steps.zip`` ->
    ``ppo_<n>_steps.normalization.npz``.
    """
    if model_zip.name == "model.zip":
        return model_zip.with_name(STATS_FILE)
    return model_zip.with_name(model_zip.stem + "." + STATS_FILE)


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {str(exc)[:200]}"


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except _READ_ERRORS as exc:
        raise DataFileError(f"{path}: not a readable JSON file ({_why(exc)})") from None
    if not isinstance(data, dict):
        raise DataFileError(f"{path}: got a JSON {type(data).__name__}, expected an object")
    return data


def _read_stats(path: Path) -> tuple[np.ndarray, np.ndarray, float, float]:
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("mean", "var", "clip_obs", "epsilon")}
        for k, a in arrays.items():
            if a.dtype.kind not in "fiu":
                raise ValueError(f"{k} has dtype {a.dtype}, expected real numbers")
        mean, var = np.asarray(arrays["mean"], np.float64), np.asarray(arrays["var"], np.float64)
        clip_obs, eps = float(arrays["clip_obs"].item()), float(arrays["epsilon"].item())
    except _READ_ERRORS as exc:
        raise DataFileError(f"{path}: not a readable normalisation file ({_why(exc)})") from None
    if mean.shape != var.shape or mean.ndim != 1 or not (np.isfinite(mean).all() and np.isfinite(var).all()) \
            or np.any(var < 0) or not (math.isfinite(clip_obs) and clip_obs > 0 and math.isfinite(eps) and eps > 0):
        raise DataFileError(f"{path}: expected finite mean and var of one shape, var >= 0, clip_obs > 0, epsilon > 0")
    return mean, var, clip_obs, eps


def _model_data(model_zip: Path) -> dict[str, Any]:
    """The zip's ``data`` entry as plain JSON (nothing deserialised)."""
    try:
        with zipfile.ZipFile(model_zip) as archive:
            data = json.loads(archive.read("data").decode())
    except _READ_ERRORS as exc:
        raise DataFileError(f"{model_zip}: not a readable Stable-Baselines3 model zip ({_why(exc)})") from None
    if not isinstance(data, dict):
        raise DataFileError(f"{model_zip}: its 'data' entry is not a JSON object")
    return data


def _serialized_keys(data: dict[str, Any]) -> list[str]:
    """Keys of a model's ``data`` that SB3 would cloudpickle-load (all get replaced)."""
    return [k for k, v in data.items() if isinstance(v, dict) and ":serialized:" in v]


def check_layer_sizes(arch: Any, where: str, allow_dict: bool = True) -> None:
    """Refuse hidden-layer sizes from a file that are not a short list of bounded sizes.

    The one bound on networks rebuilt from a run's files, for both backends: the SB3 zip's
    ``policy_kwargs["net_arch"]`` here and the RLlib ``model_config["fcnet_hiddens"]`` of
    :class:`agents.rllib_agent.RLlibAgent` (a crafted file must not make the loader allocate
    a huge network).

    Parameters
    ----------
    arch : object
        The layer sizes as read: a list of ints, or (``allow_dict``) a dict of such lists
        (SB3's ``{"pi": [...], "vf": [...]}``).
    where : str
        The file and entry, for the message.
    allow_dict : bool
        Accept a dict of lists.

    Raises
    ------
    DataFileError
        ``arch`` is not at most 16 layers of sizes in ``[1, 4096]``.
    """
    layers = [arch] if isinstance(arch, list) else (
        list(arch.values()) if allow_dict and isinstance(arch, dict) else None)
    ok = layers is not None and all(
        isinstance(lay, list) and len(lay) <= MAX_LAYERS
        and all(isinstance(h, int) and not isinstance(h, bool) and 1 <= h <= MAX_LAYER_SIZE for h in lay)
        for lay in layers
    )
    if not ok:
        raise DataFileError(f"{where}: got {str(arch)[:80]}, expected a list of at most {MAX_LAYERS} layer sizes "
                            f"in [1, {MAX_LAYER_SIZE}]")


def _check_policy_kwargs(data: dict[str, Any], model_zip: Path) -> None:
    """Refuse ``policy_kwargs`` that training does not write, or layers too large to build (a crafted zip)."""
    kw = data.get("policy_kwargs", {})
    where = f"{model_zip}: policy_kwargs"
    if not isinstance(kw, dict) or ":serialized:" in kw:
        raise DataFileError(f"{where} are not plain JSON; this zip was not written by aasoatt train")
    unknown = sorted(set(kw) - set(_POLICY_KWARGS))
    if unknown:
        raise DataFileError(f"{where}: unexpected keys {unknown}, expected some of {list(_POLICY_KWARGS)}")
    check_layer_sizes(kw.get("net_arch", []), f"{where}: net_arch")
    if "prior_matrix" in kw:
        pm = kw["prior_matrix"]
        if not (isinstance(pm, list) and len(pm) <= 2 * MAX_LAYER_SIZE and all(
                isinstance(r, list) and len(r) <= 2 * MAX_LAYER_SIZE for r in pm)):
            raise DataFileError(f"{where}: prior_matrix is not a list of rows of bounded size")


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
        if not isinstance(path, (str, os.PathLike)):
            raise ConfigError(f"path: got {type(path).__name__}, expected a run folder or a model .zip path")
        p = Path(path)
        if p.is_dir():
            p = p / "model.zip"
        if not p.is_file():
            raise DataFileError(f"{path}: no model here; expected a run folder holding model.zip, or a .zip file")
        checkpoint = p.parent.name == "checkpoints" and not (p.parent / POLICY_FILE).is_file()
        run = p.parent.parent if checkpoint else p.parent
        spec_file = run / POLICY_FILE
        if not spec_file.is_file():
            raise DataFileError(f"{spec_file}: missing; LearnedAgent needs the run's policy.json (written by training)")
        spec = _read_json(spec_file)
        for key in ("env", "policy", "normalize_obs"):
            if key not in spec:
                raise DataFileError(f"{spec_file}: missing key {key!r}")
        if not isinstance(spec["env"], dict):
            raise DataFileError(f"{spec_file}: 'env' must be an object of env keywords")
        if not isinstance(spec["normalize_obs"], bool):
            raise DataFileError(f"{spec_file}: 'normalize_obs' must be true or false, got {spec['normalize_obs']!r}")
        if spec.get("filter") is not None:
            try:
                FilterConfig.merged(spec["filter"])
            except (ConfigError, TypeError) as exc:
                raise DataFileError(f"{spec_file}: its filter settings are invalid ({exc})") from None
        obs_stats = None
        if spec["normalize_obs"]:
            stats = stats_path(p)
            if not stats.is_file():
                legacy = p.parent / _LEGACY_PICKLE
                hint = (f" ({legacy.name} is there, but pickles are never loaded: they can run arbitrary code; "
                        "retrain, or write normalization.npz from the statistics of a trusted run)"
                        if legacy.exists() else "")
                raise DataFileError(f"{stats}: missing; the policy was trained on normalised observations{hint}")
            obs_stats = _read_stats(stats)
        import torch
        from stable_baselines3 import PPO

        torch.set_num_threads(1)
        policy_class = _policy_class(spec["policy"], spec_file)
        try:
            probe = make_aasoatt_env(**spec["env"])
        except (ConfigError, TypeError) as exc:
            raise DataFileError(f"{spec_file}: its env settings are invalid ({exc})") from None
        agent0 = probe.possible_agents[0]
        data = _model_data(p)
        _check_policy_kwargs(data, p)
        custom: dict[str, Any] = dict.fromkeys(_serialized_keys(data))
        custom.update(observation_space=probe.observation_space(agent0), action_space=probe.action_space(agent0),
                      policy_class=policy_class, lr_schedule=lambda _: 0.0, clip_range=0.2, clip_range_vf=None)
        probe.close()
        try:
            model = PPO.load(p, device=device, custom_objects=custom)
        except Exception as exc:  # noqa: BLE001 - whatever a corrupted zip makes SB3/torch raise, name the file
            raise DataFileError(f"{p}: cannot load the model ({_why(exc)})") from None
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
