"""Compiled observations (numba; loaded through :mod:`aasoatt_env.compiled`).

The numbers of :func:`~aasoatt_env.sim.observations.build_observations`' numpy reference, bit for bit, in one pass
per robot.
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import jit

__all__ = ["observations"]


@jit
def _put(obs, i, c, value, bound):
    """``obs[i, c] = clip(float32(value), -bound, bound)`` (NaN stays NaN, as ``np.minimum(np.maximum(...))``)."""
    v = np.float32(value)
    if v < -bound:
        v = np.float32(-bound)
    elif v > bound:
        v = np.float32(bound)
    obs[i, c] = v


@jit
def observations(p, v, theta, u, p_d, v_d, a_d, goals, radii, centres, orad, sensing_range, k_robots, k_obstacles,
                 idx, dist, gaps, offset, has_offset, self_dim, slot_dim, bound):
    """``(N, self_dim + slot_dim (k_robots + k_obstacles))`` float32 (the reference's arguments, unpacked)."""
    n = p.shape[0]
    obs = np.zeros((n, self_dim + slot_dim * (k_robots + k_obstacles)), np.float32)
    m = gaps.shape[1]
    kk = min(k_obstacles, m)
    taken = np.zeros(m, np.bool_)
    for i in range(n):
        row = (p[i, 0] - p_d[i, 0], p[i, 1] - p_d[i, 1], goals[i, 0] - p[i, 0], goals[i, 1] - p[i, 1], v[i, 0],
               v[i, 1], math.cos(theta[i]), math.sin(theta[i]), u[i, 0], u[i, 1], v_d[i, 0], v_d[i, 1], a_d[i, 0],
               a_d[i, 1])
        for c in range(14):
            _put(obs, i, c, row[c], bound)
        if k_robots and n > 1:
            for r in range(min(k_robots, idx.shape[1])):
                if dist[i, r] <= sensing_range:
                    j, c = idx[i, r], self_dim + slot_dim * r
                    _put(obs, i, c, p[j, 0] - p[i, 0], bound)
                    _put(obs, i, c + 1, p[j, 1] - p[i, 1], bound)
                    _put(obs, i, c + 2, v[j, 0] - v[i, 0], bound)
                    _put(obs, i, c + 3, v[j, 1] - v[i, 1], bound)
                    _put(obs, i, c + 4, (-radii[j] - radii[i]) + dist[i, r], bound)
                    obs[i, c + 5] = 1.0
        taken[:] = False
        for s in range(kk):  # the kk smallest gaps, the first index on a tie (a stable sort's first kk)
            o = -1
            for q in range(m):
                if not taken[q] and (o < 0 or gaps[i, q] < gaps[i, o]):
                    o = q
            taken[o] = True
            g, oo = gaps[i, o], o + offset[i] if has_offset else o
            if g + radii[i] + orad[oo] <= sensing_range:
                c = self_dim + slot_dim * (k_robots + s)
                _put(obs, i, c, centres[oo, 0] - p[i, 0], bound)
                _put(obs, i, c + 1, centres[oo, 1] - p[i, 1], bound)
                _put(obs, i, c + 2, -v[i, 0], bound)
                _put(obs, i, c + 3, -v[i, 1], bound)
                _put(obs, i, c + 4, g, bound)
                obs[i, c + 5] = 1.0
    return obs
