"""Reference trajectories ``ref(t) -> (p_d, v_d, a_d)`` ``(N, 2)``, at rest on ``goals`` after ``duration`` [s]."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal, Protocol

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError, ScenarioError

__all__ = ["FunctionReference", "LinearReference", "Reference", "ReferenceStack", "WaypointReference", "as_reference"]

RefTriple = tuple[np.ndarray, np.ndarray, np.ndarray]


class Reference(Protocol):
    """What the environment needs from a reference (module docstring)."""

    goals: np.ndarray
    duration: float

    def __call__(self, t: float) -> RefTriple:
        """Return ``(p_d, v_d, a_d)``, each ``(N, 2)``, at time ``t``."""


COORD_MAX: float = 1e6
"""Largest coordinate [m] of a reference point, start, waypoint or obstacle."""


def _points(name: str, value: np.ndarray | list, n: int | None = None) -> np.ndarray:
    arr = check.real_array(name, value, lo=-COORD_MAX, hi=COORD_MAX, unit=" m")
    if arr.ndim != 2 or arr.shape[1] != 2 or (n is not None and arr.shape[0] != n):
        expected = f"({n}, 2)" if n is not None else "(N, 2)"
        raise ConfigError(f"{name}: got shape {arr.shape}, expected {expected}")
    return arr


class LinearReference:
    """Straight lines from ``starts`` to ``goals`` ``(N, 2)`` in ``duration`` [s] (one, or one per robot).

    ``profile``: ``"linear"`` (the paper's constant velocity) or ``"smooth"`` (minimum jerk, at rest at both ends).
    """

    def __init__(self, starts: np.ndarray, goals: np.ndarray, duration: float | np.ndarray,
                 profile: Literal["linear", "smooth"] = "linear") -> None:
        self.starts = _points("starts", starts)
        n = self.starts.shape[0]
        self.goals = _points("goals", goals, n)
        if np.ndim(duration) == 0:
            self.durations = np.full(n, check.positive("duration", duration, hi=1e6))
        else:
            d = check.real_array("duration", duration, lo=0.0, hi=1e6, unit=" s")
            if d.shape != (n,) or not np.all(d > 0):
                raise ConfigError(f"duration: got shape {d.shape} with min {d.min(initial=np.nan):g}, expected "
                                  f"a positive float or ({n},) positive travel times [s]")
            self.durations = d.copy()
        self.duration = float(self.durations.max(initial=0.0))
        if profile not in ("linear", "smooth"):
            raise ConfigError(f"profile: got {profile!r}, expected 'linear' or 'smooth'")
        self.profile = profile
        self._delta = self.goals - self.starts

    def __call__(self, t: float) -> RefTriple:
        """Return ``(p_d, v_d, a_d)`` at time ``t``."""
        return _linear(self.starts, self.goals, self._delta, self.durations, float(t), self.profile)


def _linear(starts: np.ndarray, goals: np.ndarray, delta: np.ndarray, T: np.ndarray, t: float | np.ndarray,
            profile: str) -> RefTriple:
    """:class:`LinearReference` robot by robot: time ``t`` (one, or one per robot) and durations ``T`` ``(N,)``."""
    done = (t >= T)[:, None]
    tau = (np.maximum(t, 0.0) / T)[:, None]
    if profile == "linear":
        v = np.where(done, 0.0, delta / T[:, None])
        return np.where(done, goals, starts + tau * delta), v, np.zeros(starts.shape)
    s = tau * tau * tau * (10.0 - 15.0 * tau + 6.0 * tau * tau)
    ds = 30.0 * tau * tau * (1.0 - tau) ** 2 / T[:, None]
    dds = 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau) / (T * T)[:, None]
    return np.where(done, goals, starts + s * delta), np.where(done, 0.0, ds * delta), np.where(done, 0.0, dds * delta)


class ReferenceStack:
    """Several teams' references at each team's own time: ``ref(t)`` of each, concatenated, element for element."""

    def __init__(self, refs: Sequence[Reference]) -> None:
        self.refs = list(refs)
        self._sizes = np.array([np.asarray(r.goals).shape[0] for r in self.refs], dtype=np.intp)
        profiles = {getattr(r, "profile", None) for r in self.refs}
        self._linear = bool(self.refs) and all(type(r) is LinearReference for r in self.refs) and len(profiles) == 1
        if self._linear:
            lin: list[LinearReference] = self.refs  # type: ignore[assignment]
            self._starts, self._goals, self._delta, self._T = (np.concatenate([getattr(r, a) for r in lin])
                                                               for a in ("starts", "goals", "_delta", "durations"))
            self._profile = profiles.pop()

    def __call__(self, times: Sequence[float]) -> RefTriple:
        """``(p_d, v_d, a_d)`` of the whole stack, each ``(sum N, 2)``; ``times[k]`` is team ``k``'s time."""
        if len(times) != len(self.refs):
            raise ConfigError(f"times: got {len(times)} times, expected one per team ({len(self.refs)})")
        if self._linear:
            t = float(times[0]) if len(self.refs) == 1 else np.repeat(np.asarray(times, dtype=np.float64), self._sizes)
            return _linear(self._starts, self._goals, self._delta, self._T, t, self._profile)
        parts = [self._checked(k, float(t)) for k, t in enumerate(times)]
        if len(parts) == 1:
            return parts[0]
        return tuple(np.concatenate([q[i] for q in parts]) for i in range(3))  # type: ignore[return-value]

    def _checked(self, k: int, t: float) -> RefTriple:
        """Team ``k``'s reference at ``t`` as new float64 arrays, refused unless finite and ``(N, 2)``."""
        ref, n = self.refs[k], int(self._sizes[k])
        out = tuple(np.array(x, dtype=np.float64) for x in ref(t))
        team = f" of team {k}" if len(self.refs) > 1 else ""
        for name, x in zip(("p_d", "v_d", "a_d"), out):
            what = f"reference ({type(ref).__name__}) {name} at t = {t:g} s"
            if x.shape != (n, 2):
                raise ScenarioError(f"{what}{team}: got shape {x.shape}, expected ({n}, 2)")
            if not np.isfinite(x).all():
                i = int(np.flatnonzero(~np.isfinite(x).all(axis=1))[0])
                raise ScenarioError(f"{what}: got a non-finite value {x[i].tolist()} for robot {i}{team}, expected "
                                    "finite values (a reference must be defined at every time of the episode)")
        return out  # type: ignore[return-value]


class WaypointReference:
    """Piecewise-linear paths through ``K >= 2`` waypoints ``(N, K, 2)`` (or ``(K, 2)``) at rising ``times (K,)``."""

    def __init__(self, waypoints: np.ndarray, times: np.ndarray) -> None:
        wp = check.real_array("waypoints", waypoints, lo=-COORD_MAX, hi=COORD_MAX, unit=" m")
        ts = check.real_array("times", times, lo=0.0, hi=1e6, unit=" s")
        if wp.ndim == 2:
            wp = wp[None]
        if wp.ndim != 3 or wp.shape[2] != 2 or wp.shape[1] < 2:
            raise ConfigError(f"waypoints: got shape {np.shape(waypoints)}, expected (N, K, 2) with K >= 2")
        if ts.shape != (wp.shape[1],) or np.any(np.diff(ts) <= 0):
            raise ConfigError(f"times: got {check.short_repr(ts.tolist())}, expected {wp.shape[1]} strictly increasing "
                              "times (one per waypoint)")
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
    """A reference from ``position(t) -> (N, 2)``, finished at ``duration`` [s] (``goals = position(duration)``).

    Without ``velocity``/``acceleration`` callables: central differences with step ``h`` [s].
    """

    def __init__(self, position: Callable[[float], np.ndarray], duration: float,
                 velocity: Callable[[float], np.ndarray] | None = None,
                 acceleration: Callable[[float], np.ndarray] | None = None, h: float = 1e-4) -> None:
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
            raise ConfigError("reference: got waypoints without 'times', expected "
                              "{'waypoints': (N, K, 2), 'times': (K,)}")
        ref = WaypointReference(value["waypoints"], value["times"])
    else:
        raise ConfigError(f"reference: got {type(value).__name__}, expected a Reference, a callable t -> (N, 2) "
                          "or a dict with 'waypoints' and 'times'")
    goals = np.asarray(ref.goals)  # type: ignore[union-attr]
    if goals.shape != (n, 2):
        raise ConfigError(f"reference: goals have shape {goals.shape}, expected ({n}, 2) for {n} robots")
    return ref  # type: ignore[return-value]
