"""Compiled barrier rows and the inputs' and deadlock stages' loops (numba; loaded through :mod:`aasoatt_env.compiled`).

The numpy references' operations in their order (no ``fastmath``; ``einsum``'s sums start from ``+0.0``), so the
numbers are theirs bit for bit: :func:`~.rows.numpy_rows` (``aasoatt`` barrier), ``robot_pairs``' brute force, the
inputs stage's checks, the ``multiplier`` trigger and ``A du_nom``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import literal_unroll

from aasoatt_env.numba_jit import jit, nmax, nmin

__all__ = ["aasoatt_rows", "multiplier_target", "numbers", "pairs_within"]


@jit
def _row(q, i, j, px, py, vx, vy, ax, ay, ds, vi2, vj2, A, k1, k2, fixed, auto, fade, speed_margin, Gi, Gj, rhs):
    """Fill row ``q`` of pair ``(i, j)`` (``j < 0``: an obstacle); returns ``(h, gap)`` with the true distance."""
    if fixed != fixed:  # FilterConfig.pair_margin: auto * min(1, |v_ij| / fade)
        s = math.sqrt(vx * vx + vy * vy) / fade
        margin = auto * (s if (s < 1.0 or s != s) else 1.0)
    else:
        margin = fixed
    if speed_margin != 0.0:
        margin = margin + speed_margin * (vi2 + vj2)
    rt = math.sqrt(px * px + py * py)
    r = nmax(rt, 1e-9)
    pv = px * vx + py * vy
    pa = px * ax + py * ay
    rhs[q] = (vx * vx + vy * vy) - pv * pv / (r * r) + (k1 + k2) * pv + k1 * k2 * r * (r - (ds + margin)) + pa
    for col in range(2):
        Gi[q, col] = 0.0 + A[i, 0, col] * -px + A[i, 1, col] * -py
        Gj[q, col] = -(0.0 + A[j, 0, col] * -px + A[j, 1, col] * -py) if j >= 0 else 0.0
    return pv / r + k1 * (r - ds), rt - ds


@jit
def aasoatt_rows(p, v, adot, A, radius, robots, obstacles, centers, oradius, k1, k2, fixed, auto, fade, speed_margin,
                 gap_initial):
    """Rows of the ``aasoatt`` barrier for robot pairs ``robots (P, 2)`` and robot-obstacle pairs ``(Q, 2)``.

    ``fixed``: ``FilterConfig.safety_margin`` or NaN for the speed-dependent default.  The caller checks every index
    (numba does not).  Returns ``(ri, rj, Gi, Gj, rhs, pairs, keys, h_min, gap_min)`` as ``numpy_rows``.
    """
    n, P, Q = p.shape[0], robots.shape[0], obstacles.shape[0]
    m, base = P + Q, n + oradius.shape[0] + 1
    ri, rj, out = np.empty(m, np.intp), np.empty(m, np.intp), np.empty((m, 2), np.intp)
    Gi, Gj, rhs, keys = np.empty((m, 2)), np.empty((m, 2)), np.empty(m), np.empty(m, np.int64)
    h_min, gap_min = np.inf, gap_initial
    for q in range(P):
        i, j = robots[q, 0], robots[q, 1]
        h, gap = _row(q, i, j, p[i, 0] - p[j, 0], p[i, 1] - p[j, 1], v[i, 0] - v[j, 0], v[i, 1] - v[j, 1],
                      adot[i, 0] - adot[j, 0], adot[i, 1] - adot[j, 1], radius[i] + radius[j],
                      v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1], v[j, 0] * v[j, 0] + v[j, 1] * v[j, 1], A, k1, k2,
                      fixed, auto, fade, speed_margin, Gi, Gj, rhs)
        h_min, gap_min = nmin(h_min, h), nmin(gap_min, gap)
        ri[q], rj[q], out[q, 0], out[q, 1], keys[q] = i, j, i, j, i * base + j
    for o in range(Q):
        q, i, k = P + o, obstacles[o, 0], obstacles[o, 1]
        h, gap = _row(q, i, -1, p[i, 0] - centers[k, 0], p[i, 1] - centers[k, 1], v[i, 0], v[i, 1], adot[i, 0],
                      adot[i, 1], radius[i] + oradius[k], v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1], 0.0, A, k1, k2,
                      fixed, auto, fade, speed_margin, Gi, Gj, rhs)
        h_min, gap_min = nmin(h_min, h), nmin(gap_min, gap)
        ri[q], rj[q], out[q, 0], out[q, 1], keys[q] = i, -1, i, -1 - k, i * base + n + k
    return ri, rj, Gi, Gj, rhs, out, keys, h_min, gap_min


@jit
def pairs_within(p, cand_i, cand_j, range2):
    """``(P, 2)``: the candidate pairs with ``d0 d0 + d1 d1 <= range2`` (``d = p_i - p_j``), in order."""
    C = cand_i.shape[0]
    kept = np.empty(C, np.intp)
    P = 0
    for c in range(C):
        d0, d1 = p[cand_i[c], 0] - p[cand_j[c], 0], p[cand_i[c], 1] - p[cand_j[c], 1]
        if d0 * d0 + d1 * d1 <= range2:
            kept[P] = c
            P += 1
    out = np.empty((P, 2), np.intp)
    for q in range(P):
        out[q, 0], out[q, 1] = cand_i[kept[q]], cand_j[kept[q]]
    return out


@jit
def numbers(arrays, bound, amax, reach):
    """``(ok, scale, near)``: numbers within ``bound``, ``lo <= hi``; ``max(amax, |lo|, |hi|)``; no pull-in needed.

    ``near``: :func:`~aasoatt_env.safety.inputs.bound_nominal`'s quick test with ``reach``; ``arrays``: a step's
    arrays, ``nominal_du, lo, hi`` first (``(n, 2)`` each).  numpy's numbers.
    """
    nominal, lo, hi = arrays[0], arrays[1], arrays[2]
    n = lo.shape[0]
    ok, top = True, 0.0
    for a in literal_unroll(arrays):
        for x in a.ravel():
            ok = ok and abs(x) <= bound  # (NaN fails too)
    for x in nominal.ravel():
        top = max(top, abs(x))
    scale = np.empty(n)
    smax, amin = 0.0, np.inf
    for i in range(n):
        s = amax[i]
        for c in range(2):
            ok = ok and lo[i, c] <= hi[i, c]
            s = max(s, abs(lo[i, c]), abs(hi[i, c]))
        scale[i] = s
        smax, amin = max(smax, s), min(amin, amax[i])
    return ok, scale, n > 0 and 1.5 * (top + smax) <= reach * amin


@jit
def multiplier_target(avoiding, p, v, p_d, v_d, has_reference, A, nominal, zeta, low_speed, goal_tol):
    """``(triggered (n,), zeta_i (n,), A du_nom (n, 2), any triggered)``.

    ``avoiding``: the memory (a row of the robot bound at the previous step); ``p_d, v_d`` are read with
    ``has_reference`` only (without a reference a robot that was avoiding is not done).
    """
    n = p.shape[0]
    triggered = np.empty(n, dtype=np.bool_)
    zeta_i = np.empty(n)
    target = np.empty((n, 2))
    anyone = False
    for i in range(n):
        on = avoiding[i]
        if on and has_reference:  # not done: still moving along the reference, or away from it
            vx, vy = v_d[i, 0], v_d[i, 1]
            ex, ey = p[i, 0] - p_d[i, 0], p[i, 1] - p_d[i, 1]
            on = math.sqrt(vx * vx + vy * vy) >= low_speed or math.sqrt(ex * ex + ey * ey) > goal_tol
        triggered[i] = on
        anyone |= on
        zeta_i[i] = zeta if on else 0.0
        for r in range(2):
            target[i, r] = 0.0 + A[i, r, 0] * nominal[i, 0] + A[i, r, 1] * nominal[i, 1]
    return triggered, zeta_i, target, anyone
