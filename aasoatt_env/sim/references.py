"""Reference trajectories ``p_d(t), v_d(t), a_d(t)`` for a team (SPEC section 2).

Every reference is a callable ``ref(t) -> (p_d, v_d, a_d)`` returning three
``(N, 2)`` arrays, plus ``goals`` (the final reference points, ``(N, 2)``) and
``duration`` (time after which the reference rests at the goals).

==========================  ===============================================
class                       use
==========================  ===============================================
:class:`LinearReference`    straight lines start -> goal over ``duration``
                            (constant speed, or a smooth minimum-jerk profile)
:class:`WaypointReference`  piecewise-linear paths through timed waypoints
:class:`FunctionReference`  any user callable ``t -> p_d`` (and optionally
                            ``v_d``, ``a_d``; central differences otherwise)
==========================  ===============================================
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, Protocol

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError

__all__ = [
    "FunctionReference",
    "LinearReference",
    "Reference",
    "WaypointReference",
    "as_reference",
]

RefTriple = tuple[np.ndarray, np.ndarray, np.ndarray]


class Reference(Protocol):
    """What the environment needs from a reference."""

    goals: np.ndarray
    duration: float

    def __call__(self, t: float) -> RefTriple:
        """Return ``(p_d, v_d, a_d)``, each ``(N, 2)``, at time ``t``."""
        ...


COORD_MAX: float = 1e6
"""Largest coordinate [m] of a reference point, start, waypoint or obstacle."""


def _points(name: str, value: np.ndarray | list, n: int | None = None) -> np.ndarray:
    arr = check.real_array(name, value, lo=-COORD_MAX, hi=COORD_MAX, unit=" m")
    if arr.ndim != 2 or arr.shape[1] != 2 or (n is not None and arr.shape[0] != n):
        expected = f"({n}, 2)" if n is not None else "(N, 2)"
        raise ConfigError(f"{name}: got shape {arr.shape}, expected {expected}")
    return arr


class LinearReference:
    """Straight lines from ``starts`` to ``goals`` travelled in ``duration`` seconds.

    Parameters
    ----------
    starts, goals : array_like, shape (N, 2)
        Start and goal points of each robot's controlled point.
    duration : float
        Travel time [s]; the reference rests at ``goals`` afterwards.
    profile : {"linear", "smooth"}
        ``"linear"``: constant velocity ``(goal - start) / duration`` (the
        paper's linear-in-time reference; the velocity jumps to 0 at the end).
        ``"smooth"``: minimum-jerk timing ``s = 10 tau^3 - 15 tau^4 + 6 tau^5``
        (zero velocity and acceleration at both ends).
    """

    def __init__(
        self,
        starts: np.ndarray,
        goals: np.ndarray,
        duration: float,
        profile: Literal["linear", "smooth"] = "linear",
    ) -> None:
        self.starts = _points("starts", starts)
        self.goals = _points("goals", goals, self.starts.shape[0])
        self.duration = check.positive("duration", duration, hi=1e6)
        if profile not in ("linear", "smooth"):
            raise ConfigError(f"profile: got {profile!r}, expected 'linear' or 'smooth'")
        self.profile = profile
        self._delta = self.goals - self.starts
        self._zeros = np.zeros_like(self.starts)

    def __call__(self, t: float) -> RefTriple:
        """Return ``(p_d, v_d, a_d)`` at time ``t``."""
        T = self.duration
        if t >= T:
            return self.goals.copy(), self._zeros.copy(), self._zeros.copy()
        tau = max(t, 0.0) / T
        if self.profile == "linear":
            return self.starts + tau * self._delta, self._delta / T, self._zeros.copy()
        s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)
        ds = 30.0 * tau * tau * (1.0 - tau) ** 2 / T
        dds = 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau) / (T * T)
        return self.starts + s * self._delta, ds * self._delta, dds * self._delta


class WaypointReference:
    """Piecewise-linear paths through waypoints reached at given times.

    Parameters
    ----------
    waypoints : array_like, shape (N, K, 2) or (K, 2)
        ``K >= 2`` waypoints per robot (a ``(K, 2)`` array is one robot).
    times : array_like, shape (K,)
        Strictly increasing arrival times, ``times[0]`` usually 0.
    """

    def __init__(self, waypoints: np.ndarray, times: np.ndarray) -> None:
        wp = check.real_array("waypoints", waypoints, lo=-COORD_MAX, hi=COORD_MAX, unit=" m")
        ts = check.real_array("times", times, lo=0.0, hi=1e6, unit=" s")
        if wp.ndim == 2:
            wp = wp[None]
        if wp.ndim != 3 or wp.shape[2] != 2 or wp.shape[1] < 2:
            raise ConfigError(f"waypoints: got shape {np.shape(waypoints)}, expected (N, K, 2) with K >= 2")
        if ts.shape != (wp.shape[1],) or np.any(np.diff(ts) <= 0):
            raise ConfigError(
                f"times: got {check.short_repr(ts.tolist())}, expected {wp.shape[1]} strictly increasing times "
                "(one per waypoint)"
            )
        self.waypoints, self.times = wp, ts
        self.goals = wp[:, -1].copy()
        self.duration = float(ts[-1])
        self._vel = np.diff(wp, axis=1) / np.diff(ts)[None, :, None]

    def __call__(self, t: float) -> RefTriple:
        """Return ``(p_d, v_d, a_d)`` at time ``t``."""
        zeros = np.zeros_like(self.goals)
        if t >= self.times[-1]:
            return self.goals.copy(), zeros, zeros.copy()
        if t <= self.times[0]:
            return self.waypoints[:, 0].copy(), self._vel[:, 0].copy(), zeros
        k = int(np.searchsorted(self.times, t, side="right")) - 1
        v = self._vel[:, k]
        return self.waypoints[:, k] + (t - self.times[k]) * v, v.copy(), zeros


class FunctionReference:
    """A reference from user callables.

    Parameters
    ----------
    position : callable
        ``position(t) -> (N, 2)`` array.
    velocity, acceleration : callable, optional
        Their derivatives; when omitted, central differences with step ``h``.
    duration : float
        Time after which the reference is considered finished (used for the
        episode horizon); ``goals`` is ``position(duration)``.
    h : float
        Finite-difference step [s].
    """

    def __init__(
        self,
        position: Callable[[float], np.ndarray],
        duration: float,
        velocity: Callable[[float], np.ndarray] | None = None,
        acceleration: Callable[[float], np.ndarray] | None = None,
        h: float = 1e-4,
    ) -> None:
        if not callable(position):
            raise ConfigError(f"position: got {type(position).__name__}, expected a callable t -> (N, 2)")
        self._p, self._v, self._a = position, velocity, acceleration
        self.duration = check.positive("duration", duration, hi=1e6)
        self.h = check.positive("h", h, hi=1.0)
        self.goals = _points("position(duration)", position(self.duration))

    def __call__(self, t: float) -> RefTriple:
        """Return ``(p_d, v_d, a_d)`` at time ``t``."""
        n = self.goals.shape[0]
        p = _points("position(t)", self._p(t), n)
        h = self.h
        if self._v is not None:
            v = _points("velocity(t)", self._v(t), n)
        else:
            v = (np.asarray(self._p(t + h)) - np.asarray(self._p(t - h))) / (2 * h)
        if self._a is not None:
            a = _points("acceleration(t)", self._a(t), n)
        elif self._v is not None:
            a = (np.asarray(self._v(t + h)) - np.asarray(self._v(t - h))) / (2 * h)
        else:
            a = (np.asarray(self._p(t + h)) - 2 * p + np.asarray(self._p(t - h))) / (h * h)
        return p, v, a


def as_reference(value: object, n: int, duration: float | None = None) -> Reference:
    """Coerce a user-supplied reference (object, callable or waypoints) to a :class:`Reference`."""
    if hasattr(value, "goals") and hasattr(value, "duration") and callable(value):
        ref = value  # already a reference
    elif callable(value):
        if duration is None:
            raise ConfigError("reference: a callable reference needs duration=..., got None")
        ref = FunctionReference(value, duration)  # type: ignore[arg-type]
    elif isinstance(value, dict) and "waypoints" in value:
        if "times" not in value:
            raise ConfigError(
                "reference: got waypoints without 'times', expected {'waypoints': (N, K, 2), 'times': (K,)}"
            )
        ref = WaypointReference(value["waypoints"], value["times"])
    else:
        raise ConfigError(
            f"reference: got {type(value).__name__}, expected a Reference, a callable t -> (N, 2) "
            "or a dict with 'waypoints' and 'times'"
        )
    goals = np.asarray(ref.goals)  # type: ignore[union-attr]
    if goals.shape != (n, 2):
        raise ConfigError(f"reference: goals have shape {goals.shape}, expected ({n}, 2) for {n} robots")
    return ref  # type: ignore[return-value]
