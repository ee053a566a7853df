"""Acceleration-level robot dynamics, vectorised over a team (``docs/technical_brief.md`` section 1).

State per robot: axle pose ``(x, y, theta)`` and wheel speeds ``u``; input: wheel accelerations ``du``.
The control point ``p = (x, y) + l (cos theta, sin theta)`` obeys ``p_ddot = A(theta) du + A_dot u`` with
``A = rho/2 [[c - k s, c + k s], [s + k c, s - k c]]``, ``k = l / b`` (double integrator: ``A = I``, heading
along the velocity).  A step holds ``du`` and moves the pose along the exact arc of the mean wheel speeds.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.compiled import kernels
from aasoatt_env.model.params import Team
from aasoatt_env.model.portable import atan2

__all__ = ["DT", "Kinematics", "control_point", "input_bounds", "integrate", "jacobian", "kinematics",
           "pose_from_point", "speed_box"]

DT: float = 0.005
"""The paper's physics and control step [s] (every experiment of Sec. V); the one default of ``dt``."""
_SMALL_OMEGA = 1e-9


class Kinematics(NamedTuple):
    """Control-point positions ``p`` and velocities ``v = A u`` ``(N, 2)``, ``A (N, 2, 2)``, ``adot_u (N, 2)``."""

    p: np.ndarray
    v: np.ndarray
    A: np.ndarray
    adot_u: np.ndarray


def control_point(team: Team, pose: np.ndarray) -> np.ndarray:
    """Control-point positions ``(N, 2)`` from axle poses ``(N, 3)``."""
    if not team.is_diff_drive:
        return pose[:, :2].copy()
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    return pose[:, :2] + team.offset[:, None] * np.stack((c, s), axis=1)


def pose_from_point(team: Team, p: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Axle poses ``(N, 3)`` whose control points are ``p`` at headings ``theta``."""
    theta = np.asarray(theta, dtype=np.float64)
    pose = np.empty((p.shape[0], 3))
    pose[:, 2] = theta
    if team.is_diff_drive:
        pose[:, 0] = p[:, 0] - team.offset * np.cos(theta)
        pose[:, 1] = p[:, 1] - team.offset * np.sin(theta)
    else:
        pose[:, :2] = p
    return pose


def _as_matrix(z: np.ndarray) -> np.ndarray:
    """``(N, 2)`` complex columns -> contiguous ``(N, 2, 2)`` real matrices."""
    return np.ascontiguousarray(z.view(np.float64).reshape(-1, 2, 2).transpose(0, 2, 1))


def jacobian(team: Team, theta: np.ndarray) -> np.ndarray:
    """Input matrices ``A(theta)``, shape ``(N, 2, 2)``."""
    n = theta.shape[0]
    if not team.is_diff_drive:
        return np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    return _as_matrix(np.exp(1j * theta)[:, None] * team.input_columns)


def kinematics(team: Team, pose: np.ndarray, u: np.ndarray, compiled: bool = False) -> Kinematics:
    """Control point, velocity, ``A`` and ``A_dot u`` of the team, all from one complex rotation.

    ``A u = e^{i theta} (c_0 u_R + c_1 u_L)`` (:attr:`Team.input_columns`), ``A_dot u = i omega A u``.
    ``compiled``: a differential-drive team's by :mod:`.dynamics_kernel` (the same numbers).
    """
    if compiled and team.is_diff_drive:
        return Kinematics(*kernels("dynamics").kinematics(team.input_columns, team.offset, team.turn_gain, pose, u))
    if not team.is_diff_drive:
        n = pose.shape[0]
        return Kinematics(pose[:, :2].copy(), u.copy(), jacobian(team, pose[:, 2]), np.zeros((n, 2)))
    e = np.exp(1j * pose[:, 2])
    z = e[:, None] * team.input_columns
    vz = z[:, 0] * u[:, 0] + z[:, 1] * u[:, 1]
    omega = team.turn_gain * (u[:, 0] - u[:, 1])
    adot = (1j * omega) * vz
    p = pose[:, :2] + (team.offset * e).view(np.float64).reshape(-1, 2)
    return Kinematics(p, vz.view(np.float64).reshape(-1, 2), _as_matrix(z), adot.view(np.float64).reshape(-1, 2))


def input_bounds(team: Team, u: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Bounds ``(N, 2)`` on ``du`` for the next step: ``|du| <= max_wheel_accel`` and :func:`speed_box`."""
    a = team.du_max
    if not team.speed_limited:
        return -a, a.copy()
    return speed_box(-a, a, u, team.max_wheel_speed[:, None], dt)


def speed_box(lo: np.ndarray, hi: np.ndarray, u: np.ndarray, max_speed: float | np.ndarray, dt: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """Intersect ``[lo, hi]`` on ``du`` with ``|u + du dt| <= max_speed`` (never empty: beyond it, full braking)."""
    new_hi = np.maximum(np.minimum(hi, (max_speed - u) / dt), lo)
    new_lo = np.minimum(np.maximum(lo, (-max_speed - u) / dt), new_hi)
    return new_lo, new_hi


def integrate(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float,
              compiled: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Advance poses and wheel speeds by ``dt`` holding ``du``; returns new arrays.

    ``compiled``: a differential-drive team's step by :mod:`.dynamics_kernel` (the same numbers).
    """
    if compiled and team.is_diff_drive:
        return kernels("dynamics").integrate(team.wheel_map, pose, u, du, float(dt), _SMALL_OMEGA)
    u_new = u + du * dt
    if not team.is_diff_drive:
        pose_new = pose.copy()
        pose_new[:, :2] += u * dt + 0.5 * du * dt * dt
        speed = np.hypot(u_new[:, 0], u_new[:, 1])
        moving = speed > 1e-9
        pose_new[:, 2] = np.where(moving, atan2(u_new[:, 1], u_new[:, 0]), pose[:, 2])
        return pose_new, u_new
    um = 0.5 * (u + u_new)  # mean wheel speeds over the step
    vw = np.einsum("nij,nj->ni", team.wheel_map, um)  # forward speed, yaw rate
    half = (0.5 * dt) * vw[:, 1]  # half the heading change
    # chord of the arc = path length * sin(x)/x with x = half; below _SMALL_OMEGA, 1 - x^2/6 rounds to 1
    small = np.abs(half) < _SMALL_OMEGA
    if small.any():
        safe = np.where(small, 1.0, half)
        sinc = np.where(small, 1.0, np.sin(safe) / safe)
    else:
        sinc = np.sin(half) / half
    theta = pose[:, 2]
    chord = (dt * vw[:, 0] * sinc) * np.exp(1j * (theta + half))
    pose_new = np.empty_like(pose)
    np.add(pose[:, :2], chord.view(np.float64).reshape(-1, 2), out=pose_new[:, :2])
    np.add(theta, 2.0 * half, out=pose_new[:, 2])
    return pose_new, u_new
