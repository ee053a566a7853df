"""The repair of a QP answer toward brake-safety, and the backup layer's decision for it.

:func:`~aasoatt_env.safety.backup.gatekeeper` alone keeps the team safe: it puts
every robot whose candidate is not brake-safe on the braking backup.  Braking
costs liveness, so before the gatekeeper decides, :func:`repair` nudges the
QP's answer toward brake-safety (the least change that lifts every low backup
margin, like backup-barrier rows in the QP), and :func:`gate_with_repair` is
the order in which the filter asks: a quick check of the QP's answer, the
repair and a check of it, the full check of the QP's answer only when the
repaired one still brakes someone; outside the safe set, best effort.
"""

from __future__ import annotations

import numpy as np

from aasoatt_env.model.params import Team
from aasoatt_env.safety.backup import (
    GateResult,
    _brake,
    _bucketed,
    _candidate_reach,
    _first_step,
    _obstacles_near,
    _pairs_near,
    _point,
    candidate_paths,
    gatekeeper,
    pair_margins,
)
from aasoatt_env.safety.config import FilterConfig

__all__ = ["GATE_TOL", "gate_with_repair", "repair"]

GATE_TOL: float = 1e-9
"""Distance [m] the backup check forgives (floating-point rounding of the closed-form paths)."""


def gate_with_repair(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     cfg: FilterConfig, obstacles: tuple[np.ndarray, ...] | None) -> GateResult:
    """The backup layer's decision for the QP's answer ``du``: the gatekeeper, with the repair if it brakes.

    Every answer comes from :func:`~aasoatt_env.safety.backup.gatekeeper`
    (safety is its invariant).  Whether the QP's answer passes for every robot
    is decided by the first round, which is the same with or without the blend
    levels, so it is checked without them (``blend_levels=()``: fewer rounds).
    If someone brakes, the answer is nudged by
    :func:`repair` and checked again with the blend
    levels; the full check of the QP's answer is made only when the repaired
    one still brakes someone, and of the two the one that brakes fewer robots
    is kept.  When the invariant was already broken (``safe`` False), the full
    check of the QP's answer decides.
    """
    gate_kw = dict(sensing_range=cfg.sensing_range, brake_fraction=cfg.brake_fraction, obstacles=obstacles)
    quick = gatekeeper(team, pose, u, du, cfg.dt, tol=GATE_TOL, blend_levels=(), **gate_kw)
    if not quick.braking.any():
        return quick
    if not quick.safe and quick.margin < 0.0:
        # the invariant is already broken (a start that was not brake-safe, an assumption violated):
        # best effort is the same gate with every pair held to its own margin under braking, so no
        # pair gets closer than braking would bring it while robots may still move apart (pair by
        # pair: a stack of teams decides as each team alone); the result keeps saying unsafe, and
        # the caller's bounds stay hard (they bind only when tighter than the robots' own, which
        # the backup respects)
        held = gatekeeper(team, pose, u, du, cfg.dt, tol=GATE_TOL, hold_violations=True, **gate_kw)
        return held._replace(safe=False, du=np.minimum(np.maximum(held.du, lo), hi))
    if not (cfg.backup_repair and quick.safe):
        return gatekeeper(team, pose, u, du, cfg.dt, tol=GATE_TOL, **gate_kw)
    # nudge the QP's answer toward brake-safety, then check again (usually nobody brakes then)
    repaired = repair(team, pose, u, du, cfg.dt, lo, hi, **gate_kw)
    second = gatekeeper(team, pose, u, repaired, cfg.dt, tol=GATE_TOL, **gate_kw)
    if not second.braking.any():
        return second
    first = gatekeeper(team, pose, u, du, cfg.dt, tol=GATE_TOL, **gate_kw)
    if first.safe and int(second.braking.sum()) <= int(first.braking.sum()):
        return second
    return first


def repair(
    team: Team,
    pose: np.ndarray,
    u: np.ndarray,
    du_c: np.ndarray,
    dt: float,
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    sensing_range: float,
    brake_fraction: float,
    obstacles: tuple[np.ndarray, np.ndarray] | None = None,
    target: float = 2e-4,
    rounds: int = 3,
    eps: float = 1.0,
) -> np.ndarray:
    """Nudge a candidate toward brake-safety: the least change that lifts every low backup margin.

    For every pair whose margin along :func:`~aasoatt_env.safety.backup.candidate_paths` is below
    ``target`` [m], the margin's gradient with respect to both robots' inputs is
    taken by finite differences (step ``eps`` in input units; one extra path
    set per input direction, for the robots of such pairs only), and the two
    inputs move by the least-norm change that lifts the linearised margin to
    ``2 target``; changes from several pairs add up, and the result is clipped
    to ``[lo, hi]``.  ``rounds`` rounds.  This acts like backup-barrier rows in
    the QP (a small, local correction toward the safe set), so the gatekeeper
    rarely has to brake; safety still comes from :func:`~aasoatt_env.safety.backup.gatekeeper` alone.
    """
    du = np.minimum(np.maximum(du_c, lo), hi)
    n = pose.shape[0]
    eye = np.eye(2)
    p0 = _point(team, pose)
    for _ in range(rounds):
        # reach first (O(N)): only robots with a pair that could come close need sampled paths
        p1, d1, theta1, u1 = _first_step(team, p0, pose[:, 2], u, du, dt)
        R = _candidate_reach(p0, p1, d1, _brake(team, theta1, u1, dt, brake_fraction)) + eps * dt * dt
        i, j, ds = _pairs_near(team, p0, R, sensing_range, 2.0 * target)
        oc, oi, ok, ods = _obstacles_near(team, p0, R, obstacles, 2.0 * target)
        if i.size + oi.size == 0:
            break
        S = np.unique(np.concatenate((i, j, oi)))  # rows of `base`: these robots, in this order
        loc = np.full(n, -1, dtype=np.intp)
        loc[S] = np.arange(S.size)
        base = candidate_paths(team.subset(S), pose[S], u[S], du[S], dt, brake_fraction)
        m = _bucketed(base.p, base.delta, base.length, loc[i], loc[j], ds)
        low = m < target
        i, j, ds = i[low], j[low], ds[low]
        if oi.size:
            mo = _bucketed(base.p, base.delta, base.length, loc[oi], ok, ods, centers=oc)
            lowo = mo < target
            oi, ok, ods = oi[lowo], ok[lowo], ods[lowo]
        if i.size + oi.size == 0:
            break
        M = np.unique(np.concatenate((i, j, oi)))
        m = M.size
        s_n = S.size
        L = base.p.shape[1] + 1  # a perturbation of eps dt in u adds at most one backup step
        # rows [0, s): the base paths of S; [s, 2s) and [2s, 3s): with input k of the robots M
        # perturbed (both perturbations in one call, and every margin below in one call: the same
        # numbers, row by row, as separate calls)
        P = np.concatenate((base.p, base.p[:, -1:]), axis=1)
        D = np.concatenate((base.delta, np.zeros((s_n, 1))), axis=1)
        P, D = np.concatenate((P, P, P)), np.concatenate((D, D, D))
        MM = np.concatenate((M, M))
        t = candidate_paths(team.subset(MM), pose[MM], u[MM], du[MM] + eps * np.repeat(eye, m, axis=0), dt,
                            brake_fraction, L)
        lM = loc[M]
        P[np.concatenate((s_n + lM, 2 * s_n + lM))], D[np.concatenate((s_n + lM, 2 * s_n + lM))] = t.p, t.delta
        step = np.zeros((n, 2))
        if i.size:
            li, lj = loc[i], loc[j]
            a = np.concatenate((li, s_n + li, 2 * s_n + li, li, li))
            b = np.concatenate((lj, lj, lj, s_n + lj, 2 * s_n + lj))
            mg = pair_margins(P[a], P[b], D[a], D[b], np.tile(ds, 5)).reshape(5, -1)
            m0 = mg[0]
            gi = ((mg[1:3] - m0) / eps).T
            gj = ((mg[3:5] - m0) / eps).T
            lift = (2.0 * target - m0) / np.maximum((gi * gi).sum(1) + (gj * gj).sum(1), 1e-12)
            np.add.at(step, i, lift[:, None] * gi)
            np.add.at(step, j, lift[:, None] * gj)
        if oi.size:
            lo_ = loc[oi]
            a = np.concatenate((lo_, s_n + lo_, 2 * s_n + lo_))
            mg = pair_margins(P[a], oc[np.tile(ok, 3)][:, None], D[a], 0.0, np.tile(ods, 3)).reshape(3, -1)
            m0 = mg[0]
            go = ((mg[1:3] - m0) / eps).T
            lift = (2.0 * target - m0) / np.maximum((go * go).sum(1), 1e-12)
            np.add.at(step, oi, lift[:, None] * go)
        if not step.any():
            break
        du = np.minimum(np.maximum(du + step, lo), hi)
    return du
