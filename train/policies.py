"""Loading a trained policy for a command, and the env settings it needs (both training backends).

:func:`load_policy` checks the path a user gave (``--bare``, ``--filtered``, ``--model``) and names
that option in every error; :func:`policy_env_kwargs` completes a command's env keywords with the
settings the policy was trained with and refuses a conflicting one.
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aasoatt_env.errors import ConfigError, DataFileError
from agents.learned import load_learned
from agents.run_spec import POLICY_ENV_KEYS, find_run_spec
from train.runs import check_path

__all__ = ["RAY_MISSING", "load_policy", "policy_env_kwargs"]

RAY_MISSING = ("Ray RLlib is not installed; install the rllib extra in a virtual environment of its own "
               "(ray[rllib] pins gymnasium 1.2), e.g. python3 -m venv .venv-rllib && "
               ".venv-rllib/bin/pip install -e \".[rllib]\" (README: Use it from your RL library)")
"""What the RLlib commands say without Ray (``aasoatt train --backend rllib``, a run of it given to evaluate or run)."""

_EXPECTED_MODEL = ("expected a run folder of aasoatt train holding policy.json and model.zip (or of "
                   "train.rllib: policy.json and rl_module.npz), or a model .zip / checkpoint in one")


def load_policy(path: str | os.PathLike[str], flag: str = "model") -> Any:
    """Load a trained policy (:func:`agents.learned.load_learned`), errors naming ``flag`` and ``path``.

    The path is checked first: it must be a run folder (or a checkpoint in one) or a model
    ``.zip`` with the run's ``policy.json`` beside it or above ``checkpoints/``; a Ray RLlib run
    needs Ray installed (the message says how, as ``aasoatt train --backend rllib`` does).

    Parameters
    ----------
    path : str or PathLike
        What the user gave.
    flag : str
        The option it came from (``"--bare"``, ``"--model"``, ...), named in every error.

    Returns
    -------
    LearnedAgent or RLlibAgent
        The policy, with the run's ``spec``.

    Raises
    ------
    DataFileError
        The path holds no model, or a file of it is missing or corrupted.
    ConfigError
        A Ray RLlib run without Ray installed.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError(f"{flag}: got {type(path).__name__}, {_EXPECTED_MODEL}")
    p = Path(check_path(path, flag))
    if not p.exists():
        raise DataFileError(f"{flag}: {str(path)!r}: no model here (no such file or folder); {_EXPECTED_MODEL}")
    if not p.is_dir() and p.suffix.lower() != ".zip":
        raise DataFileError(f"{flag}: got {str(path)!r}, a file that is not a model .zip; {_EXPECTED_MODEL}")
    try:
        found = find_run_spec(p)
    except DataFileError as exc:
        raise DataFileError(f"{flag}: {exc}") from None
    if found is None:
        raise DataFileError(f"{flag}: {str(path)!r}: no model here (no policy.json in it or in the run folder "
                            f"above); {_EXPECTED_MODEL}")
    if found[1].get("backend") == "rllib" and importlib.util.find_spec("ray") is None:
        raise ConfigError(f"{flag}: {str(path)!r} is a Ray RLlib run; {RAY_MISSING}")
    try:
        return load_learned(p)
    except DataFileError as exc:
        raise DataFileError(f"{flag}: {exc}") from None


def policy_env_kwargs(
    policy: Any, given: Mapping[str, Any], *, model: str, options: Mapping[str, str] | None = None,
    default_option: str = "env", hint: str = " (leave it out to take the run's)",
) -> dict[str, Any]:
    """``given`` env keywords completed with the settings ``policy`` was trained with (:data:`POLICY_ENV_KEYS`).

    Parameters
    ----------
    policy : LearnedAgent or RLlibAgent
        A loaded policy; its ``spec["env"]`` (the run's ``policy.json``) holds the settings.
    given : mapping
        Env keywords chosen by the user (or a config); they win for every other key.
    model : str
        How to name the policy in an error (e.g. ``"--model runs/x"``).
    options : mapping, optional
        The option each key came from (e.g. ``{"decision_interval": "--decision-interval"}``).
    default_option : str
        The option named for keys not in ``options``.
    hint : str
        Appended to the error (what to do instead).

    Returns
    -------
    dict
        ``given`` plus the run's settings.

    Raises
    ------
    ConfigError
        ``given`` sets one of them to another value (naming the option, both values and the model).
    """
    trained = (getattr(policy, "spec", None) or {}).get("env") or {}
    out = dict(given)
    for key in POLICY_ENV_KEYS:
        if key not in trained:
            continue
        if key in out and out[key] != trained[key]:
            flag = (options or {}).get(key, default_option)
            raise ConfigError(f"{flag}: got {key}={out[key]!r}, expected {key}={trained[key]!r}, the setting the "
                              f"policy of {model} was trained with{hint}")
        out[key] = trained[key]
    return out
