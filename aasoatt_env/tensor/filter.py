"""The decentralised AA-SOATT filter in torch, batched over teams ``(B, N)``: :func:`filter_step`, :class:`SafetyLayer`.

One step of :class:`~aasoatt_env.safety.core.SafetyFilter` with ``mode="decentralized"``: nominals clipped to the
bounds; the ``multiplier`` trigger and eqn.13's target correction (``auxiliary_velocity``) or none; the rows of
``cfg.barrier`` (registered with ``array_api=True``) for every robot and obstacle pair in sensing range, shared
reciprocally by authority around each robot's box least-squares answer; each robot's exact 2-variable QP
(:mod:`~aasoatt_env.safety.solvers.polygons`); ``negotiate=True``: the negotiation groups jointly, by the numpy
filter's own solver. With ``backup=False`` or ``backup_check="numpy"`` the answers agree with the numpy filter's
(1e-9; relaxed robots 1e-6).
``status`` bits per robot: :data:`RELAXED` (its QP, or its group's, is infeasible: rows loosened by their least
violation), :data:`GROUPED` (answered by its negotiation group, on the CPU, without gradient), :data:`BACKUP`
(braked by the backup check: the numpy filter's layer or :mod:`.backup`'s, :data:`BACKUP_CHECKS`), :data:`UNSAFE`
(the check found the robot outside the safe set: a pair failing although both brake).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np
import torch

from aasoatt_env.errors import ConfigError, StateError
from aasoatt_env.model.dynamics import pose_from_point
from aasoatt_env.model.geometry import row_norm, safe_sqrt
from aasoatt_env.safety.backup import backup_answer
from aasoatt_env.safety.barriers import PairGeometry, get_barrier
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.deadlock import rotation
from aasoatt_env.safety.decentralized import GROUP_ONE_CHANGE_ITER, solve_groups
from aasoatt_env.safety.problem import box_ls
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers.local import RELAX_TOL
from aasoatt_env.safety.solvers.polygons import FAR, LocalAnswer, least_violation, solve_polygons
from aasoatt_env.safety.stages import BACKUP, GROUPED, RELAXED, UNSAFE, Warm
from aasoatt_env.tensor.backup import gate, repair
from aasoatt_env.tensor.model import (
    TensorKinematics,
    TensorTeam,
    check_dtype_device,
    input_bounds,
    kinematics,
    matvec,
    pick,
    stacked_team,
)
from aasoatt_env.validation import MAGNITUDE_MAX, short_repr

__all__ = ["BACKUP", "BACKUP_CHECKS", "GROUPED", "RELAXED", "UNSAFE", "FilterOut", "SafetyLayer", "backup_check_of",
           "check_config", "filter_step", "torch_config"]



class FilterOut(NamedTuple):
    """One step of :func:`filter_step`, per robot ``(B, N, ...)``."""

    du: torch.Tensor  #: ``(B, N, 2)`` filtered wheel accelerations, within the bounds
    status: torch.Tensor  #: ``(B, N)`` int: bit flags (module docstring)
    avoiding: torch.Tensor  #: ``(B, N)`` bool: a half-row of the robot binds (the trigger's memory for the next step)
    triggered: torch.Tensor  #: ``(B, N)`` bool: eqn.13 acted on the robot
    correction: torch.Tensor  #: ``(B, N)`` ``|du - nominal|``
    intervened: torch.Tensor  #: ``(B, N)`` bool: the nominal was changed
    #: ``(B, N)`` smallest surface gap to a robot or obstacle in range (``D - 2 r`` without; None from the env's
    #: compiled stages, :mod:`.compiled`)
    gap: torch.Tensor | None


def torch_config(config: Any = None, mode: str | None = None, **options: Any) -> FilterConfig:
    """The torch filter's :class:`FilterConfig`, checked (:func:`check_config`).

    ``config``: None/True (the defaults), a ``FilterConfig``, or a mapping of its fields; ``options``: more fields.
    ``mode`` (None: the configuration's, decentralised where it names none) must agree with the configuration's.
    """
    if config is None or config is True:
        config = {}
    if isinstance(config, Mapping):
        if not all(isinstance(k, str) for k in config):
            raise ConfigError(f"filter: got keys {sorted(map(repr, config))}, expected FilterConfig field names")
        base, named = FilterConfig.merged(None, **{"mode": "decentralized", **config}), "mode" in config
    elif isinstance(config, FilterConfig):
        base, named = config, True
    else:
        raise ConfigError(f"filter: got {short_repr(config)}, expected True, a FilterConfig or a mapping of its "
                          "fields")
    if mode is not None and named and mode != base.mode:
        raise ConfigError(f"mode: got {mode!r}, but the filter's configuration says {base.mode!r}")
    return check_config(FilterConfig.merged(base, **({} if mode is None else {"mode": mode}), **options))


def check_config(cfg: FilterConfig) -> FilterConfig:
    """``cfg`` if the torch filter implements it, else :class:`ConfigError` naming the setting."""
    if cfg.mode != "decentralized":
        raise ConfigError(f"mode: got {cfg.mode!r}, expected 'decentralized' (the torch filter solves each robot's QP)")
    if not get_barrier(cfg.barrier).array_api:
        raise ConfigError(f"barrier: got {cfg.barrier!r}, registered without array_api=True (its rows are numpy "
                          "only), expected a barrier written with the namespace of its inputs in the torch filter")
    for name, allowed in (("deadlock", ("auxiliary_velocity", "none")), ("trigger", ("multiplier",))):
        if getattr(cfg, name) not in allowed:
            raise ConfigError(f"{name}: got {getattr(cfg, name)!r}, expected one of {list(allowed)} in the torch "
                              "filter")
    if cfg.max_wheel_speed is not None or cfg.speed_margin:
        raise ConfigError("max_wheel_speed/speed_margin: expected None/0 in the torch filter")
    return cfg


def _target(cfg: FilterConfig, kin: TensorKinematics, nom: torch.Tensor, avoiding: torch.Tensor | None,
            p_d: torch.Tensor, v_d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``A du_nom``, corrected by eqn.13 on the triggered robots; ``(target, triggered)``."""
    t = matvec(kin.a00, kin.a01, kin.a10, kin.a11, nom)
    if avoiding is None or cfg.deadlock == "none":
        return t, torch.zeros(t.shape[:-1], dtype=torch.bool, device=t.device)
    ell = kin.p - p_d
    trig = avoiding & ((row_norm(v_d) >= cfg.low_speed) | (row_norm(ell) > cfg.goal_tol))
    z = trig.to(t.dtype) * cfg.zeta  # (zeta in the state's dtype, not rounded through float32)
    return t - z[..., None] * matvec(*rotation(cfg.rotation_deg).ravel().tolist(), kin.v - v_d + cfg.k3 * ell), trig


class _Pairs(NamedTuple):
    """Each robot's rows ``(B, N, K + M)``: the other member's index (``-1``: obstacle) and validity; geometry."""

    other: torch.Tensor
    valid: torch.Tensor
    gp: torch.Tensor  #: ``p_own - p_other`` ``(2, B, N, K + M)`` (components first: contiguous)
    gv: torch.Tensor
    ga: torch.Tensor
    ds: torch.Tensor
    sep: torch.Tensor  #: ``|p_own - p_other| - ds``: the surface gap of each row
    gap: torch.Tensor  #: ``(B, N)`` smallest surface gap of a valid row (``D - 2 r`` without)
    of: torch.Tensor  #: ``(F, B, N, K + M)`` the other robot's features (:data:`_F`; 0 for obstacles)


_F = ("px", "py", "vx", "vy", "ax", "ay", "radius", "a00", "a01", "a10", "a11", "du0x", "du0y", "authority")


def _pairs(cfg: FilterConfig, feat: torch.Tensor, obstacles) -> _Pairs:
    """Rows of the robot pairs and obstacle rims within ``D``; ``feat (B, N, F)``: the robots' :data:`_F`."""
    B, N, F = feat.shape
    featT = feat.permute(2, 0, 1).contiguous()  # (F, B, N): one contiguous tensor per feature
    rad, D = featT[6], cfg.sensing_range
    dx = featT[0][:, :, None] - featT[0][:, None, :]
    dy = featT[1][:, :, None] - featT[1][:, None, :]
    d2 = dx * dx + dy * dy
    eye = torch.eye(N, dtype=torch.bool, device=feat.device)
    near = (d2 <= D * D) & ~eye
    K = int(near.sum(-1).max())
    key = torch.where(near, d2, math.inf).detach()
    idx = key.topk(K, dim=-1, largest=False).indices
    valid = near.gather(2, idx)
    of = featT.gather(2, idx.reshape(1, B, N * K).expand(F, B, N * K)).reshape(F, B, N, K)
    own = featT[:7, :, :, None]
    rel = own - of[:7]
    gp, gv, ga = rel[0:2], rel[2:4], rel[4:6]
    ds = rad[..., None] + of[6]
    other = torch.where(valid, idx, -1)
    if obstacles is not None and obstacles[1].shape[-1]:
        oc, orad = obstacles
        M = orad.shape[-1]
        op = own[0:2] - oc.permute(2, 0, 1)[:, :, None, :]
        gp = torch.cat((gp, op), 3)
        gv = torch.cat((gv, own[2:4].expand(2, B, N, M)), 3)
        ga = torch.cat((ga, own[4:6].expand(2, B, N, M)), 3)
        ds = torch.cat((ds, rad[..., None] + orad[:, None, :]), 2)
        valid = torch.cat((valid, torch.sqrt(op[0] ** 2 + op[1] ** 2) - orad[:, None, :] <= D), 2)
        other = torch.cat((other, torch.full((B, N, M), -1, dtype=other.dtype, device=feat.device)), 2)
        of = torch.cat((of, torch.zeros(F, B, N, M, dtype=of.dtype, device=of.device)), 3)
    sep = safe_sqrt(gp[0] ** 2 + gp[1] ** 2) - ds
    gap = torch.where(valid, sep, math.inf).amin(-1) if valid.shape[-1] else torch.full_like(rad, math.inf)
    gap = torch.where(torch.isinf(gap), D - 2.0 * rad, gap)
    return _Pairs(other, valid, gp, gv, ga, ds, sep, gap, of)


def _check_inputs(team: TensorTeam, arrays: dict[str, torch.Tensor], obstacles, avoiding) -> None:
    """:class:`StateError` naming the input and the entry, as the numpy filter's ``check_step`` does.

    Shapes ``(B, N, .)`` of the team's ``N``; every number finite within ``MAGNITUDE_MAX`` (one reduction if so).
    """
    if obstacles is not None:
        if not isinstance(obstacles, (tuple, list)) or len(obstacles) != 2:
            raise StateError(f"obstacles: got {short_repr(obstacles)}, expected (centres (B, M, 2), radii (B, M))")
        arrays = {**arrays, "obstacles centres": obstacles[0], "obstacles radii": obstacles[1]}
    for name, a in arrays.items():
        if not isinstance(a, torch.Tensor) or a.dtype == torch.bool or a.is_complex():
            what = f"a {a.dtype} tensor" if isinstance(a, torch.Tensor) else short_repr(a)
            raise StateError(f"{name}: got {what}, expected a real torch tensor")
        if a.device != team.radius.device:
            raise StateError(f"{name}: got a tensor on {a.device}, expected the team's device {team.radius.device}")
    pose = arrays["pose"]
    B, N = (pose.shape[0] if pose.dim() == 3 else -1), team.radius.shape[-1]
    if B == 0:
        raise StateError("pose: got 0 teams, expected at least one")
    shapes = {name: (B, N, 3 if name == "pose" else 2) for name in arrays}
    if obstacles is not None:
        M = obstacles[1].shape[-1] if obstacles[1].dim() else -1
        shapes.update({"obstacles centres": (B, M, 2), "obstacles radii": (B, M)})
    for name, a in arrays.items():
        if tuple(a.shape) != shapes[name]:
            raise StateError(f"{name}: got shape {tuple(a.shape)}, expected {shapes[name]} (teams, robots, ...)")
    if avoiding is not None and (not isinstance(avoiding, torch.Tensor) or avoiding.dtype != torch.bool
                                 or tuple(avoiding.shape) != (B, N) or avoiding.device != pose.device):
        got = (f"a {avoiding.dtype} tensor of shape {tuple(avoiding.shape)} on {avoiding.device}"
               if isinstance(avoiding, torch.Tensor) else short_repr(avoiding))
        raise StateError(f"avoiding: got {got}, expected a torch.bool tensor of shape ({B}, {N}) on {pose.device}")
    peak = torch.stack([a.detach().abs().amax().double() if a.numel() else pose.new_zeros((), dtype=torch.float64)
                        for a in arrays.values()]).max()
    if bool(peak <= MAGNITUDE_MAX):  # (NaN is not)
        if obstacles is not None and bool((obstacles[1] < 0).any()):
            b, k = (int(i) for i in torch.nonzero(obstacles[1] < 0)[0])
            raise StateError(f"obstacles radii: got {float(obstacles[1][b, k])!r} for team {b}, obstacle {k}, "
                             "expected a radius >= 0")
        return
    for name, a in arrays.items():
        bad = ~(a.detach().abs() <= MAGNITUDE_MAX)
        if bad.any():
            b, k = (int(i) for i in torch.nonzero(bad)[0][:2])
            what = "obstacle" if name.startswith("obstacles") else "robot"
            raise StateError(f"{name}: got {a[b, k].tolist()} for team {b}, {what} {k}, expected finite values within "
                             f"+-{MAGNITUDE_MAX:g}")


def filter_step(team: TensorTeam, cfg: FilterConfig, pose: torch.Tensor, u: torch.Tensor, nominal: torch.Tensor,
                p_d: torch.Tensor, v_d: torch.Tensor, obstacles: tuple[torch.Tensor, torch.Tensor] | None = None,
                avoiding: torch.Tensor | None = None, backup_check: str | None = None) -> FilterOut:
    """One decentralised filter step of ``B`` teams of ``N`` robots (module docstring).

    ``pose`` ``(B, N, 3)``, wheel speeds ``u`` and ``nominal`` wheel accelerations ``(B, N, 2)``, the reference
    ``p_d, v_d`` ``(B, N, 2)``, ``obstacles`` ``(centres (B, M, 2), radii (B, M))``, ``avoiding`` the previous step's
    ``FilterOut.avoiding`` (None: a first step).  Differentiable in ``pose``, ``u``, ``nominal`` (closed forms).
    ``backup_check`` (with ``cfg.backup``): :data:`BACKUP_CHECKS` (None: the device's, :func:`backup_check_of`).
    """
    check = backup_check_of(backup_check, pose.device)
    _check_inputs(team, dict(pose=pose, u=u, nominal=nominal, p_d=p_d, v_d=v_d), obstacles, avoiding)
    kin = kinematics(team, pose, u)
    lo, hi = input_bounds(team, u, cfg.dt)
    B, N, _ = pose.shape
    scale = torch.maximum(team.max_wheel_accel.expand(B, N), torch.maximum(lo.abs(), hi.abs()).amax(-1))
    nom = torch.minimum(torch.maximum(nominal, lo), hi)
    target, trig = _target(cfg, kin, nom, avoiding, p_d, v_d)
    du0 = box_ls(kin.a00, kin.a01, kin.a10, kin.a11, target, lo, hi)
    a_own = team.max_point_accel.expand(B, N)[..., None]
    feat = torch.cat((kin.p, kin.v, kin.adot, torch.stack((team.radius.expand(B, N), kin.a00, kin.a01, kin.a10,
                      kin.a11), -1), du0, a_own), -1)
    pr = _pairs(cfg, feat, obstacles)
    a_oth = pr.of[13]
    tot = a_own + a_oth  # the pair's a_i+ + a_j+
    # the registered barrier's own rows on tensors: pair vectors as (B, N, K, 2), the discrete-time margin on d_s
    p, v, a = (x.permute(1, 2, 3, 0) for x in (pr.gp, pr.gv, pr.ga))
    geom = PairGeometry(None, None, p, v, a, pr.ds + cfg.pair_margin(v), pr.ds, tot)
    rhs, keep = get_barrier(cfg.barrier).rows(geom, cfg)  # keep: the pairs it keeps (None: all)
    rows = pr.valid if keep is None else pr.valid & keep  # (the backup check sees every pair in range)
    # own half-row G = -A_own^T p_(own - other); the other's G' = A_other^T p_(own - other)
    gx = -(kin.a00[..., None] * pr.gp[0] + kin.a10[..., None] * pr.gp[1])
    gy = -(kin.a01[..., None] * pr.gp[0] + kin.a11[..., None] * pr.gp[1])
    base = gx * du0[..., None, 0] + gy * du0[..., None, 1]
    robot = pr.other >= 0
    of = pr.of
    ogx = of[7] * pr.gp[0] + of[9] * pr.gp[1]
    ogy = of[8] * pr.gp[0] + of[10] * pr.gp[1]
    base_o = torch.where(robot, ogx * of[11] + ogy * of[12], 0.0)
    pos = tot > 0
    low = torch.arange(N, device=pose.device)[None, :, None] < pr.other  # own index is the pair's i
    safe_tot = torch.where(pos, tot, 1.0)
    share = torch.where(pos, torch.where(low, a_own / safe_tot, 1.0 - a_oth / safe_tot), 0.5)
    need = torch.where(low, (base - rhs) + base_o, (base_o - rhs) + base)
    h = torch.where(robot, base - need * share, base - (base - rhs))
    hr = _HalfRows(rows, gx, gy, h, rhs, ogx, ogy)
    return _solve(team, cfg, kin, lo, hi, scale, nominal, target, trig, pr, hr, du0, pose, u, obstacles, check)


class _HalfRows(NamedTuple):
    """Each robot's rows ``(B, N, K + M)``: kept, its half, the whole row's ``rhs``, the other robot's part.

    The half-row is ``(gx, gy) du_own <= h``; the whole row ``(gx, gy) du_own + (ogx, ogy) du_other <= rhs``.
    """

    on: torch.Tensor
    gx: torch.Tensor
    gy: torch.Tensor
    h: torch.Tensor
    rhs: torch.Tensor
    ogx: torch.Tensor
    ogy: torch.Tensor


def _solve(team, cfg, kin, lo, hi, scale, nominal, target, trig, pr, hr, du0, pose, u, obstacles,
           check) -> FilterOut:
    """The robots' QPs in ``w = A du`` (``solve_polygons``), trigger memory, groups, the answer and its report."""
    rows, gx, gy, h = hr.on, hr.gx, hr.gy, hr.h
    B, N, K = h.shape
    det = kin.a00 * kin.a11 - kin.a01 * kin.a10
    i00, i01, i10, i11 = kin.a11 / det, -kin.a01 / det, -kin.a10 / det, kin.a00 / det  # A^-1
    # half-planes in w: box rows of A^-1 (x <= hi, -x <= -lo), then the half-rows (A^-T G)' w <= h
    ax = torch.cat((torch.stack((i00, i10, -i00, -i10), -1), i00[..., None] * gx + i10[..., None] * gy), -1)
    ay = torch.cat((torch.stack((i01, i11, -i01, -i11), -1), i01[..., None] * gx + i11[..., None] * gy), -1)
    bb = torch.cat((hi, -lo, h), -1)
    nrm = safe_sqrt(ax * ax + ay * ay)
    valid = torch.cat((torch.ones(B, N, 4, dtype=torch.bool, device=h.device), rows), -1) & (nrm > 0)
    inv = torch.where(valid, 1.0 / torch.where(valid, nrm, 1.0), 0.0)
    C = ax.shape[-1]
    nx, ny = (ax * inv).reshape(-1, C), (ay * inv).reshape(-1, C)
    b = torch.where(valid, bb * inv, FAR).reshape(-1, C)
    t_box = matvec(kin.a00, kin.a01, kin.a10, kin.a11, du0).reshape(-1, 2)
    sol = solve_polygons(target.reshape(-1, 2), nx, ny, b, t_box, C - 4)
    if not bool(sol.feasible.all()):
        sol = _relaxed(sol, target.reshape(-1, 2), nx, ny, b, t_box, gx, gy, h, rows, inv[..., 4:], lo, hi,
                       du0, scale)
    du = torch.minimum(torch.maximum(matvec(i00, i01, i10, i11, sol.w.reshape(B, N, 2)), lo), hi)
    # the trigger's memory: z = lam |G| / (s max|H|), lam = mu / |A^-T G|, H = 2 A'A (decentralized._half_multipliers)
    lam = sol.mu.reshape(B, N, C)[..., 4:].detach() * inv[..., 4:].detach()
    hmax = 2.0 * torch.maximum(torch.maximum(kin.a00 ** 2 + kin.a10 ** 2, kin.a01 ** 2 + kin.a11 ** 2),
                               (kin.a00 * kin.a01 + kin.a10 * kin.a11).abs()).detach()  # (H's diagonal is >= 0)
    z = lam * torch.sqrt(gx * gx + gy * gy).detach() / (scale.detach() * hmax)[..., None]
    avoiding = ((z > cfg.eta_tol) & rows).any(-1)
    status = torch.where(sol.feasible.reshape(B, N), 0, RELAXED)
    if cfg.negotiate and bool(trig.any()):
        du, avoiding, status = _negotiate(cfg, kin, lo, hi, scale, target, du0, trig, pr, hr, du, avoiding, status)
    if cfg.backup:
        if check == "numpy":
            du, braking, broken = _numpy_backup(team, cfg, kin, pose, u, du, lo, hi, scale, pr, obstacles)
        else:
            if cfg.backup_repair:
                du = repair(team, cfg, pose, u, du, lo, hi, pr.other, pr.valid, pr.ds, obstacles)
            du, braking, broken = gate(team, cfg, pose, u, du, lo, hi, pr.other, pr.valid, pr.ds, obstacles)
        status = status | torch.where(braking, BACKUP, 0) | torch.where(broken, UNSAFE, 0)
    corr = row_norm(du - nominal)
    return FilterOut(du, status, avoiding, trig, corr, corr.detach() > 1e-9 * scale, pr.gap)


def _relaxed(sol: LocalAnswer, t, nx, ny, b, t_box, gx, gy, h, valid, inv, lo, hi, du0, scale) -> LocalAnswer:
    """The infeasible robots' answers: their rows loosened by the least violation, as the numpy local solver."""
    bad = torch.nonzero(~sol.feasible).flatten()
    gx, gy, h, valid, inv, lo, hi, du0 = (x.reshape(-1, x.shape[-1])[bad] for x in (gx, gy, h, valid, inv, lo, hi, du0))
    G = safe_sqrt(gx * gx + gy * gy)
    ok = valid & (G > 0)
    ig = torch.where(ok, 1.0 / torch.where(ok, G, 1.0), 0.0)
    _, viol = least_violation(gx * ig, gy * ig, torch.where(ok, h * ig, FAR), lo, hi, du0.detach())
    loosen = (viol * (1.0 + 1e-6) + RELAX_TOL * scale.reshape(-1)[bad, None]) * ok
    rows = torch.where(ok, (h + loosen.detach() * G) * inv, FAR)
    again = solve_polygons(t[bad], nx[bad], ny[bad], torch.cat((b[bad, :4], rows), 1), t_box[bad], rows.shape[1])
    return LocalAnswer(sol.w.index_copy(0, bad, again.w), sol.mu.index_copy(0, bad, again.mu),
                       sol.feasible.index_copy(0, bad, torch.zeros_like(again.feasible)))


def _negotiate(cfg: FilterConfig, kin: TensorKinematics, lo, hi, scale, target, du0, trig, pr: _Pairs,
               hr: _HalfRows, du, avoiding, status) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The numpy filter's negotiation groups (``negotiation_rows``), solved jointly by its solver on the CPU.

    Their robots get the groups' answer (a constant: no gradient), the trigger memory of the groups' multipliers and
    ``GROUPED``, with ``RELAXED`` where the answer violates one of their rows (an inconsistent group's least-violation
    answer).  One numpy call for every group of every team (:func:`~aasoatt_env.safety.decentralized.solve_groups`).
    """
    robot = hr.on & (pr.other >= 0)
    j = torch.clamp(pr.other, min=0)
    touch = robot & (pr.sep.detach() < cfg.negotiate_gap)
    member = trig | (touch & pick(trig, j)).any(-1)
    whole = robot & member[..., None] & pick(member, j)
    grouped = whole.any(-1)
    if not bool(grouped.any()):
        return du, avoiding, status
    B, N, K = whole.shape
    dev = du.device
    sub = torch.nonzero(grouped.flatten()).flatten()
    local = torch.full((B * N,), -1, dtype=torch.long, device=dev)
    local[sub] = torch.arange(sub.shape[0], device=dev)
    flat = torch.arange(B * N, device=dev).reshape(B, N)
    own, oth = local[flat][..., None].expand(B, N, K), local[pick(flat, j)]
    once = whole & (torch.arange(N, device=dev)[None, :, None] < pr.other)  # each whole row from its lower index
    kept = hr.on & grouped[..., None] & ~whole  # a grouped robot's halves of the other rows, obstacle rows whole

    g, go = torch.stack((hr.gx, hr.gy), -1), torch.stack((hr.ogx, hr.ogy), -1)
    A = torch.stack((kin.a00, kin.a01, kin.a10, kin.a11), -1).reshape(B, N, 2, 2)
    A, t, lo_s, hi_s, sc, d0 = (_numpy(x.flatten(0, 1)[sub]) for x in (A, target, lo, hi, scale, du0))
    ri, rj, owner = _numpy(own[once]), _numpy(oth[once]), _numpy(own[kept])
    Gi, Gj, rhs, G, h = _numpy(g[once]), _numpy(go[once]), _numpy(hr.rhs[once]), _numpy(g[kept]), _numpy(hr.h[kept])
    ans, _, _ = solve_groups(A, t, lo_s, hi_s, sc, Warm(d0 / sc[:, None], None), np.ones(sub.shape[0], bool),
                             (ri, rj, Gi, Gj, rhs), (owner, G, h), _policy(cfg), cfg.compiled,
                             _numpy(sub) // N)  # (each robot's team)
    m, x = ri.shape[0], ans.du
    over = np.concatenate(((Gi * x[ri]).sum(1) + (Gj * x[rj]).sum(1) - rhs, (G * x[owner]).sum(1) - h))
    tol = 1e-9 * np.concatenate((np.hypot(*Gi.T) * np.maximum(sc[ri], sc[rj]), np.hypot(*G.T) * sc[owner]))

    def robots(flag: np.ndarray) -> np.ndarray:
        """The grouped robots of the flagged rows: both of a whole row's, a kept half's owner."""
        out = np.zeros(sub.shape[0], dtype=bool)
        out[np.concatenate((ri, owner))[flag]] = out[rj[flag[:m]]] = True
        return out

    bound, loose = robots(ans.z > cfg.eta_tol), robots(over > tol)

    def put(base: torch.Tensor, new: np.ndarray) -> torch.Tensor:
        return base.flatten(0, 1).index_copy(0, sub, torch.as_tensor(new, dtype=base.dtype, device=dev)).view_as(base)

    mark = np.where(loose, GROUPED | RELAXED, GROUPED)
    return put(du, x), put(avoiding, bound), put(status, mark)


BACKUP_CHECKS: tuple[str, ...] = ("numpy", "torch")
"""The backup stage: ``"numpy"``, the numpy filter's backup layer on the CPU (one call for every team: the same
answers, the same guarantee; no gradient through the robots it changes); ``"torch"``, :mod:`.backup`'s sampled braking
check on the device (no transfer; its repair and braking are torch operations)."""


def backup_check_of(value: str | None, device: torch.device) -> str:
    """``value`` checked against :data:`BACKUP_CHECKS`; None: ``"numpy"`` on a CPU, ``"torch"`` on other devices."""
    if value is None:
        return "numpy" if torch.device(device).type == "cpu" else "torch"
    if value not in BACKUP_CHECKS:
        raise ConfigError(f"backup_check: got {value!r}, expected one of {list(BACKUP_CHECKS)} or None")
    return value


def _numpy_backup(team: TensorTeam, cfg: FilterConfig, kin: TensorKinematics, pose, u, du, lo, hi, scale,
                  pr: _Pairs, obstacles) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The numpy backup stage's ``(du, braking, unsafe)`` ``(B, N, ...)`` for the teams stacked as one.

    :func:`~aasoatt_env.safety.backup.backup_answer` with ``Team.group`` (no pair across teams) and the robot pairs of
    the filter's table.
    """
    B, N, _ = pr.other.shape
    dev = du.device
    if team.source is None:
        raise ConfigError("backup_check: 'numpy' needs a team built by TensorTeam.from_team (its numpy team)")
    stacked = stacked_team(team.source, B)

    def cpu(x: torch.Tensor) -> np.ndarray:
        return np.ascontiguousarray(_numpy(x.flatten(0, 1)))

    once = pr.valid & (torch.arange(N, device=dev)[None, :, None] < pr.other)  # every robot pair in range once
    b, n, k = torch.nonzero(once, as_tuple=True)
    pairs = _numpy(torch.stack((b * N + n, b * N + pr.other[b, n, k]), -1))  # (indices in the stacked team)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    obs = None
    if obstacles is not None and obstacles[1].shape[-1]:
        M = obstacles[1].shape[-1]
        obs = (_numpy(obstacles[0]).reshape(B * M, 2), _numpy(obstacles[1]).reshape(B * M),
               np.repeat(np.arange(B, dtype=np.int64), M))
    ans = backup_answer(stacked, pose_from_point(stacked, cpu(kin.p), cpu(pose[..., 2])), cpu(u), cpu(du), cpu(lo),
                        cpu(hi), cpu(scale), cfg, obs, pairs)

    def back(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, device=dev).reshape(B, N, *a.shape[1:])

    changed = back(ans.braking | ans.nudged)[..., None]  # (the masks are bool arrays)
    return torch.where(changed, back(ans.du).to(du.dtype), du), back(ans.braking), back(ans.unsafe)


def _numpy(x: torch.Tensor) -> np.ndarray:
    """``x`` on the CPU as numpy, floats as float64 (the numpy filter's stages)."""
    return x.detach().to("cpu", torch.float64 if x.is_floating_point() else x.dtype).numpy()


@functools.cache
def _policy(cfg: FilterConfig) -> SolverPolicy:
    """The numpy decentralised filter's solver route for the negotiation groups."""
    return SolverPolicy(cfg.solver, active_set=cfg.active_set, compiled=cfg.compiled,
                        one_change_iter=GROUP_ONE_CHANGE_ITER, iterations=cfg.neural_iterations)


class SafetyLayer(torch.nn.Module):
    """:func:`filter_step` as a layer: ``forward(pose, u, nominal, p_d, v_d, obstacles=None, avoiding=None) -> du``.

    Stateless (the trigger's memory is an argument); ``team``: a numpy :class:`~aasoatt_env.model.params.Team`;
    ``backup_check``: :data:`BACKUP_CHECKS` (None: the device's default, :func:`backup_check_of`).
    """

    def __init__(self, team, config: FilterConfig | Mapping[str, Any] | None = None, dtype: torch.dtype = torch.float64,
                 device: str | torch.device = "cpu", backup_check: str | None = None, **options) -> None:
        super().__init__()
        check_dtype_device(dtype, device)
        self.config = torch_config(config, **options)
        self.team = TensorTeam.from_team(team, dtype, device)
        self.backup_check = backup_check_of(backup_check, torch.device(device))

    def forward(self, pose, u, nominal, p_d, v_d, obstacles=None, avoiding=None) -> torch.Tensor:
        """The filtered wheel accelerations ``(B, N, 2)``."""
        return filter_step(self.team, self.config, pose, u, nominal, p_d, v_d, obstacles, avoiding,
                           self.backup_check).du
