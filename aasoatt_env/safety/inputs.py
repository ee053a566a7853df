"""What the safety filter accepts: its team, and every array of a step (the first stage of the pipeline).

Errors name the argument, the robot (or obstacle) and what was expected.  The compiled stages
read without bounds checks, so these checks also keep them in bounds.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aasoatt_env.compiled import kernels
from aasoatt_env.errors import ConfigError, StateError
from aasoatt_env.model.dynamics import Kinematics, speed_box
from aasoatt_env.model.params import Team
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.stages import StepInput
from aasoatt_env.validation import MAGNITUDE_MAX

__all__ = ["MIN_BRAKING_ROOM", "NOMINAL_RANGE", "bound_nominal", "check_step", "check_team", "refuse_rows_beyond"]

MIN_BRAKING_ROOM: float = 0.1
"""With the backup layer the sensing range must exceed the largest safety distance by this much [m]:
every robot's braking path must fit in half the difference (:func:`~aasoatt_env.safety.backup.reach_limit`)."""


NOMINAL_RANGE: float = 100.0
"""A nominal farther than this many times the robot's wheel-acceleration bound from the centre of its box is
pulled in radially to that distance before the QP (:func:`bound_nominal`)."""


def bound_nominal(nominal: np.ndarray, lo: np.ndarray, hi: np.ndarray, scale: np.ndarray,
                  max_wheel_accel: np.ndarray) -> np.ndarray:
    """The nominal the QP is given: pulled radially to at most ``NOMINAL_RANGE * max_wheel_accel`` from the box.

    The same array where no robot's nominal is that far from its box's centre: those answers are the QP's
    for the nominal itself, bit for bit.  A farther nominal keeps its direction and is scaled back, so the
    solvers work on a well-scaled problem (a target of 1e6 defeats any tolerance at the rows' scale); the
    answer then differs from the unscaled QP's by about the box's size over ``NOMINAL_RANGE`` at most (the
    farther the nominal, the closer both come to the feasible set's support point in its direction).
    """
    if nominal.size == 0 or (1.5 * (float(np.abs(nominal).max()) + float(scale.max()))
                             <= NOMINAL_RANGE * float(max_wheel_accel.min())):
        return nominal  # (|nominal - centre| <= |nominal| + |centre| <= sqrt(2) (max|nominal| + max scale))
    reach = NOMINAL_RANGE * max_wheel_accel
    centre = 0.5 * (lo + hi)
    d = nominal - centre
    dist = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    far = dist > reach * (1.0 + 1e-12)  # (a pulled-in nominal stays as it is: the projection is idempotent)
    if not far.any():
        return nominal
    return np.where(far[:, None], centre + d * (reach / np.where(far, dist, 1.0))[:, None], nominal)


def refuse_rows_beyond(name: str, a: np.ndarray, what: str) -> None:
    """Raise :class:`StateError` naming the first row of ``a`` ``(K, ...)`` with NaN, inf or ``|x| > MAGNITUDE_MAX``."""
    bad = np.flatnonzero(~(np.abs(a) <= MAGNITUDE_MAX).reshape(a.shape[0], -1).all(axis=1))
    if bad.size:
        row = a[bad[0]]
        kind = f"a value beyond +-{MAGNITUDE_MAX:g}" if np.isfinite(row).all() else "a non-finite value"
        raise StateError(f"{name}: got {kind} {np.atleast_1d(row).tolist()} for {what}(s) {bad[:10].tolist()} "
                         f"({what} index {bad[0]}), expected finite values within +-{MAGNITUDE_MAX:g}")


def check_team(team: Team, config: FilterConfig) -> None:
    """One float per robot in every parameter array; a sensing range that covers contact and (backup) braking room."""
    for name in ("radius", "wheel_radius", "half_track", "offset", "max_wheel_accel", "max_wheel_speed",
                 "max_point_accel"):
        a = getattr(team, name)
        if not (isinstance(a, np.ndarray) and a.shape == (team.n,) and a.dtype.kind == "f"):
            raise ConfigError(f"team.{name}: got {type(a).__name__} of shape {np.shape(a)}, expected a float "
                              f"array of shape ({team.n},) (one value per robot; make_team builds it)")
    if not bool((team.max_wheel_accel > 0.0).all() and np.isfinite(team.max_wheel_accel).all()):
        k = int(np.flatnonzero(~((team.max_wheel_accel > 0.0) & np.isfinite(team.max_wheel_accel)))[0])
        raise ConfigError(f"team.max_wheel_accel: got {float(team.max_wheel_accel[k])!r} for robot {k}, expected a "
                          "finite bound > 0")
    if team.group is not None and (np.shape(team.group) != (team.n,)
                                   or np.asarray(team.group).dtype.kind not in "iu"):
        raise ConfigError(f"team.group: got {np.asarray(team.group).dtype} array of shape "
                          f"{np.shape(team.group)}, expected integers of shape ({team.n},)")
    ds_max = 2.0 * float(team.radius.max(initial=0.0))
    need = ds_max + (MIN_BRAKING_ROOM if config.backup else 0.0)
    if not config.sensing_range > need:
        raise ConfigError(f"sensing_range: got {config.sensing_range:g} m, expected > {need:g} m for robots of "
                          f"radius up to {ds_max / 2:g} m (safety distance {ds_max:g} m"
                          + (f" plus {MIN_BRAKING_ROOM:g} m for the backup layer's braking paths)" if config.backup
                             else ")"))


def _reference(reference: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(p_d, v_d)`` of ``(p_d, v_d)`` or ``(p_d, v_d, a_d)``, each ``(N, 2)`` or flat ``(2N,)``."""
    try:
        ok = len(reference) in (2, 3)
    except TypeError:
        ok = False
    if not ok:
        raise StateError(f"reference: got {type(reference).__name__}, expected (p_d, v_d) or (p_d, v_d, a_d) of "
                         f"({n}, 2) arrays")
    p_d, v_d = np.asarray(reference[0], dtype=np.float64), np.asarray(reference[1], dtype=np.float64)
    if p_d.shape != (n, 2) and p_d.shape in ((2 * n,), (1, 2 * n)):
        p_d = p_d.reshape(n, 2)
    if v_d.shape != (n, 2) and v_d.shape in ((2 * n,), (1, 2 * n)):
        v_d = v_d.reshape(n, 2)
    return p_d, v_d


def _obstacles(obstacles: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(centres (M, 2), radii (M,), groups (M,) or None)`` as float64 arrays (their numbers checked later)."""
    if not isinstance(obstacles, (tuple, list)) or len(obstacles) not in (2, 3):
        raise StateError(f"obstacles: got {type(obstacles).__name__}, expected (centres (M, 2), radii (M,)) "
                         "or (centres, radii, groups (M,))")
    radii = np.asarray(obstacles[1], dtype=np.float64)
    if radii.ndim != 1:
        raise StateError(f"obstacles radii: got shape {radii.shape}, expected (M,)")
    m = radii.shape[0]
    centres = np.asarray(obstacles[0], dtype=np.float64)
    if m == 0 and centres.size == 0:
        centres = centres.reshape(0, 2)
    if centres.shape != (m, 2):
        raise StateError(f"obstacles centres: got shape {centres.shape}, expected ({m}, 2)")
    groups = obstacles[2] if len(obstacles) > 2 else None
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (m,) or (m and (groups.dtype.kind not in "biuf" or not np.isfinite(groups).all())):
            raise StateError(f"obstacles groups: got {groups.dtype} array of shape {groups.shape}, expected finite "
                             f"group labels of shape ({m},)")
    return np.ascontiguousarray(centres), np.ascontiguousarray(radii), groups


_NAMES = ("nominal_du", "lo", "hi", "u", "theta", "kin.p", "kin.v", "kin.A", "kin.adot_u", "reference p_d",
          "reference v_d", "obstacles centres", "obstacles radii")


def check_step(team: Team, cfg: FilterConfig, kin: Kinematics, u: Any, theta: Any, nominal_du: Any, lo: Any,
               hi: Any, reference: Any = None, obstacles: Any = None) -> StepInput:
    """One step's inputs as float64 arrays of the team's shapes, every number finite within ``MAGNITUDE_MAX``.

    The arrays given where they are C-contiguous, writeable float64, copies otherwise (one array type for the
    kernels).  The bounds are tightened by ``cfg.max_wheel_speed`` where set.  Errors name the array and the robot.
    """
    n = team.n
    pair = (n, 2)
    given = [nominal_du, lo, hi, u, theta, kin.p, kin.v, kin.A, kin.adot_u]
    shapes = [pair, pair, pair, pair, (n,), pair, pair, (n, 2, 2), pair]
    if reference is not None:
        given += _reference(reference, n)
        shapes += [pair, pair]
    if obstacles is not None:
        obstacles = _obstacles(obstacles)
        given += obstacles[:2]
        shapes += [obstacles[0].shape, obstacles[1].shape]
    arrays = [a if type(a) is np.ndarray and a.dtype is _F64 and a.flags.c_contiguous and a.flags.writeable
              else np.array(a, dtype=np.float64, order="C") for a in given]  # (one array type for the kernels)
    if [a.shape for a in arrays] != shapes:
        names = _NAMES if reference is not None else _NAMES[:9] + _NAMES[11:]
        for name, a, shape in zip(names, arrays, shapes):
            if a.shape != shape:
                raise StateError(f"{name}: got shape {a.shape}, expected {shape}")
    nominal, lo, hi, u, theta, p, v, A, adot = arrays[:9]
    ok, scale, near = kernels("inputs").numbers(tuple(arrays), MAGNITUDE_MAX, team.max_wheel_accel, NOMINAL_RANGE) \
        if cfg.compiled else (False, None, False)
    if not ok:  # the numpy reference: raises where a number is refused
        _check_numbers(arrays, _NAMES if reference is not None else _NAMES[:9] + _NAMES[11:])
    if obstacles is not None and not bool((obstacles[1] >= 0.0).all()):
        k = int(np.flatnonzero(~(obstacles[1] >= 0.0))[0])
        raise StateError(f"obstacles radii: got {float(obstacles[1][k])!r} for obstacle {k}, expected a radius >= 0")
    if scale is None or cfg.max_wheel_speed is not None:
        if cfg.max_wheel_speed is not None:
            lo, hi = speed_box(lo, hi, u, cfg.max_wheel_speed, cfg.dt)
        scale = np.maximum(team.max_wheel_accel, np.maximum(np.abs(lo), np.abs(hi)).max(axis=1))  # (> 0: check_team)
    return StepInput(team, p, v, A, adot, u, theta, nominal, lo, hi,
                     None if reference is None else (arrays[9], arrays[10]), obstacles, scale, bool(near))


def _check_numbers(arrays: list[np.ndarray], names: tuple[str, ...]) -> None:
    """Raise :class:`StateError` naming the array and row of a number beyond ``MAGNITUDE_MAX``, or ``lo > hi``.

    ``arrays`` start with ``nominal_du, lo, hi``.
    """
    flat = np.concatenate(arrays, axis=None)
    if not max(-float(flat.min()), float(flat.max())) <= MAGNITUDE_MAX:  # (NaN fails too)
        for name, a in zip(names, arrays):
            refuse_rows_beyond(name, a.reshape(a.shape[0], -1) if a.shape[0] else np.zeros((0, 1)),
                               "obstacle" if name.startswith("obstacles") else "robot")
    lo, hi = arrays[1], arrays[2]
    if (lo > hi).any():
        k = int(np.flatnonzero((lo > hi).any(axis=1))[0])
        raise StateError(f"lo/hi: got lo {lo[k].tolist()} > hi {hi[k].tolist()} for robot {k}, expected lo <= hi")


_F64 = np.dtype(np.float64)
