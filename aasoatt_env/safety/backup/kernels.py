"""The backup layer's compiled check and repair (numba; imported only through :mod:`aasoatt_env.compiled`).

:func:`gate_full` is one :func:`~aasoatt_env.safety.backup.gate.gatekeeper` call and :func:`repair_full` one
:func:`~aasoatt_env.safety.backup.repair.repair` call, per robot, pair and sample (helpers: :mod:`.kernel_paths`), on
the block of :func:`~aasoatt_env.safety.backup.gate.kernel_args`, whose shapes the caller checked.
"""

import numpy as np

from aasoatt_env.numba_jit import jit, nmax
from aasoatt_env.safety.backup import kernel_paths as kp

__all__ = ["gate_full", "repair_full"]


@jit
def _store(C, F, NEED, k, g, base, p1, dev, pdot, w, rate, steps, reach, bulge):
    """Robot ``g``'s path on level ``k``: ``C`` (step end, velocity), ``F`` (``kp.D1 .. kp.REACH``), ``NEED``."""
    C[k, g, 0], C[k, g, 1], NEED[k, g] = p1, pdot, steps + base
    F[k, g, 0], F[k, g, 1], F[k, g, 2], F[k, g, 3], F[k, g, 4] = dev, w, rate, bulge, reach


@jit
def _gate_levels(pose, u, du_c, dt, levels, quick, diff, rob, cols, p0, hd, limit):
    """Every level's inputs ``(nl, n, 2)`` and path parameters ``C, F, NEED`` (``gate._levels``)."""
    n, nl = pose.shape[0], levels.shape[0]
    last = nl - 1
    du_all, C = np.empty((nl, n, 2)), np.empty((nl, n, 2), dtype=np.complex128)
    F, NEED = np.zeros((nl, n, 5)), np.empty((nl, n), dtype=np.int64)
    for g in range(n):  # the backup from now: level `last`
        rc = kp.consts(rob, cols, g)
        den = nmax(kp.brake_time1(diff, rc, u[g, 0], u[g, 1]), dt)
        _store(C, F, NEED, last, g, 1, 0j, 0.0, *kp.brake1(diff, rc, hd[g], u[g, 0], u[g, 1], dt))
        du_all[last, g, 0], du_all[last, g, 1] = -u[g, 0] / den, -u[g, 1] / den
    for k in range(nl - 1):  # one step blending the candidate and the backup, then the backup
        a = levels[k]
        out = False
        for g in range(n):
            b0, b1 = du_all[last, g, 0], du_all[last, g, 1]
            da0, da1 = b0 + a * (du_c[g, 0] - b0), b1 + a * (du_c[g, 1] - b1)
            du_all[k, g, 0], du_all[k, g, 1] = da0, da1
            _store(C, F, NEED, k, g, 2, *kp.candidate1(diff, kp.consts(rob, cols, g), p0[g], pose[g, 2], hd[g],
                                                       u[g, 0], u[g, 1], da0, da1, dt))
            out = out or F[k, g, kp.REACH] > limit[g]
        if k == 0 and quick and not out:  # no candidate leaves the range: levels (1, 0), rows 0 and last
            keep = np.array([0, last])
            return du_all[keep], C[keep], F[keep], NEED[keep]
    return du_all, C, F, NEED


@jit
def _in_pairs(n, a, c):
    """``(n,)``: the robots of pairs ``a``, ``c`` (``c < 0``: an obstacle); row ``g`` of the paths is robot ``g``'s."""
    used = np.zeros(n, dtype=np.bool_)
    for q in range(a.shape[0]):
        used[a[q]] = True
        if c[q] >= 0:
            used[c[q]] = True
    return used


@jit
def _gate_rounds(lev, broken, limit, p0, C, F, NEED, has_bulge, dt, a, c, ds, at, tol, hold):
    """The gatekeeper's rounds (``gate._rounds``): ``lev``, ``broken`` updated in place; ``(margins, rounds)``."""
    n, P, last = lev.shape[0], a.shape[0], NEED.shape[0] - 1
    used = _in_pairs(n, a, c)
    L = 2
    for g in range(n):
        for k in range(last + 1 if used[g] else 0):
            L = max(L, NEED[k, g])
    cur, curd = np.empty((n, L), dtype=np.complex128), np.empty((n, L - 1))
    tol_p = np.full(P, tol)
    if hold:  # each pair's tolerance the larger of tol and its margin when both members brake now
        for g in range(n):
            if used[g]:
                kp.fill_row(cur, curd, g, last, last, p0, C, F, has_bulge, dt, NEED[last, g], True)
        for q in range(P):
            m = kp.pair_margin(cur, curd, NEED[last, a[q]], 0 if c[q] < 0 else NEED[last, c[q]], a[q], c[q], ds[q],
                               at[q])
            fl = -m if -m > 0.0 else 0.0  # NaN: no floor (numpy's fmax)
            tol_p[q] = max(tol_p[q], fl * (1.0 + 1e-9))
    marg, todo = np.full(P, np.inf), np.ones(P, dtype=np.bool_)
    filled, demote = np.full(n, -1, dtype=np.int64), np.zeros(n, dtype=np.bool_)
    rounds = 0
    while True:
        rounds += 1
        for g in range(n):  # the paths of the robots' current levels: only changed rows are made again
            if used[g] and lev[g] != filled[g]:
                kp.fill_row(cur, curd, g, lev[g], last, p0, C, F, has_bulge, dt, NEED[lev[g], g], True)
                filled[g] = lev[g]
        demote[:] = False
        any_demote = False
        for q in range(P):
            if not todo[q]:
                continue
            g, h = a[q], c[q]
            st = h < 0
            m = kp.pair_margin(cur, curd, NEED[lev[g], g], 0 if st else NEED[lev[h], h], g, h, ds[q], at[q])
            marg[q] = -np.inf if m != m else m  # a margin that is not a number fails
            if marg[q] < -tol_p[q]:
                if lev[g] == last and (st or lev[h] == last):  # not brake-safe before: nothing to demote
                    broken[g] = True
                    if not st:
                        broken[h] = True
                for x in (g, h):
                    if x >= 0 and lev[x] != last:
                        demote[x] = any_demote = True
        if not any_demote:
            return marg, rounds
        for g in range(n):  # one level down, then past any level whose path leaves the range limit
            if demote[g]:
                lev[g] += 1
                while lev[g] < last and F[lev[g], g, kp.REACH] > limit[g]:
                    lev[g] += 1
        for q in range(P):
            todo[q] = demote[a[q]] or (c[q] >= 0 and demote[c[q]])


@jit
def gate_full(pose, u, du_c, dt, levels, quick, diff, rob, cols, group, has_group, sensing_range, cand, oc, orad,
              ogroup, has_ogroup, limit, tol, hold):
    """``gatekeeper``: ``(du, braking, broken, share, robot_margin, out_of_range, rounds, n_pairs, margin)``."""
    n = pose.shape[0]
    p0, hd = kp.starts(diff, rob, pose)
    du_all, C, F, NEED = _gate_levels(pose, u, du_c, dt, levels, quick, diff, rob, cols, p0, hd, limit)
    last = NEED.shape[0] - 1
    R, lev = np.empty(n), np.zeros(n, dtype=np.int64)
    broken, out_of_range = np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_)
    for g in range(n):
        for k in range(last + 1):
            if F[k, g, kp.REACH] != F[k, g, kp.REACH]:  # a reach that is not a number bounds nothing
                F[k, g, kp.REACH] = np.inf
            R[g] = F[k, g, kp.REACH] if k == 0 else max(R[g], F[k, g, kp.REACH])
        while lev[g] < last and F[lev[g], g, kp.REACH] > limit[g]:  # a level whose path leaves the range is skipped
            lev[g] += 1
        broken[g], out_of_range[g] = F[last, g, kp.REACH] > limit[g], F[0, g, kp.REACH] > limit[g]
    a, c, ds, at = kp.near(cand, p0, R, rob, group, has_group, sensing_range, oc, orad, ogroup, has_ogroup, 1e-12)
    margin = 0.5 * sensing_range
    for g in range(n):
        margin = min(margin, limit[g])
    robot_margin, rounds = limit.copy(), 0
    if a.shape[0]:
        marg, rounds = _gate_rounds(lev, broken, limit, p0, C, F, NEED, not diff, dt, a, c, ds, at, tol, hold)
        for q in range(a.shape[0]):
            for x in (a[q], c[q]):
                if x >= 0:
                    robot_margin[x] = min(robot_margin[x], marg[q])
        for g in range(n):
            margin = min(margin, robot_margin[g])
    du, share = np.empty((n, 2)), np.empty(n)
    for g in range(n):
        du[g, 0], du[g, 1] = du_all[lev[g], g, 0], du_all[lev[g], g, 1]
        share[g] = levels[lev[g] if lev[g] < last else levels.shape[0] - 1]
    return du, lev > 0, broken, share, robot_margin, out_of_range, rounds, a.shape[0], margin


@jit
def _moved_step(diff, rob, cols, p0, hd, pose, u, du, g, d, eps, dt, k):
    """Samples ``k``, ``k + 1`` and step ``k``'s deviation of robot ``g``'s path with input ``d`` moved by ``eps``."""
    e0 = du[g, 0] + (eps if d == 0 else 0.0)
    e1 = du[g, 1] + (eps if d == 1 else 0.0)
    p1, dev, pdot, w, rate, steps, _, bulge = kp.candidate1(diff, kp.consts(rob, cols, g), p0[g], pose[g, 2], hd[g],
                                                            u[g, 0], u[g, 1], e0, e1, dt)
    pa0, dm0 = kp.sample_at(p0[g], p1, dev, pdot, w, rate, steps, bulge, not diff, dt, k)
    pa1, _ = kp.sample_at(p0[g], p1, dev, pdot, w, rate, steps, bulge, not diff, dt, k + 1)
    return pa0, pa1, dm0


@jit
def _repair_rows(rowp, rowd, made, a, c, p0, C, F, NEED, has_bulge, dt):
    """Candidate paths (row ``g``: robot ``g``) of robots in pairs, each kept until ``made`` drops it: ``(p, d, L)``."""
    used = _in_pairs(p0.shape[0], a, c)
    L = 2
    for g in range(p0.shape[0]):
        if used[g]:
            L = max(L, NEED[0, g])
    if L > rowp.shape[1]:
        rowp, rowd = np.empty((p0.shape[0], L), dtype=np.complex128), np.empty((p0.shape[0], L - 1))
        made[:] = False
    for g in range(p0.shape[0]):
        if used[g] and not made[g]:
            kp.fill_row(rowp, rowd, g, 0, 1, p0, C, F, has_bulge, dt, NEED[0, g], False)
            made[g] = True
    return rowp, rowd, L


@jit
def _low_pairs(cur, curd, need, a, c, ds, at, target, L, tie):
    """Pairs whose margin is below ``target``: ``(low, margin at the closest step, that step)``."""
    P = a.shape[0]
    low, m0, kk = np.zeros(P, dtype=np.bool_), np.empty(P), np.empty(P, dtype=np.int64)
    for q in range(P):
        g, h = a[q], c[q]
        nh = 0 if h < 0 else need[h]
        if kp.pair_margin(cur, curd, need[g], nh, g, h, ds[q], at[q]) < target:
            low[q] = True
            best, kk[q] = kp.pair_min(cur, curd, need[g], nh, g, h, at[q], L - 1, tie)
            m0[q] = best - ds[q]
    return low, m0, kk


@jit
def _lifts(cur, curd, need, a, c, ds, at, low, m0, kk, target, eps, diff, rob, cols, p0, hd, pose, u, du, dt):
    """The summed least-norm lifts ``(n, 2)`` of the low pairs, by finite differences at their closest steps."""
    P = a.shape[0]
    grad, lift = np.zeros((P, 2, 2)), np.zeros(P)
    for q in range(P):
        if not low[q]:
            continue
        k = kk[q]
        for side in range(1 if c[q] < 0 else 2):
            mv, fx = (a[q], c[q]) if side == 0 else (c[q], a[q])
            if fx < 0:
                qf0 = qf1 = at[q]
                dfx = 0.0
            else:
                qf0, qf1 = cur[fx, min(k, need[fx] - 1)], cur[fx, min(k + 1, need[fx] - 1)]
                dfx = curd[fx, k] if k < need[fx] - 1 else 0.0
            for d in range(2):
                pa0, pa1, dm0 = _moved_step(diff, rob, cols, p0, hd, pose, u, du, mv, d, eps, dt, k)
                grad[q, side, d] = (kp.segment_margin(pa0, pa1, qf0, qf1, dm0, dfx) - ds[q] - m0[q]) / eps
        nrm = (grad[q, 0, 0] * grad[q, 0, 0] + grad[q, 0, 1] * grad[q, 0, 1]) + (
            grad[q, 1, 0] * grad[q, 1, 0] + grad[q, 1, 1] * grad[q, 1, 1])
        lift[q] = (2.0 * target - m0[q]) / max(nrm, 1e-12)
    step = np.zeros((p0.shape[0], 2))
    for side in range(3):  # in numpy's order: every pair's first member, then second, then the obstacles'
        for q in range(P):
            if low[q] and (c[q] < 0) == (side == 2):
                g, s = (c[q], 1) if side == 1 else (a[q], 0)
                step[g, 0] += lift[q] * grad[q, s, 0]
                step[g, 1] += lift[q] * grad[q, s, 1]
    return step


@jit
def repair_full(pose, u, du_c, lo, hi, dt, diff, rob, cols, group, has_group, sensing_range, cand, oc, orad,
                ogroup, has_ogroup, target, rounds, eps, tie):
    """One ``repair`` call: the nudged candidate ``(n, 2)`` (``tie``: the closest-step tie of ``gate.CLOSEST_TIE``)."""
    n = pose.shape[0]
    du = np.empty((n, 2))
    for g in range(n):
        for d in range(2):
            du[g, d] = min(max(du_c[g, d], lo[g, d]), hi[g, d])
    p0, hd = kp.starts(diff, rob, pose)
    C, F, NEED = np.empty((1, n, 2), dtype=np.complex128), np.zeros((1, n, 5)), np.empty((1, n), dtype=np.int64)
    R = np.empty(n)
    rowp, rowd, made = np.empty((n, 2), dtype=np.complex128), np.empty((n, 1)), np.zeros(n, dtype=np.bool_)
    for _ in range(rounds):
        for g in range(n):  # reach first: only robots with a pair that could come close need paths
            _store(C, F, NEED, 0, g, 2, *kp.candidate1(diff, kp.consts(rob, cols, g), p0[g], pose[g, 2], hd[g],
                                                       u[g, 0], u[g, 1], du[g, 0], du[g, 1], dt))
            R[g] = F[0, g, kp.REACH] + eps * dt * dt
        a, c, ds, at = kp.near(cand, p0, R, rob, group, has_group, sensing_range, oc, orad, ogroup, has_ogroup,
                            2.0 * target)
        if a.shape[0] == 0:
            break
        rowp, rowd, L = _repair_rows(rowp, rowd, made, a, c, p0, C, F, NEED, not diff, dt)
        low, m0, kk = _low_pairs(rowp, rowd, NEED[0], a, c, ds, at, target, L, tie)
        if not low.any():
            break
        step = _lifts(rowp, rowd, NEED[0], a, c, ds, at, low, m0, kk, target, eps, diff, rob, cols, p0, hd, pose,
                      u, du, dt)
        if not (step != 0.0).any():
            break
        for g in range(n):
            for d in range(2):
                v = min(max(du[g, d] + step[g, d], lo[g, d]), hi[g, d])
                if v != du[g, d]:
                    made[g] = False  # its path is made again when asked for
                du[g, d] = v
    return du
