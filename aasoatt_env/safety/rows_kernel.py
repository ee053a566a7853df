"""The paper's barrier rows of every robot pair in one compiled call (numba; through :mod:`aasoatt_env.compiled`).

:func:`aasoatt_rows` is what :meth:`aasoatt_env.safety.core.SafetyFilter.step`
does in numpy for the neighbour search and the rows (on either side of the
deadlock rule, which leaves these rows alone), for the ``aasoatt`` barrier
(eqn.7-8) of robot pairs, written as one loop over the pairs
instead of some forty small array operations (whose overhead, not their
arithmetic, is a small team's or a training stack's step):

1. the pairs within the sensing range, from candidates (the brute force's
   pairs of :func:`~aasoatt_env.model.geometry.robot_pairs`, with its distance
   test; or the pairs it found);
2. each pair's relative position, velocity and drift acceleration, and its
   safety distance with the discrete-time margin
   (:meth:`~aasoatt_env.safety.config.FilterConfig.pair_margin` and
   ``speed_margin``);
3. the barrier's value with the true safety distance (the smallest is the
   result's ``barrier_min``) and the surface gap (the smallest is the margin
   without the backup layer);
4. the row ``rhs`` of :func:`~aasoatt_env.safety.barriers.barrier_rows`, the
   row normals in wheel coordinates ``G_i = A_i^T c``, ``G_j = -A_j^T c``
   (``c = -p_ij``) and the warm-start keys.

The operations are numpy's, in numpy's order (numba compiles without
``fastmath``, so no product is fused into a sum; ``einsum``'s sums start from
``+0.0`` here too), so the numbers are the reference's bit for bit
(``tests/test_compiled.py`` compares them on random and coincident pairs, and
every step of filtered episodes).
The filter takes this path with the compiled kernels, the ``aasoatt`` barrier, a
deadlock strategy that leaves the rows alone and no obstacles; every other
step takes the numpy reference.
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import jit as _jit
from aasoatt_env.numba_jit import nmax as _nmax
from aasoatt_env.numba_jit import nmin as _nmin

__all__ = ["aasoatt_rows"]


@_jit
def aasoatt_rows(p, v, adot, A, radius, cand_i, cand_j, range2, k1, k2, fixed_margin, auto_margin, fade_speed,
                 speed_margin, key_base, gap_initial):
    """The robot pairs within range and their rows of the ``aasoatt`` barrier (module docstring).

    Parameters
    ----------
    p, v, adot : numpy.ndarray
        ``(n, 2)`` control-point positions, velocities and drift accelerations ``A_dot u``.
    A : numpy.ndarray
        ``(n, 2, 2)`` input matrices.
    radius : numpy.ndarray
        ``(n,)`` radii.
    cand_i, cand_j : numpy.ndarray
        ``(C,)`` candidate pairs, robot indices in ``[0, n)`` (checked by the caller: numba does not
        check bounds).
    range2 : float
        The squared sensing range: a candidate is kept where ``d0 d0 + d1 d1 <= range2``
        (``d = p_i - p_j``), as :func:`~aasoatt_env.model.geometry.robot_pairs`' brute force keeps it
        (``inf``: every candidate, the pairs found already).
    k1, k2 : float
        The barrier's gains.
    fixed_margin : float
        ``FilterConfig.safety_margin``, or NaN for the speed-dependent default
        ``auto_margin * min(1, |v_ij| / fade_speed)``.
    speed_margin : float
        ``FilterConfig.speed_margin``: ``speed_margin (|v_i|^2 + |v_j|^2)`` is added to the margin.
    key_base : int
        The warm-start key of pair ``(i, j)`` is ``i * key_base + j``.
    gap_initial : float
        The smallest gap without pairs.

    Returns
    -------
    tuple
        ``(pairs (P, 2), p_ij (P, 2), G_i (P, 2), G_j (P, 2), rhs (P,), keys (P,), barrier_min, gap_min)``
        for the ``P`` candidates kept, in their order.
    """
    C = cand_i.shape[0]
    P = 0
    kept = np.empty(C, dtype=np.int64)
    for c in range(C):
        i, j = cand_i[c], cand_j[c]
        d0, d1 = p[i, 0] - p[j, 0], p[i, 1] - p[j, 1]
        if d0 * d0 + d1 * d1 <= range2:
            kept[P] = c
            P += 1
    pairs = np.empty((P, 2), dtype=np.int64)
    rel = np.empty((P, 2))
    Gi = np.empty((P, 2))
    Gj = np.empty((P, 2))
    rhs = np.empty(P)
    keys = np.empty(P, dtype=np.int64)
    h_min = np.inf
    gap_min = gap_initial
    k12 = k1 + k2
    kk = k1 * k2
    auto = fixed_margin != fixed_margin
    for q in range(P):
        i, j = cand_i[kept[q]], cand_j[kept[q]]
        pairs[q, 0], pairs[q, 1] = i, j
        px, py = p[i, 0] - p[j, 0], p[i, 1] - p[j, 1]
        vx, vy = v[i, 0] - v[j, 0], v[i, 1] - v[j, 1]
        ax, ay = adot[i, 0] - adot[j, 0], adot[i, 1] - adot[j, 1]
        ds = radius[i] + radius[j]
        if auto:  # pair_margin: auto_margin * np.minimum(1.0, speed / fade_speed)
            s = math.sqrt(vx * vx + vy * vy) / fade_speed
            margin = auto_margin * (s if (s < 1.0 or s != s) else 1.0)
        else:
            margin = fixed_margin
        if speed_margin != 0.0:
            margin = margin + speed_margin * ((v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1])
                                              + (v[j, 0] * v[j, 0] + v[j, 1] * v[j, 1]))
        rt = math.sqrt(px * px + py * py)
        r = _nmax(rt, 1e-9)
        pv = px * vx + py * vy
        h_min = _nmin(h_min, pv / r + k1 * (r - ds))
        gap_min = _nmin(gap_min, rt - ds)
        vv = vx * vx + vy * vy
        pa = px * ax + py * ay
        rhs[q] = vv - pv * pv / (r * r) + k12 * pv + kk * r * (r - (ds + margin)) + pa
        cx, cy = -px, -py
        for col in range(2):  # (einsum's sums start from +0.0)
            Gi[q, col] = 0.0 + A[i, 0, col] * cx + A[i, 1, col] * cy
            Gj[q, col] = -(0.0 + A[j, 0, col] * cx + A[j, 1, col] * cy)
        rel[q, 0], rel[q, 1] = px, py
        keys[q] = i * key_base + j
    return pairs, rel, Gi, Gj, rhs, keys, h_min, gap_min
