"""The default deadlock trigger and the target it corrects, compiled (numba; through :mod:`aasoatt_env.compiled`).

:func:`multiplier_target` makes, in one call, what the centralised step computes in
numpy before its compiled rows and QP (:meth:`aasoatt_env.safety.core.SafetyFilter.step`)
with the ``multiplier`` trigger (:mod:`aasoatt_env.safety.deadlock`, the default):
which robots are triggered, their ``zeta_i`` and the nominal's target
``A du_nom``, with numpy's operations in numpy's order (the ``sqrt`` of the
sums of squares, ``einsum``'s sums from ``+0.0``), so the same numbers bit for
bit (``tests/test_compiled.py``).  The strategy's correction of the triggered
robots' targets stays the registry's numpy function (:class:`~aasoatt_env.safety.deadlock.Strategy`).
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import jit

__all__ = ["multiplier_target"]


@jit
def multiplier_target(avoiding, p, v, p_d, v_d, has_reference, A, nominal, zeta, low_speed, goal_tol):
    """The ``multiplier`` trigger, each robot's ``zeta_i`` and the nominal's target.

    Parameters
    ----------
    avoiding : numpy.ndarray
        ``(n,)`` bool: the deadlock memory (a robot had a binding row at the previous step; all
        False where there is none).
    p, v : numpy.ndarray
        Control points and their velocities ``(n, 2)``.
    p_d, v_d : numpy.ndarray
        The reference ``(n, 2)``, read only with ``has_reference`` (without one a robot is not done
        while it was avoiding).
    has_reference : bool
        Whether ``p_d, v_d`` are the reference.
    A, nominal : numpy.ndarray
        Input matrices ``(n, 2, 2)`` and the nominal ``du`` ``(n, 2)``.
    zeta, low_speed, goal_tol : float
        :class:`~aasoatt_env.safety.config.FilterConfig`'s deadlock gain and "done" thresholds.

    Returns
    -------
    tuple
        ``(triggered (n,) bool, zeta_i (n,), A du_nom (n, 2), any triggered)``.  Every array is
        float64 (bool) and C-contiguous, of the shapes the caller checked (read without bounds checks).
    """
    n = p.shape[0]
    triggered = np.empty(n, dtype=np.bool_)
    zeta_i = np.empty(n)
    target = np.empty((n, 2))
    anyone = False
    for i in range(n):
        on = avoiding[i]
        if on and has_reference:  # _not_done: still moving along the reference, or away from it
            vx, vy = v_d[i, 0], v_d[i, 1]
            ex, ey = p[i, 0] - p_d[i, 0], p[i, 1] - p_d[i, 1]
            on = math.sqrt(vx * vx + vy * vy) >= low_speed or math.sqrt(ex * ex + ey * ey) > goal_tol
        triggered[i] = on
        anyone |= on
        zeta_i[i] = zeta if on else 0.0
        for r in range(2):
            target[i, r] = 0.0 + A[i, r, 0] * nominal[i, 0] + A[i, r, 1] * nominal[i, 1]
    return triggered, zeta_i, target, anyone
