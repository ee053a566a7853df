"""A run's ``policy.json``: found, read and checked field by field, for either training backend.

``policy.json`` says what a trained policy needs (the env it acts in, the filter it was trained
behind, the policy class, whether its observations are normalised).  Every field is checked
here: unknown keys, types, allowed values, and the env and filter settings by building them.

The settings a policy's actions depend on (:data:`POLICY_ENV_KEYS`, the policy class,
``normalize_obs``) are also stored inside the weights file as a *policy record*
(:func:`policy_record`), so an edit of ``policy.json`` that would silently change what the
weights mean (``action_mode``, ``decision_interval``, ``normalize_obs``) is refused
(:func:`check_record`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from aasoatt_env.errors import ConfigError, DataFileError
from aasoatt_env.validation import short_repr
from agents.run_files import parse_json, read_json

__all__ = ["POLICY_ENV_KEYS", "POLICY_FILE", "RECORD_ENTRY", "check_record", "check_spec", "find_run_spec",
           "policy_record", "record_bytes"]

POLICY_FILE = "policy.json"
RECORD_ENTRY = "aasoatt_policy.json"
"""Name of the policy record inside an SB3 model zip (and, as bytes, inside ``rl_module.npz``)."""
POLICY_ENV_KEYS: tuple[str, ...] = ("dt", "decision_interval", "action_mode", "sensing_range", "num_neighbors",
                                    "num_obstacles")
"""Env settings a trained policy depends on: its decision period, what its actions mean and its
observation layout (a run's ``policy.json`` records them; an env for the policy must have them)."""
_FORMAT = 1


def find_run_spec(path: str | os.PathLike[str]) -> tuple[Path, dict[str, Any]] | None:
    """The ``policy.json`` that describes ``path`` (a run folder, a file in it, or a checkpoint under ``checkpoints/``).

    Returns ``(spec_file, spec)``, or None where there is none; the file is read by
    :func:`agents.run_files.read_json` (bounded size and depth).
    """
    p = Path(path)
    base = p if p.is_dir() else p.parent
    for folder in (base, base.parent, base.parent.parent):
        spec_file = folder / POLICY_FILE
        if spec_file.is_file():
            return spec_file, read_json(spec_file)
    return None


def _make_probe(spec: dict[str, Any], spec_file: Path) -> Any:
    from aasoatt_env.api.factory import make_env

    try:
        return make_env(**spec["env"])
    except (ConfigError, TypeError) as exc:
        raise DataFileError(f"{spec_file}: its env settings are invalid ({exc})") from None


def check_spec(spec: dict[str, Any], spec_file: Path, *, keys: Iterable[str], policies: Iterable[str]) -> Any:
    """Check every shared field of a ``policy.json``; return a probe env built from its ``env``.

    Parameters
    ----------
    spec : dict
        The parsed file.
    spec_file : Path
        For the messages.
    keys : iterable of str
        The keys this backend writes (others are refused).
    policies : iterable of str
        Allowed values of ``policy``.

    Raises
    ------
    DataFileError
        Unknown or missing keys, a ``format`` other than 1, a policy class not in ``policies``,
        ``normalize_obs`` not a bool, env or filter settings that do not build, a filter whose
        ``dt`` is not the env's.
    """
    allowed = set(keys)
    unknown = sorted(set(spec) - allowed)
    if unknown:
        raise DataFileError(f"{spec_file}: unexpected keys {unknown[:6]}, expected keys among {sorted(allowed)}")
    for key in ("env", "policy", "normalize_obs"):
        if key not in spec:
            raise DataFileError(f"{spec_file}: missing key {key!r}")
    if spec.get("format", _FORMAT) != _FORMAT or isinstance(spec.get("format"), bool):
        raise DataFileError(f"{spec_file}: format: got {short_repr(spec['format'], 40)}, expected {_FORMAT}")
    if not isinstance(spec["env"], dict):
        raise DataFileError(f"{spec_file}: 'env' must be an object of env keywords")
    if not isinstance(spec["normalize_obs"], bool):
        raise DataFileError(f"{spec_file}: 'normalize_obs' must be true or false, got {spec['normalize_obs']!r}")
    names = sorted(policies)
    if not isinstance(spec["policy"], str) or spec["policy"] not in names:
        raise DataFileError(f"{spec_file}: policy {str(spec['policy'])[:60]!r} is unknown, expected one of "
                            f"{' or '.join(repr(n) for n in names)}")
    probe = _make_probe(spec, spec_file)
    if spec.get("filter") is not None:
        _check_filter(spec["filter"], float(probe.unwrapped.dt), spec_file)
    return probe


def _check_filter(settings: Any, dt: float, spec_file: Path) -> None:
    from aasoatt_env.safety.config import FilterConfig

    try:
        fc = FilterConfig.merged(settings)
    except (ConfigError, TypeError) as exc:
        raise DataFileError(f"{spec_file}: its filter settings are invalid ({exc})") from None
    if fc.dt != dt:
        raise DataFileError(f"{spec_file}: filter dt: got {fc.dt!r}, expected the env's dt = {dt!r}")


def policy_record(spec: dict[str, Any]) -> dict[str, Any]:
    """What weights depend on: a ``policy.json``'s :data:`POLICY_ENV_KEYS`, policy class and ``normalize_obs``."""
    env = spec.get("env") or {}
    return {"format": _FORMAT, "env": {k: env[k] for k in POLICY_ENV_KEYS if k in env},
            "policy": spec.get("policy"), "normalize_obs": spec.get("normalize_obs")}


def record_bytes(spec: dict[str, Any]) -> bytes:
    """:func:`policy_record` as canonical JSON (what the weights files store)."""
    return json.dumps(policy_record(spec), sort_keys=True, separators=(",", ":")).encode()


def check_record(stored: bytes | None, spec: dict[str, Any], spec_file: Path, weights: Path) -> None:
    """Refuse a ``policy.json`` whose policy-dependent settings differ from the record in the weights file.

    ``stored`` is None for runs written before records existed (nothing to compare).
    """
    if stored is None:
        return
    record = parse_json(stored, f"{weights}: {RECORD_ENTRY}")
    mine = policy_record(spec)
    if record == mine:
        return
    diffs = [f"{k}: {mine['env'].get(k)!r} (trained with {record.get('env', {}).get(k)!r})"
             for k in sorted(set(mine["env"]) | set(record.get("env", {})))
             if mine["env"].get(k) != record.get("env", {}).get(k)]
    diffs += [f"{k}: {mine[k]!r} (trained with {record.get(k)!r})" for k in ("policy", "normalize_obs")
              if mine[k] != record.get(k)]
    raise DataFileError(f"{spec_file}: differs from the settings its weights were trained with ({'; '.join(diffs)}; "
                        f"recorded in {weights.name}); expected the policy.json written by training")
