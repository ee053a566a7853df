"""The braking backup check in torch (a gatekeeper, ``docs/technical_brief.md`` section 9), batched over teams.

The backup: every wheel brakes at ``brake_fraction * max_wheel_accel`` toward zero speed. :func:`gate` applies a
candidate ``du`` where, from the state it leads to, braking everyone keeps every pair in range at least ``d_s`` apart
(and the step itself does); robots of failing pairs brake instead, until the braking set stops growing (at worst
everyone brakes, which keeps a brake-safe state brake-safe). A robot also brakes where its path until it stops could
exceed half of ``D - 2 max r`` (pairs out of range cannot meet before both stop). :func:`repair` first nudges the
candidate toward brake-safety. Not the numpy backup layer: braking paths are exact-arc steps of ``tau >= dt``, at
most :data:`SAMPLES` over the team's own horizon (its slowest robot's stop), each piece checked as a segment less
``2 tau^2 / 8`` of each robot's largest point acceleration (twice the chord deviation).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from aasoatt_env.model.geometry import safe_sqrt
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.tensor.model import TensorTeam, arc, integrate, pick, points

__all__ = ["GATE_TOL", "REPAIR_TARGET", "SAMPLES", "brake_du", "gate", "repair"]

SAMPLES: int = 24  #: most samples of a braking path
_CHUNK = 1 << 22  # most pair-sample elements of one chunk of braking paths
GATE_TOL: float = 2.5e-4  #: overlap [m] the check forgives: a quarter of the 1 mm the campaign counts as a collision
REPAIR_TARGET: float = 2e-4  #: margin [m] below which :func:`repair` lifts a pair row (to twice this)


def brake_du(team: TensorTeam, u: torch.Tensor, step: float, frac: float) -> torch.Tensor:
    """Wheel accelerations that brake toward zero at ``frac`` of the bound, reaching 0 exactly within ``step``."""
    a = (frac * team.max_wheel_accel)[..., None]
    return torch.maximum(torch.minimum(-u / step, a), -a)


def _point_accel(team: TensorTeam, u: torch.Tensor, frac: float) -> torch.Tensor:
    """``(B, N)`` bound on ``|p_ddot|`` while braking from ``u``: ``|A| a sqrt(2) + |omega| |p_dot|``.

    The wheels' part ``|A| a sqrt(2)`` is taken twice over (bounding ``sqrt(2)`` of it), ``a = frac max_wheel_accel``.
    """
    k = team.half_k / team.half
    lin = team.half * torch.sqrt(1.0 + k * k) * (frac * team.max_wheel_accel) * math.sqrt(2.0) * math.sqrt(2.0)
    return lin + team.turn_gain * (u[..., 0] - u[..., 1]).abs() * _speed(team, u)


def _speed(team: TensorTeam, u: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` the control point's speed ``|p_dot|``."""
    k = team.half_k / team.half
    return team.half * safe_sqrt((u[..., 0] + u[..., 1]) ** 2 + (k * (u[..., 0] - u[..., 1])) ** 2)


def _seg(q0x, q0y, q1x, q1y) -> torch.Tensor:
    """Distance from the origin to the segments ``q0 -> q1`` (components)."""
    dx, dy = q1x - q0x, q1y - q0y
    dd = dx * dx + dy * dy
    t = torch.clamp(-(q0x * dx + q0y * dy) / torch.where(dd > 0, dd, torch.ones_like(dd)), 0.0, 1.0)
    cx, cy = q0x + t * dx, q0y + t * dy
    return safe_sqrt(cx * cx + cy * cy)


class _Rows:
    """Each robot's pair rows ``(B, N, KM)``: the other member's values, and ``p_own - p_other`` per component."""

    def __init__(self, other: torch.Tensor, obstacles, dtype: torch.dtype) -> None:
        B, N, KM = other.shape
        self.robot, self.idx = other >= 0, torch.clamp(other, min=0)
        self.cx = self.cy = torch.zeros(B, N, KM, dtype=dtype, device=other.device)
        if obstacles is not None and obstacles[1].shape[-1]:
            oc = obstacles[0]
            pad = torch.zeros(B, N, KM - oc.shape[1], 2, dtype=oc.dtype, device=oc.device)
            self.cx, self.cy = torch.cat((pad, oc[:, None].expand(B, N, *oc.shape[1:])), 2).unbind(-1)

    def at(self, x: torch.Tensor) -> torch.Tensor:
        """The other robot's ``(B, N, KM)`` of ``x`` ``(B, N)`` (0 for obstacles)."""
        o = pick(x, self.idx)
        return torch.where(self.robot, o, torch.zeros_like(o))  # (of x's dtype, bool included)

    def rel(self, x, y, xo, yo) -> tuple[torch.Tensor, torch.Tensor]:
        """``p_own - p_other`` of own points ``x, y`` and the others' ``xo, yo`` ``(B, N)`` (obstacles: centre)."""
        return (x[..., None] - torch.where(self.robot, pick(xo, self.idx), self.cx),
                y[..., None] - torch.where(self.robot, pick(yo, self.idx), self.cy))


class _End(NamedTuple):
    """A robot's state after the step: control point, stop time, braking distance bound, step acceleration bound."""

    x: torch.Tensor
    y: torch.Tensor
    stop: torch.Tensor
    braking: torch.Tensor
    acc: torch.Tensor


def _end(team: TensorTeam, cfg: FilterConfig, acc0: torch.Tensor, pose1, u1) -> _End:
    x1, y1 = points(team, pose1)
    stop = torch.maximum(u1[..., 0].abs(), u1[..., 1].abs()) / (cfg.brake_fraction * team.max_wheel_accel)  # [s]
    return _End(x1, y1, stop, _speed(team, u1) * stop, torch.maximum(acc0, _point_accel(team, u1, 1.0)))


def _margins(team: TensorTeam, cfg: FilterConfig, rows: _Rows, start, pose1, u1, valid,
             ds, other: tuple | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Each pair row's smallest ``distance - d_s`` ``(B, N, K + M)`` and a bound on each robot's path [m] ``(B, N)``.

    Over the step and braking after it; ``start``: ``(x0, y0, acc0)``, the step's control points and
    :func:`_point_accel` at the full bound; ``other``: the other members' ``(pose1, u1)`` (default: the robots').
    """
    dt, frac = cfg.dt, cfg.brake_fraction
    x0, y0, acc0 = start
    own = _end(team, cfg, acc0, pose1, u1)
    oth = own if other is None else _end(team, cfg, acc0, *other)
    path_len = safe_sqrt((own.x - x0) ** 2 + (own.y - y0) ** 2) + dt * dt / 8.0 * acc0 + own.braking
    dev_step = dt * dt / 8.0 * (own.acc[..., None] + rows.at(oth.acc))
    q0x, q0y = rows.rel(x0, y0, x0, y0)
    q1x, q1y = rows.rel(own.x, own.y, oth.x, oth.y)
    out = _seg(q0x, q0y, q1x, q1y) - dev_step - ds
    gap1 = safe_sqrt(q1x * q1x + q1y * q1y) - ds
    risky = valid & (gap1 <= (own.braking + 1e-9)[..., None] + rows.at(oth.braking + 1e-9) + 1e-6)
    out = torch.where(valid, out, math.inf)
    if not bool(risky.any()):
        return out, path_len
    # each team's braking horizon (its slowest robot's stop) in at most SAMPLES samples of tau >= dt
    horizon = own.stop.amax(-1) if other is None else torch.maximum(own.stop.amax(-1), oth.stop.amax(-1))
    tau = torch.clamp(horizon / SAMPLES, min=dt)  # (B,)
    steps = int(torch.ceil(horizon / tau - 1e-9).amax())
    if steps <= 0:
        return out, path_len
    xs, ys, accs = _braking_path(team, frac, pose1, u1, tau[:, None], steps)
    xo, yo, acco = (xs, ys, accs) if other is None else _braking_path(team, frac, *other, tau[:, None], steps)
    # the braking paths of the risky rows only, a chunk of rows at once: (S, rows)
    bb, nn, rr = torch.nonzero(risky, as_tuple=True)
    jj, robot = rows.idx[bb, nn, rr], rows.robot[bb, nn, rr]
    tau2 = 2.0 * tau * tau / 8.0
    per = max(1, _CHUNK // steps)
    for first in range(0, bb.numel(), per):
        b, n, r, j, rob = (v[first:first + per] for v in (bb, nn, rr, jj, robot))
        qx = xs[:, b, n] - torch.where(rob, xo[:, b, j], rows.cx[b, n, r])
        qy = ys[:, b, n] - torch.where(rob, yo[:, b, j], rows.cy[b, n, r])
        dev = tau2[b] * (accs[:, b, n] + torch.where(rob, acco[:, b, j], 0.0))
        seg = _seg(torch.cat((q1x[b, n, r][None], qx[:-1])), torch.cat((q1y[b, n, r][None], qy[:-1])), qx, qy)
        out = out.index_put((b, n, r), torch.minimum(out[b, n, r], (seg - dev - ds[b, n, r]).amin(0)))
    return out, path_len


def _braking_path(team: TensorTeam, frac: float, pose: torch.Tensor, u: torch.Tensor, tau: torch.Tensor,
                  steps: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every robot braking from ``(pose, u)``: control points and point-acceleration bounds at samples ``(S, B, N)``.

    ``x, y`` at samples ``1..S``; the bound on ``|p_ddot|`` over each sample step; ``tau`` ``(B, 1)`` the team's step.
    Each wheel decelerates at ``frac * max_wheel_accel`` until it stops (:func:`brake_du` held for ``tau``), so its
    speeds at the samples are known at once; the exact-arc steps between them (:func:`~.model.arc`) are summed.
    """
    k = torch.arange(steps + 1, dtype=u.dtype, device=u.device)[:, None, None, None]
    dec = k * (frac * team.max_wheel_accel * tau)[..., None]  # (S + 1, B, N, 1)
    us = torch.sign(u) * torch.clamp(u.abs() - dec, min=0.0)  # (S + 1, B, N, 2)
    half, m = arc(team, us[:-1], us[1:], tau)
    turned = torch.cumsum(2.0 * half, 0)
    theta = pose[..., 2] + turned  # heading at each sample
    ang = pose[..., 2] + torch.cat((torch.zeros_like(turned[:1]), turned[:-1])) + half  # at each step's middle
    x = pose[..., 0] + torch.cumsum(m * torch.cos(ang), 0)
    y = pose[..., 1] + torch.cumsum(m * torch.sin(ang), 0)
    return x + team.offset * torch.cos(theta), y + team.offset * torch.sin(theta), _point_accel(team, us[:-1], frac)


def repair(team: TensorTeam, cfg: FilterConfig, pose, u, du, lo, hi, other, valid, ds, obstacles,
           target: float = REPAIR_TARGET, rounds: int = 3, eps: float = 1.0) -> torch.Tensor:
    """Nudge the candidate ``du`` toward brake-safety before :func:`gate` checks it (the numpy layer's repair, in kind).

    Every pair row whose margin (:func:`_margins`) is below ``target`` [m] asks the least change of its robot's input
    that lifts the margin to ``2 target`` (finite differences of step ``eps``): all of it for an obstacle row, half
    for a robot pair. The changes add up, clipped to ``[lo, hi]``, ``rounds`` times; the gate still checks the answer.
    The change is a constant to autograd (the derivative of the answer is the candidate's).
    """
    rows = _Rows(other, obstacles, u.dtype)
    start = (*points(team, pose), _point_accel(team, u, 1.0))
    half = torch.where(rows.robot, 0.5, 1.0).to(u.dtype)
    unit = eps * torch.eye(2, dtype=u.dtype, device=u.device)  # the two input directions' steps
    with torch.no_grad():
        cand = du.detach()
        for _ in range(rounds):
            base = integrate(team, pose, u, cand, cfg.dt)
            m, _ = _margins(team, cfg, rows, start, *base, valid, ds)
            low = valid & (m < target)
            if not bool(low.any()):
                break
            moved = (_margins(team, cfg, rows, start, *integrate(team, pose, u, cand + unit[d], cfg.dt), valid, ds,
                              other=base)[0] for d in range(2))
            g = torch.stack([torch.where(low, (mp - m) / eps, 0.0) for mp in moved], -1)  # (B, N, K + M, 2)
            gg = (g * g).sum(-1)
            lift = torch.where(low & (gg > 1e-12), half * (2.0 * target - m) / gg.clamp(min=1e-12), 0.0)
            cand = torch.minimum(torch.maximum(cand + (lift[..., None] * g).sum(-2), lo), hi)
        step = cand - du.detach()
    return torch.minimum(torch.maximum(du + step, lo), hi)


def gate(team: TensorTeam, cfg: FilterConfig, pose, u, du, lo, hi, other, valid, ds, obstacles,
         tol: float = GATE_TOL) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(du applied, braking (B, N), broken (B, N))`` for the candidate ``du`` (module docstring).

    ``other``, ``valid``, ``ds`` ``(B, N, K + M)``: each robot's pair rows as the filter found them (``-1``: an
    obstacle, last ``M``).  A candidate passes at a margin ``>= 0``; ``broken``: a pair below ``-tol`` although both
    of its robots brake (the state was not brake-safe; ``tol`` absorbs the sampling's step-to-step differences).
    """
    limit = 0.5 * (cfg.sensing_range - 2.0 * float(team.radius.max()))
    with torch.no_grad():
        brake = torch.minimum(torch.maximum(brake_du(team, u, cfg.dt, cfg.brake_fraction), lo), hi)
        braking = torch.zeros(u.shape[:2], dtype=torch.bool, device=u.device)
        rows = _Rows(other, obstacles, u.dtype)
        start = (*points(team, pose), _point_accel(team, u, 1.0))
        for _ in range(u.shape[1] + 1):
            cand = torch.where(braking[..., None], brake, du.detach())
            m, path_len = _margins(team, cfg, rows, start, *integrate(team, pose, u, cand, cfg.dt), valid, ds)
            both = braking[..., None] & (rows.at(braking) | ~rows.robot)
            new = braking | ((m < 0.0) & ~both).any(-1) | (path_len > limit)
            if bool((new == braking).all()):
                broken = ((m < -tol) & both).any(-1)
                break
            braking = new
    return torch.where(braking[..., None], brake, du), braking, broken
