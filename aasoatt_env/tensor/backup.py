"""The braking backup check in torch (a gatekeeper, ``docs/technical_brief.md`` section 9), batched over teams.

The backup: every wheel brakes at ``brake_fraction * max_wheel_accel`` toward zero speed.  A candidate ``du`` is
applied where, from the state it leads to, braking everyone keeps every pair in range at least ``d_s`` apart (and
the step itself does); robots of failing pairs brake instead, and the check repeats until the braking set stops
growing (it only grows, so it ends; at worst everyone brakes, which keeps a brake-safe state brake-safe).  A robot
also brakes where its path until it stops could exceed half of ``D - 2 max r`` (the range limit: a pair out of
sensing range cannot meet before both stop).

Not the numpy backup layer (no repair, no blend levels, its own sampling): the braking path is integrated with the
exact-arc step at ``tau >= dt`` (at most :data:`SAMPLES` samples) and each sample-to-sample piece is checked as the
segment of relative positions minus ``2 * tau^2 / 8`` of each robot's largest point acceleration while braking
(its chord deviation, and as much again for the coarse integration); pairs too far apart to meet before both stop
are not integrated.  float32 rounds distances at 10 m by about 1 µm; the campaign states the dtype it shows.
"""

from __future__ import annotations

import math

import torch

from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.tensor.model import TensorTeam, integrate, kinematics

__all__ = ["GATE_TOL", "SAMPLES", "brake_du", "gate"]

SAMPLES: int = 24  #: most samples of a braking path
GATE_TOL: float = 2.5e-4  #: overlap [m] the check forgives: a quarter of the 1 mm the campaign counts as a collision


def brake_du(team: TensorTeam, u: torch.Tensor, step: float, frac: float) -> torch.Tensor:
    """Wheel accelerations that brake toward zero at ``frac`` of the bound, reaching 0 exactly within ``step``."""
    a = (frac * team.max_wheel_accel)[..., None]
    return torch.maximum(torch.minimum(-u / step, a), -a)


def _point_accel(team: TensorTeam, u: torch.Tensor, frac: float) -> torch.Tensor:
    """``(B, N)`` bound on ``|p_ddot|`` while braking from ``u``: ``|A| a sqrt(2) + |omega| |p_dot|``."""
    a = frac * team.max_wheel_accel
    k = team.half_k / team.half
    lin = team.half * torch.sqrt(1.0 + k * k) * a * math.sqrt(2.0) * math.sqrt(2.0)
    omega = team.turn_gain * (u[..., 0] - u[..., 1]).abs()
    speed = team.half * torch.sqrt((u[..., 0] + u[..., 1]) ** 2 + (k * (u[..., 0] - u[..., 1])) ** 2)
    return lin + omega * speed


def _seg(q0: torch.Tensor, q1: torch.Tensor) -> torch.Tensor:
    """Distance from the origin to the segments ``q0 -> q1`` ``(..., 2)``."""
    d = q1 - q0
    dd = (d * d).sum(-1)
    t = torch.clamp(-(q0 * d).sum(-1) / torch.where(dd > 0, dd, torch.ones_like(dd)), 0.0, 1.0)
    c = q0 + t[..., None] * d
    return torch.sqrt((c * c).sum(-1))


def _margins(team: TensorTeam, cfg: FilterConfig, pose0, u0, pose1, u1, du, other, valid, ds, obstacles):
    """``(B, N, K + M)`` smallest ``distance - d_s`` of each pair row over the step and the braking path after it."""
    B, N, KM = other.shape
    dt, frac = cfg.dt, cfg.brake_fraction
    p0, p1 = kinematics(team, pose0, u0).p, kinematics(team, pose1, u1).p
    stop = (u1.abs().amax(-1) / (frac * team.max_wheel_accel))  # (B, N) [s]
    speed = _speed(team, u1)
    reach = speed * stop + 1e-9
    acc_step = torch.maximum(_point_accel(team, u0, 1.0), _point_accel(team, u1, 1.0))
    j = torch.clamp(other, min=0)
    robot = other >= 0
    flat = j.reshape(B, N * KM)

    def at(x):  # the other member's (B, N, KM, ...)
        if x.dim() == 2:
            return x.gather(1, flat).reshape(B, N, KM)
        return x.gather(1, flat[..., None].expand(B, N * KM, x.shape[-1])).reshape(B, N, KM, x.shape[-1])

    if obstacles is not None and obstacles[1].shape[-1]:
        oc = obstacles[0]
        M = oc.shape[1]
        cen = torch.cat((torch.zeros(B, N, KM - M, 2, dtype=p0.dtype, device=p0.device),
                         oc[:, None].expand(B, N, M, 2)), 2)
    else:
        cen = torch.zeros(B, N, KM, 2, dtype=p0.dtype, device=p0.device)

    def rel(p):
        return p[:, :, None, :] - torch.where(robot[..., None], at(p), cen)

    zero = torch.zeros_like(ds)
    dev_step = dt * dt / 8.0 * (acc_step[..., None] + torch.where(robot, at(acc_step), zero))
    out = _seg(rel(p0), rel(p1)) - dev_step - ds
    q1 = rel(p1)
    gap1 = torch.sqrt((q1 * q1).sum(-1)) - ds
    risky = valid & (gap1 <= reach[..., None] + torch.where(robot, at(reach), zero) + 1e-6)
    out = torch.where(valid, out, torch.full_like(out, float("inf")))
    if not bool(risky.any()):
        return out
    horizon = float(stop.amax())
    tau = max(dt, horizon / SAMPLES)
    steps = int(math.ceil(horizon / tau - 1e-9))
    pose, u, path = pose1, u1, torch.full_like(out, float("inf"))
    q_prev = q1
    for _ in range(steps):
        a_now = _point_accel(team, u, frac)
        pose, u = integrate(team, pose, u, brake_du(team, u, tau, frac), tau)
        q = rel(kinematics(team, pose, u).p)
        dev = 2.0 * tau * tau / 8.0 * (a_now[..., None] + torch.where(robot, at(a_now), zero))
        path = torch.minimum(path, _seg(q_prev, q) - dev - ds)
        q_prev = q
    return torch.minimum(out, torch.where(risky, path, torch.full_like(path, float("inf"))))


def _reach(team: TensorTeam, cfg: FilterConfig, pose0, u0, pose1, u1) -> torch.Tensor:
    """``(B, N)`` bound on the control point's path over the step and the braking after it [m]."""
    p0, p1 = kinematics(team, pose0, u0).p, kinematics(team, pose1, u1).p
    step = torch.sqrt(((p1 - p0) ** 2).sum(-1)) + cfg.dt * cfg.dt / 8.0 * _point_accel(team, u0, 1.0)
    stop = u1.abs().amax(-1) / (cfg.brake_fraction * team.max_wheel_accel)
    return step + _speed(team, u1) * stop


def _speed(team: TensorTeam, u: torch.Tensor) -> torch.Tensor:
    k = team.half_k / team.half
    return team.half * torch.sqrt((u[..., 0] + u[..., 1]) ** 2 + (k * (u[..., 0] - u[..., 1])) ** 2)


def gate(team: TensorTeam, cfg: FilterConfig, pose, u, du, lo, hi, other, valid, ds, obstacles,
         tol: float = GATE_TOL) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(du applied, braking (B, N), broken (B, N))`` for the candidate ``du`` (module docstring).

    ``other``, ``valid``, ``ds`` ``(B, N, K + M)``: each robot's pair rows (``-1``: an obstacle, last ``M``), as
    the filter found them.  A candidate passes at a margin ``>= 0``; ``broken``: a pair below ``-tol`` although both
    of its robots brake (the state was not brake-safe; ``tol`` absorbs the sampled paths' differences from one
    step to the next); those robots brake too.
    """
    limit = 0.5 * (cfg.sensing_range - 2.0 * float(team.radius.max()))
    with torch.no_grad():
        brake = torch.minimum(torch.maximum(brake_du(team, u, cfg.dt, cfg.brake_fraction), lo), hi)
        braking = torch.zeros(u.shape[:2], dtype=torch.bool, device=u.device)
        robot = other >= 0
        j = torch.clamp(other, min=0)
        for _ in range(u.shape[1] + 1):
            cand = torch.where(braking[..., None], brake, du.detach())
            pose1, u1 = integrate(team, pose, u, cand, cfg.dt)
            m = _margins(team, cfg, pose, u, pose1, u1, cand, other, valid, ds, obstacles)
            far = _reach(team, cfg, pose, u, pose1, u1) > limit
            fail = m < 0.0
            both = braking[..., None] & torch.where(robot, braking.gather(1, j.reshape(j.shape[0], -1))
                                                   .reshape(j.shape), torch.ones_like(fail))
            new = braking | (fail & ~both).any(-1) | far
            if bool((new == braking).all()):
                broken = ((m < -tol) & both).any(-1)
                break
            braking = new
    return torch.where(braking[..., None], brake, du), braking, broken
