"""The envs' one set of action checks; errors name the agent (env) or the ``[team, robot]`` entry (batches)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from aasoatt_env.errors import ActionError

__all__ = ["checked_actions", "parse_actions", "real_actions"]

_NOMINAL_MAX = 1e6  # largest nominal action behind a filter (in units of the bound): larger ones are a bug

_FLOAT_MAX = float(np.finfo(np.float64).max)
_REAL = "(a float or integer dtype)"


def _bool_at(value: Any) -> tuple[int, ...] | None:
    """Index of the first boolean inside nested lists/tuples (a bool, or a boolean array or tensor), or None."""
    if isinstance(value, np.ndarray):
        return () if value.dtype.kind == "b" else None
    dtype = getattr(value, "dtype", None)
    if dtype is not None:
        return () if "bool" in str(dtype) else None
    if isinstance(value, (bool, np.bool_)):
        return ()
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            at = _bool_at(v)
            if at is not None:
                return (i, *at)
    return None


def real_actions(value: Any, name: Callable[[tuple[int, ...]], str], expected: str,
                 shape: tuple[int, ...] | None = None) -> np.ndarray:
    """``value`` as an array of real numbers (no booleans, even one among numbers; of ``shape``), else an error."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):
        raise ActionError(f"{name(())}: got {type(value).__name__}, expected {expected} {_REAL}") from None
    if arr.dtype.kind not in "fiu":
        raise ActionError(f"{name(())}: got shape {arr.shape} (dtype {arr.dtype}), expected {expected} {_REAL}")
    at = None if isinstance(value, np.ndarray) else _bool_at(value)
    if at is not None:
        raise ActionError(f"{name(at)}: got booleans, expected {expected} {_REAL}")
    if shape is not None and arr.shape != shape:
        raise ActionError(f"{name(())}: got shape {arr.shape}, expected {shape}")
    return arr


def checked_actions(act: np.ndarray, nominal: bool, clip: bool, name: Callable[[int], str]) -> np.ndarray:
    """Finite actions ``(R, 2)`` within their bound, clipped (in place) to ``[-1, 1]`` unless ``nominal``.

    The bound is ``_NOMINAL_MAX`` for a ``nominal``, else ``1 + 1e-6`` (any finite value with ``clip``).
    """
    peak = float(np.abs(act).max(initial=0.0))
    accept = _NOMINAL_MAX if nominal else (_FLOAT_MAX if clip else 1.0 + 1e-6)
    if not peak <= accept:  # also NaN and inf
        if not math.isfinite(peak):
            bad = int(np.flatnonzero(~np.isfinite(act).all(axis=1))[0])
            raise ActionError(f"{name(bad)}: got non-finite values {act[bad].tolist()}, expected finite numbers")
        bad = int(np.flatnonzero(np.abs(act).max(axis=1) > accept)[0])
        raise ActionError(f"{name(bad)}: got {act[bad].tolist()}, expected " + (
            f"a nominal within [-{_NOMINAL_MAX:g}, {_NOMINAL_MAX:g}] (in units of the wheel-acceleration bound; "
            "the filter keeps the bounds)" if nominal else "values in [-1, 1] (or clip_actions=True)"))
    if not nominal and peak > 1.0:
        np.minimum(np.maximum(act, -1.0, out=act), 1.0, out=act)
    return act


def parse_actions(actions: Any, live: np.ndarray, nominal: bool, clip: bool, offset: int = 0) -> np.ndarray:
    """Checked actions ``(K N, 2)`` of teams ``(K, N) = live.shape`` (done agents' rows 0, first team ``offset``)."""
    k, n = live.shape
    expected = f"real numbers of shape ({k}, {n}, 2)"

    def robot(at: tuple[int, ...]) -> str:  # an entry of nested (K, N, 2) or (K N, 2) sequences
        if not at:
            return "actions"
        if np.ndim(actions) == 3:
            return f"actions[{at[0] + offset}" + (f", {at[1]}]" if len(at) > 1 else "]")
        return f"actions[{at[0] // n + offset}, {at[0] % n}]"

    arr = real_actions(actions, robot, expected)
    if arr.size != k * n * 2 or arr.shape not in ((k, n, 2), (k * n, 2)):
        raise ActionError(f"actions: got shape {arr.shape} (dtype {arr.dtype}), expected {expected}")
    act = arr.reshape(k * n, 2).astype(np.float64)
    act[~live.ravel()] = 0.0  # the env ignores actions of agents that are done
    return checked_actions(act, nominal, clip, lambda row: f"actions[{row // n + offset}, {row % n}]")
