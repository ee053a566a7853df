"""What the safety filter accepts: its team and every array of a step, checked before any compiled part reads them.

:class:`~aasoatt_env.safety.core.SafetyFilter` calls :func:`check_team` when it is
given a team and :func:`check_inputs` on every step; errors name the argument,
the robot (or obstacle) and what was expected.  The compiled kernels read
without bounds checks, so these checks are also what keeps them in bounds.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.errors import ConfigError, StateError
from aasoatt_env.model.dynamics import Kinematics
from aasoatt_env.model.params import Team
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.validation import MAGNITUDE_MAX

__all__ = ["MIN_BRAKING_ROOM", "check_inputs", "check_team", "refuse_rows_beyond"]

_F64 = np.dtype(np.float64)

MIN_BRAKING_ROOM: float = 0.1
"""With the backup layer, the sensing range must exceed the largest safety distance by this much [m]:
every robot's braking path must fit in half of the difference (:func:`~aasoatt_env.safety.backup.reach_limit`)."""


def refuse_rows_beyond(name: str, a: np.ndarray, what: str) -> None:
    """Raise :class:`StateError` naming the first row of ``a`` ``(K, ...)`` with NaN, inf or ``|x| > MAGNITUDE_MAX``."""
    bad = np.flatnonzero(~(np.abs(a) <= MAGNITUDE_MAX).reshape(a.shape[0], -1).all(axis=1))
    if bad.size:
        row = a[bad[0]]
        kind = f"a value beyond +-{MAGNITUDE_MAX:g}" if np.isfinite(row).all() else "a non-finite value"
        raise StateError(f"{name}: got {kind} {np.atleast_1d(row).tolist()} for {what}(s) {bad[:10].tolist()} "
                         f"({what} index {bad[0]}), expected finite values within +-{MAGNITUDE_MAX:g}")


def check_team(team: Team, config: FilterConfig) -> None:
    """One value per robot in every parameter array; a sensing range that covers contact and room to brake.

    The braking room (:data:`MIN_BRAKING_ROOM`) only with the backup layer.
    """
    for name in ("radius", "wheel_radius", "half_track", "offset", "max_wheel_accel", "max_wheel_speed",
                 "max_point_accel"):  # (a Team built directly: the compiled parts read them without bounds checks)
        a = getattr(team, name)
        if not (isinstance(a, np.ndarray) and a.shape == (team.n,) and a.dtype.kind == "f"):
            raise ConfigError(f"team.{name}: got {type(a).__name__} of shape {np.shape(a)}, expected a float "
                              f"array of shape ({team.n},) (one value per robot; make_team builds it)")
    if team.group is not None and (np.shape(team.group) != (team.n,)
                                   or np.asarray(team.group).dtype.kind not in "iu"):
        raise ConfigError(f"team.group: got {np.asarray(team.group).dtype} array of shape "
                          f"{np.shape(team.group)}, expected integers of shape ({team.n},)")
    ds_max = 2.0 * float(team.radius.max(initial=0.0))
    need = ds_max + (MIN_BRAKING_ROOM if config.backup else 0.0)
    if not config.sensing_range > need:
        raise ConfigError(
            f"sensing_range: got {config.sensing_range:g} m, expected > {need:g} m for robots of radius up "
            f"to {ds_max / 2:g} m (safety distance {ds_max:g} m"
            + (f" plus {MIN_BRAKING_ROOM:g} m for the backup layer's braking paths)" if config.backup else ")")
        )


def check_inputs(
    n: int, kin: Kinematics, u: np.ndarray, theta: np.ndarray, nominal_du: np.ndarray,
    lo: np.ndarray, hi: np.ndarray, reference: Any = None, obstacles: Any = None, *, compiled: bool = False,
) -> tuple[Kinematics, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, Any, Any]:
    """Shapes, finiteness and magnitudes (``<= MAGNITUDE_MAX``) of every state array of ``n`` robots.

    Errors name the robot.

    Returns the state, the nominal, the bounds, the reference and the obstacles' centres and radii as
    float64 arrays.

    One pass over all the numbers (a concatenation and one ``max |x|``) when
    they are fine; the culprit is looked for only when they are not.  With
    ``compiled`` (the filter's kernels), a step whose arrays are already float64 of
    the right shapes, without obstacles, has its numbers tested by one compiled
    call (:mod:`~aasoatt_env.safety.inputs_kernel`); any other input, or numbers
    that fail, take the path above (the same errors).
    """
    if compiled and obstacles is None:
        fast = _fast_path(n, kin, u, theta, nominal_du, lo, hi, reference)
        if fast is not None:
            return fast
    nominal_du = np.asarray(nominal_du, dtype=np.float64)
    if nominal_du.shape != (n, 2):
        raise StateError(f"nominal_du: got shape {nominal_du.shape}, expected ({n}, 2)")
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    if lo.shape != (n, 2) or hi.shape != (n, 2):
        raise StateError(f"lo/hi: got shapes {lo.shape}/{hi.shape}, expected ({n}, 2)")
    arrays = [("nominal_du", nominal_du, (n, 2)), ("lo", lo, (n, 2)), ("hi", hi, (n, 2)), ("u", u, (n, 2)),
              ("theta", theta, (n,)), ("kin.p", kin.p, (n, 2)), ("kin.v", kin.v, (n, 2)),
              ("kin.A", kin.A, (n, 2, 2)), ("kin.adot_u", kin.adot_u, (n, 2))]
    if reference is not None:
        # (p_d, v_d), or (p_d, v_d, a_d) as a reference returns it; each (N, 2) or flat (2N,)
        try:
            ok = len(reference) in (2, 3)
        except TypeError:
            ok = False
        if not ok:
            raise StateError(f"reference: got {type(reference).__name__}, expected (p_d, v_d) or (p_d, v_d, a_d) "
                             f"of ({n}, 2) arrays")
        reference = tuple(np.asarray(reference[k], dtype=np.float64) for k in (0, 1))
        reference = tuple(r.reshape(n, 2) if r.shape in ((2 * n,), (1, 2 * n)) else r for r in reference)
        arrays += [("reference p_d", reference[0], (n, 2)), ("reference v_d", reference[1], (n, 2))]
    if obstacles is not None:
        if not isinstance(obstacles, (tuple, list)) or len(obstacles) not in (2, 3):
            raise StateError(f"obstacles: got {type(obstacles).__name__}, expected (centres (M, 2), radii (M,)) "
                             "or (centres, radii, groups (M,))")
        radii = np.asarray(obstacles[1], dtype=np.float64)
        m = radii.shape[0] if radii.ndim == 1 else -1
        if m < 0:
            raise StateError(f"obstacles radii: got shape {radii.shape}, expected (M,)")
        centres = np.asarray(obstacles[0], dtype=np.float64)
        if m == 0 and centres.size == 0:
            centres = centres.reshape(0, 2)
        arrays += [("obstacles centres", centres, (m, 2)), ("obstacles radii", radii, (m,))]
        groups = obstacles[2] if len(obstacles) > 2 else None
        if groups is not None:
            groups = np.asarray(groups)
            if groups.shape != (m,) or (m and (groups.dtype.kind not in "biuf" or not np.isfinite(groups).all())):
                raise StateError(f"obstacles groups: got {groups.dtype} array of shape {groups.shape}, "
                                 f"expected finite group labels of shape ({m},)")
        obstacles = (centres, radii) if len(obstacles) == 2 else (centres, radii, groups)
    flat = []
    for name, arr, shape in arrays:
        a = np.asarray(arr)
        if a.shape != shape:
            raise StateError(f"{name}: got shape {a.shape}, expected {shape}")
        flat.append(a.ravel())
    allv = np.concatenate(flat)
    # (the largest |x| as the larger of -min and max: no temporary; a NaN propagates to both)
    big = max(-float(allv.min()), float(allv.max())) if allv.size else 0.0
    if not big <= MAGNITUDE_MAX:  # NaN, inf or beyond the magnitude every input is checked against
        for name, arr, shape in arrays:
            a = np.asarray(arr, dtype=np.float64).reshape(shape[0], -1) if shape[0] else np.zeros((0, 1))
            refuse_rows_beyond(name, a, "obstacle" if name.startswith("obstacles") else "robot")
    if (lo > hi).any():
        raise StateError("lo/hi: bounds must be finite with lo <= hi")
    if obstacles is not None and radii.size and not bool((radii >= 0.0).all()):
        k = int(np.flatnonzero(~(radii >= 0.0))[0])
        raise StateError(f"obstacles radii: got {float(radii[k])!r} for obstacle {k}, expected a radius >= 0")
    # the state in float64 (as every other input): float32 or integer arrays give every path the same numbers
    fields = (kin.p, kin.v, kin.A, kin.adot_u)
    if not all(type(a) is np.ndarray and a.dtype == np.float64 for a in fields):
        kin = Kinematics(*(np.asarray(a, dtype=np.float64) for a in fields))
    u, theta = np.asarray(u, dtype=np.float64), np.asarray(theta, dtype=np.float64)
    return kin, u, theta, nominal_du, lo, hi, reference, obstacles


def _fast_path(n: int, kin: Kinematics, u: Any, theta: Any, nominal_du: Any, lo: Any, hi: Any,
               reference: Any) -> tuple | None:
    """:func:`check_inputs`' answer by the compiled test, or None where the numpy check must decide.

    Parameters
    ----------
    n, kin, u, theta, nominal_du, lo, hi, reference
        :func:`check_inputs`' arguments (no obstacles).

    Returns
    -------
    tuple or None
        :func:`check_inputs`' return (the caller's own arrays) where every array is a float64
        ``numpy.ndarray`` of its shape, the reference a tuple or list of ``(N, 2)`` arrays (or
        None) and the numbers pass; None otherwise (any other form, or a number that fails).
        The kernel gets the arrays as :func:`~aasoatt_env.compiled.c64` gives them (a copy of a
        read-only or strided one): one compiled specialisation whatever the caller's layouts.
    """
    if reference is not None:
        if type(reference) not in (tuple, list) or len(reference) not in (2, 3):
            return None
        p_d, v_d = reference[0], reference[1]
    else:
        p_d, v_d = kin.p, kin.v  # (checked twice: no reference to check)
    pair = (n, 2)
    for a in (nominal_du, lo, hi, u, kin.p, kin.v, kin.adot_u, p_d, v_d):
        if not (type(a) is np.ndarray and a.dtype == _F64 and a.shape == pair):
            return None
    A = kin.A
    if not (type(theta) is np.ndarray and theta.dtype == _F64 and theta.shape == (n,)
            and type(A) is np.ndarray and A.dtype == _F64 and A.shape == (n, 2, 2)):
        return None
    if not kernels("inputs").numbers_ok(MAGNITUDE_MAX, *(c64(a) for a in (nominal_du, lo, hi, u, theta, kin.p, kin.v,
                                                                          A, kin.adot_u, p_d, v_d))):
        return None
    return kin, u, theta, nominal_du, lo, hi, (None if reference is None else (p_d, v_d)), None


