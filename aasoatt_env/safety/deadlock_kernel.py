"""The deadlock stage's ``multiplier`` trigger and ``A du_nom`` in one compiled loop (numba).

numpy's operations in numpy's order (``sqrt`` of sums of squares; ``einsum``'s sums from ``+0.0``): its numbers.
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import jit

__all__ = ["multiplier_target"]


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
