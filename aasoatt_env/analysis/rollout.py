"""Recorded episodes: the :class:`Rollout` container and its incremental :class:`RolloutBuilder`.

Shapes are checked once on construction (``_PER_STEP``, ``_STATIC``, ``_OPTIONAL`` below), so the metrics never
check them again; a rollout is saved as one ``.npz`` that :meth:`Rollout.load` reads without pickle.
"""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.cli_support import atomic_write
from aasoatt_env.errors import ConfigError, DataFileError

__all__ = ["Rollout", "RolloutBuilder", "checked_array"]

FORMAT_VERSION = 1  # written into saved files
Template = tuple[str | int, ...]  # a shape; its strings are sizes bound by the first array that has them
_KINDS: dict[str, type] = {"f": np.float64, "b": np.bool_, "U": np.str_}  # the dtype kinds of the fields below

# (name, shape, dtype kind: "f" float, "b" bool, "U" str); control points p_i, velocities dp_i, references p_d_i,
# v_d_i, headings [rad]; optional: nominal and applied actions, flags (in collision avoidance, deadlock rule
# active, braked by the backup layer), solver status, total slack, solve time [s].
_PER_STEP: tuple[tuple[str, Template, str], ...] = (
    ("positions", ("T", "N", 2), "f"), ("velocities", ("T", "N", 2), "f"), ("headings", ("T", "N"), "f"),
    ("references", ("T", "N", 2), "f"), ("reference_velocities", ("T", "N", 2), "f"))
_STATIC: tuple[tuple[str, Template, str], ...] = (
    ("goals", ("N", 2), "f"), ("radii", ("N",), "f"), ("obstacle_centers", ("M", 2), "f"),
    ("obstacle_radii", ("M",), "f"))
_OPTIONAL: tuple[tuple[str, Template, str], ...] = (
    ("nominal_actions", ("T", "N", 2), "f"), ("actions", ("T", "N", 2), "f"), ("avoiding", ("T", "N"), "b"),
    ("triggered", ("T", "N"), "b"), ("backup", ("T", "N"), "b"), ("solver_status", ("T",), "U"),
    ("slack", ("T",), "f"), ("solve_time", ("T",), "f"))


def _fmt_shape(template: Template, sizes: dict[str, int] | None = None) -> str:
    dims = [str(sizes.get(s, s) if sizes is not None and isinstance(s, str) else s) for s in template]
    return "(" + ", ".join(dims) + ("," if len(dims) == 1 else "") + ")"


def checked_array(name: str, value: Any, template: Template, sizes: dict[str, int], kind: str = "f", *,
                  finite: bool = True) -> np.ndarray:
    """``value`` as a fresh array of dtype ``kind`` and shape ``template`` (bound into ``sizes``), finite floats.

    ``kind``: ``"f"`` real numbers (no strings, no complex), ``"b"`` bool (or 0/1), ``"U"`` str.
    """
    try:
        raw = np.asarray(value)
        if kind == "f" and raw.dtype.kind in "cSUV":
            raise ConfigError(f"{name}: got dtype {raw.dtype}, expected real numbers")
        if kind == "b" and raw.dtype != np.bool_ and raw.size and not np.isin(raw, (0, 1)).all():
            raise ConfigError(f"{name}: got non-boolean values, expected bool (or 0/1) entries")
        arr = np.array(value if kind == "U" else raw, dtype=_KINDS[kind])
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{name}: cannot be converted to a {np.dtype(_KINDS[kind]).name} array ({exc})") from None
    if not (arr.ndim == len(template) and all(dim == (sym if isinstance(sym, int) else sizes.setdefault(sym, dim))
                                              for dim, sym in zip(arr.shape, template))):
        extra = f" ({len(template)} dimensions)" if arr.ndim != len(template) else ""
        raise ConfigError(f"{name}: got shape {arr.shape}, expected {_fmt_shape(template)} = "
                          f"{_fmt_shape(template, sizes)}{extra}")
    if kind == "f" and finite and not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise ConfigError(f"{name}: got a non-finite value at index {bad}, expected finite numbers")
    return arr


@dataclass
class Rollout:
    """One recorded episode (fields: ``_PER_STEP``, ``_STATIC``, ``_OPTIONAL``), its arrays copied and checked."""

    dt: float
    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    headings: np.ndarray
    references: np.ndarray
    reference_velocities: np.ndarray
    goals: np.ndarray
    radii: np.ndarray
    obstacle_centers: np.ndarray | None = None
    obstacle_radii: np.ndarray | None = None
    nominal_actions: np.ndarray | None = None
    actions: np.ndarray | None = None
    avoiding: np.ndarray | None = None
    triggered: np.ndarray | None = None
    backup: np.ndarray | None = None
    solver_status: np.ndarray | None = None
    slack: np.ndarray | None = None
    solve_time: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    ARRAY_FIELDS: ClassVar[tuple[str, ...]] = ("times", *(n for n, _, _ in (*_PER_STEP, *_STATIC, *_OPTIONAL)))
    OPTIONAL_FIELDS: ClassVar[tuple[str, ...]] = tuple(n for n, _, _ in _OPTIONAL)
    PER_STEP_FIELDS: ClassVar[tuple[str, ...]] = ("times", *(n for n, t, _ in (*_PER_STEP, *_OPTIONAL) if t[0] == "T"))
    """Fields with one entry per recorded step (cut by :meth:`window`)."""

    def __post_init__(self) -> None:
        self.dt = check.positive("dt", self.dt)
        sizes: dict[str, int] = {}
        self.times = checked_array("times", self.times, ("T",), sizes)
        if sizes["T"] < 1:
            raise ConfigError("times: got shape (0,), expected at least one recorded step")
        if np.any(np.diff(self.times) < 0):
            raise ConfigError("times: got decreasing time stamps, expected non-decreasing")
        self.obstacle_centers = np.zeros((0, 2)) if self.obstacle_centers is None else self.obstacle_centers
        self.obstacle_radii = np.zeros(0) if self.obstacle_radii is None else self.obstacle_radii
        for name, template, kind in (*_PER_STEP, *_STATIC, *_OPTIONAL):
            if getattr(self, name) is not None:
                setattr(self, name, checked_array(name, getattr(self, name), template, sizes, kind))
        for name in ("radii", "obstacle_radii"):
            if not np.all(getattr(self, name) > 0):
                raise ConfigError(f"{name}: got {getattr(self, name).tolist()}, expected positive radii")
        self.metadata = {} if self.metadata is None else self.metadata
        if not isinstance(self.metadata, dict):
            raise ConfigError(f"metadata: got {type(self.metadata).__name__}, expected a dict")
        try:
            json.dumps(self.metadata)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"metadata: not JSON-serialisable ({exc})") from None

    @property
    def n_steps(self) -> int:
        """Number of recorded steps ``T``."""
        return int(self.times.shape[0])

    @property
    def n_robots(self) -> int:
        """Number of robots ``N``."""
        return int(self.positions.shape[1])

    @property
    def n_obstacles(self) -> int:
        """Number of static obstacles ``M``."""
        return int(self.obstacle_centers.shape[0])

    @property
    def duration(self) -> float:
        """Time from first to last step [s]."""
        return float(self.times[-1] - self.times[0])

    def window(self, t_end: float | None) -> Rollout:
        """The part recorded at times ``<= t_end`` (the rollout itself if None or if it ends earlier)."""
        if t_end is None:
            return self
        k = int(np.searchsorted(self.times, t_end + 1e-9, side="right"))
        if k >= self.n_steps:
            return self
        cut = {name: getattr(self, name)[:k] for name in self.PER_STEP_FIELDS if getattr(self, name) is not None}
        return dataclasses.replace(self, **cut)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the rollout to a compressed ``.npz`` file, atomically (``.npz`` is appended if missing)."""
        arrays = {"format_version": np.array(FORMAT_VERSION), "dt": np.array(self.dt),
                  "metadata": np.array(json.dumps(self.metadata))}
        arrays.update({n: getattr(self, n) for n in self.ARRAY_FIELDS if getattr(self, n) is not None})
        target = os.fspath(path)
        atomic_write(target if target.endswith(".npz") else target + ".npz",
                     lambda tmp: np.savez_compressed(tmp, **arrays))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Rollout:
        """Read a rollout written by :meth:`save`; a missing, unreadable, pickled or invalid file: DataFileError."""
        name = str(path)
        if not os.path.isfile(path):
            raise DataFileError(f"{name}: no such rollout file")
        try:
            with np.load(path, allow_pickle=False) as data:
                files = set(data.files)
                version = int(data["format_version"]) if "format_version" in files else FORMAT_VERSION
                if version > FORMAT_VERSION:
                    raise DataFileError(f"{name}: format_version {version}, expected <= {FORMAT_VERSION}")
                optional = {*Rollout.OPTIONAL_FIELDS, "obstacle_centers", "obstacle_radii"}
                missing = [f for f in ("dt", *Rollout.ARRAY_FIELDS) if f not in files and f not in optional]
                if missing:
                    raise DataFileError(f"{name}: missing field {missing[0]!r}; not a rollout file")
                kwargs: dict[str, Any] = {f: data[f] for f in ("dt", *Rollout.ARRAY_FIELDS) if f in files}
                kwargs["dt"] = kwargs["dt"][()]  # a 0-d array; Rollout checks it is a finite positive number
                kwargs["metadata"] = json.loads(str(data["metadata"])) if "metadata" in files else {}
        except DataFileError:
            raise
        except MemoryError:  # a crafted header can claim any shape
            raise DataFileError(f"{name}: an array in this file is too large to load; not a rollout file") from None
        except (OSError, ValueError, EOFError, KeyError, TypeError, zipfile.BadZipFile, zlib.error, NotImplementedError,
                RecursionError) as exc:  # corrupted zip or deflate data, JSON nested beyond the recursion limit
            if isinstance(exc, ValueError) and "allow_pickle" in str(exc):  # numpy's advice to unpickle: never
                raise DataFileError(f"{name}: not a readable rollout file (not an .npz archive of plain "
                                    "arrays; files are never unpickled)") from None
            raise DataFileError(f"{name}: not a readable rollout file ({type(exc).__name__}: "
                                f"{str(exc)[:200]})") from None
        try:
            return cls(**kwargs)
        except ConfigError as exc:
            raise DataFileError(f"{name}: invalid rollout ({exc})") from None


class RolloutBuilder:
    """Accumulate an episode step by step (arrays copied; optional fields at every step or none), then build it."""

    _DTYPES: ClassVar[dict[str, type]] = {"times": np.float64, **{n: _KINDS[k] for n, _, k in (*_PER_STEP, *_OPTIONAL)}}

    def __init__(self, dt: float, *, goals: Any = None, radii: Any = None, obstacle_centers: Any = None,
                 obstacle_radii: Any = None, metadata: dict[str, Any] | None = None) -> None:
        self.dt = dt
        self.static: dict[str, Any] = {"goals": goals, "radii": radii, "obstacle_centers": obstacle_centers,
                                       "obstacle_radii": obstacle_radii}
        self.metadata: dict[str, Any] = dict(metadata or {})
        self._data: dict[str, list[np.ndarray]] = {name: [] for name in self._DTYPES}
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, *, time: float, positions: Any, velocities: Any, headings: Any, references: Any,
               reference_velocities: Any, **optional: Any) -> None:
        """Record one step: per-robot arrays ``(N, 2)`` (``headings`` ``(N,)``) and optional fields (None: absent)."""
        unknown = set(optional) - set(Rollout.OPTIONAL_FIELDS)
        if unknown:
            raise ConfigError(f"append: unknown field(s) {sorted(unknown)}, expected some of "
                              f"{list(Rollout.OPTIONAL_FIELDS)}")
        given = {k: v for k, v in optional.items() if v is not None}
        for name in Rollout.OPTIONAL_FIELDS:
            have = len(self._data[name])
            if self._n > 0 and (name in given) != (have == self._n):
                raise ConfigError(f"{name}: given at {have} of the {self._n} previous steps and "
                                  f"{'' if name in given else 'not '}at step {self._n}; expected at every step or "
                                  "at none")
        given.update(times=time, positions=positions, velocities=velocities, headings=headings, references=references,
                     reference_velocities=reference_velocities)
        for name, value in given.items():
            self._data[name].append(np.array(value, dtype=self._DTYPES[name]))
        self._n += 1

    def build(self, **overrides: Any) -> Rollout:
        """Stack the recorded steps into a :class:`Rollout` (``overrides``: ``dt``, static fields, more metadata)."""
        allowed = {"dt", "metadata", *self.static}
        unknown = set(overrides) - allowed
        if unknown:
            raise ConfigError(f"build: unknown argument(s) {sorted(unknown)}, expected some of {sorted(allowed)}")
        if self._n == 0:
            raise ConfigError("build: no step recorded, expected at least one append()")
        static = {**self.static, **{k: v for k, v in overrides.items() if k in self.static}}
        for name in ("goals", "radii"):
            if static[name] is None:
                raise ConfigError(f"{name}: missing, pass it to RolloutBuilder(...) or build(...)")
        metadata = {**self.metadata, **(overrides.get("metadata") or {})}
        kwargs: dict[str, Any] = {"dt": overrides.get("dt", self.dt), "metadata": metadata, **static}
        for name, values in self._data.items():
            if values:
                try:
                    kwargs[name] = np.stack(values)
                except ValueError:
                    shapes = sorted({np.shape(v) for v in values})
                    raise ConfigError(f"{name}: per-step shapes differ {shapes}, expected one shape") from None
        return Rollout(**kwargs)
