"""The braking backup layer's backup policy: proportional braking, and its paths in closed form.

The paper's barrier rows assume control authority the wheels do not have once a
robot is fast or spinning (the drift ``A_dot u`` grows with the wheel speeds,
the authority is fixed by ``|du| <= a``), so its QP can become infeasible and
then neither the least-violation point nor the nominal is safe.  This layer
checks the QP's answer against a *backup policy* every robot can always
execute, and applies the backup where the answer would leave the set of states
from which the backup keeps every pair apart (a gatekeeper in the sense of
Agrawal and Panagou; a backup-set barrier in the sense of Gurriet et al.).
This module is the backup policy and its paths; the check is
:mod:`aasoatt_env.safety.gatekeeper`.

Backup policy (:func:`braking_du`, :func:`brake_time`)
    Proportional braking in ``T`` seconds: ``du = -u / T`` (``-u / dt`` in the
    last step), so both wheel speeds fall linearly to zero together and their
    ratio, hence the curvature, stays constant: the control point moves on a
    fixed circle (a straight line when ``omega = 0``) while its speed falls
    linearly.  ``T = max(s / a, |p_dot| / a_b)`` with ``s = max|u_k|``: never
    faster than the wheels allow (``|du| <= a``), and the control point never
    decelerates faster than ``a_b = brake_fraction * rho * a`` (double
    integrator: ``brake_fraction * a``), the same for all robots of one kind, so
    a convoy of robots at equal speeds brakes in step and keeps its spacing.
    Both terms scale with the speeds, so after one braking step ``T`` is
    exactly ``T - dt``: the policy is memoryless and *time-consistent* (braking
    from the state reached by braking continues the same trajectory).

Closed form (:func:`braking_trajectory`)
    With the speed scale ``sigma_k = max(0, 1 - k dt / T)`` and the arc
    parameter ``tau_k = dt sum_{m<k} (sigma_m + sigma_{m+1}) / 2`` (the simulator
    moves the pose along the exact arc of the step-mean wheel speeds, so the
    trapezoid is exact), ``p(tau) = p0 + p_dot0 tau E(omega0 tau)`` with
    ``E(x) = (e^{ix} - 1) / (ix)``: the sampled path equals stepping
    :func:`aasoatt_env.model.dynamics.integrate` with :func:`braking_du`.

Candidate paths (:func:`candidate_paths`, :func:`candidate_samples_at`)
    One step with a candidate input, then the backup from there: what the
    gatekeeper checks and the repair nudges.  Everything is vectorised over
    robots.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.model.params import Team

__all__ = [
    "MAX_BRAKE_STEPS",
    "Trajectories",
    "brake_decel",
    "brake_time",
    "braking_du",
    "braking_trajectory",
    "candidate_paths",
    "candidate_samples_at",
    "reach_limit",
]


# --------------------------------------------------------------------------- helpers
_EPS = float(np.finfo(np.float64).eps)

MAX_BRAKE_STEPS: int = 100_000
"""Longest braking the layer samples, in physics steps (500 s at ``dt = 5 ms``); a robot that would need
more (wheel speeds far beyond any robot's) gets an unbounded reach: it is never called brake-safe."""


def _sinc(x: np.ndarray) -> np.ndarray:
    """``numpy.sinc`` of a float64 array, written out (the same operations, without its dtype dispatch)."""
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
    """``D / 2 - r_i`` per robot ``(N,)``: the farthest it may get from where it is along its step and braking path.

    Two robots farther apart than ``D`` (not seen by each other) that both stay
    within their limits of their positions keep ``>= r_i + r_j = d_s`` apart.  The
    limit is the robot's own, not the team's, so a group of robots checked alone
    gets the limits it has in the whole team (for equal radii it is ``(D - d_s) / 2``).
    """
    return 0.5 * float(sensing_range) - team.radius


class Trajectories(NamedTuple):
    """Sampled control-point paths of a team, one sample per physics step.

    Attributes
    ----------
    p : numpy.ndarray
        ``(N, L)`` complex positions at steps ``0 .. L-1`` (padded with the rest position).
    delta : numpy.ndarray
        ``(N, L-1)``: bound on the deviation of the path within step ``k`` from
        the linear-in-time interpolation of ``p[:, k], p[:, k+1]`` [m].
    length : numpy.ndarray
        ``(N,)`` int: samples that matter (``p[:, length-1:]`` is the rest position).
    reach : numpy.ndarray
        ``(N,)``: bound on the distance of the modelled path from ``p[:, 0]`` [m].
    """

    p: np.ndarray
    delta: np.ndarray
    length: np.ndarray
    reach: np.ndarray


class _Brake(NamedTuple):
    pdot: np.ndarray
    omega: np.ndarray
    rate: np.ndarray  # dt / T, at most 1 (1 when at rest or stopping within one step)
    steps: np.ndarray  # steps to stop
    reach: np.ndarray  # envelope of the continuous braking arc + the largest deviation within a step
    bulge: np.ndarray | None  # a point mass's deviation within a braking step from its chord (None: wheeled)


def brake(team: Team, theta: np.ndarray, u: np.ndarray, dt: float, brake_fraction: float,
           T: np.ndarray | None = None) -> _Brake:
    """Closed-form parameters of braking from headings ``theta`` and wheel speeds ``u`` (``T``: their brake_time)."""
    pdot, w = _velocity(team, theta, u)
    if T is None:
        T = brake_time(team, u, brake_fraction)
    moving = T > 0
    ratio = np.where(moving, T / dt, 0.0)
    # at most 1: a robot that stops within one step (T < dt, e.g. subnormal speeds, where 1 / ratio
    # would overflow to inf and the paths to NaN) has the same samples with rate 1 as with dt / T
    rate = np.where(moving, 1.0 / np.maximum(ratio, 1.0), 1.0)
    # a braking too long to sample (MAX_BRAKE_STEPS; e.g. absurd wheel speeds) gets an unbounded reach below
    steps = np.where(moving, np.clip(np.ceil(ratio - 1e-12), 1.0, MAX_BRAKE_STEPS), 0.0).astype(np.int64)
    speed = np.abs(pdot) * moving
    # arc parameter at rest, of the *stepped* braking (the trapezoid of the sampled paths, whose last
    # step stops from sigma > 0 within a whole dt): dt (1/2 + (K - 1)(1 - K / (2 r))), r = T / dt,
    # K = ceil(r) steps; at least the continuous T / 2, more when r is not an integer
    K = steps.astype(np.float64)
    tau_end = np.where(moving, dt * (0.5 + (K - 1.0) * (1.0 - K / (2.0 * np.maximum(ratio, 1.0)))), 0.0)
    # farthest point of the braking arc from its start: the chord of the swept angle (a diameter past pi)
    aw = np.abs(w)
    past_half = aw * tau_end > np.pi
    tau_env = np.where(past_half, np.pi / np.where(past_half, aw, 1.0), tau_end)
    envelope = speed * tau_env * _sinc(aw * tau_env / (2.0 * np.pi))
    # within a braking step a wheeled robot moves on an arc at the step-mean speeds (the simulator's
    # step): it deviates from its chord by the sagitta; a point mass decelerates along a parabola,
    # |du| dt^2 / 8 from its chord, with |du| <= speed / T = speed rate / dt in every braking step
    reach = envelope + (dt * dt / 8.0) * speed * aw
    if not team.is_diff_drive:
        bulge = (dt / 8.0) * speed * rate
        reach = reach + bulge
    reach = np.where(ratio > MAX_BRAKE_STEPS, np.inf, reach)
    return _Brake(pdot * moving, w, rate, steps, reach, None if team.is_diff_drive else bulge)


def brake_samples(p0: np.ndarray, b: _Brake, dt: float, L: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``(N, L)`` and deviation bounds ``(N, L-1)`` (sagitta; a point mass: its parabola) from ``p0``."""
    k = np.arange(L, dtype=np.float64)
    sigma = np.clip(1.0 - k[None, :] * b.rate[:, None], 0.0, 1.0)
    tau = np.empty_like(sigma)
    tau[:, 0] = 0.0
    np.cumsum(0.5 * dt * (sigma[:, :-1] + sigma[:, 1:]), axis=1, out=tau[:, 1:])
    w = b.omega[:, None]
    p = p0[:, None] + (b.pdot[:, None] * tau) * _E(w * tau)
    s = 0.5 * (sigma[:, :-1] + sigma[:, 1:])  # step-mean speed scale
    delta = (dt * dt / 8.0) * np.abs(b.pdot)[:, None] * (s * s) * np.abs(w)
    if b.bulge is not None:  # point masses: the parabola of each braking step (at rest past its horizon)
        delta = delta + np.where((sigma[:, :-1] > 0.0) & (k[None, :-1] < b.steps[:, None]), b.bulge[:, None], 0.0)
    return p, delta


def braking_trajectory(team: Team, pose: np.ndarray, u: np.ndarray, dt: float, brake_fraction: float,
                       length: int | None = None) -> Trajectories:
    """Closed-form backup paths of the team's control points (module docstring).

    ``p[:, k]`` is the control point after ``k`` braking steps; it equals stepping
    :func:`aasoatt_env.model.dynamics.integrate` with :func:`braking_du` (to rounding).
    """
    b = brake(team, pose[:, 2], u, dt, brake_fraction)
    L = int(b.steps.max(initial=0)) + 1 if length is None else int(length)
    p, delta = brake_samples(point(team, pose), b, dt, max(L, 1))
    return Trajectories(p, delta, b.steps + 1, b.reach)


def first_step(team: Team, p0: np.ndarray, theta: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One step holding ``du`` (the simulator's step): point, its deviation from the chord, heading, speeds.

    A wheeled robot moves on the arc of the step-mean wheel speeds (deviation: the sagitta); a point
    mass on the parabola of the held acceleration (deviation ``|du| dt^2 / 8``).
    """
    u1 = u + du * dt
    pdot_m, w_m = _velocity(team, theta, 0.5 * (u + u1))
    p1 = p0 + pdot_m * dt * _E(w_m * dt)
    dev = (dt * dt / 8.0) * np.abs(pdot_m) * np.abs(w_m)
    if not team.is_diff_drive:
        dev = dev + (dt * dt / 8.0) * np.hypot(du[:, 0], du[:, 1])
    return p1, dev, theta + w_m * dt, u1


def candidate_reach(p0: np.ndarray, p1: np.ndarray, d1: np.ndarray, b1: _Brake) -> np.ndarray:
    """Bound on the distance from ``p0`` of one step to ``p1`` (deviation ``d1``) and the braking after it."""
    return np.abs(p1 - p0) + d1 + b1.reach


def candidate_paths(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float, brake_fraction: float,
                    length: int | None = None) -> Trajectories:
    """One step with ``du``, then the backup: samples at steps ``0 .. L-1`` (``p[:, 0]`` is the current point)."""
    p0 = point(team, pose)
    p1, d1, theta1, u1 = first_step(team, p0, pose[:, 2], u, du, dt)
    b1 = brake(team, theta1, u1, dt, brake_fraction)
    L = max(int(b1.steps.max(initial=0)) + 2 if length is None else int(length), 2)
    p, delta = candidate_samples(p0, p1, d1, b1, dt, L)
    return Trajectories(p, delta, b1.steps + 2, candidate_reach(p0, p1, d1, b1))


def candidate_samples(p0: np.ndarray, p1: np.ndarray, d1: np.ndarray, b1: _Brake, dt: float, L: int
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``(N, L)``, deviation bounds ``(N, L-1)``: the point ``p0``, the step to ``p1`` (``d1``), braking."""
    p = np.empty((p0.shape[0], L), dtype=np.complex128)
    delta = np.empty((p0.shape[0], L - 1))
    p[:, 0], delta[:, 0] = p0, d1
    p[:, 1:], delta[:, 1:] = brake_samples(p1, b1, dt, L - 1)
    return p, delta


def candidate_samples_at(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float,
                         brake_fraction: float, s: np.ndarray, rows: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``s`` of :func:`candidate_paths` in closed form, without the others.

    Parameters
    ----------
    s : numpy.ndarray
        ``(R, S)`` int sample indices per row (0: the current point, 1: after the step with ``du``,
        ``k + 1``: after ``k`` braking steps); a row per robot unless ``rows`` is given.
    rows : numpy.ndarray, optional
        ``(R,)``: the robot of each row of ``s`` (a robot's path is made once, then sampled
        for each of its rows).

    Returns
    -------
    tuple of numpy.ndarray
        Positions ``(R, S)`` complex and the deviation bounds ``(R, S)`` of the steps ``s -> s + 1``:
        the same numbers as ``candidate_paths(...).p`` and ``.delta`` at those indices, to rounding
        (the arc parameter of braking step ``k`` is the sum of the sampled trapezoids written out:
        ``dt (k - r k^2 / 2)`` while the speed scale ``1 - k r`` is positive, ``r = dt / T``).
    """
    p0 = point(team, pose)
    p1, d1, theta1, u1 = first_step(team, p0, pose[:, 2], u, du, dt)
    b = brake(team, theta1, u1, dt, brake_fraction)
    if rows is not None:
        p0, p1, d1, b = p0[rows], p1[rows], d1[rows], take_robots(b, rows)
    r = b.rate[:, None]
    kf = np.floor(1.0 / r)  # the last braking step with a speed scale >= 0
    k = np.maximum(s - 1, 0).astype(np.float64)
    kc = np.minimum(k, kf)
    tau = dt * (kc - 0.5 * r * kc * kc + np.where(k > kf, 0.5 * np.clip(1.0 - kf * r, 0.0, 1.0), 0.0))
    w = b.omega[:, None]
    p = p1[:, None] + (b.pdot[:, None] * tau) * _E(w * tau)
    p = np.where(s == 0, p0[:, None], p)
    sig = 0.5 * (np.clip(1.0 - k * r, 0.0, 1.0) + np.clip(1.0 - (k + 1.0) * r, 0.0, 1.0))
    delta = (dt * dt / 8.0) * np.abs(b.pdot)[:, None] * (sig * sig) * np.abs(w)
    if b.bulge is not None:
        delta = delta + np.where((np.clip(1.0 - k * r, 0.0, 1.0) > 0.0) & (k < b.steps[:, None]), b.bulge[:, None],
                                 0.0)
    return p, np.where(s == 0, d1[:, None], delta)


def take_robots(b: _Brake, idx: np.ndarray) -> _Brake:
    """The braking parameters of robots ``idx``."""
    return _Brake(b.pdot[idx], b.omega[idx], b.rate[idx], b.steps[idx], b.reach[idx],
                  None if b.bulge is None else b.bulge[idx])
