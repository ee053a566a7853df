"""The backup layer's compiled kernels (numba; imported only through :mod:`aasoatt_env.compiled`).

The same loops as :func:`~aasoatt_env.safety.gatekeeper.gatekeeper` and
:func:`~aasoatt_env.safety.repair.repair`, written once per pair and sample:

- :func:`gate_full`: one gatekeeper call (closed-form set-up per robot and
  level, the pairs that could meet, the rounds, the result);
- :func:`repair_full`: one repair call (its rounds of finite-difference lifts).

Both take the team, pair and obstacle block of
:func:`~aasoatt_env.safety.gatekeeper._kernel_args` (``diff, offset, cols,
turn_gain, max_wheel_accel, brake_decel, radius, group, has_group,
sensing_range, candidate pairs, obstacle centres (complex), radii, groups,
has_groups``), checked there: numba does not check bounds.  Every helper
repeats numpy's operations in numpy's order (the names say which numpy
function; :func:`E1` takes one sine for two, noted there), with two
exceptions: a pair's distance on a step is ``sqrt(x^2 + y^2)`` (numpy's
``abs`` takes ``hypot``: the last bit), and the gatekeeper's braking samples
rotate by a recurrence (:func:`fill_brake`: ~1e-13 of the path's length).
So the results differ from the reference by rounding alone; the repair's
rows keep the sines and cosines (its finite differences compare them with
:func:`sample_at`'s closed form).
"""

from __future__ import annotations

import numpy as np

from aasoatt_env.numba_jit import jit as _jit
from aasoatt_env.numba_jit import nmax as _nmax
from aasoatt_env.safety.backup.kernel_paths import (
    brake1,
    brake_time1,
    candidate1,
    fill_row,
    heading_of,
    near_obstacles,
    near_pairs,
    pair_closest,
    pair_margin,
    point1,
    rows_of,
    sample_at,
    segment_margin,
)

__all__ = ["gate_full", "repair_full"]
# --------------------------------------------------------------------------- gatekeeper
@_jit
def _gate_rounds(lev, broken, reach, limit, need, p0, p1, d1, pdot, omega, rate, bulge, has_bulge, dt,
                i, j, ds, oi, ok, ods, oc, tol, hold):
    """The gatekeeper's rounds (:func:`~aasoatt_env.safety.gatekeeper.gatekeeper`, after its set-up).

    Parameters
    ----------
    lev, broken : numpy.ndarray
        ``(n,)`` int64 starting levels (range condition applied) and bool broken flags; updated in place.
    reach : numpy.ndarray
        ``(levels, n)`` path reaches (NaN already made inf); ``limit`` ``(n,)`` the range limits.
    need : numpy.ndarray
        ``(levels, n)`` int64 samples each robot's path needs on each level.
    p0 : numpy.ndarray
        ``(n,)`` complex control points; ``p1``, ``d1`` ``(levels, n)`` the first step's end and
        deviation per blend level (row ``last`` unused).
    pdot, omega, rate, bulge : numpy.ndarray
        ``(levels, n)`` braking parameters per level (``_Brake``; ``bulge`` zeros for wheeled robots).
    i, j, ds : numpy.ndarray
        Robot pairs to check and their safety distances; ``oi, ok, ods`` robot-obstacle pairs with
        obstacle centres ``oc`` (complex).
    tol : float
        Accepted violation [m]; ``hold``: the ``hold_violations`` floors.

    Returns
    -------
    tuple
        ``(marg, omarg, rounds)``: the pairs' margins on the final levels (NaN reported as -inf).
    """
    n = lev.shape[0]
    last = reach.shape[0] - 1
    P, Q = i.shape[0], oi.shape[0]
    loc, rob, M = rows_of(n, i, j, oi)
    L = 2
    for r in range(M):
        for k in range(last + 1):
            L = max(L, need[k, rob[r]])
    cur = np.empty((M, L), dtype=np.complex128)
    curd = np.empty((M, L - 1))
    tol_p = np.full(P, tol)
    tol_o = np.full(Q, tol)
    if hold:  # each pair's own floor: its margin when both members brake now
        for r in range(M):
            g = rob[r]
            fill_row(cur, curd, r, g, last, last, p0, p1, d1, pdot, omega, rate, bulge, has_bulge, dt,
                      need[last, g], True)
        for q in range(P):
            m = pair_margin(cur, curd, need[last, i[q]], need[last, j[q]], loc[i[q]], loc[j[q]], ds[q], False, 0j)
            fl = -m if -m > 0.0 else 0.0  # NaN: no floor (numpy's fmax); the larger of floor and tol (gatekeeper)
            tol_p[q] = max(tol_p[q], fl * (1.0 + 1e-9))
        for q in range(Q):
            m = pair_margin(cur, curd, need[last, oi[q]], 0, loc[oi[q]], 0, ods[q], True, oc[ok[q]])
            fl = -m if -m > 0.0 else 0.0
            tol_o[q] = max(tol_o[q], fl * (1.0 + 1e-9))
    marg = np.full(P, np.inf)
    omarg = np.full(Q, np.inf)
    todo = np.ones(P, dtype=np.bool_)
    otodo = np.ones(Q, dtype=np.bool_)
    filled = np.full(M, -1, dtype=np.int64)
    demote = np.zeros(n, dtype=np.bool_)
    rounds = 0
    while True:
        rounds += 1
        for r in range(M):  # the paths of the robots' current levels: only changed rows are made again
            g = rob[r]
            if lev[g] != filled[r]:
                fill_row(cur, curd, r, g, lev[g], last, p0, p1, d1, pdot, omega, rate, bulge, has_bulge, dt,
                          need[lev[g], g], True)
                filled[r] = lev[g]
        demote[:] = False
        any_demote = False
        for q in range(P):
            if not todo[q]:
                continue
            a, c = i[q], j[q]
            m = pair_margin(cur, curd, need[lev[a], a], need[lev[c], c], loc[a], loc[c], ds[q], False, 0j)
            if m != m:  # a margin that is not a number verifies nothing: it fails
                m = -np.inf
            marg[q] = m
            if m < -tol_p[q]:
                if lev[a] == last and lev[c] == last:  # not brake-safe before: nothing to demote
                    broken[a] = True
                    broken[c] = True
                if lev[a] != last:
                    demote[a] = True
                    any_demote = True
                if lev[c] != last:
                    demote[c] = True
                    any_demote = True
        for q in range(Q):
            if not otodo[q]:
                continue
            a = oi[q]
            m = pair_margin(cur, curd, need[lev[a], a], 0, loc[a], 0, ods[q], True, oc[ok[q]])
            if m != m:
                m = -np.inf
            omarg[q] = m
            if m < -tol_o[q]:
                if lev[a] == last:
                    broken[a] = True
                else:
                    demote[a] = True
                    any_demote = True
        if not any_demote:
            break
        for g in range(n):  # one level down, then past any level whose path leaves the range limit
            if demote[g]:
                lev[g] += 1
                while lev[g] < last and reach[lev[g], g] > limit[g]:
                    lev[g] += 1
        for q in range(P):
            todo[q] = demote[i[q]] or demote[j[q]]
        for q in range(Q):
            otodo[q] = demote[oi[q]]
    return marg, omarg, rounds


@_jit
def gate_full(pose, u, du_c, dt, levels_in, quick, diff, offset, cols, tg, amax, adec, radius, group, has_group,
              sensing_range, cand, oc, orad, ogroup, has_ogroup, limit, tol, hold):
    """The whole :func:`~aasoatt_env.safety.gatekeeper.gatekeeper` for one call (its set-up, pairs and rounds).

    Parameters
    ----------
    pose, u, du_c : numpy.ndarray
        Axle poses ``(n, 3)``, wheel speeds and candidate inputs ``(n, 2)``.
    dt : float
        Physics step [s].
    levels_in : numpy.ndarray
        The shares tried, 1 first, the blend levels descending, 0 (the backup) last.
    quick : bool
        The gatekeeper's ``quick`` (blend levels only where a candidate leaves the range limit).
    diff, ..., has_ogroup
        The block of :func:`~aasoatt_env.safety.gatekeeper._kernel_args` (module docstring);
        ``cand`` holds every pair of one group within ``sensing_range`` (a superset is fine).
    limit : numpy.ndarray
        :func:`~aasoatt_env.safety.backup.reach_limit` ``(n,)``.
    tol, hold : float, bool
        The gatekeeper's ``tol`` and ``hold_violations``.

    Returns
    -------
    tuple
        ``(du, braking, broken, share, robot_margin, out_of_range, rounds, n_pairs, margin)``:
        the fields of :class:`~aasoatt_env.safety.gatekeeper.GateResult`.
    """
    n = pose.shape[0]
    nl_full = levels_in.shape[0]
    last_full = nl_full - 1
    p0 = np.empty(n, dtype=np.complex128)
    du_all = np.empty((nl_full, n, 2))
    P1 = np.empty((nl_full, n), dtype=np.complex128)
    D1 = np.zeros((nl_full, n))
    PD = np.empty((nl_full, n), dtype=np.complex128)
    OM = np.empty((nl_full, n))
    RT = np.empty((nl_full, n))
    NEED = np.empty((nl_full, n), dtype=np.int64)
    RE = np.empty((nl_full, n))
    BU = np.zeros((nl_full, n))
    HD = np.empty(n, dtype=np.complex128)
    for g in range(n):  # the backup from now: level `last`
        c0, c1 = cols[g, 0], cols[g, 1]
        HD[g] = heading_of(diff, pose[g, 2])
        p0[g] = point1(diff, offset[g], pose[g, 0], pose[g, 1], HD[g])
        T = brake_time1(diff, c0, c1, amax[g], adec[g], u[g, 0], u[g, 1])
        pdot, w, rate, steps, reach, bulge = brake1(diff, c0, c1, tg[g], amax[g], adec[g], HD[g], u[g, 0], u[g, 1],
                                                     dt)
        PD[last_full, g], OM[last_full, g], RT[last_full, g] = pdot, w, rate
        NEED[last_full, g], RE[last_full, g], BU[last_full, g] = steps + 1, reach, bulge
        den = _nmax(T, dt)
        du_all[last_full, g, 0] = -u[g, 0] / den
        du_all[last_full, g, 1] = -u[g, 1] / den
    nl = nl_full
    for k in range(nl_full - 1):  # one step blending the candidate and the backup, then the backup
        a = levels_in[k]
        out = False
        for g in range(n):
            b0, b1 = du_all[last_full, g, 0], du_all[last_full, g, 1]
            da0 = b0 + a * (du_c[g, 0] - b0)
            da1 = b1 + a * (du_c[g, 1] - b1)
            du_all[k, g, 0], du_all[k, g, 1] = da0, da1
            p1, dev, pdot, w, rate, steps, reach, bulge = candidate1(
                diff, cols[g, 0], cols[g, 1], tg[g], amax[g], adec[g], p0[g], pose[g, 2], HD[g], u[g, 0], u[g, 1],
                da0, da1, dt)
            P1[k, g], D1[k, g], PD[k, g], OM[k, g], RT[k, g] = p1, dev, pdot, w, rate
            NEED[k, g], RE[k, g], BU[k, g] = steps + 2, reach, bulge
            out = out or reach > limit[g]
        if k == 0 and quick and not out:
            nl = 2  # no candidate leaves the range: the blends would change nothing below
            break
    if nl != nl_full:  # levels (1, 0): rows 0 and last
        keep = np.array([0, last_full])
        du_all, P1, D1, PD, OM, RT, NEED, RE, BU = (du_all[keep], P1[keep], D1[keep], PD[keep], OM[keep],
                                                     RT[keep], NEED[keep], RE[keep], BU[keep])
    last = nl - 1
    R = np.empty(n)
    lev = np.zeros(n, dtype=np.int64)
    broken = np.zeros(n, dtype=np.bool_)
    out_of_range = np.zeros(n, dtype=np.bool_)
    for g in range(n):
        for k in range(nl):
            if RE[k, g] != RE[k, g]:  # a reach that is not a number bounds nothing: unbounded
                RE[k, g] = np.inf
            R[g] = RE[k, g] if k == 0 else max(R[g], RE[k, g])
        while lev[g] < last and RE[lev[g], g] > limit[g]:  # a level whose path leaves the range is skipped
            lev[g] += 1
        broken[g] = RE[last, g] > limit[g]
        out_of_range[g] = RE[0, g] > limit[g]
    pi, pj, pds = near_pairs(cand, p0, R, radius, group, has_group, sensing_range, 1e-12)
    oi, ok, ods = near_obstacles(p0, R, radius, group, has_group, oc, orad, ogroup, has_ogroup, 1e-12)
    margin = 0.5 * sensing_range
    for g in range(n):
        margin = min(margin, limit[g])
    robot_margin = limit.copy()
    rounds = 0
    P, Q = pi.shape[0], oi.shape[0]
    if P + Q > 0:
        marg, omarg, rounds = _gate_rounds(lev, broken, RE, limit, NEED, p0, P1, D1, PD, OM, RT, BU, not diff, dt,
                                          pi, pj, pds, oi, ok, ods, oc, tol, hold)
        for q in range(P):
            robot_margin[pi[q]] = min(robot_margin[pi[q]], marg[q])
            robot_margin[pj[q]] = min(robot_margin[pj[q]], marg[q])
        for q in range(Q):
            robot_margin[oi[q]] = min(robot_margin[oi[q]], omarg[q])
        for g in range(n):
            margin = min(margin, robot_margin[g])
    du = np.empty((n, 2))
    share = np.empty(n)
    for g in range(n):
        du[g, 0] = du_all[lev[g], g, 0]
        du[g, 1] = du_all[lev[g], g, 1]
        share[g] = levels_in[lev[g] if lev[g] < last else last_full]
    return du, lev > 0, broken, share, robot_margin, out_of_range, rounds, P + Q, margin


@_jit
def _moved_step(diff, cols, tg, amax, adec, p0, hd, pose, u, du, g, d, eps, dt, k):
    """Samples ``k``, ``k + 1`` and step ``k``'s deviation of robot ``g``'s path with input ``d`` moved by ``eps``.

    :func:`~aasoatt_env.safety.backup.candidate_samples_at` for the repair's finite difference.
    """
    e0 = du[g, 0] + (eps if d == 0 else 0.0)
    e1 = du[g, 1] + (eps if d == 1 else 0.0)
    p1, dev, pdot, w, rate, steps, _, bulge = candidate1(
        diff, cols[g, 0], cols[g, 1], tg[g], amax[g], adec[g], p0[g], pose[g, 2], hd[g], u[g, 0], u[g, 1], e0, e1,
        dt)
    pa0, dm0 = sample_at(p0[g], p1, dev, pdot, w, rate, steps, bulge, not diff, dt, k)
    pa1, _ = sample_at(p0[g], p1, dev, pdot, w, rate, steps, bulge, not diff, dt, k + 1)
    return pa0, pa1, dm0


# --------------------------------------------------------------------------- repair
@_jit
def repair_full(pose, u, du_c, lo, hi, dt, diff, offset, cols, tg, amax, adec, radius, group, has_group,
                sensing_range, cand, oc, orad, ogroup, has_ogroup, target, rounds, eps, tie):
    """:func:`~aasoatt_env.safety.repair.repair` for one call: the nudged candidate ``(n, 2)``.

    The same rounds in the same order: the low pairs' finite-difference gradients at their
    closest steps (``tie``: :data:`~aasoatt_env.safety.gatekeeper.CLOSEST_TIE`), their least-norm
    lifts summed robot by robot as ``numpy.add.at`` does, the clip to ``[lo, hi]``.

    Parameters
    ----------
    pose, u, du_c, lo, hi : numpy.ndarray
        Axle poses ``(n, 3)``; wheel speeds, candidate inputs and their bounds ``(n, 2)``.
    dt : float
        Physics step [s].
    diff, ..., has_ogroup
        The block of :func:`~aasoatt_env.safety.gatekeeper._kernel_args` (module docstring).
    target, rounds, eps, tie
        The repair's ``target``, ``rounds`` and ``eps``, and the closest-step tie.
    """
    n = pose.shape[0]
    du = np.empty((n, 2))
    for g in range(n):
        for d in range(2):
            du[g, d] = min(max(du_c[g, d], lo[g, d]), hi[g, d])
    p0 = np.empty(n, dtype=np.complex128)
    hd = np.empty(n, dtype=np.complex128)
    for g in range(n):
        hd[g] = heading_of(diff, pose[g, 2])
        p0[g] = point1(diff, offset[g], pose[g, 0], pose[g, 1], hd[g])
    P1 = np.empty((1, n), dtype=np.complex128)
    D1 = np.empty((1, n))
    PD = np.empty((1, n), dtype=np.complex128)
    OM = np.empty((1, n))
    RT = np.empty((1, n))
    BU = np.empty((1, n))
    NEED = np.empty(n, dtype=np.int64)
    R = np.empty(n)
    slack = 2.0 * target
    ee = eps * dt * dt
    # each robot's candidate path (row g), made once and kept until its input changes (numpy's _PathCache)
    Lc = 2
    rowp = np.empty((n, Lc), dtype=np.complex128)
    rowd = np.empty((n, Lc - 1))
    made = np.zeros(n, dtype=np.bool_)
    used = np.zeros(n, dtype=np.bool_)
    for _ in range(rounds):
        for g in range(n):  # reach first: only robots with a pair that could come close need paths
            p1, dev, pdot, w, rate, steps, reach, bulge = candidate1(
                diff, cols[g, 0], cols[g, 1], tg[g], amax[g], adec[g], p0[g], pose[g, 2], hd[g], u[g, 0], u[g, 1],
                du[g, 0], du[g, 1], dt)
            P1[0, g], D1[0, g], PD[0, g], OM[0, g], RT[0, g], BU[0, g] = p1, dev, pdot, w, rate, bulge
            NEED[g], R[g] = steps + 2, reach + ee
        i, j, ds = near_pairs(cand, p0, R, radius, group, has_group, sensing_range, slack)
        oi, ok, ods = near_obstacles(p0, R, radius, group, has_group, oc, orad, ogroup, has_ogroup, slack)
        P, Q = i.shape[0], oi.shape[0]
        if P + Q == 0:
            break
        used[:] = False
        for q in range(P):
            used[i[q]] = True
            used[j[q]] = True
        for q in range(Q):
            used[oi[q]] = True
        L = 2
        for g in range(n):
            if used[g]:
                L = max(L, NEED[g])
        if L > Lc:
            Lc = L
            rowp = np.empty((n, Lc), dtype=np.complex128)
            rowd = np.empty((n, Lc - 1))
            made[:] = False
        for g in range(n):
            if used[g] and not made[g]:
                fill_row(rowp, rowd, g, g, 0, 1, p0, P1, D1, PD, OM, RT, BU, not diff, dt, NEED[g], False)
                made[g] = True
        cur, curd = rowp, rowd
        # the low pairs: margin below target; their margin and closest step over the whole rows
        low = np.zeros(P, dtype=np.bool_)
        m0 = np.empty(P)
        kk = np.empty(P, dtype=np.int64)
        nlow = 0
        for q in range(P):
            a, c = i[q], j[q]
            if pair_margin(cur, curd, NEED[a], NEED[c], a, c, ds[q], False, 0j) < target:
                low[q] = True
                nlow += 1
                best, k = pair_closest(cur, curd, NEED[a], NEED[c], a, c, False, 0j, L - 1, tie)
                m0[q], kk[q] = best - ds[q], k
        olow = np.zeros(Q, dtype=np.bool_)
        om0 = np.empty(Q)
        okk = np.empty(Q, dtype=np.int64)
        for q in range(Q):
            a = oi[q]
            if pair_margin(cur, curd, NEED[a], 0, a, 0, ods[q], True, oc[ok[q]]) < target:
                olow[q] = True
                nlow += 1
                best, k = pair_closest(cur, curd, NEED[a], 0, a, 0, True, oc[ok[q]], L - 1, tie)
                om0[q], okk[q] = best - ods[q], k
        if nlow == 0:
            break
        # gradients at the closest step: that step's samples of one member with one input moved by eps
        gi = np.zeros((P, 2))
        gj = np.zeros((P, 2))
        lift = np.zeros(P)
        for q in range(P):
            if not low[q]:
                continue
            k = kk[q]
            for side in range(2):
                mv, fx = (i[q], j[q]) if side == 0 else (j[q], i[q])
                qf0, qf1 = cur[fx, min(k, NEED[fx] - 1)], cur[fx, min(k + 1, NEED[fx] - 1)]
                dfx = curd[fx, k] if k < NEED[fx] - 1 else 0.0
                for d in range(2):
                    pa0, pa1, dm0 = _moved_step(diff, cols, tg, amax, adec, p0, hd, pose, u, du, mv, d, eps, dt, k)
                    mg = segment_margin(pa0, pa1, qf0, qf1, dm0, dfx) - ds[q]
                    if side == 0:
                        gi[q, d] = (mg - m0[q]) / eps
                    else:
                        gj[q, d] = (mg - m0[q]) / eps
            nrm = (gi[q, 0] * gi[q, 0] + gi[q, 1] * gi[q, 1]) + (gj[q, 0] * gj[q, 0] + gj[q, 1] * gj[q, 1])
            lift[q] = (2.0 * target - m0[q]) / max(nrm, 1e-12)
        go = np.zeros((Q, 2))
        olift = np.zeros(Q)
        for q in range(Q):
            if not olow[q]:
                continue
            k, mv = okk[q], oi[q]
            for d in range(2):
                pa0, pa1, dm0 = _moved_step(diff, cols, tg, amax, adec, p0, hd, pose, u, du, mv, d, eps, dt, k)
                mg = segment_margin(pa0, pa1, oc[ok[q]], oc[ok[q]], dm0, 0.0) - ods[q]
                go[q, d] = (mg - om0[q]) / eps
            olift[q] = (2.0 * target - om0[q]) / max(go[q, 0] * go[q, 0] + go[q, 1] * go[q, 1], 1e-12)
        # the lifts add up robot by robot, in numpy's order (every pair's first member, then second, then obstacles)
        step = np.zeros((n, 2))
        for q in range(P):
            if low[q]:
                step[i[q], 0] += lift[q] * gi[q, 0]
                step[i[q], 1] += lift[q] * gi[q, 1]
        for q in range(P):
            if low[q]:
                step[j[q], 0] += lift[q] * gj[q, 0]
                step[j[q], 1] += lift[q] * gj[q, 1]
        for q in range(Q):
            if olow[q]:
                step[oi[q], 0] += olift[q] * go[q, 0]
                step[oi[q], 1] += olift[q] * go[q, 1]
        moved = False
        for g in range(n):
            for d in range(2):
                if step[g, d] != 0.0:
                    moved = True
        if not moved:
            break
        for g in range(n):
            for d in range(2):
                v = min(max(du[g, d] + step[g, d], lo[g, d]), hi[g, d])
                if v != du[g, d]:
                    made[g] = False  # its path is made again when asked for
                du[g, d] = v
    return du
