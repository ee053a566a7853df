"""The backup policy, proportional braking, and the robots' braking and candidate paths in closed form.

Backup: ``du = -u / T`` (``-u / dt`` in the last step), ``T = max(s / a, |p_dot| / a_b)``, ``s = max|u_k|``, ``a_b =
brake_fraction * rho * a``: both wheel speeds fall linearly to zero, the control point keeps a fixed circle, and braking
from a braked state continues the same path (time-consistent).  The closed forms equal stepping ``integrate`` with
:func:`braking_du`.  A candidate path: one step holding a candidate input, then the backup.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.model.params import Team

__all__ = ["MAX_BRAKE_STEPS", "Trajectories", "brake_decel", "brake_time", "braking_du", "braking_trajectory",
           "candidate_paths", "candidate_samples_at", "reach_limit"]

_EPS = float(np.finfo(np.float64).eps)

MAX_BRAKE_STEPS: int = 100_000  #: longest braking sampled [steps]; a longer one has unbounded reach (never brake-safe)


def _sinc(x: np.ndarray) -> np.ndarray:
    """``numpy.sinc`` of a float64 array (the same operations, without its dtype dispatch)."""
    y = np.pi * x
    y = np.where(y, y, _EPS)
    return np.sin(y) / y


def _E(x: np.ndarray) -> np.ndarray:
    """``(e^{ix} - 1) / (ix) = e^{ix/2} sinc(x/2)``, stable at 0."""
    return np.exp(0.5j * x) * _sinc(x / (2.0 * np.pi))


def point(team: Team, pose: np.ndarray) -> np.ndarray:
    """Control points ``(N,)`` complex from axle poses ``(N, 3)``."""
    c = pose[:, 0] + 1j * pose[:, 1]
    return c + team.offset * np.exp(1j * pose[:, 2]) if team.is_diff_drive else c


def _velocity(team: Team, theta: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Complex control-point velocity ``(N,)`` and yaw rate ``(N,)``."""
    if not team.is_diff_drive:
        return u[:, 0] + 1j * u[:, 1], np.zeros(u.shape[0])
    cols = team.input_columns
    pdot = np.exp(1j * theta) * (cols[:, 0] * u[:, 0] + cols[:, 1] * u[:, 1])
    return pdot, team.turn_gain * (u[:, 0] - u[:, 1])


def brake_decel(team: Team, brake_fraction: float) -> np.ndarray:
    """The backup's control-point deceleration ``a_b`` per robot ``(N,)`` [m/s^2]."""
    straight = team.max_wheel_accel * team.wheel_radius if team.is_diff_drive else team.max_wheel_accel
    return brake_fraction * straight


def brake_time(team: Team, u: np.ndarray, brake_fraction: float) -> np.ndarray:
    """Braking time ``T = max(s / a, |p_dot| / a_b)`` per robot ``(N,)`` (0 at rest)."""
    s = np.abs(u).max(axis=1)
    if team.is_diff_drive:
        cols = team.input_columns
        speed = np.abs(cols[:, 0] * u[:, 0] + cols[:, 1] * u[:, 1])
    else:
        speed = np.hypot(u[:, 0], u[:, 1])
    return np.maximum(s / team.max_wheel_accel, speed / brake_decel(team, brake_fraction))


def braking_du(team: Team, u: np.ndarray, dt: float, brake_fraction: float) -> np.ndarray:
    """The backup's wheel accelerations ``(N, 2)``: ``-u / T``, or ``-u / dt`` when it stops in this step."""
    T = brake_time(team, u, brake_fraction)
    return -u / np.maximum(T, dt)[:, None]


def reach_limit(team: Team, sensing_range: float) -> np.ndarray:
    """``D / 2 - r_i`` per robot: how far it may get, so that robots out of sensing range stay apart."""
    return 0.5 * float(sensing_range) - team.radius


class Trajectories(NamedTuple):
    """Sampled control-point paths, one sample per physics step."""

    p: np.ndarray  #: ``(N, L)`` complex positions (padded with the rest position)
    delta: np.ndarray  #: ``(N, L-1)`` bounds on each step's deviation from its chord [m]
    length: np.ndarray  #: ``(N,)`` the samples that matter
    reach: np.ndarray  #: ``(N,)`` a bound on the distance from ``p[:, 0]`` [m]


class Brake(NamedTuple):
    """Braking per robot (:func:`brake`); ``rate = dt / T <= 1``, ``bulge``: a point mass's deviation in a step."""

    pdot: np.ndarray
    omega: np.ndarray
    rate: np.ndarray
    steps: np.ndarray
    reach: np.ndarray
    bulge: np.ndarray | None

    def take(self, idx: np.ndarray) -> Brake:
        """The parameters of robots ``idx``."""
        return Brake(*(None if a is None else a[idx] for a in self))


def brake(team: Team, theta: np.ndarray, u: np.ndarray, dt: float, brake_fraction: float,
          T: np.ndarray | None = None) -> Brake:
    """Braking parameters from headings ``theta`` and wheel speeds ``u`` (``T``: their brake time, if known)."""
    pdot, w = _velocity(team, theta, u)
    if T is None:
        T = brake_time(team, u, brake_fraction)
    moving = T > 0
    ratio = np.where(moving, T / dt, 0.0)
    # rate at most 1: stopping within one step (subnormal speeds) has the same samples, and no overflow
    rate = np.where(moving, 1.0 / np.maximum(ratio, 1.0), 1.0)
    steps = np.where(moving, np.clip(np.ceil(ratio - 1e-12), 1.0, MAX_BRAKE_STEPS), 0.0).astype(np.int64)
    speed = np.abs(pdot) * moving
    # arc parameter at rest of the stepped braking: dt (1/2 + (K - 1)(1 - K / (2 r))), r = T / dt, K steps
    K = steps.astype(np.float64)
    tau_end = np.where(moving, dt * (0.5 + (K - 1.0) * (1.0 - K / (2.0 * np.maximum(ratio, 1.0)))), 0.0)
    # the farthest point of the arc from its start: the chord of the swept angle (a diameter past pi)
    aw = np.abs(w)
    past_half = aw * tau_end > np.pi
    tau_env = np.where(past_half, np.pi / np.where(past_half, aw, 1.0), tau_end)
    envelope = speed * tau_env * _sinc(aw * tau_env / (2.0 * np.pi))
    # within a step: a wheeled robot's sagitta; a point mass's parabola, |du| dt^2 / 8 with |du| <= speed / T
    reach = envelope + (dt * dt / 8.0) * speed * aw
    if not team.is_diff_drive:
        bulge = (dt / 8.0) * speed * rate
        reach = reach + bulge
    reach = np.where(ratio > MAX_BRAKE_STEPS, np.inf, reach)
    return Brake(pdot * moving, w, rate, steps, reach, None if team.is_diff_drive else bulge)


def _deviation(b: Brake, lo: np.ndarray, hi: np.ndarray, k: np.ndarray, dt: float) -> np.ndarray:
    """Deviation bounds of braking steps ``k`` whose speed scales run from ``lo`` to ``hi`` (``b`` per row)."""
    s = 0.5 * (lo + hi)  # step-mean speed scale
    delta = (dt * dt / 8.0) * np.abs(b.pdot)[:, None] * (s * s) * np.abs(b.omega)[:, None]
    if b.bulge is not None:  # point masses: the parabola of each braking step (at rest past its horizon)
        delta = delta + np.where((lo > 0.0) & (k < b.steps[:, None]), b.bulge[:, None], 0.0)
    return delta


def brake_samples(p0: np.ndarray, b: Brake, dt: float, L: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``(N, L)`` and deviation bounds ``(N, L-1)`` of braking from ``p0``."""
    k = np.arange(L, dtype=np.float64)
    sigma = np.clip(1.0 - k[None, :] * b.rate[:, None], 0.0, 1.0)
    tau = np.empty_like(sigma)
    tau[:, 0] = 0.0
    np.cumsum(0.5 * dt * (sigma[:, :-1] + sigma[:, 1:]), axis=1, out=tau[:, 1:])
    w = b.omega[:, None]
    p = p0[:, None] + (b.pdot[:, None] * tau) * _E(w * tau)
    return p, _deviation(b, sigma[:, :-1], sigma[:, 1:], k[None, :-1], dt)


def braking_trajectory(team: Team, pose: np.ndarray, u: np.ndarray, dt: float, brake_fraction: float,
                       length: int | None = None) -> Trajectories:
    """Closed-form backup paths of the team's control points: ``p[:, k]`` after ``k`` braking steps."""
    b = brake(team, pose[:, 2], u, dt, brake_fraction)
    L = int(b.steps.max(initial=0)) + 1 if length is None else int(length)
    p, delta = brake_samples(point(team, pose), b, dt, max(L, 1))
    return Trajectories(p, delta, b.steps + 1, b.reach)


class Candidate(NamedTuple):
    """One step holding an input (its end ``p1`` and deviation ``d1``), then the backup ``b1``; ``reach`` of both."""

    p1: np.ndarray
    d1: np.ndarray
    b1: Brake
    reach: np.ndarray


def candidate(team: Team, p0: np.ndarray, theta: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float,
              brake_fraction: float) -> Candidate:
    """One step holding ``du`` from control points ``p0`` (the simulator's step), then braking."""
    u1 = u + du * dt
    pdot_m, w_m = _velocity(team, theta, 0.5 * (u + u1))
    p1 = p0 + pdot_m * dt * _E(w_m * dt)
    dev = (dt * dt / 8.0) * np.abs(pdot_m) * np.abs(w_m)
    if not team.is_diff_drive:
        dev = dev + (dt * dt / 8.0) * np.hypot(du[:, 0], du[:, 1])
    b1 = brake(team, theta + w_m * dt, u1, dt, brake_fraction)
    return Candidate(p1, dev, b1, np.abs(p1 - p0) + dev + b1.reach)


def candidate_samples(p0: np.ndarray, c: Candidate, dt: float, L: int) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``(N, L)`` and deviation bounds ``(N, L-1)`` of candidate paths from ``p0``."""
    p = np.empty((p0.shape[0], L), dtype=np.complex128)
    delta = np.empty((p0.shape[0], L - 1))
    p[:, 0], delta[:, 0] = p0, c.d1
    p[:, 1:], delta[:, 1:] = brake_samples(c.p1, c.b1, dt, L - 1)
    return p, delta


def candidate_paths(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float, brake_fraction: float,
                    length: int | None = None) -> Trajectories:
    """One step with ``du``, then the backup: samples at steps ``0 .. L-1`` (``p[:, 0]`` is the current point)."""
    p0 = point(team, pose)
    c = candidate(team, p0, pose[:, 2], u, du, dt, brake_fraction)
    L = max(int(c.b1.steps.max(initial=0)) + 2 if length is None else int(length), 2)
    p, delta = candidate_samples(p0, c, dt, L)
    return Trajectories(p, delta, c.b1.steps + 2, c.reach)


def candidate_samples_at(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float,
                         brake_fraction: float, s: np.ndarray, rows: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``s`` ``(R, S)`` of :func:`candidate_paths` alone, in closed form: ``(p, delta)``.

    ``s``: 0 now, 1 after the step with ``du``, ``k + 1`` after ``k`` braking steps; ``rows`` ``(R,)``: each row's
    robot (None: one each).
    """
    p0 = point(team, pose)
    c = candidate(team, p0, pose[:, 2], u, du, dt, brake_fraction)
    p1, d1, b = c.p1, c.d1, c.b1
    if rows is not None:
        p0, p1, d1, b = p0[rows], p1[rows], d1[rows], b.take(rows)
    r = b.rate[:, None]
    kf = np.floor(1.0 / r)  # the last braking step with a speed scale >= 0
    k = np.maximum(s - 1, 0).astype(np.float64)
    kc = np.minimum(k, kf)
    tau = dt * (kc - 0.5 * r * kc * kc + np.where(k > kf, 0.5 * np.clip(1.0 - kf * r, 0.0, 1.0), 0.0))
    w = b.omega[:, None]
    p = p1[:, None] + (b.pdot[:, None] * tau) * _E(w * tau)
    p = np.where(s == 0, p0[:, None], p)
    delta = _deviation(b, np.clip(1.0 - k * r, 0.0, 1.0), np.clip(1.0 - (k + 1.0) * r, 0.0, 1.0), k, dt)
    return p, np.where(s == 0, d1[:, None], delta)
