"""The one validation layer: typed checks whose errors read ``"<name>: got <value>, expected <what>"``.

Every entry point checks its inputs here (:class:`~aasoatt_env.errors.ConfigError`); types are checked before any
conversion: ``True`` is not 1, ``"2"`` is not 2, a complex number is not real.
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Iterable
from typing import Any

import numpy as np

from aasoatt_env.errors import ConfigError, UnknownKeywordError

__all__ = ["MAGNITUDE_MAX", "boolean", "choice", "integer", "parse_assignments", "parse_value", "positive", "real",
           "real_array", "reject_unknown", "shapes", "short_repr"]

MAGNITUDE_MAX: float = 1e9
"""Largest magnitude :func:`real` accepts by default (SI units; far larger values overflow when squared)."""


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def short_repr(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters."""
    try:
        text = repr(value)
    except Exception:  # noqa: BLE001 - a broken __repr__ must not hide the real error
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def shapes(expected: Iterable[tuple[str, Any, tuple[int, ...]]], note: str = "") -> None:
    """Raise ``ValueError`` naming the first ``(name, array, shape)`` of another shape (``note`` ends the message)."""
    for name, a, shape in expected:
        if np.shape(a) != shape:
            raise ValueError(f"{name}: got shape {np.shape(a)}, expected {shape}{note}")


def _describe(kind: str, lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    """``"a finite positive number"``, ``"an integer >= 1"``, ``"a finite number in [0, 1]"``, ..."""
    if lo == 0 and lo_open and kind != "an integer":
        positive = kind.replace("number", "positive number")
        return positive if hi is None else f"{positive} {'<' if hi_open else '<='} {hi:g}"
    if hi is None and lo is not None:
        return f"{kind} {'>' if lo_open else '>='} {lo:g}"
    if hi is None and lo is None:
        return kind
    left, right = ("(-inf" if lo is None else f"{'(' if lo_open else '['}{lo:g}"), f"{hi:g}{')' if hi_open else ']'}"
    return f"{kind} in {left}, {right}"


def real(name: str, value: Any, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
         hi_open: bool = False, allow_inf: bool = False) -> float:
    """Return ``value`` (a real number: not a bool, not a string) as a float in ``[lo, hi]``.

    ``lo_open``/``hi_open`` exclude a bound; ``allow_inf`` accepts ``+inf`` ("no limit").
    """
    lo, hi = (-MAGNITUDE_MAX if lo is None else lo), (MAGNITUDE_MAX if hi is None else hi)
    expected = _describe(f"a {'' if allow_inf else 'finite '}number", lo, hi, lo_open, hi_open)
    expected += " or inf" if allow_inf else ""
    if not _is_real(value):
        raise ConfigError(f"{name}: got {short_repr(value)} ({type(value).__name__}), expected {expected}")
    try:
        v = float(value)
    except OverflowError:  # an int beyond the float range
        v = math.nan
    inside = (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
    if not ((math.isfinite(v) and inside) or (allow_inf and v == math.inf)):
        raise ConfigError(f"{name}: got {short_repr(value)}, expected {expected}")
    return v


def positive(name: str, value: Any, *, allow_inf: bool = False, hi: float | None = None,
             lo: float | None = None) -> float:
    """:func:`real` with ``value > 0`` (or ``>= lo`` when given) and ``<= hi``."""
    return real(name, value, lo=0.0 if lo is None else lo, lo_open=lo is None, hi=hi, allow_inf=allow_inf)


def integer(name: str, value: Any, *, lo: int | None = None, hi: int | None = None) -> int:
    """Return ``value`` as an int in ``[lo, hi]``: ``20.0`` is one; ``True``, ``"3"`` and ``2.5`` are not."""
    rng = _describe("an integer", lo, hi, False, False)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ConfigError(f"{name}: got {short_repr(value)} ({type(value).__name__}), expected {rng}")
    integral = isinstance(value, numbers.Integral) or (math.isfinite(float(value)) and float(value).is_integer())
    v = int(value) if integral else 0
    if not integral or (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(f"{name}: got {short_repr(value)}, expected {rng}")
    return v


def real_array(name: str, value: Any, *, lo: float = -MAGNITUDE_MAX, hi: float = MAGNITUDE_MAX,
               unit: str = "") -> np.ndarray:
    """Return ``value`` as a new float64 array of finite numbers in ``[lo, hi]`` (any shape; no bools, complex, str)."""
    def bad(detail: str = "") -> ConfigError:
        return ConfigError(f"{name}: got {short_repr(value)}{detail}, expected an array of finite numbers in "
                           f"[{lo:g}, {hi:g}]{unit}")

    try:
        raw = np.asarray(value)
        if raw.dtype.kind == "O" and all(_is_real(x) for x in raw.reshape(-1).tolist()):  # ints beyond int64
            raw = np.array([float(x) for x in raw.reshape(-1).tolist()]).reshape(raw.shape)
    except (TypeError, ValueError, OverflowError):  # ragged nesting, a broken __array__, ints beyond floats
        raise bad() from None
    if raw.dtype.kind == "O":
        raise bad()
    if raw.dtype.kind not in "fiu":
        raise bad(f" (dtype {raw.dtype})")
    arr = np.array(raw, dtype=np.float64)
    if arr.size and not (np.isfinite(arr).all() and arr.min() >= lo and arr.max() <= hi):
        raise bad()
    return arr


def boolean(name: str, value: Any) -> bool:
    """Return ``value`` if it is a bool (``True``/``False``, numpy bool), else raise."""
    if not isinstance(value, (bool, np.bool_)):
        raise ConfigError(f"{name}: got {short_repr(value)} ({type(value).__name__}), expected True or False")
    return bool(value)


def choice(name: str, value: Any, options: Iterable[str]) -> str:
    """Return ``value`` if it is one of ``options`` (strings), else raise listing them."""
    opts = list(options)
    if not isinstance(value, str) or value not in opts:
        raise ConfigError(f"{name}: got {short_repr(value)}, expected one of {sorted(opts)}")
    return value


def reject_unknown(owner: str, given: Iterable[str], known: Iterable[str]) -> None:
    """Raise :class:`~aasoatt_env.errors.UnknownKeywordError` naming the ``given`` keywords not ``known``."""
    known_set = set(known)
    unknown = sorted(str(k) for k in given if k not in known_set)
    if unknown:
        clauses = ", ".join(f"got an unexpected keyword argument {k!r}" for k in unknown)
        raise UnknownKeywordError(f"{owner}() {clauses}; expected keywords among {sorted(known_set)}")


def parse_value(text: str) -> Any:
    """A command-line ``KEY=VALUE`` value: JSON when it parses (numbers, true/false, lists), else the string."""
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError):  # not JSON, or nested beyond the parser's depth
        return text


def parse_assignments(items: Iterable[str] | None, flag: str) -> dict[str, Any]:
    """``["k1=2", "solver=daqp"]`` -> ``{"k1": 2, "solver": "daqp"}`` (dashes in keys become underscores)."""
    out: dict[str, Any] = {}
    for item in items or ():
        if "=" not in item:
            raise ConfigError(f"{flag}: got {item!r}, expected KEY=VALUE")
        key, val = item.split("=", 1)
        out[key.strip().replace("-", "_")] = parse_value(val.strip())
    return out

