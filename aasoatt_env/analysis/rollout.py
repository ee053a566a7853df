"""Recorded episodes: the :class:`Rollout` container and its incremental :class:`RolloutBuilder`.

A :class:`Rollout` holds the per-step arrays of one episode (``T`` recorded steps,
``N`` robots, ``M`` static obstacles) in the form :mod:`aasoatt_env.analysis.metrics`
consumes.  Shapes are validated once, in ``__post_init__``, and every array is
stored as a fresh ``numpy`` array with a fixed dtype (``float64``, ``bool`` or
``str``), so downstream code never has to re-check them.

=========================  ==========  ==================================================
field                      shape       meaning
=========================  ==========  ==================================================
``dt``                     scalar      time between two recorded steps [s]
``times``                  ``(T,)``    time stamp of each recorded step [s]
``positions``              ``(T,N,2)`` control points ``p_i``
``velocities``             ``(T,N,2)`` control-point velocities ``dp_i``
``headings``               ``(T,N)``   headings ``theta_i`` [rad]
``references``             ``(T,N,2)`` reference points ``p_d_i``
``reference_velocities``   ``(T,N,2)`` reference velocities ``v_d_i``
``goals``                  ``(N,2)``   final goals
``radii``                  ``(N,)``    robot disc radii
``obstacle_centers``       ``(M,2)``   static obstacle centres (``M`` may be 0)
``obstacle_radii``         ``(M,)``    static obstacle radii
``nominal_actions``        ``(T,N,2)`` optional: nominal (unfiltered) actions
``actions``                ``(T,N,2)`` optional: applied (filtered) actions
``avoiding``               ``(T,N)``   optional, bool: robot in collision avoidance
``triggered``              ``(T,N)``   optional, bool: deadlock rule active
``backup``                 ``(T,N)``   optional, bool: braked by the backup layer
``solver_status``          ``(T,)``    optional, str: QP status of each step
``slack``                  ``(T,)``    optional: total relaxation of the step's rows
``solve_time``             ``(T,)``    optional: QP wall time of the step [s]
``metadata``               dict        JSON-serialisable: scenario, method, parameters
=========================  ==========  ==================================================

:meth:`Rollout.save` writes a single ``.npz`` file (the metadata as a JSON
string, strings as fixed-width unicode, so loading never needs pickle) and
:meth:`Rollout.load` reads it back.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from aasoatt_env.errors import ConfigError, DataFileError

__all__ = ["Rollout", "RolloutBuilder"]

#: Version tag written into saved files.
FORMAT_VERSION = 1

# (name, shape template, dtype kind); "T", "N", "M" are the symbolic sizes.
_PER_STEP: tuple[tuple[str, tuple[str | int, ...], str], ...] = (
    ("positions", ("T", "N", 2), "f"),
    ("velocities", ("T", "N", 2), "f"),
    ("headings", ("T", "N"), "f"),
    ("references", ("T", "N", 2), "f"),
    ("reference_velocities", ("T", "N", 2), "f"),
)
_STATIC: tuple[tuple[str, tuple[str | int, ...], str], ...] = (
    ("goals", ("N", 2), "f"),
    ("radii", ("N",), "f"),
    ("obstacle_centers", ("M", 2), "f"),
    ("obstacle_radii", ("M",), "f"),
)
_OPTIONAL: tuple[tuple[str, tuple[str | int, ...], str], ...] = (
    ("nominal_actions", ("T", "N", 2), "f"),
    ("actions", ("T", "N", 2), "f"),
    ("avoiding", ("T", "N"), "b"),
    ("triggered", ("T", "N"), "b"),
    ("backup", ("T", "N"), "b"),
    ("solver_status", ("T",), "U"),
    ("slack", ("T",), "f"),
    ("solve_time", ("T",), "f"),
)


def _fmt_shape(shape: tuple[str | int, ...]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def _as_array(name: str, value: Any, kind: str) -> np.ndarray:
    """Convert ``value`` to a fresh array of the dtype ``kind`` ('f', 'b' or 'U')."""
    try:
        if kind == "f":
            raw = np.asarray(value)
            if raw.dtype.kind in "cSUV":  # no silent loss of an imaginary part, no parsing of strings
                raise ConfigError(f"{name}: got dtype {raw.dtype}, expected real numbers")
            arr = np.array(raw, dtype=np.float64)
        elif kind == "b":
            arr = np.array(value)
            if arr.dtype != np.bool_:
                if arr.size and not np.isin(arr, (0, 1)).all():
                    raise ConfigError(f"{name}: got non-boolean values, expected bool (or 0/1) entries")
                arr = arr.astype(np.bool_)
        else:
            arr = np.array(value, dtype=np.str_)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        dtype = {"f": "float", "b": "bool", "U": "str"}[kind]
        raise ConfigError(f"{name}: cannot be converted to a {dtype} array ({exc})") from None
    return arr


def _check_shape(name: str, arr: np.ndarray, template: tuple[str | int, ...], sizes: dict[str, int]) -> None:
    """Check ``arr.shape`` against ``template``; bind unknown symbols into ``sizes``."""
    expected = _fmt_shape(template)
    bound = _fmt_shape(tuple(sizes.get(s, s) if isinstance(s, str) else s for s in template))
    if arr.ndim != len(template):
        raise ConfigError(
            f"{name}: got shape {arr.shape}, expected {expected} = {bound} ({len(template)} dimensions)"
        )
    for dim, sym in zip(arr.shape, template):
        if isinstance(sym, int):
            ok = dim == sym
        elif sym in sizes:
            ok = dim == sizes[sym]
        else:
            sizes[sym] = dim
            ok = True
        if not ok:
            bound = _fmt_shape(tuple(sizes.get(s, s) if isinstance(s, str) else s for s in template))
            raise ConfigError(f"{name}: got shape {arr.shape}, expected {expected} = {bound}")


@dataclass
class Rollout:
    """One recorded episode of ``T`` steps, ``N`` robots and ``M`` static obstacles.

    See the module docstring for the field table.  All arrays are copied and
    converted on construction; a :class:`~aasoatt_env.errors.ConfigError` names
    the first field whose shape or value is wrong and the shape it should have.

    Parameters
    ----------
    dt : float
        Time between two recorded steps [s] (positive).
    times : array_like, shape (T,)
        Time stamps [s], non-decreasing.
    positions, velocities, references, reference_velocities : array_like, shape (T, N, 2)
        Control points, their velocities, reference points ``p_d`` and reference velocities.
    headings : array_like, shape (T, N)
        Headings [rad].
    goals : array_like, shape (N, 2)
        Final goal of each robot.
    radii : array_like, shape (N,)
        Disc radius of each robot (positive).
    obstacle_centers : array_like, shape (M, 2), optional
        Static obstacle centres; default: no obstacles.
    obstacle_radii : array_like, shape (M,), optional
        Static obstacle radii (positive).
    nominal_actions, actions : array_like, shape (T, N, 2), optional
        Nominal and applied (filtered) actions.
    avoiding, triggered, backup : array_like of bool, shape (T, N), optional
        Robot in collision avoidance; deadlock-resolution rule active.
    solver_status : array_like of str, shape (T,), optional
        QP status string of each step.
    slack, solve_time : array_like, shape (T,), optional
        Total relaxation of the step's constraint rows; solver wall time [s].
    metadata : dict, optional
        JSON-serialisable description (scenario, method, parameters).
    """

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

    ARRAY_FIELDS: ClassVar[tuple[str, ...]] = tuple(
        name for name, _, _ in (("times", ("T",), "f"), *_PER_STEP, *_STATIC, *_OPTIONAL)
    )
    OPTIONAL_FIELDS: ClassVar[tuple[str, ...]] = tuple(name for name, _, _ in _OPTIONAL)
    PER_STEP_FIELDS: ClassVar[tuple[str, ...]] = ("times",) + tuple(
        name for name, template, _ in (*_PER_STEP, *_OPTIONAL) if template[0] == "T"
    )
    """Fields with one entry per recorded step (cut by :meth:`window`)."""

    def __post_init__(self) -> None:
        if isinstance(self.dt, (str, bytes, np.str_, np.bytes_, bool, np.bool_)):
            raise ConfigError(f"dt: got {self.dt!r}, expected a finite positive number")
        try:
            dt = float(self.dt)
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"dt: got {self.dt!r}, expected a finite positive number") from None
        if not math.isfinite(dt) or dt <= 0:
            raise ConfigError(f"dt: got {self.dt!r}, expected a finite positive number")
        self.dt = dt

        sizes: dict[str, int] = {}
        times = _as_array("times", self.times, "f")
        _check_shape("times", times, ("T",), sizes)
        if sizes["T"] < 1:
            raise ConfigError("times: got shape (0,), expected at least one recorded step")
        if not np.isfinite(times).all():
            raise ConfigError("times: got non-finite values, expected finite time stamps")
        if np.any(np.diff(times) < 0):
            raise ConfigError("times: got decreasing time stamps, expected non-decreasing")
        self.times = times

        if self.obstacle_centers is None:
            self.obstacle_centers = np.zeros((0, 2))
        if self.obstacle_radii is None:
            self.obstacle_radii = np.zeros(0)

        for name, template, kind in (*_PER_STEP, *_STATIC, *_OPTIONAL):
            value = getattr(self, name)
            if value is None:
                continue
            arr = _as_array(name, value, kind)
            _check_shape(name, arr, template, sizes)
            if kind == "f" and not np.isfinite(arr).all():
                bad = np.argwhere(~np.isfinite(arr))[0].tolist()
                raise ConfigError(f"{name}: got a non-finite value at index {bad}, expected finite numbers")
            setattr(self, name, arr)

        if not np.all(self.radii > 0):
            raise ConfigError(f"radii: got {self.radii.tolist()}, expected positive radii")
        if not np.all(self.obstacle_radii > 0):
            raise ConfigError(f"obstacle_radii: got {self.obstacle_radii.tolist()}, expected positive radii")

        if self.metadata is None:
            self.metadata = {}
        if not isinstance(self.metadata, dict):
            raise ConfigError(f"metadata: got {type(self.metadata).__name__}, expected a dict")
        try:
            json.dumps(self.metadata)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"metadata: not JSON-serialisable ({exc})") from None

    # ------------------------------------------------------------------ sizes
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
        """Time between the first and the last recorded step [s]."""
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

    # ------------------------------------------------------------------- I/O
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the rollout to a compressed ``.npz`` file.

        Optional fields that are ``None`` are left out; ``metadata`` is stored as
        a JSON string.  NumPy appends ``.npz`` to ``path`` if it lacks it.

        Parameters
        ----------
        path : str or path-like
            Destination file.
        """
        arrays: dict[str, np.ndarray] = {
            "format_version": np.array(FORMAT_VERSION),
            "dt": np.array(self.dt),
            "metadata": np.array(json.dumps(self.metadata)),
        }
        for name in self.ARRAY_FIELDS:
            value = getattr(self, name)
            if value is not None:
                arrays[name] = value
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Rollout:
        """Read a rollout written by :meth:`save`.

        Parameters
        ----------
        path : str or path-like
            A ``.npz`` file.

        Returns
        -------
        Rollout
            The validated rollout.

        Raises
        ------
        DataFileError
            Naming the file: it is missing, not a readable ``.npz`` (truncated,
            corrupted, empty), or a field is missing, of the wrong shape or not finite.
        """
        name = str(path)
        if not os.path.isfile(path):
            raise DataFileError(f"{name}: no such rollout file")
        try:
            with np.load(path, allow_pickle=False) as data:
                files = set(data.files)
                version = int(data["format_version"]) if "format_version" in files else FORMAT_VERSION
                if version > FORMAT_VERSION:
                    raise DataFileError(f"{name}: format_version {version}, expected <= {FORMAT_VERSION}")
                kwargs: dict[str, Any] = {}
                for field_name in ("dt", *cls.ARRAY_FIELDS):
                    if field_name in files:
                        kwargs[field_name] = data[field_name]
                    elif field_name not in cls.OPTIONAL_FIELDS and field_name not in ("obstacle_centers",
                                                                                     "obstacle_radii"):
                        raise DataFileError(f"{name}: missing field {field_name!r}; not a rollout file")
                kwargs["dt"] = kwargs["dt"][()]  # a 0-d array; Rollout checks it is a finite positive number
                kwargs["metadata"] = json.loads(str(data["metadata"])) if "metadata" in files else {}
        except DataFileError:
            raise
        except MemoryError:  # a crafted header can claim any shape
            raise DataFileError(f"{name}: an array in this file is too large to load; not a rollout file") from None
        except (OSError, ValueError, EOFError, KeyError, TypeError, zipfile.BadZipFile, zlib.error, NotImplementedError,
                RecursionError) as exc:
            # corrupted zip/deflate data, an unsupported zip feature, JSON nested beyond the recursion limit
            if isinstance(exc, ValueError) and "allow_pickle" in str(exc):  # numpy's advice: load it unsafely. Never
                raise DataFileError(f"{name}: not a readable rollout file (not an .npz archive of plain "
                                    "arrays; files are never unpickled)") from None
            raise DataFileError(f"{name}: not a readable rollout file ({type(exc).__name__}: "
                                f"{str(exc)[:200]})") from None
        try:
            return cls(**kwargs)
        except ConfigError as exc:
            raise DataFileError(f"{name}: invalid rollout ({exc})") from None


class RolloutBuilder:
    """Accumulate an episode step by step, then :meth:`build` a :class:`Rollout`.

    Each :meth:`append` copies its arrays into per-field lists (so callers may
    reuse their buffers); :meth:`build` stacks them once.  An optional field must
    be given at every step or at none.

    Parameters
    ----------
    dt : float
        Time between recorded steps [s].
    goals, radii, obstacle_centers, obstacle_radii : array_like, optional
        Static fields; may also be passed (or overridden) in :meth:`build`.
    metadata : dict, optional
        JSON-serialisable metadata; :meth:`build` merges its own on top.

    Examples
    --------
    >>> b = RolloutBuilder(dt=0.1, goals=[[1.0, 0.0]], radii=[0.5])
    >>> for k in range(3):
    ...     b.append(time=0.1 * k, positions=[[0.1 * k, 0.0]], velocities=[[1.0, 0.0]],
    ...              headings=[0.0], references=[[0.1 * k, 0.0]], reference_velocities=[[1.0, 0.0]])
    >>> b.build().positions.shape
    (3, 1, 2)
    """

    _STEP_FIELDS: ClassVar[tuple[str, ...]] = (
        "times",
        *(n for n, _, _ in _PER_STEP),
        *(n for n, _, _ in _OPTIONAL),
    )
    _REQUIRED_STEP: ClassVar[frozenset[str]] = frozenset(("times", *(n for n, _, _ in _PER_STEP)))

    def __init__(
        self,
        dt: float,
        *,
        goals: Any = None,
        radii: Any = None,
        obstacle_centers: Any = None,
        obstacle_radii: Any = None,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        self.dt = dt
        self.static: dict[str, Any] = {
            "goals": goals,
            "radii": radii,
            "obstacle_centers": obstacle_centers,
            "obstacle_radii": obstacle_radii,
        }
        self.metadata: dict[str, Any] = dict(metadata or {})
        self._data: dict[str, list[Any]] = {name: [] for name in self._STEP_FIELDS}
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(
        self,
        *,
        time: float,
        positions: Any,
        velocities: Any,
        headings: Any,
        references: Any,
        reference_velocities: Any,
        **optional: Any,
    ) -> None:
        """Record one step.

        Parameters
        ----------
        time : float
            Time stamp of the step [s].
        positions, velocities, references, reference_velocities : array_like, shape (N, 2)
            Per-robot values at this step.
        headings : array_like, shape (N,)
            Per-robot headings.
        **optional
            Any of ``nominal_actions``, ``actions`` (``(N, 2)``), ``avoiding``,
            ``triggered``, ``backup`` (``(N,)`` bool), ``solver_status`` (str), ``slack``,
            ``solve_time`` (float).  ``None`` values are ignored.

        Raises
        ------
        ConfigError
            On an unknown keyword, or an optional field given at some steps only.
        """
        unknown = set(optional) - set(Rollout.OPTIONAL_FIELDS)
        if unknown:
            raise ConfigError(
                f"append: unknown field(s) {sorted(unknown)}, "
                f"expected some of {list(Rollout.OPTIONAL_FIELDS)}"
            )
        given = {k for k, v in optional.items() if v is not None}
        for name in Rollout.OPTIONAL_FIELDS:
            have = len(self._data[name])
            if self._n > 0 and (name in given) != (have == self._n):
                raise ConfigError(
                    f"{name}: given at {have} of the {self._n} previous steps "
                    f"and {'' if name in given else 'not '}at step {self._n}; "
                    "expected at every step or at none"
                )
        self._data["times"].append(float(time))
        self._data["positions"].append(np.array(positions, dtype=np.float64))
        self._data["velocities"].append(np.array(velocities, dtype=np.float64))
        self._data["headings"].append(np.array(headings, dtype=np.float64))
        self._data["references"].append(np.array(references, dtype=np.float64))
        self._data["reference_velocities"].append(np.array(reference_velocities, dtype=np.float64))
        for name in given:
            value = optional[name]
            if name == "solver_status":
                self._data[name].append(str(value))
            elif name in ("slack", "solve_time"):
                self._data[name].append(float(value))
            elif name in ("avoiding", "triggered", "backup"):
                self._data[name].append(np.array(value, dtype=np.bool_))
            else:
                self._data[name].append(np.array(value, dtype=np.float64))
        self._n += 1

    def build(self, **overrides: Any) -> Rollout:
        """Stack the recorded steps into a validated :class:`Rollout`.

        Parameters
        ----------
        **overrides
            ``goals``, ``radii``, ``obstacle_centers``, ``obstacle_radii`` or
            ``dt`` replace the constructor's values; ``metadata`` is merged into
            the constructor's metadata.

        Returns
        -------
        Rollout

        Raises
        ------
        ConfigError
            If nothing was recorded, a static field is missing, the per-step arrays
            have inconsistent shapes, or an override is unknown.
        """
        allowed = {"dt", "metadata", *self.static}
        unknown = set(overrides) - allowed
        if unknown:
            raise ConfigError(
                f"build: unknown argument(s) {sorted(unknown)}, expected some of {sorted(allowed)}"
            )
        if self._n == 0:
            raise ConfigError("build: no step recorded, expected at least one append()")
        static = {**self.static, **{k: v for k, v in overrides.items() if k in self.static}}
        for name in ("goals", "radii"):
            if static[name] is None:
                raise ConfigError(f"{name}: missing, pass it to RolloutBuilder(...) or build(...)")
        metadata = {**self.metadata, **(overrides.get("metadata") or {})}
        kwargs: dict[str, Any] = {"dt": overrides.get("dt", self.dt), "metadata": metadata, **static}
        for name in self._STEP_FIELDS:
            values = self._data[name]
            if not values:
                continue
            if name in ("times", "solver_status", "slack", "solve_time"):
                kwargs[name] = values
                continue
            try:
                kwargs[name] = np.stack(values)
            except ValueError:
                shapes = sorted({np.shape(v) for v in values})
                raise ConfigError(f"{name}: per-step shapes differ {shapes}, expected one shape") from None
        return Rollout(**kwargs)
