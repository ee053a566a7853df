"""Compiled neighbour search and contact components (numba; loaded through :mod:`aasoatt_env.compiled`).

:func:`cell_pairs` tests the candidates of a grid of cells a little wider than the radius (every pair lies
in one 3x3 block) as the brute force does: the pairs and order of :func:`~aasoatt_env.model.geometry.robot_pairs`.
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import jit

__all__ = ["cell_pairs", "components", "nearest"]

_WIDEN = 1e-6  # cells are radius * (1 + _WIDEN) wide: rounding never splits a pair two cells apart


@jit
def _grid(p, cell):
    """Whether each point is finite, its cell ``(cx, cy)`` and the grid's size ``(nx, ny)`` (0: over 2^31 cells)."""
    n = p.shape[0]
    ok = np.empty(n, np.bool_)
    x0, y0, x1, y1 = math.inf, math.inf, -math.inf, -math.inf
    for i in range(n):
        ok[i] = math.isfinite(p[i, 0]) and math.isfinite(p[i, 1])
        if ok[i]:
            x0, y0, x1, y1 = min(x0, p[i, 0]), min(y0, p[i, 1]), max(x1, p[i, 0]), max(y1, p[i, 1])
    cx, cy = np.zeros(n, np.int64), np.zeros(n, np.int64)
    if (x1 - x0) / cell > 2.0**31 or (y1 - y0) / cell > 2.0**31:
        return ok, cx, cy, 0, 0
    nx, ny = 1, 1
    for i in range(n):
        if ok[i]:
            cx[i] = int(math.floor((p[i, 0] - x0) / cell))
            cy[i] = int(math.floor((p[i, 1] - y0) / cell))
            nx, ny = max(nx, cx[i] + 3), max(ny, cy[i] + 3)
    return ok, cx, cy, nx, ny


@jit
def cell_pairs(p, radius, groups, has_groups):
    """``(pairs, True)``: ``(P, 2)`` int64, ``i < j``, sorted, ``|p_i - p_j|^2 <= radius^2``, of one group each.

    ``radius`` is finite and > 0; non-finite points pair with nothing; ``(empty, False)`` where cell keys overflow.
    """
    n = p.shape[0]
    r2 = radius * radius
    ok, cx, cy, nx, ny = _grid(p, radius * (1.0 + _WIDEN))
    if nx == 0:
        return np.empty((0, 2), np.int64), False
    dense = nx * ny <= 8 * n + 64  # one slot per cell; else the occupied cells' keys, searched
    key = np.empty(n, np.int64)
    for i in range(n):
        key[i] = (cx[i] + 1) * ny + (cy[i] + 1) if ok[i] else -1
    order = np.argsort(key, kind="mergesort")
    skey = key[order]
    start = np.zeros(nx * ny + 1 if dense else 1, np.int64)
    if dense:
        for i in range(n):
            if ok[i]:
                start[key[i] + 1] += 1
        for c in range(nx * ny):
            start[c + 1] += start[c]
    first = n - int(ok.sum())  # the points without a cell sort first (key -1)
    out = np.empty((max(16, 8 * n), 2), np.int64)
    m = 0
    buf = np.empty(max(n, 1), np.int64)
    for i in range(n):
        if not ok[i]:
            continue
        nb = 0
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                k = (cx[i] + 1 + dx) * ny + (cy[i] + 1 + dy)
                if dense:
                    s, e = first + start[k], first + start[k + 1]
                else:
                    s = np.searchsorted(skey, k)
                    e = s
                    while e < n and skey[e] == k:
                        e += 1
                for t in range(s, e):
                    j = order[t]
                    if j <= i or (has_groups and groups[j] != groups[i]):
                        continue
                    ddx = p[i, 0] - p[j, 0]
                    ddy = p[i, 1] - p[j, 1]
                    if ddx * ddx + ddy * ddy <= r2:
                        q = nb  # insertion: the row's pairs in ascending j
                        while q > 0 and buf[q - 1] > j:
                            buf[q] = buf[q - 1]
                            q -= 1
                        buf[q] = j
                        nb += 1
        if m + nb > out.shape[0]:
            grown = np.empty((2 * (m + nb), 2), np.int64)
            grown[:m] = out[:m]
            out = grown
        for q in range(nb):
            out[m, 0], out[m, 1] = i, buf[q]
            m += 1
    return out[:m].copy(), True


@jit
def _find(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@jit
def components(n, a, b):
    """Label ``(n,)`` of each point's component under the edges ``(a[k], b[k])``: its smallest index."""
    parent = np.arange(n)
    for k in range(a.shape[0]):
        ra, rb = _find(parent, a[k]), _find(parent, b[k])
        if ra != rb:
            if ra < rb:
                parent[rb] = ra
            else:
                parent[ra] = rb
    lab = np.empty(n, np.int64)
    for i in range(n):
        lab[i] = _find(parent, i)
    return lab


@jit
def nearest(p, radii, teams, k, equal):
    """``_nearest`` and ``_robot_gaps`` of ``teams`` equal teams stacked in ``p``, robot by robot.

    Each robot's ``k`` nearest of its team ``(K N, k)`` (stack indices, centre distances; -1, inf: none), nearest
    first and the lower index on a tie (a stable sort's order), and its surface gap to the nearest ``(K N,)`` (inf:
    alone); ``equal (K,)``: the team's radii are equal (its gap is the nearest distance less ``2 r``).  Finite ``p``.
    """
    total = p.shape[0]
    n = total // teams
    idx = np.full((total, k), -1, np.int64)
    dist = np.full((total, k), np.inf)
    gap = np.full(total, np.inf)
    x, y = p[:, 0].copy(), p[:, 1].copy()
    row = np.empty(n)
    for t in range(teams):
        o = t * n
        for a in range(n):
            i = o + a
            for b in range(n):  # (a loop of its own: it vectorises)
                dx, dy = x[i] - x[o + b], y[i] - y[o + b]
                row[b] = math.sqrt(dx * dx + dy * dy)
            row[a] = np.inf
            g = np.inf
            if equal[t]:
                for b in range(n):
                    g = row[b] if row[b] < g else g
                g -= 2.0 * radii[i]
            else:
                for b in range(n):
                    e = (row[b] - radii[i]) - radii[o + b]
                    g = e if e < g else g
            gap[i] = g
            for q in range(min(k, n - 1)):  # k passes of a branch-free argmin: the lower index on a tie
                best, bi = np.inf, -1
                for b in range(n):
                    better = row[b] < best
                    best = row[b] if better else best
                    bi = b if better else bi
                if bi < 0:
                    break
                dist[i, q], idx[i, q] = best, o + bi
                row[bi] = np.inf
    return idx, dist, gap
