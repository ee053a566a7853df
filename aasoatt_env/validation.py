"""The one validation layer: typed checks with the valid range in the message.

Every entry point (env and scenario keywords, :class:`~aasoatt_env.safety.config.FilterConfig`,
:class:`~aasoatt_env.sim.rewards.RewardConfig`, the command line, the loaders)
checks its inputs with these functions, so a bad value always gets the same kind
of error: a :class:`~aasoatt_env.errors.ConfigError` (a ``ValueError``) of the
form ``"<name>: got <value>, expected <what>"``.  Types are checked *before*
any conversion: ``True`` is not the integer 1, ``"2"`` is not the number 2 and
a complex number is not a real one.  Unknown keyword arguments are a
``TypeError`` (Python's convention), see :func:`reject_unknown`.
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from aasoatt_env.errors import ConfigError, UnknownKeywordError

__all__ = [
    "MAGNITUDE_MAX",
    "boolean",
    "choice",
    "integer",
    "parse_assignments",
    "parse_value",
    "positive",
    "real",
    "real_array",
    "reject_unknown",
    "shapes",
    "short_repr",
]


MAGNITUDE_MAX: float = 1e9
"""Largest magnitude :func:`real` accepts when no tighter bound is given.

No parameter of this library is meaningful beyond ``1e9`` in SI units, and much
larger finite values (``1e308``) overflow to ``inf`` the first time they are
squared, so they are rejected at the edge instead of surfacing as ``inf``/NaN
rewards or corrections later."""


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _interval(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    left = "-inf" if lo is None else f"{lo:g}"
    right = "inf" if hi is None else f"{hi:g}"
    return f"{'(' if lo_open or lo is None else '['}{left}, {right}{')' if hi_open or hi is None else ']'}"


def short_repr(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters (a huge int or list must not flood the message)."""
    try:
        text = repr(value)
    except Exception:  # noqa: BLE001 - a broken __repr__ must not hide the real error
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def shapes(expected: Iterable[tuple[str, Any, tuple[int, ...]]], note: str = "") -> None:
    """Raise ``ValueError`` naming the first ``(name, array, shape)`` whose array has another shape.

    For arrays a compiled kernel reads without bounds checks; ``note`` ends the message
    (what the expected shapes refer to).
    """
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
    return f"{kind} in {_interval(lo, hi, lo_open, hi_open)}"


def real(
    name: str,
    value: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    allow_inf: bool = False,
) -> float:
    """Return ``value`` as a float after checking its type, finiteness and range.

    Parameters
    ----------
    name : str
        Name used in the error message (e.g. ``"RobotParams.radius"``).
    value : object
        A real number (``int``, ``float`` or numpy scalar; not ``bool``, not a string).
    lo, hi : float, optional
        Bounds of the valid interval.
    lo_open, hi_open : bool
        Whether the bounds are excluded.
    allow_inf : bool
        Accept ``+inf`` (e.g. "no limit").

    Raises
    ------
    ConfigError
        Naming ``name``, the value and the valid interval.
    """
    if hi is None:
        hi = MAGNITUDE_MAX
    if lo is None:
        lo = -MAGNITUDE_MAX
    expected = _describe(f"a {'' if allow_inf else 'finite '}number", lo, hi, lo_open, hi_open)
    if allow_inf:
        expected += " or inf"
    if not _is_real(value):
        raise ConfigError(f"{name}: got {short_repr(value)} ({type(value).__name__}), expected {expected}")
    try:
        v = float(value)
    except OverflowError:  # an int beyond the float range
        raise ConfigError(f"{name}: got {short_repr(value)}, expected {expected}") from None
    ok = not math.isnan(v) and (math.isfinite(v) or (allow_inf and v == math.inf))
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None and math.isfinite(v):
        ok = v < hi if hi_open else v <= hi
    if not ok:
        raise ConfigError(f"{name}: got {short_repr(value)}, expected {expected}")
    return v


def positive(
    name: str, value: Any, *, allow_inf: bool = False, hi: float | None = None, lo: float | None = None
) -> float:
    """:func:`real` with ``value > 0`` (or ``>= lo`` when given) and ``<= hi``."""
    if lo is not None:
        return real(name, value, lo=lo, hi=hi, allow_inf=allow_inf)
    return real(name, value, lo=0.0, lo_open=True, hi=hi, allow_inf=allow_inf)


def integer(name: str, value: Any, *, lo: int | None = None, hi: int | None = None) -> int:
    """Return ``value`` as an int after checking it is an integer (not a bool) in ``[lo, hi]``.

    An integral float (``20.0``) is accepted; ``True``, ``"3"``, ``2.5``, NaN and
    infinities are not.  ``hi`` bounds sizes whose work would be unreasonable
    (the message says so).
    """
    rng = _describe("an integer", lo, hi, False, False)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ConfigError(f"{name}: got {short_repr(value)} ({type(value).__name__}), expected {rng}")
    if isinstance(value, numbers.Integral):
        v = int(value)
    else:
        f = float(value)
        if not (math.isfinite(f) and f.is_integer()):
            raise ConfigError(f"{name}: got {short_repr(value)}, expected {rng}")
        v = int(f)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(f"{name}: got {short_repr(value)}, expected {rng}")
    return v


def real_array(
    name: str, value: Any, *, lo: float = -MAGNITUDE_MAX, hi: float = MAGNITUDE_MAX, unit: str = ""
) -> np.ndarray:
    """Return ``value`` as a new float64 array of finite numbers in ``[lo, hi]`` (any shape; callers check it).

    Types are checked before conversion: booleans, complex numbers, strings
    (``"2"``) and other objects are refused, not coerced.
    """
    rng = f"finite numbers in [{lo:g}, {hi:g}]{unit}"
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError, OverflowError):  # ragged nesting, broken __array__
        raise ConfigError(f"{name}: got {short_repr(value)}, expected an array of {rng}") from None
    if raw.dtype.kind == "O":  # Python ints beyond int64, or a mix of objects
        if not all(_is_real(x) for x in raw.reshape(-1).tolist()):
            raise ConfigError(f"{name}: got {short_repr(value)}, expected an array of {rng}")
        try:
            raw = np.array([float(x) for x in raw.reshape(-1).tolist()]).reshape(raw.shape)
        except OverflowError:
            raise ConfigError(f"{name}: got {short_repr(value)}, expected an array of {rng}") from None
    elif raw.dtype.kind not in "fiu":
        raise ConfigError(f"{name}: got {short_repr(value)} (dtype {raw.dtype}), expected an array of {rng}")
    arr = np.array(raw, dtype=np.float64)
    if arr.size and not (np.isfinite(arr).all() and arr.min() >= lo and arr.max() <= hi):
        raise ConfigError(f"{name}: got {short_repr(value)}, expected an array of {rng}")
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
    """Raise :class:`~aasoatt_env.errors.UnknownKeywordError` (a ``TypeError``) naming unknown keywords.

    The keywords of ``given`` that are not in ``known`` are named, and the known ones listed.

    The wording is Python's own (``f() got an unexpected keyword argument 'x'``):
    some clients (TorchRL's ``GymEnv``) probe constructors and match on it.
    """
    known_set = set(known)
    unknown = sorted(str(k) for k in given if k not in known_set)
    if unknown:
        clauses = ", ".join(f"got an unexpected keyword argument {k!r}" for k in unknown)
        raise UnknownKeywordError(f"{owner}() {clauses}; expected keywords among {sorted(known_set)}")


def parse_value(text: str) -> Any:
    """A command-line ``KEY=VALUE`` value: JSON when it parses (numbers, true/false, lists), else the string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
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


def mapping(name: str, value: Any) -> Mapping[str, Any]:
    """Return ``value`` if it is a mapping with string keys, else raise."""
    if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
        raise ConfigError(f"{name}: got {type(value).__name__}, expected a mapping of option names to values")
    return value
