"""The files of an RLlib run: the shared module's weights (plain arrays, with the policy record) and checkpoints."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.errors import ConfigError
from agents.run_spec import RECORD_ENTRY, record_bytes
from train.runs import save_npz

__all__ = ["MODULE_ID", "WEIGHTS_FILE", "module_weights", "resume_checkpoint", "save_checkpoint",
           "weights_with_record"]

MODULE_ID = "default_policy"
"""The one RLModule every robot acts with."""
WEIGHTS_FILE = "rl_module.npz"


def module_weights(algo: Any) -> dict[str, np.ndarray]:
    """The shared RLModule's weights from the learner (local or remote) as numpy arrays."""
    from ray.rllib.core import COMPONENT_LEARNER, COMPONENT_LEARNER_GROUP, COMPONENT_RL_MODULE

    state = algo.get_state(components=f"{COMPONENT_LEARNER_GROUP}/{COMPONENT_LEARNER}/{COMPONENT_RL_MODULE}/"
                                      f"{MODULE_ID}")
    weights = state[COMPONENT_LEARNER_GROUP][COMPONENT_LEARNER][COMPONENT_RL_MODULE][MODULE_ID]
    return {k: np.asarray(v) for k, v in weights.items()}


def resume_checkpoint(path: str) -> Path:
    """The RLlib checkpoint to resume from: ``path`` itself, or the last ``checkpoints/iter_<n>`` of a run folder."""
    p = Path(path).expanduser()
    if (p / "rllib_checkpoint.json").is_file():
        return p.resolve()
    found = sorted((p / "checkpoints").glob("iter_*/rllib_checkpoint.json"))
    if not found:
        raise ConfigError(f"RLlibConfig.resume: got {path!r}, expected an RLlib checkpoint folder or a run folder "
                          "with checkpoints/iter_<n>")
    return found[-1].parent.resolve()


def save_checkpoint(algo: Any, run: Path, iteration: int, spec: dict[str, Any]) -> Path:
    """An RLlib checkpoint ``checkpoints/iter_<n>`` (with the module's weights as ``rl_module.npz``), atomically.

    Written into a temporary folder beside it and renamed once complete.
    """
    ckpt = run / "checkpoints" / f"iter_{iteration:06d}"
    tmp = ckpt.with_name(f".{ckpt.name}.tmp")
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    try:
        algo.save_to_path(str(tmp.resolve()))  # RLlib wants an absolute path (a relative one is read as a URI)
        save_npz(tmp / WEIGHTS_FILE, **weights_with_record(algo, spec))
        os.replace(tmp, ckpt)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ckpt


def weights_with_record(algo: Any, spec: dict[str, Any]) -> dict[str, np.ndarray]:
    """The module's weights and the policy record of ``spec`` (bytes as a ``uint8`` array): ``rl_module.npz``."""
    return {**module_weights(algo), RECORD_ENTRY: np.frombuffer(record_bytes(spec), dtype=np.uint8)}
