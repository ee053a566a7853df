"""The gatekeeper (a candidate passes where braking from the state it leads to keeps every pair apart) and the repair.

Pair check (:func:`pair_margins`): within a step a wheeled robot's arc leaves its chord by at most its sagitta
``|p_dot| |omega| dt^2 / 8``, a point mass's parabola by ``|du| dt^2 / 8``; the distance from the origin to the segment
of relative positions minus both bounds the pair's distance over the step from below (safe: ``>= d_s`` at every step).
Obstacles are robots that never move.  The repair nudges a QP answer toward brake-safety.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.geometry import robot_pairs
from aasoatt_env.model.params import SUBSET_OF, Team
from aasoatt_env.safety.backup import paths
from aasoatt_env.validation import shapes

__all__ = ["BLEND_LEVELS", "CLOSEST_TIE", "GateResult", "gatekeeper", "pair_margins", "repair"]

BLEND_LEVELS: tuple[float, ...] = (0.5,)  #: default blend shares of candidate and backup (``gatekeeper``'s)
CLOSEST_TIE: float = 1e-12  #: steps within this [m] of a pair's smallest distance tie for its closest step
_ONE_BUCKET_CELLS = 4096  # pair batches with at most this many samples in all: one call, not one per horizon bucket


def pair_margins(pi: np.ndarray, pj: np.ndarray, di: np.ndarray, dj: np.ndarray | float, ds: np.ndarray,
                 closest: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Smallest ``distance - d_s`` of each pair along sampled paths, a lower bound between samples.

    ``pi``, ``pj`` ``(P, L)`` complex positions (``pj`` ``(P, 1)``: a static point); ``di``, ``dj`` ``(P, L-1)``
    deviation bounds (``dj`` may be 0).  ``closest``: also the first step within :data:`CLOSEST_TIE` of the minimum.
    """
    q = pi - pj
    if q.shape[1] == 1:
        m = np.abs(q[:, 0]) - ds
        return (m, np.zeros(m.shape[0], dtype=np.intp)) if closest else m
    # ``t = clip(-dot / where(dd > 0, dd, 1), 0, 1)``, ``|q0 + t dq| - di - dj``, in place
    q0 = q[:, :-1]
    dq = q[:, 1:] - q0
    dr, dm = dq.real, dq.imag
    dd = dr * dr
    tmp = dm * dm
    dd += tmp
    t = q0.real * dr
    np.multiply(q0.imag, dm, out=tmp)
    t += tmp
    np.negative(t, out=t)
    np.copyto(dd, 1.0, where=~(dd > 0.0))
    t /= dd
    np.clip(t, 0.0, 1.0, out=t)
    np.multiply(t, dq, out=dq)
    dq += q0
    dist = np.abs(dq)
    dist -= di
    dist -= dj
    if closest:  # which of tied steps wins must not hang on the last bit; a NaN wins
        low = dist.min(axis=1)
        k = np.where(np.isnan(low), dist.argmin(axis=1), (dist <= low[:, None] + CLOSEST_TIE).argmax(axis=1))
        return dist[np.arange(k.shape[0]), k] - ds, k
    return dist.min(axis=1) - ds


def bucketed_margins(P: np.ndarray, D: np.ndarray, need: np.ndarray, ii: np.ndarray, jj: np.ndarray, ds: np.ndarray,
                     centers: np.ndarray | None = None) -> np.ndarray:
    """:func:`pair_margins` of rows ``ii``, ``jj`` of ``P`` (``centers``: static ``jj``) by horizon bucket."""
    out = np.empty(ii.shape[0])
    if ii.size == 0:
        return out
    lens = np.maximum(need[ii] if centers is not None else np.maximum(need[ii], need[jj]), 2)
    if ii.size * int(lens.max()) <= max(2 * int(lens.sum()), _ONE_BUCKET_CELLS):
        bucket = np.zeros(ii.shape[0], dtype=np.int64)  # small or even: one call (padding samples are at rest)
    else:
        bucket = np.frexp(lens - 1)[1].astype(np.int64)  # ceil(log2(lens)), exactly
    for b in np.unique(bucket):
        sel = np.flatnonzero(bucket == b)
        Lb = int(lens[sel].max())
        a, c = ii[sel], jj[sel]
        if centers is None:
            out[sel] = pair_margins(P[a, :Lb], P[c, :Lb], D[a, : Lb - 1], D[c, : Lb - 1], ds[sel])
        else:
            out[sel] = pair_margins(P[a, :Lb], centers[c][:, None], D[a, : Lb - 1], 0.0, ds[sel])
    return out


class GateResult(NamedTuple):
    """What :func:`gatekeeper` decided, per robot ``(N,)`` unless said."""

    du: np.ndarray  #: ``(N, 2)`` the inputs to apply
    braking: np.ndarray  #: blended toward, or put on, the backup
    margin: float  #: least ``distance - d_s`` [m] of the checked pairs along the inputs' horizon (else range limits)
    safe: bool  #: the state was brake-safe
    broken: np.ndarray  #: in a pair failing even when both brake, or its braking leaves the range limit
    share: np.ndarray  #: the candidate's share in the input (1: the candidate, 0: the backup)
    rounds: int
    n_pairs: int  #: robot and obstacle pairs checked
    robot_margin: np.ndarray  #: each robot's least pair margin, at most its range limit
    out_of_range: np.ndarray  #: the candidate path leaves the range limit
    held: np.ndarray | None = None  #: :func:`~.layer.gate_with_repair`'s best effort outside the safe set (None: none)


def gatekeeper(team: Team, pose: np.ndarray, u: np.ndarray, du_c: np.ndarray, dt: float, *, sensing_range: float,
               brake_fraction: float, obstacles: tuple[np.ndarray, ...] | None = None, tol: float = 0.0,
               blend_levels: tuple[float, ...] = BLEND_LEVELS, hold_violations: bool = False, quick: bool = False,
               near_pairs: np.ndarray | None = None, compiled: bool = False, checked: bool = False) -> GateResult:
    """Accept the candidate ``du_c`` for every robot whose pairs stay brake-safe; put the others on the backup.

    Levels: the candidate (share 1), the blends ``du_b + a (du_c - du_b)`` for ``a`` in ``blend_levels`` (one step,
    then the backup), the backup from now (share 0); a level whose path leaves the robot's
    :func:`~aasoatt_env.safety.backup.reach_limit` is skipped, and failing pairs' members move one level down until
    none fails.  The backup is time-consistent, so a brake-safe state stays brake-safe and a team at rest without
    overlap never collides, whatever the candidate, provided every robot checks the same state with the real bounds
    and ``dt``, applies the inputs as returned, and ``tol`` [m] absorbs the rounding (:data:`~.layer.GATE_TOL`).

    ``pose`` ``(N, 3)``; ``obstacles``: ``(centres (M, 2), radii (M,)[, groups (M,)])``; ``blend_levels`` in
    ``(0, 1]`` (``()``: brake at once); ``tol < 0`` asks a clearance; ``hold_violations``: outside the safe set, hold
    a pair failing even when both brake at that margin, not mark it broken; ``quick``: the candidate's verdict only;
    ``near_pairs`` ``(P, 2)``: a superset of the same-group pairs within ``D`` (None: searched); ``checked``: the
    caller vouches for every shape and index.
    """
    levels = levels_of(tuple(blend_levels))
    if not checked:
        near_pairs = validate(team, pose, obstacles, near_pairs, u=u, du_c=du_c)
    if compiled:
        du, braking, broken, share, robot_margin, out_of_range, rounds, n_pairs, margin = kernels().gate_full(
            c64(pose), c64(u), c64(du_c), float(dt), levels, bool(quick),
            *kernel_args(team, pose, brake_fraction, sensing_range, obstacles, near_pairs),
            team_block(team, brake_fraction, sensing_range)[1], float(tol), bool(hold_violations))
        return GateResult(du, braking, float(margin), not bool(broken.any()), broken, share, int(rounds), int(n_pairs),
                          robot_margin, out_of_range)
    n = pose.shape[0]
    p0 = paths.point(team, pose)
    limit = paths.reach_limit(team, sensing_range)
    levels, du_all, firsts, b0, reach = _levels(team, pose, p0, u, du_c, dt, brake_fraction, levels, quick, limit)
    last = len(levels) - 1
    lev = _in_range(np.zeros(n, dtype=np.int64), reach, limit)
    broken = reach[last] > limit
    R = reach.max(axis=0)
    i, j, ds = pairs_near(team, p0, R, sensing_range, 1e-12, near_pairs)
    oc, oi, ok, ods = obstacles_near(team, p0, R, obstacles, 1e-12)
    rounds, robot_margin = 0, limit.copy()
    if i.size + oi.size:
        lp = (p0, firsts, b0, np.unique(np.concatenate((i, j, oi))), dt)
        rounds, marg, omarg = _rounds(lp, lev, broken, reach, limit, (i, j, ds), (oi, ok, ods, oc), tol,
                                      hold_violations)
        np.minimum.at(robot_margin, np.concatenate((i, j, oi)), np.concatenate((marg, marg, omarg)))
    margin = float(robot_margin.min(initial=float(limit.min(initial=0.5 * float(sensing_range)))))
    return GateResult(du_all[lev, np.arange(n)], lev > 0, margin, not bool(broken.any()), broken,
                      levels[lev], rounds, int(i.size + oi.size), robot_margin, reach[0] > limit)


def _levels(team: Team, pose: np.ndarray, p0: np.ndarray, u: np.ndarray, du_c: np.ndarray, dt: float,
            brake_fraction: float, levels: np.ndarray, quick: bool, limit: np.ndarray) -> tuple:
    """``(levels, inputs (levels, N, 2), candidates per blend level, the backup from now, reaches (levels, N))``."""
    theta = pose[:, 2]
    T0 = paths.brake_time(team, u, brake_fraction)
    du_b = -u / np.maximum(T0, dt)[:, None]  # braking_du
    firsts, dus = [], []
    for k, a in enumerate(levels[:-1]):
        dus.append(du_b + a * (du_c - du_b))
        firsts.append(paths.candidate(team, p0, theta, u, dus[-1], dt, brake_fraction))
        if k == 0 and quick and not bool((firsts[0].reach > limit).any()):
            levels = levels[[0, -1]]  # no candidate leaves the range: the blends would change nothing
            break
    b0 = paths.brake(team, theta, u, dt, brake_fraction, T0)
    reach = np.stack([c.reach for c in firsts] + [b0.reach])
    np.copyto(reach, np.inf, where=np.isnan(reach))  # a reach that is not a number bounds nothing
    return levels, np.stack(dus + [du_b]), firsts, b0, reach


def _in_range(lev: np.ndarray, reach: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Each robot's first level from ``lev`` on whose path stays within its range limit (or the backup)."""
    for k in range(reach.shape[0] - 1):
        lev = np.where((lev == k) & (reach[k] > limit), k + 1, lev)
    return lev


def _level_rows(p0: np.ndarray, firsts: list, b0, g: np.ndarray, k: int, dt: float, L: int) -> tuple:
    """Samples ``(len(g), L)`` and deviations ``(len(g), L-1)`` of robots ``g``' paths on level ``k``."""
    if k == len(firsts):
        return paths.brake_samples(p0[g], b0.take(g), dt, L)
    c = firsts[k]
    return paths.candidate_samples(p0[g], c._replace(p1=c.p1[g], d1=c.d1[g], b1=c.b1.take(g)), dt, L)


def _rounds(lp: tuple, lev: np.ndarray, broken: np.ndarray, reach: np.ndarray, limit: np.ndarray,
            pairs: tuple, obst: tuple, tol: float, hold: bool) -> tuple[int, np.ndarray, np.ndarray]:
    """The rounds on robots ``lp[3]``' paths (:func:`_level_rows`): ``lev``, ``broken`` in place; margins."""
    (i, j, ds), (oi, ok, ods, oc), (p0, firsts, b0, M, dt) = pairs, obst, lp
    n, last = lev.shape[0], reach.shape[0] - 1
    need = np.stack([c.b1.steps[M] + 2 for c in firsts] + [b0.steps[M] + 1])  # samples per level and row
    L = max(int(need.max(initial=0)), 2)
    loc = np.full(n, -1, dtype=np.intp)
    loc[M] = np.arange(M.size)
    li, lj, lo_ = loc[i], loc[j], loc[oi]
    rows_m = np.arange(M.size)
    tol_p, tol_o = np.full(i.shape[0], float(tol)), np.full(oi.shape[0], float(tol))
    if hold:  # each pair's own floor, the larger of it and tol: its margin when both members brake now
        Pb, Db = _level_rows(p0, firsts, b0, M, last, dt, L)
        tol_p = np.fmax(tol_p, np.fmax(0.0, -bucketed_margins(Pb, Db, need[last], li, lj, ds)) * (1.0 + 1e-9))
        tol_o = np.fmax(tol_o, np.fmax(0.0, -bucketed_margins(Pb, Db, need[last], lo_, ok, ods, oc)) * (1.0 + 1e-9))
    marg, omarg = np.full(i.shape[0], np.inf), np.full(oi.shape[0], np.inf)
    todo, otodo = np.ones(i.shape[0], dtype=bool), np.ones(oi.shape[0], dtype=bool)
    cur = np.empty((M.size, L), dtype=np.complex128)
    curd = np.empty((M.size, L - 1))
    filled = np.full(M.size, -1)  # the level whose paths are in a row of `cur`
    rounds = 0
    while True:
        rounds += 1
        lm = lev[M]
        stale = lm != filled  # only rows whose level changed are made again
        for k in np.unique(lm[stale]):
            r = np.flatnonzero(stale & (lm == k))
            cur[r], curd[r] = _level_rows(p0, firsts, b0, M[r], int(k), dt, L)
        filled = lm
        cneed = need[lm, rows_m]
        idx, oidx = np.flatnonzero(todo), np.flatnonzero(otodo)
        marg[idx] = bucketed_margins(cur, curd, cneed, li[idx], lj[idx], ds[idx])
        omarg[oidx] = bucketed_margins(cur, curd, cneed, lo_[oidx], ok[oidx], ods[oidx], centers=oc)
        np.copyto(marg, -np.inf, where=np.isnan(marg))  # a margin that is not a number fails
        np.copyto(omarg, -np.inf, where=np.isnan(omarg))
        bad, obad = idx[marg[idx] < -tol_p[idx]], oidx[omarg[oidx] < -tol_o[oidx]]
        a, c, o = i[bad], j[bad], oi[obad]
        at_backup = lev == last  # a pair failing with its members on the backup was not brake-safe before
        both = at_backup[a] & at_backup[c]
        broken[a[both]] = broken[c[both]] = broken[o[at_backup[o]]] = True
        demote = np.zeros(n, dtype=bool)
        demote[a] = demote[c] = demote[o] = True
        demote &= ~at_backup
        if not demote.any():
            return rounds, marg, omarg
        # a blend's reach is not bounded by those of the levels around it: the range condition again
        lev[:] = _in_range(np.where(demote, lev + 1, lev), reach, limit)
        todo, otodo = demote[i] | demote[j], demote[oi]


@functools.lru_cache(maxsize=64)
def levels_of(blend_levels: tuple) -> np.ndarray:
    """The check's levels, highest first (read-only): 1 (the candidate), the blend shares, 0 (the backup from now)."""
    levels = np.array(sorted(set(float(x) for x in blend_levels) | {1.0}, reverse=True) + [0.0])
    if not all(0.0 < a <= 1.0 for a in levels[:-1]):  # also refuses NaN
        raise ValueError(f"blend_levels: got {blend_levels!r}, expected shares in (0, 1]")
    levels.flags.writeable = False
    return levels


_EMPTY_INT = np.empty(0, dtype=np.int64)
_NO_OC = np.empty(0, dtype=np.complex128)
_NO_R = np.empty(0)


def team_block(team: Team, brake_fraction: float, sensing_range: float) -> tuple:
    """``((diff, robots (N, 5), input columns, group, has_group, D), reach limits)``, cached on the team."""
    key = ("gatekeeper", float(brake_fraction), float(sensing_range))
    block = team.derived.get(key)
    if block is None and SUBSET_OF in team.derived:
        whole, idx = team.derived[SUBSET_OF]
        (diff, rob, cols, group, has_group, rng), limit = team_block(whole, brake_fraction, sensing_range)
        block = team.derived[key] = ((diff, rob[idx], cols[idx], group[idx] if has_group else group, has_group, rng),
                                     limit[idx])
    if block is None:  # robots: offset, turn gain, wheel acceleration bound, backup deceleration, radius
        rob = np.column_stack((team.offset, team.turn_gain, team.max_wheel_accel,
                               paths.brake_decel(team, brake_fraction), team.radius))
        group = team.group if team.group is not None else _EMPTY_INT
        block = team.derived[key] = ((team.is_diff_drive, rob, team.input_columns, group, team.group is not None,
                                      float(sensing_range)), paths.reach_limit(team, sensing_range))
    return block


def validate(team: Team, pose: np.ndarray, obstacles: tuple[np.ndarray, ...] | None, near_pairs: np.ndarray | None,
             **per_robot: np.ndarray) -> np.ndarray | None:
    """Refuse (``ValueError``) any shape or pair index the kernels would misread; ``near_pairs`` as an array."""
    n = team.n
    shapes([("pose", pose, (n, 3)), *((k, a, (n, 2)) for k, a in per_robot.items())], f" for a team of {n} robots")
    if obstacles is not None and np.asarray(obstacles[1]).size:
        c, orad = np.asarray(obstacles[0]), np.asarray(obstacles[1])
        grouped = team.group is not None and len(obstacles) > 2 and obstacles[2] is not None
        m = orad.shape[0] if orad.ndim == 1 else -1
        if c.shape != (m, 2) or (grouped and np.shape(obstacles[2]) != (m,)):
            raise ValueError(f"obstacles: got centres {c.shape}, radii {orad.shape}"
                             + (f", groups {np.shape(obstacles[2])}" if grouped else "")
                             + ", expected (M, 2), (M,) and (M,)")
    if near_pairs is not None:
        near_pairs = np.asarray(near_pairs)
        if (near_pairs.ndim != 2 or near_pairs.shape[1] != 2 or near_pairs.dtype.kind not in "iu"
                or (near_pairs.size and not (0 <= near_pairs.min() and near_pairs.max() < n))):
            raise ValueError(f"near_pairs: got a {near_pairs.dtype} array of shape {near_pairs.shape}, expected "
                             f"(P, 2) integer robot indices in [0, {n})")
    return near_pairs


def kernel_args(team: Team, pose: np.ndarray, brake_fraction: float, sensing_range: float,
                obstacles: tuple[np.ndarray, ...] | None, near_pairs: np.ndarray | None) -> tuple:
    """The kernels' block: :func:`team_block`'s, the candidate pairs (``near_pairs`` or searched), the obstacles."""
    if near_pairs is None:
        p0 = paths.point(team, pose)
        near_pairs = robot_pairs(np.stack((p0.real, p0.imag), axis=1), sensing_range, groups=team.group)
    oc, orad, ogroup = _obstacle_arrays(team, obstacles)
    return (*team_block(team, brake_fraction, sensing_range)[0], np.ascontiguousarray(near_pairs, dtype=np.int64),
            oc, orad, _EMPTY_INT if ogroup is None else ogroup, ogroup is not None)


def pairs_near(team: Team, p0: np.ndarray, R: np.ndarray, sensing_range: float, slack: float,
               near_pairs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robot pairs ``(i, j, d_s)`` within ``sensing_range`` that could come within ``d_s + slack`` (``R``: reaches)."""
    rad = team.radius
    if near_pairs is None:
        search = min(float(sensing_range), 2.0 * float(rad.max(initial=0.0)) + 2.0 * float(R.max(initial=0.0))
                     + slack)
        pr = robot_pairs(np.stack((p0.real, p0.imag), axis=1), search, groups=team.group, compiled=False)
    else:  # as robot_pairs at the range: <= D kept, and with groups, pairs of one group only
        pr = near_pairs
        drop = np.abs(p0[pr[:, 0]] - p0[pr[:, 1]]) > sensing_range
        if team.group is not None:
            drop |= team.group[pr[:, 0]] != team.group[pr[:, 1]]
        if drop.any():
            pr = pr[~drop]
    i, j = pr[:, 0], pr[:, 1]
    ds = rad[i] + rad[j]
    keep = np.abs(p0[i] - p0[j]) < ds + R[i] + R[j] + slack
    return i[keep], j[keep], ds[keep]


def obstacles_near(team: Team, p0: np.ndarray, R: np.ndarray, obstacles: tuple[np.ndarray, ...] | None,
                   slack: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robot-obstacle pairs that could come within ``d_s + slack``: ``(centres (M,) complex, i, k, d_s)``."""
    oc, orad, ogroup = _obstacle_arrays(team, obstacles)
    rad = team.radius
    near = np.abs(p0[:, None] - oc[None, :]) < rad[:, None] + orad[None, :] + R[:, None] + slack
    if ogroup is not None:
        near &= team.group[:, None] == ogroup[None, :]
    oi, ok = np.nonzero(near)
    return oc, oi, ok, rad[oi] + orad[ok]


def _obstacle_arrays(team: Team, obstacles: tuple[np.ndarray, ...] | None) -> tuple:
    """``(centres (M,) complex, radii (M,), groups (M,), or None where the team or the obstacles have none)``."""
    if obstacles is None or not np.asarray(obstacles[1]).size:
        return _NO_OC, _NO_R, None
    c, orad = np.asarray(obstacles[0], dtype=np.float64), np.asarray(obstacles[1], dtype=np.float64)
    grouped = team.group is not None and len(obstacles) > 2 and obstacles[2] is not None
    return c[:, 0] + 1j * c[:, 1], orad, np.asarray(obstacles[2]) if grouped else None


def repair(team: Team, pose: np.ndarray, u: np.ndarray, du_c: np.ndarray, dt: float, lo: np.ndarray, hi: np.ndarray,
           *, sensing_range: float, brake_fraction: float, obstacles: tuple[np.ndarray, ...] | None = None,
           target: float = 2e-4, rounds: int = 3, eps: float = 1.0, near_pairs: np.ndarray | None = None,
           compiled: bool = False, checked: bool = False) -> np.ndarray:
    """Nudge a candidate toward brake-safety: the least change that lifts every low backup margin.

    Each pair whose candidate-path margin is below ``target`` [m] moves both inputs by the least-norm change lifting
    it to ``2 target`` (finite differences, step ``eps``, at its closest step); the changes add up, clipped to
    ``[lo, hi]``, ``rounds`` times.  Safety still comes from the gatekeeper (``near_pairs``, ``compiled``, ``checked``
    as there).
    """
    if not checked:
        near_pairs = validate(team, pose, obstacles, near_pairs, u=u, du_c=du_c, lo=lo, hi=hi)
    if compiled:
        block = kernel_args(team, pose, brake_fraction, sensing_range, obstacles, near_pairs)
        pose, u, du_c, lo, hi = (c64(a) for a in (pose, u, du_c, lo, hi))
        return kernels().repair_full(pose, u, du_c, lo, hi, float(dt), *block, float(target), int(rounds),
                                     float(eps), CLOSEST_TIE)
    du = np.minimum(np.maximum(du_c, lo), hi)
    n = pose.shape[0]
    p0 = paths.point(team, pose)
    for _ in range(rounds):
        # reach first (O(N)): only robots with a pair that could come close need sampled paths
        R = paths.candidate(team, p0, pose[:, 2], u, du, dt, brake_fraction).reach + eps * dt * dt
        i, j, ds = pairs_near(team, p0, R, sensing_range, 2.0 * target, near_pairs)
        oc, oi, ok, ods = obstacles_near(team, p0, R, obstacles, 2.0 * target)
        if i.size + oi.size == 0:
            break
        S = np.unique(np.concatenate((i, j, oi)))  # rows of the paths: these robots, in this order
        loc = np.full(n, -1, dtype=np.intp)
        loc[S] = np.arange(S.size)
        t = paths.candidate_paths(team.subset(S), pose[S], u[S], du[S], dt, brake_fraction)
        P, D, need = t.p, t.delta, t.length
        low = bucketed_margins(P, D, need, loc[i], loc[j], ds) < target
        i, j, ds = i[low], j[low], ds[low]
        if oi.size:
            lowo = bucketed_margins(P, D, need, loc[oi], ok, ods, centers=oc) < target
            oi, ok, ods = oi[lowo], ok[lowo], ods[lowo]
        if i.size + oi.size == 0:
            break
        step = _lifts(team, pose, u, du, dt, brake_fraction, target, eps, (P, D), loc, (i, j, ds), (oc, oi, ok, ods))
        if not step.any():
            break
        du = np.minimum(np.maximum(du + step, lo), hi)
    return du


def _lifts(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float, brake_fraction: float,
           target: float, eps: float, base: tuple, loc: np.ndarray, pairs: tuple, obst: tuple) -> np.ndarray:
    """The summed least-norm lifts ``(n, 2)`` of the low pairs, by finite differences at their closest steps."""
    (P, D), (i, j, ds), (oc, oi, ok, ods) = base, pairs, obst
    n = pose.shape[0]
    step = np.zeros((n, 2))
    U = np.unique(np.concatenate((i, j, oi)))  # every robot of a low pair with each input moved: rows 2 q + d
    at = np.full(n, -1, dtype=np.intp)
    at[U] = 2 * np.arange(U.size)
    R2 = np.repeat(U, 2)
    sub = (team.subset(R2), pose[R2], u[R2], du[R2] + eps * np.tile(np.eye(2), (U.size, 1)), dt, brake_fraction)
    if i.size:
        li, lj = loc[i], loc[j]
        m0, k = pair_margins(P[li], P[lj], D[li], D[lj], ds, closest=True)
        s4 = np.tile(k[:, None] + np.arange(2), (4, 1))
        fix = np.concatenate((lj, lj, li, li))
        pm, dm = paths.candidate_samples_at(*sub, s4, rows=np.concatenate((at[i], at[i] + 1, at[j], at[j] + 1)))
        mg = pair_margins(pm, P[fix[:, None], s4], dm[:, :1], D[fix, s4[:, 0]][:, None], np.tile(ds, 4))
        mg = mg.reshape(4, -1)
        gi = ((mg[0:2] - m0) / eps).T
        gj = ((mg[2:4] - m0) / eps).T
        lift = (2.0 * target - m0) / np.maximum((gi * gi).sum(1) + (gj * gj).sum(1), 1e-12)
        np.add.at(step, i, lift[:, None] * gi)
        np.add.at(step, j, lift[:, None] * gj)
    if oi.size:
        lo_ = loc[oi]
        m0, k = pair_margins(P[lo_], oc[ok][:, None], D[lo_], 0.0, ods, closest=True)
        s2 = np.tile(k[:, None] + np.arange(2), (2, 1))
        pm, dm = paths.candidate_samples_at(*sub, s2, rows=np.concatenate((at[oi], at[oi] + 1)))
        mg = pair_margins(pm, oc[np.tile(ok, 2)][:, None], dm[:, :1], 0.0, np.tile(ods, 2)).reshape(2, -1)
        go = ((mg - m0) / eps).T
        lift = (2.0 * target - m0) / np.maximum((go * go).sum(1), 1e-12)
        np.add.at(step, oi, lift[:, None] * go)
    return step
