"""``RLlibAgent``: a policy trained with Ray RLlib (:mod:`train.rllib`) behind the agents' interface.

>>> agent = RLlibAgent.load("runs/rllib_ppo_random_goals_4r_filter_s0")   # doctest: +SKIP
>>> env = agent.make_env()                   # the env settings it was trained with
>>> obs, _ = env.reset(seed=0); agent.reset(env)
>>> obs, *_ = env.step(agent.act(obs, env))

Like :class:`agents.learned.LearnedAgent` it reads only the observations (one shared policy
evaluated on each live robot's observation, batched) and runs bare or behind the filter;
``aasoatt evaluate`` and ``aasoatt run --controller learned`` recognise an RLlib run by the
``"backend": "rllib"`` of its ``policy.json``.

Acting mirrors RLlib's own inference path: ``module.forward_inference({"obs": ...})``, the
module's inference action distribution made deterministic (the Gaussian mean; ``sample``
with ``deterministic=False``), then RLlib's default action normalisation, which for our
``Box(-1, 1)`` actions is a clip to ``[-1, 1]``.

Loading without unpickling: :meth:`RLlibAgent.load` rebuilds the module from the run's
``policy.json`` (PPO's default RLModule, the saved ``model_config``, the spaces of the env it
describes) and loads ``rl_module.npz`` (plain arrays) into it strictly: every weight must be
there with its shape.  RLlib's own checkpoints pickle their classes and states;
:meth:`RLlibAgent.from_checkpoint` reads one (``RLModule.from_checkpoint``) for checkpoints
made elsewhere, and unpickles: use it only on files you trust.

Ray is imported only when a policy is loaded (``ray[rllib]``: the ``rllib`` extra); no Ray
instance is started.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env as make_aasoatt_env
from aasoatt_env.errors import ConfigError, DataFileError

__all__ = ["RLlibAgent", "find_run_spec"]

POLICY_FILE = "policy.json"
WEIGHTS_FILE = "rl_module.npz"
_MODULES = {"DefaultPPOTorchRLModule"}
_MODEL_CONFIG_KEYS = ("fcnet_hiddens", "fcnet_activation", "vf_share_layers")
"""``model_config`` entries that :mod:`train.rllib` writes; anything else in a ``policy.json`` is refused."""
_ACTIVATIONS = ("tanh", "relu", "elu", "swish", "silu", "linear")


def _check_model_config(model_config: Any, spec_file: Path) -> None:
    """Refuse a ``model_config`` that training does not write, or layers too large to build (a crafted file).

    Runs before Ray is imported; the layer bound is the one of the SB3 loader
    (:func:`agents.learned.check_layer_sizes`).
    """
    from agents.learned import check_layer_sizes  # (agents.learned imports this module)

    where = f"{spec_file}: model_config"
    if not isinstance(model_config, dict):
        raise DataFileError(f"{where}: got a {type(model_config).__name__}, expected an object")
    unknown = sorted(set(model_config) - set(_MODEL_CONFIG_KEYS))
    if unknown:
        raise DataFileError(f"{where}: unexpected keys {unknown}, expected some of {list(_MODEL_CONFIG_KEYS)}")
    check_layer_sizes(model_config.get("fcnet_hiddens", []), f"{where}.fcnet_hiddens", allow_dict=False)
    act = model_config.get("fcnet_activation", "tanh")
    if act not in _ACTIVATIONS:
        raise DataFileError(f"{where}.fcnet_activation: got {str(act)[:40]!r}, expected one of {list(_ACTIVATIONS)}")
    if not isinstance(model_config.get("vf_share_layers", False), bool):
        raise DataFileError(f"{where}.vf_share_layers: got {model_config['vf_share_layers']!r}, expected true or false")


def find_run_spec(path: str | os.PathLike[str]) -> tuple[Path, dict[str, Any]] | None:
    """The ``policy.json`` that describes ``path`` (a run folder, a file in it, or a checkpoint under ``checkpoints/``).

    Returns ``(spec_file, spec)``, or None where there is none.
    """
    p = Path(path)
    base = p if p.is_dir() else p.parent
    for folder in (base, base.parent, base.parent.parent):
        spec_file = folder / POLICY_FILE
        if spec_file.is_file():
            try:
                spec = json.loads(spec_file.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise DataFileError(f"{spec_file}: not a readable JSON file ({exc})") from None
            if not isinstance(spec, dict):
                raise DataFileError(f"{spec_file}: got a JSON {type(spec).__name__}, expected an object")
            return spec_file, spec
    return None


@contextlib.contextmanager
def _quiet_rllib() -> Iterator[None]:
    """Silence RLlib's warnings (not errors) while a module is built."""
    logs = [logging.getLogger(name) for name in ("ray.rllib", "ray._common.deprecation")]
    levels = [log.level for log in logs]
    for log in logs:
        log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for log, level in zip(logs, levels):
            log.setLevel(level)


def _read_weights(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            weights = {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFileError(f"{path}: not a readable weights file ({type(exc).__name__}: {exc})") from None
    bad = [k for k, v in weights.items() if not np.isfinite(v).all()]
    if bad:
        raise DataFileError(f"{path}: non-finite weights in {bad}")
    return weights


class RLlibAgent:
    """A shared RLlib policy acting for every live robot (see the module docstring).

    Parameters
    ----------
    module : ray.rllib.core.rl_module.RLModule
        A torch RLModule with a continuous action distribution.
    spec : dict, optional
        The run's ``policy.json`` (``env``, ``filter``, ...); needed by :meth:`make_env` and by
        ``aasoatt evaluate``.
    deterministic : bool
        Act with the distribution's deterministic action (the mean) or sample.
    """

    def __init__(self, module: Any, spec: dict[str, Any] | None = None, deterministic: bool = True) -> None:
        import torch

        self.module = module
        self.module.eval()
        self.spec = dict(spec or {})
        self.deterministic = bool(deterministic)
        self._dist_cls = module.get_inference_action_dist_cls()
        space = module.action_space
        self._low = np.asarray(space.low, dtype=np.float32)
        self._high = np.asarray(space.high, dtype=np.float32)
        self._obs_shape = tuple(module.observation_space.shape)
        self._torch = torch

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | os.PathLike[str], device: str = "cpu", deterministic: bool = True) -> RLlibAgent:
        """Load a run of :mod:`train.rllib` (its folder, or ``checkpoints/iter_<n>``) without unpickling.

        Parameters
        ----------
        path : str or PathLike
            The run folder (final weights) or one of its checkpoints.
        device : str
            Only ``"cpu"`` (inference of a small MLP).
        deterministic : bool
            Mean action (True) or sampled.

        Raises
        ------
        DataFileError
            A file is missing, corrupted, or does not fit the module (the message names it); a
            ``model_config`` with unknown entries or layer sizes beyond the SB3 loader's bounds
            (:func:`agents.learned.check_layer_sizes`) is refused before Ray is imported.
        """
        if device != "cpu":
            raise ConfigError(f"device: got {device!r}, expected 'cpu'")
        p = Path(path)
        found = find_run_spec(p)
        if found is None:
            raise DataFileError(f"{path}: no policy.json here or two levels up; expected a run folder of "
                                "train.rllib or one of its checkpoints/iter_<n>")
        spec_file, spec = found
        if spec.get("backend") != "rllib":
            raise DataFileError(f"{spec_file}: got backend {spec.get('backend')!r}, expected 'rllib' "
                                "(Stable-Baselines3 runs load with agents.learned.LearnedAgent)")
        weights_file = (p if p.is_dir() else p.parent) / WEIGHTS_FILE
        if not weights_file.is_file():
            raise DataFileError(f"{weights_file}: missing; an RLlib run keeps its weights in {WEIGHTS_FILE}")
        for key in ("env", "policy", "model_config"):
            if key not in spec:
                raise DataFileError(f"{spec_file}: missing key {key!r}")
        if spec["policy"] not in _MODULES or not isinstance(spec["model_config"], dict) \
                or not isinstance(spec["env"], dict):
            raise DataFileError(f"{spec_file}: expected policy among {sorted(_MODULES)}, model_config and env "
                                "objects")
        _check_model_config(spec["model_config"], spec_file)
        try:
            probe = make_aasoatt_env(**spec["env"])
        except (ConfigError, TypeError) as exc:
            raise DataFileError(f"{spec_file}: its env settings are invalid ({exc})") from None
        agent0 = probe.possible_agents[0]
        obs_space, act_space = probe.observation_space(agent0), probe.action_space(agent0)
        probe.close()

        import torch
        from ray.rllib.algorithms.ppo import PPOConfig

        torch.set_num_threads(1)
        module_spec = PPOConfig().get_default_rl_module_spec()
        module_spec.observation_space, module_spec.action_space = obs_space, act_space
        module_spec.model_config = dict(spec["model_config"])
        with _quiet_rllib():  # RLlib's own builder logs a DeprecationWarning about itself
            module = module_spec.build()
        weights = _read_weights(weights_file)
        try:
            module.load_state_dict({k: torch.from_numpy(v) for k, v in weights.items()}, strict=True)
        except RuntimeError as exc:
            raise DataFileError(f"{weights_file}: does not fit the module of {spec_file} ({exc})") from None
        return cls(module, spec, deterministic)

    @classmethod
    def from_checkpoint(
        cls, checkpoint: str | os.PathLike[str], module_id: str = "shared", deterministic: bool = True
    ) -> RLlibAgent:
        """Load the RLModule ``module_id`` of any RLlib ``Algorithm`` checkpoint (this unpickles: trusted files only).

        ``checkpoint`` is the folder of ``Algorithm.save_to_path`` or of one RLModule in it
        (``<ckpt>/learner_group/learner/rl_module/<module_id>``).  The run's ``policy.json`` is
        picked up where the checkpoint lies in a run folder of :mod:`train.rllib`.
        """
        import torch
        from ray.rllib.core import COMPONENT_LEARNER, COMPONENT_LEARNER_GROUP, COMPONENT_RL_MODULE
        from ray.rllib.core.rl_module.rl_module import RLModule

        torch.set_num_threads(1)
        p = Path(checkpoint).expanduser().resolve()  # RLlib reads a relative path as a URI
        if not any(p.glob("module_state*")):
            p = p / COMPONENT_LEARNER_GROUP / COMPONENT_LEARNER / COMPONENT_RL_MODULE / module_id
        if not p.is_dir():
            raise DataFileError(f"{checkpoint}: no RLModule {module_id!r}; expected {p}")
        found = find_run_spec(Path(checkpoint))
        with _quiet_rllib():
            module = RLModule.from_checkpoint(str(p))
        return cls(module, found[1] if found else None, deterministic)

    # ------------------------------------------------------------------ env helpers
    def make_env(self, filter: bool | None = None, **overrides: Any) -> Any:
        """An env with the training settings; ``filter``: behind the filter or not (default: as trained)."""
        if "env" not in self.spec:
            raise ConfigError("RLlibAgent.make_env: this policy has no policy.json (env settings unknown)")
        use = self.spec.get("filter") is not None if filter is None else filter
        cfg = (self.spec.get("filter") or {}) if use else None
        return make_aasoatt_env(**{**self.spec["env"], **overrides}, filter=cfg)

    # ------------------------------------------------------------------ acting
    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Observations ``(n, obs_dim)`` -> actions ``(n, act_dim)`` float32 in the action bounds."""
        torch = self._torch
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32).reshape(-1, *self._obs_shape))
        with torch.no_grad():
            out = self.module.forward_inference({"obs": x})
            dist = self._dist_cls.from_logits(out["action_dist_inputs"])
            if self.deterministic:
                dist = dist.to_deterministic()
            a = dist.sample().cpu().numpy().astype(np.float32)
        # RLlib's default normalize_actions: unsquash [-1, 1] to [low, high] and clip (for our Box(-1, 1): a clip)
        a = self._low + (a + 1.0) * (self._high - self._low) / 2.0
        return np.clip(a, self._low, self._high)

    def reset(self, env: Any) -> None:
        """Check that ``env``'s observations and action mode match the policy (stateless otherwise)."""
        base = env.unwrapped
        shape = tuple(base.observation_space(base.possible_agents[0]).shape)
        if shape != self._obs_shape:
            raise ConfigError(f"RLlibAgent: got an env with observation shape {shape}, expected {self._obs_shape} "
                              "(same num_neighbors/num_obstacles as in training)")
        mode = self.spec.get("env", {}).get("action_mode")
        if mode is not None and mode != base.action_mode:
            raise ConfigError(f"RLlibAgent: got an env with action_mode={base.action_mode!r}, expected {mode!r} "
                              "(as trained)")

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        """One action per live agent of ``env`` (robots that are done get none)."""
        agents = list(env.agents)
        if not agents:
            return {}
        actions = self(np.stack([np.asarray(observations[a], dtype=np.float32) for a in agents]))
        return {a: actions[i] for i, a in enumerate(agents)}
