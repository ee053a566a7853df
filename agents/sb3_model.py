"""Reading a Stable-Baselines3 model zip by a fixed list of names, never through SB3's loader.

``PPO.load`` unpickles the zip's ``data`` entries and sets every attribute a tensor file names
(``pytorch_variables.pth`` may name ``policy.action_net.weight.__class__``).  Here the zip is
read as plain data:

1. ``data`` is parsed as JSON (bounded size and depth); only ``policy_kwargs`` (the keys training
   writes, layer sizes bounded, the network's parameter count at most
   :data:`MAX_POLICY_PARAMETERS`) and the step counters are read; cloudpickled entries are ignored;
2. the policy network is built from those keywords and the run's spaces;
3. ``policy.pth`` must hold exactly that network's parameter names with their shapes, finite
   (:func:`agents.run_files.read_tensors`), and only then is it copied in;
4. ``pytorch_variables.pth`` must be empty (PPO keeps none); ``policy.optimizer.pth`` is read only
   to resume training (:func:`read_optimizer_state`), against the optimiser it will go into.

Every entry's declared size is bounded before it is read.
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.errors import DataFileError
from agents.run_files import READ_ERRORS, load_tensor_file, parse_json, read_tensors, zip_member
from agents.run_spec import RECORD_ENTRY

__all__ = ["MAX_LAYERS", "MAX_LAYER_SIZE", "MAX_POLICY_PARAMETERS", "LoadedModel", "check_layer_sizes",
           "parameter_count", "read_model", "read_optimizer_state"]

MAX_LAYER_SIZE: int = 4096
"""Largest hidden layer a run may have (training refuses more; the loaders refuse a file with more)."""
MAX_LAYERS: int = 16
"""Most hidden layers a run may have (as :data:`MAX_LAYER_SIZE`)."""
MAX_POLICY_PARAMETERS: int = 1 << 22
"""Most parameters (actor, critic and heads together: 4,194,304, 16 MiB of float32) a policy may have;
checked from the layer sizes before a network is built, by training and by the loaders."""
_TENSOR_BYTES = 4 * 4 * MAX_POLICY_PARAMETERS + (1 << 20)
"""Bound on a tensor entry's size (the optimiser holds three copies of the parameters)."""
_POLICY_KWARGS = ("net_arch", "log_std_init", "prior_matrix")
"""``policy_kwargs`` that ``aasoatt train`` writes; anything else in a model zip is refused."""


@dataclass
class LoadedModel:
    """A policy read from a model zip: what acting, fine-tuning and resuming need (not an SB3 algorithm)."""

    policy: Any
    observation_space: Any
    action_space: Any
    policy_kwargs: dict[str, Any]
    num_timesteps: int = 0
    n_updates: int = 0
    path: Path = field(default_factory=Path)

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        """Actions for a batch of observations (SB3's ``predict``: clipped to the action space)."""
        return self.policy.predict(obs, deterministic=deterministic)


def check_layer_sizes(arch: Any, where: str, allow_dict: bool = True) -> None:
    """Refuse hidden-layer sizes from a file that are not a short list of bounded sizes.

    The one bound on networks rebuilt from a run's files, for both backends: the SB3 zip's
    ``policy_kwargs["net_arch"]`` and the RLlib ``model_config["fcnet_hiddens"]``.

    Parameters
    ----------
    arch : object
        The layer sizes as read: a list of ints, or (``allow_dict``) a dict ``{"pi": [...], "vf": [...]}``.
    where : str
        The file and entry, for the message.
    allow_dict : bool
        Accept SB3's dict of the actor's and the critic's layers.

    Raises
    ------
    DataFileError
        ``arch`` is not at most :data:`MAX_LAYERS` layers of sizes in ``[1, MAX_LAYER_SIZE]``.
    """
    if allow_dict and isinstance(arch, dict) and set(arch) <= {"pi", "vf"}:
        layers = list(arch.values())
    else:
        layers = [arch] if isinstance(arch, list) else None
    ok = layers is not None and all(
        isinstance(lay, list) and len(lay) <= MAX_LAYERS
        and all(isinstance(h, int) and not isinstance(h, bool) and 1 <= h <= MAX_LAYER_SIZE for h in lay)
        for lay in layers
    )
    if not ok:
        raise DataFileError(f"{where}: got {str(arch)[:80]}, expected a list of at most {MAX_LAYERS} layer sizes "
                            f"in [1, {MAX_LAYER_SIZE}]")


def parameter_count(obs_dim: int, act_dim: int, arch: list[int] | dict[str, list[int]], prior: bool = False) -> int:
    """Parameters of SB3's actor-critic MLP for these layer sizes (counted, not built)."""

    def mlp(layers: list[int], out: int) -> int:
        sizes = [obs_dim, *layers]
        return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:])) + sizes[-1] * out + out

    pi, vf = (arch.get("pi", []), arch.get("vf", [])) if isinstance(arch, dict) else (arch, arch)
    return mlp(list(pi), act_dim) + mlp(list(vf), 1) + act_dim + (act_dim * obs_dim if prior else 0)


def check_parameter_count(n: int, where: str) -> None:
    """Refuse a network of more than :data:`MAX_POLICY_PARAMETERS` parameters (before it is built)."""
    if n > MAX_POLICY_PARAMETERS:
        raise DataFileError(f"{where}: a network of {n:,} parameters, expected at most {MAX_POLICY_PARAMETERS:,}")


def _policy_kwargs(data: dict[str, Any], where: str, obs_dim: int, act_dim: int, prior: bool) -> dict[str, Any]:
    """``policy_kwargs`` of a zip's ``data``: the keys training writes, bounded, finite."""
    kw = data.get("policy_kwargs", {})
    if not isinstance(kw, dict) or ":serialized:" in kw:
        raise DataFileError(f"{where} are not plain JSON; this zip was not written by aasoatt train")
    unknown = sorted(set(kw) - set(_POLICY_KWARGS))
    if unknown:
        raise DataFileError(f"{where}: unexpected keys {unknown}, expected some of {list(_POLICY_KWARGS)}")
    arch = kw.get("net_arch", [64, 64])
    check_layer_sizes(arch, f"{where}: net_arch")
    check_parameter_count(parameter_count(obs_dim, act_dim, arch, prior), f"{where}: net_arch")
    out: dict[str, Any] = {"net_arch": arch}
    if "log_std_init" in kw:
        v = kw["log_std_init"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not -20.0 <= v <= 5.0:
            raise DataFileError(f"{where}: log_std_init: got {str(v)[:40]}, expected a number in [-20, 5]")
        out["log_std_init"] = float(v)
    if "prior_matrix" in kw:
        pm = kw["prior_matrix"]
        ok = isinstance(pm, list) and len(pm) == act_dim and all(
            isinstance(r, list) and len(r) == obs_dim and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in r) for r in pm)
        if not ok:
            raise DataFileError(f"{where}: prior_matrix is not {act_dim} rows of {obs_dim} finite numbers")
    return out


def _counter(data: dict[str, Any], key: str, where: str) -> int:
    v = data.get(key, 0)
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 10**12:
        raise DataFileError(f"{where}: {key}: got {str(v)[:40]}, expected an integer in [0, 1e12]")
    return v


def read_model(model_zip: Path, policy_class: Any, observation_space: Any, action_space: Any,
               device: str = "cpu") -> tuple[LoadedModel, bytes | None]:
    """Build the policy of ``model_zip`` and copy in its checked weights; also return its policy record.

    Parameters
    ----------
    model_zip : Path
        An SB3 model zip written by ``aasoatt train``.
    policy_class : type
        ``ActorCriticPolicy`` or :class:`agents.prior.TrackingPriorPolicy` (from ``policy.json``).
    observation_space, action_space : gymnasium.spaces.Box
        One robot's spaces, from the env ``policy.json`` describes.
    device : str
        Torch device of the policy.

    Raises
    ------
    DataFileError
        Any entry missing, oversized, crafted or inconsistent (see the module docstring).
    """
    import torch

    where = str(model_zip)
    obs_dim, act_dim = int(np.prod(observation_space.shape)), int(np.prod(action_space.shape))
    try:
        with zipfile.ZipFile(model_zip) as archive:
            data = parse_json(zip_member(archive, "data", 1 << 24, where), f"{where}: data", max_bytes=1 << 24)
            kw = _policy_kwargs(data, f"{where}: policy_kwargs", obs_dim, act_dim,
                                policy_class.__name__ == "TrackingPriorPolicy")
            names = set(archive.namelist())
            record = zip_member(archive, RECORD_ENTRY, 1 << 16, where) if RECORD_ENTRY in names else None
            if "pytorch_variables.pth" in names:
                read_tensors(zip_member(archive, "pytorch_variables.pth", 1 << 16, where),
                             f"{where}: cannot load the model: pytorch_variables.pth", {})
            raw = zip_member(archive, "policy.pth", _TENSOR_BYTES, where)
    except DataFileError:
        raise
    except READ_ERRORS as exc:
        raise DataFileError(f"{where}: not a readable Stable-Baselines3 model zip ({type(exc).__name__}: "
                            f"{str(exc)[:200]})") from None
    policy = policy_class(observation_space, action_space, lambda _: 0.0, **kw).to(device)
    expected = {k: tuple(v.shape) for k, v in policy.state_dict().items()}
    tensors = read_tensors(raw, f"{where}: cannot load the model: policy.pth", expected)
    with torch.no_grad():
        policy.load_state_dict(tensors, strict=True)
    policy.set_training_mode(False)
    model = LoadedModel(policy, observation_space, action_space, kw, _counter(data, "num_timesteps", where),
                        _counter(data, "_n_updates", where), model_zip)
    return model, record


def read_optimizer_state(model_zip: Path, optimizer: Any) -> dict[str, Any]:
    """The Adam state of ``model_zip``, checked against ``optimizer`` (the one it will be loaded into).

    Only per-parameter tensors (``step``, ``exp_avg``, ``exp_avg_sq``) are taken, each with the
    shape of its parameter and finite; the hyper-parameters stay those of ``optimizer``.

    Raises
    ------
    DataFileError
        Not the state of this network's Adam.
    """
    import torch

    where = f"{model_zip}: policy.optimizer.pth"
    try:
        with zipfile.ZipFile(model_zip) as archive:
            raw = zip_member(archive, "policy.optimizer.pth", _TENSOR_BYTES, str(model_zip))
    except READ_ERRORS as exc:
        raise DataFileError(f"{where}: not readable ({type(exc).__name__}: {str(exc)[:200]})") from None
    state = load_tensor_file(raw, where)
    mine = optimizer.state_dict()
    params = [p for group in optimizer.param_groups for p in group["params"]]
    per_param = state.get("state") if isinstance(state, dict) else None
    if not isinstance(per_param, dict) or not set(per_param) <= set(range(len(params))):
        raise DataFileError(f"{where}: expected the Adam state of a network of {len(params)} parameter tensors")
    out: dict[int, dict[str, Any]] = {}
    for i, entry in per_param.items():
        shape = tuple(params[i].shape)
        want = {"step": (), "exp_avg": shape, "exp_avg_sq": shape}
        if not isinstance(entry, dict) or set(entry) != set(want):
            raise DataFileError(f"{where}: parameter {i}: expected entries {sorted(want)}")
        for key, shp in want.items():
            t = entry[key]
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != shp or not bool(torch.isfinite(t).all()) \
                    or (key != "exp_avg" and bool((t < 0).any())):
                raise DataFileError(f"{where}: parameter {i} {key}: expected a finite tensor of shape {shp}"
                                    + ("" if key == "exp_avg" else " (>= 0)"))
        out[i] = {k: entry[k].clone() for k in want}
    return {"state": out, "param_groups": mine["param_groups"]}
