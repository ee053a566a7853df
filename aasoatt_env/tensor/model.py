"""The robot model in torch: team parameters, kinematics, input bounds and the exact-arc step, batched ``(B, N)``.

The same equations as :mod:`aasoatt_env.model.dynamics` (differential drive), in numpy's order of operations, so
float64 results agree to rounding; every function is differentiable in the state.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

from aasoatt_env.errors import ConfigError
from aasoatt_env.model.dynamics import _SMALL_OMEGA
from aasoatt_env.model.params import Team, stack_teams

__all__ = ["TensorKinematics", "TensorTeam", "arc", "check_dtype_device", "input_bounds", "integrate", "kinematics",
           "matvec", "pick", "points", "pose_from_point", "stacked_team"]


def check_dtype_device(dtype: Any, device: Any) -> None:
    """:class:`ConfigError` unless ``dtype`` is float32 or float64 and ``device`` a torch device this machine has."""
    if dtype not in (torch.float32, torch.float64):
        raise ConfigError(f"dtype: got {dtype!r}, expected torch.float32 or torch.float64")
    try:
        kind = torch.device(device).type
    except (TypeError, RuntimeError) as exc:
        raise ConfigError(f"device: got {device!r}, expected a torch device such as 'cpu' or 'cuda'") from exc
    if kind == "meta":
        raise ConfigError(f"device: got {device!r}, expected a device whose tensors hold values (the steps read them)")
    if kind == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device: got {device!r}, but torch.cuda.is_available() is False on this machine")


class TensorTeam(NamedTuple):
    """A team's parameters as ``(N,)`` tensors (broadcast over teams); built by :meth:`from_team`."""

    radius: torch.Tensor
    offset: torch.Tensor
    half: torch.Tensor  #: ``rho / 2``
    half_k: torch.Tensor  #: ``rho / 2 * l / b`` (imaginary part of ``A``'s first column at heading 0)
    turn_gain: torch.Tensor  #: ``rho / (2 b)``
    max_wheel_accel: torch.Tensor
    max_wheel_speed: torch.Tensor
    max_point_accel: torch.Tensor
    speed_limited: bool
    source: Team | None = None  #: the numpy team (the numpy backup check's)

    @classmethod
    def from_team(cls, team: Team, dtype: torch.dtype, device: torch.device | str) -> TensorTeam:
        """The tensors of a numpy :class:`~aasoatt_env.model.params.Team` (differential drive only)."""
        if not team.is_diff_drive:
            raise ConfigError(f"robots: got model {team.model!r}, expected 'diff_drive' (the torch path models "
                              "differential-drive robots only)")
        cols = team.input_columns[:, 0]

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(a, dtype=np.float64), device=device).to(dtype)

        return cls(t(team.radius), t(team.offset), t(cols.real), t(cols.imag), t(team.turn_gain),
                   t(team.max_wheel_accel), t(team.max_wheel_speed), t(team.max_point_accel), team.speed_limited, team)


class TensorKinematics(NamedTuple):
    """Control points ``p``, velocities ``v``, drift ``adot = A_dot u`` ``(B, N, 2)``; ``A`` as four ``(B, N)``."""

    p: torch.Tensor
    v: torch.Tensor
    adot: torch.Tensor
    a00: torch.Tensor
    a01: torch.Tensor
    a10: torch.Tensor
    a11: torch.Tensor


def kinematics(team: TensorTeam, pose: torch.Tensor, u: torch.Tensor) -> TensorKinematics:
    """:func:`aasoatt_env.model.dynamics.kinematics`: ``A = e^{i theta} (h (1 + i k), h (1 - i k))`` column-wise."""
    c, s = torch.cos(pose[..., 2]), torch.sin(pose[..., 2])
    h, hk = team.half, team.half_k
    a00, a10 = c * h - s * hk, c * hk + s * h  # e * h(1 + ik)
    a01, a11 = c * h + s * hk, s * h - c * hk  # e * h(1 - ik)
    v = matvec(a00, a01, a10, a11, u)
    omega = team.turn_gain * (u[..., 0] - u[..., 1])
    adot = torch.stack((-omega * v[..., 1], omega * v[..., 0]), -1)
    return TensorKinematics(torch.stack(points(team, pose), dim=-1), v, adot, a00, a01, a10, a11)


def matvec(a00, a01, a10, a11, x: torch.Tensor) -> torch.Tensor:
    """``M x`` ``(..., 2)`` for the 2x2 matrices ``M = [[a00, a01], [a10, a11]]`` (tensors ``(...)`` or floats)."""
    return torch.stack((a00 * x[..., 0] + a01 * x[..., 1], a10 * x[..., 0] + a11 * x[..., 1]), -1)


def pick(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``x[b, idx[b, n, k]]`` ``(B, N, K, ...)`` of ``x`` ``(B, M, ...)`` and indices ``idx`` ``(B, N, K)``."""
    B, N, K = idx.shape
    tail = x.shape[2:]
    flat = idx.reshape(B, N * K, *(1,) * len(tail)).expand(B, N * K, *tail)
    return x.gather(1, flat).reshape(B, N, K, *tail)


def points(team: TensorTeam, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The control points' components ``(...)`` of axle poses ``(..., 3)``: ``offset`` ahead of the axle."""
    return pose[..., 0] + team.offset * torch.cos(pose[..., 2]), pose[..., 1] + team.offset * torch.sin(pose[..., 2])


def input_bounds(team: TensorTeam, u: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds ``(B, N, 2)`` on ``du``: ``|du| <= max_wheel_accel`` and the wheel-speed box where limited."""
    a = team.max_wheel_accel[..., None].expand(u.shape)
    lo, hi = -a, a
    if not team.speed_limited:
        return lo, hi
    ms = team.max_wheel_speed[..., None]
    new_hi = torch.maximum(torch.minimum(hi, (ms - u) / dt), lo)
    return torch.minimum(torch.maximum(lo, (-ms - u) / dt), new_hi), new_hi


def arc(team: TensorTeam, u: torch.Tensor, u_new: torch.Tensor, dt) -> tuple[torch.Tensor, torch.Tensor]:
    """The exact arc of a step from wheel speeds ``u`` to ``u_new`` over ``dt``: half the heading change and the chord.

    ``dt`` a float or a tensor broadcasting with ``u[..., 0]``.
    """
    um = 0.5 * (u + u_new)
    fwd = team.half * um[..., 0] + team.half * um[..., 1]
    half = (0.5 * dt) * (team.turn_gain * um[..., 0] + (-team.turn_gain) * um[..., 1])
    small = half.abs() < _SMALL_OMEGA
    safe = torch.where(small, torch.ones_like(half), half)
    sinc = torch.where(small, 1.0 - half * half / 6.0, torch.sin(safe) / safe)
    return half, dt * fwd * sinc


def integrate(team: TensorTeam, pose: torch.Tensor, u: torch.Tensor, du: torch.Tensor,
              dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`aasoatt_env.model.dynamics.integrate`: hold ``du`` for ``dt`` along the exact arc."""
    u_new = u + du * dt
    half, m = arc(team, u, u_new, dt)
    theta = pose[..., 2]
    ang = theta + half
    new = torch.stack((pose[..., 0] + m * torch.cos(ang), pose[..., 1] + m * torch.sin(ang), theta + 2.0 * half), -1)
    return new, u_new


def pose_from_point(team: TensorTeam, p: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Axle poses ``(B, N, 3)`` whose control points are ``p`` at headings ``theta``."""
    return torch.stack((p[..., 0] - team.offset * torch.cos(theta), p[..., 1] - team.offset * torch.sin(theta),
                        theta), -1)


def stacked_team(team: Team, copies: int) -> Team:
    """``copies`` of a numpy team stacked as one, each its own group (built once per team and count)."""
    key = ("stacked", copies)
    if key not in team.derived:
        team.derived[key] = stack_teams([team] * copies)
    return team.derived[key]
