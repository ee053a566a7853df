"""The gatekeeper of the braking backup layer: keeps the team collision-free for any nominal.

It checks the QP's answer against the backup policy of
:mod:`aasoatt_env.safety.backup` (proportional braking, in closed form) every
robot can always execute, and applies the backup where the answer would leave
the set of states from which the backup keeps every pair apart (a gatekeeper in
the sense of Agrawal and Panagou; a backup-set barrier in the sense of Gurriet
et al.).

Pair check (:func:`pair_margins`)
    Within a step a wheeled robot's simulated path is an arc at constant speed,
    which deviates from the straight, linear-in-time interpolation of its end
    points by at most its sagitta ``|p_dot| |omega| dt^2 / 8``; a point mass's
    is the parabola of its held acceleration, ``|du| dt^2 / 8`` off.  The distance from the origin to a
    segment of *relative* positions minus both robots' sagittas bounds the
    pair's distance from below over that step; a pair is safe over a horizon
    when that bound is ``>= d_s = r_i + r_j`` on every step.  Obstacles are
    robots that never move.

Gatekeeper (:func:`gatekeeper`) and its invariance argument: see its docstring.
Everything is vectorised over robots and pairs; Python loops run only over the
gatekeeper's rounds and over a few length buckets of the pair batch.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.geometry import robot_pairs
from aasoatt_env.model.params import SUBSET_OF, Team
from aasoatt_env.safety.backup.paths import (
    brake,
    brake_decel,
    brake_samples,
    brake_time,
    candidate_reach,
    candidate_samples,
    first_step,
    point,
    reach_limit,
    take_robots,
)

__all__ = ["BLEND_LEVELS", "GateResult", "gatekeeper", "pair_margins"]

BLEND_LEVELS: tuple[float, ...] = (0.5,)
"""The check's default blend shares between the candidate and the backup (``gatekeeper``'s ``blend_levels``)."""


# --------------------------------------------------------------------------- pair check
CLOSEST_TIE: float = 1e-12
"""Steps whose distance is within this [m] of a pair's smallest count as tied for its closest step."""


def pair_margins(pi: np.ndarray, pj: np.ndarray, di: np.ndarray, dj: np.ndarray | float, ds: np.ndarray,
                 closest: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Smallest ``distance - d_s`` of each pair along sampled paths (a lower bound between samples).

    Parameters
    ----------
    pi, pj : numpy.ndarray
        ``(P, L)`` complex positions of the two members at the same steps
        (``pj`` may be ``(P, 1)`` for a static obstacle).
    di, dj : numpy.ndarray or float
        ``(P, L-1)`` deviation bounds per step (``dj`` may be 0).
    ds : numpy.ndarray
        ``(P,)`` safety distances.

    closest : bool
        Also return the step ``k`` of each minimum ``(P,)`` int: the first step within
        :data:`CLOSEST_TIE` of it.

    Returns
    -------
    numpy.ndarray
        ``(P,)``: ``min_k (dist(0, [q_k, q_{k+1}]) - di_k - dj_k) - ds`` with ``q = pi - pj``.
    """
    q = pi - pj
    if q.shape[1] == 1:
        m = np.abs(q[:, 0]) - ds
        return (m, np.zeros(m.shape[0], dtype=np.intp)) if closest else m
    # the operations of ``t = clip(-dot / where(dd > 0, dd, 1), 0, 1)``, ``|q0 + t dq| - di - dj``, in place
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
    if closest:
        low = dist.min(axis=1)
        # the first step within rounding of the smallest (a robot at rest ties many steps: which one
        # wins must not hang on the last bit), or the first NaN
        k = np.where(np.isnan(low), dist.argmin(axis=1), (dist <= low[:, None] + CLOSEST_TIE).argmax(axis=1))
        return dist[np.arange(k.shape[0]), k] - ds, k
    return dist.min(axis=1) - ds


_ONE_BUCKET_CELLS = 4096
"""Pair batches with at most this many samples in all are checked in one call rather than by horizon bucket."""


def bucketed_margins(P: np.ndarray, D: np.ndarray, need: np.ndarray, ii: np.ndarray, jj: np.ndarray, ds: np.ndarray,
              centers: np.ndarray | None = None) -> np.ndarray:
    """:func:`pair_margins` of pairs ``(ii, jj)`` of rows of ``P``, in buckets of similar horizon.

    ``need[r]`` is the number of samples row ``r`` needs; with ``centers`` the
    second member is the static point ``centers[jj]``.
    """
    out = np.empty(ii.shape[0])
    if ii.size == 0:
        return out
    lens = np.maximum(need[ii] if centers is not None else np.maximum(need[ii], need[jj]), 2)
    top = int(lens.max())
    if ii.size * top <= max(2 * int(lens.sum()), _ONE_BUCKET_CELLS):
        bucket = np.zeros(ii.shape[0], dtype=np.int64)  # small or even: one call (padding samples are at rest)
    else:
        bucket = np.ceil(np.log2(lens)).astype(np.int64)
    for b in np.unique(bucket):
        sel = np.flatnonzero(bucket == b)
        Lb = int(lens[sel].max())
        a, c = ii[sel], jj[sel]
        if centers is None:
            out[sel] = pair_margins(P[a, :Lb], P[c, :Lb], D[a, : Lb - 1], D[c, : Lb - 1], ds[sel])
        else:
            out[sel] = pair_margins(P[a, :Lb], centers[c][:, None], D[a, : Lb - 1], 0.0, ds[sel])
    return out


# --------------------------------------------------------------------------- gatekeeper
class GateResult(NamedTuple):
    """What :func:`gatekeeper` decided.

    Attributes
    ----------
    du : numpy.ndarray
        ``(N, 2)`` inputs to apply: the backup for ``braking`` robots, the candidate otherwise.
    braking : numpy.ndarray
        ``(N,)`` bool: robots whose candidate was not accepted (blended toward, or put on, the backup).
    margin : float
        Smallest ``distance - d_s`` over the checked pairs along the horizon of
        the returned assignment [m] (the smallest :func:`reach_limit`, ``D / 2 - max r_i``,
        when no pair is close enough to matter).
    safe : bool
        The current state was brake-safe for every checked pair: the returned
        assignment keeps the team in the safe set.  False means the invariant
        was already broken (an earlier overlap, a start that was not brake-safe,
        or an assumption of the guarantee violated).
    broken : numpy.ndarray
        ``(N,)`` bool: robots in a pair that fails even when both brake (or that
        reach beyond the range limit when braking).  No input can promise them
        safety; the caller decides what they do (the filter applies its QP to robots beyond the range
        limit, and re-runs the gate with ``hold_violations`` for pairs that fail when both brake).
    share : numpy.ndarray
        ``(N,)``: the share ``a`` of the candidate in the applied input (1: the
        candidate, 0: the backup).
    rounds : int
        Gatekeeper rounds.
    n_pairs : int
        Robot and robot-obstacle pairs checked.
    robot_margin : numpy.ndarray
        ``(N,)``: the smallest such margin over each robot's checked pairs
        (its :func:`reach_limit` for a robot without one); ``margin`` is their minimum.
    out_of_range : numpy.ndarray
        ``(N,)`` bool: robots whose candidate path leaves :func:`reach_limit`
        (too fast for the sensing range: no change of a pair's margin lets them keep it).
    """

    du: np.ndarray
    braking: np.ndarray
    margin: float
    safe: bool
    broken: np.ndarray
    share: np.ndarray
    rounds: int
    n_pairs: int
    robot_margin: np.ndarray
    out_of_range: np.ndarray


def gatekeeper(
    team: Team,
    pose: np.ndarray,
    u: np.ndarray,
    du_c: np.ndarray,
    dt: float,
    *,
    sensing_range: float,
    brake_fraction: float,
    obstacles: tuple[np.ndarray, np.ndarray] | None = None,
    tol: float = 0.0,
    blend_levels: tuple[float, ...] = BLEND_LEVELS,
    hold_violations: bool = False,
    quick: bool = False,
    near_pairs: np.ndarray | None = None,
    compiled: bool = False,
    checked: bool = False,
) -> GateResult:
    """Accept the candidate ``du_c`` for every robot whose pairs stay brake-safe; put the others on the backup.

    Algorithm (one physics step, whole team)
        1. Paths per level: ``B_a`` for each share ``a`` in ``1 > blend_levels > 0``
           (one step with ``du_b + a (du_c - du_b)``, then the backup from
           there) and ``B_0``, the backup from now.  Every robot starts at the
           candidate (``a = 1``).
        2. Range condition: a level whose path reaches farther than
           :func:`reach_limit` from where the robot is, is skipped.
        3. Every pair that could meet (``|p_ij| < d_s + R_i + R_j``, ``R`` the
           reach of the paths) is checked on the members' current levels; the
           check covers the step itself and the whole backup horizon.  The
           members of failing pairs move one level down (toward the backup;
           past any level the range condition skips: a blend's reach is not
           bounded by those of the levels around it), and their pairs are
           checked again.  Levels only go down, so this
           ends; at worst all brake.

    Invariance
        Call a state *brake-safe* when the backup from it keeps every pair
        ``>= d_s`` and every robot's backup reach within :func:`reach_limit`.
        Let the current state ``x`` be brake-safe and ``x'`` the state after the
        returned inputs.  The backup is time-consistent, so the backup paths
        from ``x'`` are the tails of the robots' final ``B_a``.  Pairs with both
        members on the backup follow tails of paths that passed at ``x``; the
        other pairs were checked now on the step and the whole backup from
        ``x'``; pairs that cannot meet
        within their reach, and unseen pairs beyond the sensing range ``D``
        (robot ``i``'s paths stay within ``D / 2 - r_i`` of its start), stay
        apart.  Obstacles are robots that never move.  So ``x'`` is brake-safe
        and no pair came closer than ``d_s`` during the step.  A team at rest
        without overlap is brake-safe, hence the team never collides, whatever
        the candidate.  Assumptions: every robot runs this filter with the same
        state, the bounds ``|du| <= a`` and ``dt`` are the real ones, the
        returned inputs are applied as they are, and floating-point rounding
        is absorbed by ``tol`` (the filter passes
        :data:`~aasoatt_env.safety.repair.GATE_TOL`, twice what a scenario's start
        may overlap, so a touching team at rest is brake-safe).

    Parameters
    ----------
    team : Team
        Robot parameters.
    pose : numpy.ndarray
        Axle poses ``(N, 3)``.
    u : numpy.ndarray
        Wheel speeds ``(N, 2)``.
    du_c : numpy.ndarray
        Candidate inputs ``(N, 2)`` within the bounds (the QP's answer).
    dt : float
        Physics step [s].
    sensing_range : float
        ``D`` [m].
    brake_fraction : float
        The backup's point deceleration as a fraction of the straight-line
        braking capability (:func:`brake_time`).
    obstacles : tuple of numpy.ndarray, optional
        ``(centres (M, 2), radii (M,))`` of static discs; ``(centres, radii, groups (M,))``
        with a grouped team (``team.group``): an obstacle acts on its group's robots only.
    tol : float
        Accepted violation [m] (negative: a clearance required; the filter passes
        :data:`~aasoatt_env.safety.repair.GATE_TOL`).
    blend_levels : tuple of float
        Intermediate steps between the candidate and the backup, ``du = du_b + a (du_c - du_b)``
        for each ``a`` (tried from the largest down): a robot that fails with the candidate first
        tries these gentler blends, and brakes only if they fail too.  ``()``: brake at once.
    hold_violations : bool
        Best effort outside the safe set: a pair whose margin is negative even when both members
        brake is held to that margin (its own tolerance) instead of being marked broken, so no pair
        gets closer than braking would bring it while robots may still move apart.  ``safe`` then
        says only whether the range condition held; the caller reports the state.
    quick : bool
        Only the verdict on the candidate is wanted: the blend levels are used only when some
        robot's candidate path leaves :func:`reach_limit` (without them such a robot could only
        brake).  The first round, which robots the candidate fails, is the same either way.
        Without such a robot, one that fails a pair goes straight to the backup; with one
        (``out_of_range.any()``), the answer is the full check's.
    near_pairs : numpy.ndarray, optional
        ``(P, 2)`` robot pairs including every pair (of one group, with ``team.group``)
        within ``sensing_range`` of each other's control points: the candidates of the
        pair search, made once for several calls on one state.  A pair missing here is
        not checked, so it is a safety input.  None: searched here.
    compiled : bool
        Run the whole check in the compiled kernel (:mod:`aasoatt_env.compiled`;
        ``ImportError`` without numba): the same decisions, inputs and margins to rounding.
    checked : bool
        The caller vouches for every shape and pair index (the filter's own arrays): their checks
        are skipped.  The compiled kernel reads without bounds checks, so anything else must leave it False.
    """
    levels = levels_of(tuple(blend_levels))
    if not checked:
        near_pairs = validate(team, pose, obstacles, near_pairs, u=u, du_c=du_c)
    if compiled:
        return _gatekeeper_compiled(team, pose, u, du_c, dt, sensing_range, brake_fraction, obstacles, tol, levels,
                                    hold_violations, quick, near_pairs)
    n = pose.shape[0]
    theta = pose[:, 2]
    p0 = point(team, pose)
    T0 = brake_time(team, u, brake_fraction)
    du_b = -u / np.maximum(T0, dt)[:, None]  # braking_du
    limit = reach_limit(team, sensing_range)

    # closed-form parameters per level (cheap, O(N)): a step blending the candidate and the backup,
    # du_b + a (du_c - du_b), then the backup from there; level `last` is the backup from now
    b0 = brake(team, theta, u, dt, brake_fraction, T0)
    firsts = []
    reaches = []
    for k, a in enumerate(levels[:-1]):
        du_a = du_b + a * (du_c - du_b)
        p1, d1, theta1, u1 = first_step(team, p0, theta, u, du_a, dt)
        b1 = brake(team, theta1, u1, dt, brake_fraction)
        firsts.append((du_a, p1, d1, b1))
        reaches.append(candidate_reach(p0, p1, d1, b1))
        if k == 0 and quick and not bool((reaches[0] > limit).any()):
            levels = (1.0, 0.0)  # no candidate leaves the range: the blends would change nothing below
            break
    last = len(levels) - 1
    reach = np.stack(reaches + [b0.reach])
    np.copyto(reach, np.inf, where=np.isnan(reach))  # a reach that is not a number bounds nothing: unbounded
    R = reach.max(axis=0)

    # a level whose path leaves the reach limit is skipped at once
    def in_range(lev: np.ndarray) -> np.ndarray:
        """Each robot's first level from ``lev`` on whose path stays within its range limit (or the backup)."""
        for k in range(last):
            lev = np.where((lev == k) & (reach[k] > limit), k + 1, lev)
        return lev

    lev = in_range(np.zeros(n, dtype=np.int64))
    broken = reach[last] > limit

    # pairs that could meet within their reach (fixed for the call); only their robots need paths
    i, j, ds = pairs_near(team, p0, R, sensing_range, 1e-12, near_pairs)
    oc, oi, ok, ods = obstacles_near(team, p0, R, obstacles, 1e-12)
    du_all = np.stack([f[0] for f in firsts] + [du_b])  # (levels, N, 2)
    limit_margin = float(limit.min(initial=0.5 * float(sensing_range)))
    if i.size + oi.size == 0:
        rows = np.arange(n)
        share = np.asarray(levels)[lev]
        return GateResult(du_all[lev, rows], lev > 0, limit_margin, not bool(broken.any()), broken, share, 0, 0,
                          limit.copy(), reach[0] > limit)

    M = np.unique(np.concatenate((i, j, oi)))  # robots with a pair to check
    loc = np.full(n, -1, dtype=np.intp)
    loc[M] = np.arange(M.size)
    need = np.empty((len(levels), M.size), dtype=np.int64)  # samples each robot's path needs, per level
    for k, (_, _, _, b1) in enumerate(firsts):
        need[k] = b1.steps[M] + 2
    need[last] = b0.steps[M] + 1
    L = max(int(need.max(initial=0)), 2)

    def level_rows(k: int, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Samples ``(r, L)`` and sagittas ``(r, L-1)`` of level ``k`` for the rows ``r`` of ``M``."""
        g = M[r]
        if k == last:
            return brake_samples(p0[g], take_robots(b0, g), dt, L)
        _, p1, d1, b1 = firsts[k]
        return candidate_samples(p0[g], p1[g], d1[g], take_robots(b1, g), dt, L)

    li, lj, lo_ = loc[i], loc[j], loc[oi]
    rows_m = np.arange(M.size)

    tol_p, tol_o = np.full(i.shape[0], float(tol)), np.full(oi.shape[0], float(tol))
    if hold_violations:  # each pair's own floor: its margin when both members brake now
        # (the larger of the floor and tol, not their sum: a sum let a pair pushed together lose tol more
        # on every step, found by an adversarial tester on touching packs, 2026-12-02)
        Pb, Db = level_rows(last, rows_m)
        if i.size:
            tol_p = np.fmax(tol_p, np.fmax(0.0, -bucketed_margins(Pb, Db, need[last], li, lj, ds)) * (1.0 + 1e-9))
        if oi.size:
            floor = np.fmax(0.0, -bucketed_margins(Pb, Db, need[last], lo_, ok, ods, centers=oc))
            tol_o = np.fmax(tol_o, floor * (1.0 + 1e-9))
    marg = np.full(i.shape[0], np.inf)
    omarg = np.full(oi.shape[0], np.inf)
    todo = np.ones(i.shape[0], dtype=bool)
    otodo = np.ones(oi.shape[0], dtype=bool)
    cur = np.empty((M.size, L), dtype=np.complex128)
    curd = np.empty((M.size, L - 1))
    filled = np.full(M.size, -1)  # the level whose paths are in a row of `cur`
    rounds = 0
    while True:
        rounds += 1
        lm = lev[M]
        cneed = need[lm, rows_m]
        # the paths of the robots' current levels: only rows whose level changed are (re)made
        stale = lm != filled
        for k in np.unique(lm[stale]):
            r = np.flatnonzero(stale & (lm == k))
            cur[r], curd[r] = level_rows(int(k), r)
        filled = lm
        idx, oidx = np.flatnonzero(todo), np.flatnonzero(otodo)
        if idx.size:
            marg[idx] = bucketed_margins(cur, curd, cneed, li[idx], lj[idx], ds[idx])
        if oidx.size:
            omarg[oidx] = bucketed_margins(cur, curd, cneed, lo_[oidx], ok[oidx], ods[oidx], centers=oc)
        # a margin that is not a number verifies nothing: it fails (and is reported as -inf, not NaN)
        np.copyto(marg, -np.inf, where=np.isnan(marg))
        np.copyto(omarg, -np.inf, where=np.isnan(omarg))
        demote = np.zeros(n, dtype=bool)
        bad = idx[marg[idx] < -tol_p[idx]]
        obad = oidx[omarg[oidx] < -tol_o[oidx]]
        demote[i[bad]] = True
        demote[j[bad]] = True
        demote[oi[obad]] = True
        # a pair failing with both members on the backup was not brake-safe before: nothing to demote
        at_backup = lev == last
        both = at_backup[i[bad]] & at_backup[j[bad]]
        broken[i[bad][both]] = True
        broken[j[bad][both]] = True
        broken[oi[obad][at_backup[oi[obad]]]] = True
        demote &= ~at_backup
        if not demote.any():
            break
        # a blend's reach is not bounded by those of the levels around it: the range condition again
        lev = in_range(np.where(demote, lev + 1, lev))
        todo = demote[i] | demote[j]
        otodo = demote[oi]

    rows = np.arange(n)
    share = np.asarray(levels)[lev]
    robot_margin = limit.copy()
    np.minimum.at(robot_margin, np.concatenate((i, j, oi)), np.concatenate((marg, marg, omarg)))
    return GateResult(du_all[lev, rows], lev > 0, float(robot_margin.min(initial=limit_margin)),
                      not bool(broken.any()), broken, share, rounds, int(i.size + oi.size), robot_margin,
                      reach[0] > limit)


_EMPTY_INT = np.empty(0, dtype=np.int64)


@functools.lru_cache(maxsize=64)
def _levels_array(levels: tuple[float, ...]) -> np.ndarray:
    a = np.array(levels)
    a.flags.writeable = False
    return a


@functools.lru_cache(maxsize=64)
def levels_of(blend_levels: tuple) -> tuple[float, ...]:
    """The check's levels, highest first: 1 (the candidate), the blend shares, 0 (the backup from now)."""
    levels = tuple(sorted(set(float(x) for x in blend_levels) | {1.0}, reverse=True)) + (0.0,)
    if not all(0.0 < a <= 1.0 for a in levels[:-1]):  # also refuses NaN
        raise ValueError(f"blend_levels: got {blend_levels!r}, expected shares in (0, 1]")
    return levels


def team_block(team: Team, brake_fraction: float, sensing_range: float) -> tuple:
    """The per-robot constants of :func:`kernel_args`' block and the reach limits, made once per team."""
    key = ("gatekeeper", float(brake_fraction), float(sensing_range))
    block = team.derived.get(key)
    if block is None and SUBSET_OF in team.derived:  # a subset's: the whole team's indexed (every entry is
        whole, idx = team.derived[SUBSET_OF]  # the robot's own, so the same numbers)
        (diff, offset, cols, tg, amax, adec, radius, group, has_group, rng), limit = team_block(
            whole, brake_fraction, sensing_range)
        block = team.derived[key] = (
            (diff, offset[idx], cols[idx], tg[idx], amax[idx], adec[idx], radius[idx],
             group[idx] if has_group else group, has_group, rng), limit[idx])
    if block is None:
        group = team.group if team.group is not None else _EMPTY_INT
        block = team.derived[key] = (
            (team.is_diff_drive, team.offset, team.input_columns, team.turn_gain, team.max_wheel_accel,
             brake_decel(team, brake_fraction), team.radius, group, team.group is not None, float(sensing_range)),
            reach_limit(team, sensing_range))
    return block


def validate(team: Team, pose: np.ndarray, obstacles: tuple[np.ndarray, ...] | None, near_pairs: np.ndarray | None,
             **per_robot: np.ndarray) -> np.ndarray | None:
    """Refuse (``ValueError``) what the compiled kernels would read out of bounds; ``near_pairs`` as an array.

    ``pose`` ``(n, 3)`` for the team's ``n`` robots, each of ``per_robot`` (by name) ``(n, 2)``, the
    obstacles' centres ``(M, 2)`` with ``M`` radii (and groups), ``near_pairs`` ``(P, 2)`` robot indices.
    """
    n = team.n
    for name, a in (("pose", pose), *per_robot.items()):
        if np.shape(a) != ((n, 3) if name == "pose" else (n, 2)):
            raise ValueError(f"{name}: got shape {np.shape(a)}, expected ({n}, {3 if name == 'pose' else 2}) "
                             f"for a team of {n} robots")
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
    """The team, pair and obstacle block of the compiled kernels (:mod:`aasoatt_env.safety.backup.kernels`).

    ``(diff, offset, cols, turn_gain, max_wheel_accel, brake_decel, radius, group, has_group,
    sensing_range, candidate pairs, obstacle centres (complex), radii, groups, has_groups)``; the
    candidate pairs are ``near_pairs``, or every pair within the sensing range when None.  Shapes
    are the caller's to check (:func:`validate`).
    """
    if near_pairs is None:
        p0 = point(team, pose)
        near_pairs = robot_pairs(np.stack((p0.real, p0.imag), axis=1), sensing_range, groups=team.group)
    oc, orad, ogroup, has_ogroup = _NO_OC, _NO_R, _EMPTY_INT, False
    if obstacles is not None and np.asarray(obstacles[1]).size:
        c, orad = np.asarray(obstacles[0], dtype=np.float64), np.asarray(obstacles[1], dtype=np.float64)
        oc = c[:, 0] + 1j * c[:, 1]
        if team.group is not None and len(obstacles) > 2 and obstacles[2] is not None:
            ogroup, has_ogroup = np.asarray(obstacles[2]), True
    return (*team_block(team, brake_fraction, sensing_range)[0], np.ascontiguousarray(near_pairs, dtype=np.int64),
            oc, orad, ogroup, has_ogroup)


_NO_OC = np.empty(0, dtype=np.complex128)
_NO_R = np.empty(0)


def _gatekeeper_compiled(team: Team, pose: np.ndarray, u: np.ndarray, du_c: np.ndarray, dt: float,
                         sensing_range: float, brake_fraction: float, obstacles: tuple[np.ndarray, ...] | None,
                         tol: float, levels: tuple[float, ...], hold_violations: bool, quick: bool,
                         near_pairs: np.ndarray | None) -> GateResult:
    """:func:`gatekeeper` by the compiled kernel (:func:`aasoatt_env.safety.numba_kernels.gate_full`)."""
    block = kernel_args(team, pose, brake_fraction, sensing_range, obstacles, near_pairs)
    du, braking, broken, share, robot_margin, out_of_range, rounds, n_pairs, margin = kernels().gate_full(
        c64(pose), c64(u), c64(du_c), float(dt), _levels_array(levels), bool(quick), *block,
        team_block(team, brake_fraction, sensing_range)[1],
        float(tol), bool(hold_violations))
    return GateResult(du, braking, float(margin), not bool(broken.any()), broken, share, int(rounds), int(n_pairs),
                      robot_margin, out_of_range)


def pairs_near(team: Team, p0: np.ndarray, R: np.ndarray, sensing_range: float, slack: float,
                near_pairs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robot pairs ``(i, j, d_s)`` that could come within ``d_s + slack`` while each stays within ``R`` of ``p0``.

    Only pairs within the sensing range are considered: found here, or taken from
    ``near_pairs`` ``(P, 2)``, a superset of them.
    """
    rad = team.radius
    if near_pairs is None:
        pts = np.stack((p0.real, p0.imag), axis=1)
        search = min(float(sensing_range), 2.0 * float(rad.max(initial=0.0)) + 2.0 * float(R.max(initial=0.0))
                     + slack)
        pr = robot_pairs(pts, search, groups=team.group, compiled=False)  # (the numpy reference's path)
    else:
        pr = near_pairs
        # as robot_pairs at the range: <= D kept, and with groups, pairs of one group only
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
    """Robot-obstacle pairs that could come within ``d_s + slack``: ``(centres (M,) complex, i, k, d_s)``.

    ``obstacles`` is ``(centres, radii)`` or ``(centres, radii, groups)``: with
    groups (and ``team.group``) an obstacle acts on the robots of its group only.
    """
    if obstacles is None or not np.asarray(obstacles[1]).size:
        return np.empty(0, dtype=np.complex128), np.empty(0, dtype=np.intp), np.empty(0, dtype=np.intp), np.empty(0)
    c, orad = np.asarray(obstacles[0], dtype=np.float64), np.asarray(obstacles[1], dtype=np.float64)
    oc = c[:, 0] + 1j * c[:, 1]
    rad = team.radius
    near = np.abs(p0[:, None] - oc[None, :]) < rad[:, None] + orad[None, :] + R[:, None] + slack
    if team.group is not None and len(obstacles) > 2 and obstacles[2] is not None:
        near &= team.group[:, None] == np.asarray(obstacles[2])[None, :]
    oi, ok = np.nonzero(near)
    return oc, oi, ok, rad[oi] + orad[ok]
