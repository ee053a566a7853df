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

Loading without unpickling: :meth:`RLlibAgent.load` checks every field of the run's
``policy.json`` (:mod:`agents.run_spec`), rebuilds the module from it (PPO's default RLModule,
the saved ``model_config`` with bounded layer sizes, the spaces of the env it describes) and reads
``rl_module.npz`` (plain arrays) by the module's own parameter names and shapes, checked from
the archive's headers before any data is read, finite (:func:`agents.run_files.read_npz`).
RLlib's own checkpoints pickle their classes and states; :meth:`RLlibAgent.from_checkpoint`
reads one (``RLModule.from_checkpoint``) for checkpoints made elsewhere, and unpickles: use it
only on files you trust.

Ray is imported only when a policy is loaded (``ray[rllib]``: the ``rllib`` extra); no Ray
instance is started.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env as make_aasoatt_env
from aasoatt_env.errors import ConfigError, DataFileError
from agents.run_files import read_npz
from agents.run_spec import RECORD_ENTRY, check_record, check_spec, find_run_spec, record_bytes
from agents.sb3_model import check_layer_sizes, check_parameter_count, parameter_count

__all__ = ["RLlibAgent", "find_run_spec"]

WEIGHTS_FILE = "rl_module.npz"
_MODULES = ("DefaultPPOTorchRLModule",)
_SPEC_KEYS = ("format", "backend", "env", "filter", "policy", "module_id", "model_config", "normalize_obs",
              "ray_version")
_MODULE_IDS = ("default_policy", "shared")
_MODEL_CONFIG_KEYS = ("fcnet_hiddens", "fcnet_activation", "vf_share_layers")
"""``model_config`` entries that :mod:`train.rllib` writes; anything else in a ``policy.json`` is refused."""
_ACTIVATIONS = ("tanh", "relu", "elu", "swish", "silu", "linear")


def _check_model_config(model_config: Any, spec_file: Path, obs_dim: int, act_dim: int) -> None:
    """Refuse a ``model_config`` that training does not write, or a network too large to build (a crafted file).

    Runs before Ray is imported; the bounds are the SB3 loader's (:mod:`agents.sb3_model`).
    """
    where = f"{spec_file}: model_config"
    if not isinstance(model_config, dict):
        raise DataFileError(f"{where}: got a {type(model_config).__name__}, expected an object")
    unknown = sorted(set(model_config) - set(_MODEL_CONFIG_KEYS))
    if unknown:
        raise DataFileError(f"{where}: unexpected keys {unknown}, expected some of {list(_MODEL_CONFIG_KEYS)}")
    hidden = model_config.get("fcnet_hiddens", [256, 256])
    check_layer_sizes(hidden, f"{where}.fcnet_hiddens", allow_dict=False)
    check_parameter_count(parameter_count(obs_dim, 2 * act_dim, hidden), f"{where}.fcnet_hiddens")
    act = model_config.get("fcnet_activation", "tanh")
    if act not in _ACTIVATIONS:
        raise DataFileError(f"{where}.fcnet_activation: got {str(act)[:40]!r}, expected one of {list(_ACTIVATIONS)}")
    if not isinstance(model_config.get("vf_share_layers", False), bool):
        raise DataFileError(f"{where}.vf_share_layers: got {model_config['vf_share_layers']!r}, expected true or false")


def _check_rllib_spec(spec: dict[str, Any], spec_file: Path) -> tuple[Any, Any]:
    """Every field of an RLlib run's ``policy.json``; the spaces of one robot."""
    if spec.get("backend") != "rllib":
        raise DataFileError(f"{spec_file}: got backend {str(spec.get('backend'))[:40]!r}, expected 'rllib' "
                            "(Stable-Baselines3 runs load with agents.learned.LearnedAgent)")
    for key in ("model_config",):
        if key not in spec:
            raise DataFileError(f"{spec_file}: missing key {key!r}")
    probe = check_spec(spec, spec_file, keys=_SPEC_KEYS, policies=_MODULES)
    agent0 = probe.possible_agents[0]
    obs_space, act_space = probe.observation_space(agent0), probe.action_space(agent0)
    probe.close()
    if spec["normalize_obs"]:
        raise DataFileError(f"{spec_file}: normalize_obs: got true, expected false (RLlib runs are not normalised)")
    if spec.get("module_id", "shared") not in _MODULE_IDS:
        raise DataFileError(f"{spec_file}: module_id: got {str(spec['module_id'])[:40]!r}, expected one of "
                            f"{list(_MODULE_IDS)}")
    if not isinstance(spec.get("ray_version", ""), str) or len(spec.get("ray_version", "")) > 40:
        raise DataFileError(f"{spec_file}: ray_version: expected a version string")
    _check_model_config(spec["model_config"], spec_file, int(np.prod(obs_space.shape)),
                        int(np.prod(act_space.shape)))
    return obs_space, act_space


def _load_weights(module: Any, weights_file: Path, spec: dict[str, Any], spec_file: Path) -> None:
    """Copy ``rl_module.npz`` into ``module``: its own parameter names and shapes, finite, and the policy record."""
    import torch

    expected = {k: tuple(v.shape) for k, v in module.state_dict().items()}
    record = record_bytes(spec)
    arrays = read_npz(weights_file, expected, optional={RECORD_ENTRY: (len(record),)})
    stored = arrays.pop(RECORD_ENTRY, None)
    check_record(None if stored is None else stored.astype(np.uint8).tobytes(), spec, spec_file, weights_file)
    state = {k: torch.from_numpy(v.astype(np.float32)) for k, v in arrays.items()}
    with torch.no_grad():
        module.load_state_dict(state, strict=True)


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
            ``policy.json`` with unknown entries or layer sizes beyond the SB3 loader's bounds
            (:mod:`agents.sb3_model`) is refused before Ray is imported.
        """
        if device != "cpu":
            raise ConfigError(f"device: got {device!r}, expected 'cpu'")
        p = Path(path)
        found = find_run_spec(p)
        if found is None:
            raise DataFileError(f"{path}: no policy.json here or two levels up; expected a run folder of "
                                "train.rllib or one of its checkpoints/iter_<n>")
        spec_file, spec = found
        obs_space, act_space = _check_rllib_spec(spec, spec_file)
        weights_file = (p if p.is_dir() else p.parent) / WEIGHTS_FILE
        if not weights_file.is_file():
            raise DataFileError(f"{weights_file}: missing; an RLlib run keeps its weights in {WEIGHTS_FILE}")

        import torch
        from ray.rllib.algorithms.ppo import PPOConfig

        torch.set_num_threads(1)
        module_spec = PPOConfig().get_default_rl_module_spec()
        module_spec.observation_space, module_spec.action_space = obs_space, act_space
        module_spec.model_config = dict(spec["model_config"])
        with _quiet_rllib():  # RLlib's own builder logs a DeprecationWarning about itself
            module = module_spec.build()
        _load_weights(module, weights_file, spec, spec_file)
        return cls(module, spec, deterministic)

    @classmethod
    def from_checkpoint(
        cls, checkpoint: str | os.PathLike[str], module_id: str | None = None, deterministic: bool = True
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
        found = find_run_spec(Path(checkpoint))
        module_id = module_id or (found[1].get("module_id") if found else None) or "default_policy"
        p = Path(checkpoint).expanduser().resolve()  # RLlib reads a relative path as a URI
        if not any(p.glob("module_state*")):
            p = p / COMPONENT_LEARNER_GROUP / COMPONENT_LEARNER / COMPONENT_RL_MODULE / module_id
        if not p.is_dir():
            raise DataFileError(f"{checkpoint}: no RLModule {module_id!r}; expected {p}")
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
