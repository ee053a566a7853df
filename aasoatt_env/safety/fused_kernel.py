"""The rows, solve and backup stages of a warm centralised step in one compiled call (:mod:`.fused`).

It calls the stages' own kernels in the pipeline's order, so where it answers its numbers are the pipeline's.
"""

from __future__ import annotations

import numpy as np

from aasoatt_env.numba_jit import jit
from aasoatt_env.safety.backup.kernels import gate_full
from aasoatt_env.safety.centralized_kernel import CLOSED_FORM, VERIFIED, solve_decomposed
from aasoatt_env.safety.rows_kernel import aasoatt_rows

__all__ = ["fused_step", "warm_rows"]


@jit
def warm_rows(prev_keys, prev_z, keys):
    """The previous multipliers on these rows' keys (``prev_keys`` increasing; 0 for a new row)."""
    out = np.zeros(keys.shape[0])
    P = prev_keys.shape[0]
    for r in range(keys.shape[0]):
        k, a, b = keys[r], 0, P
        while a < b:
            mid = (a + b) // 2
            if prev_keys[mid] < k:
                a = mid + 1
            else:
                b = mid
        if a < P and prev_keys[a] == k:
            out[r] = prev_z[a]
    return out


@jit
def fused_step(rows_in, qp_in, prev, settings, eta_tol, gate_in, gate_block):
    """One warm step's rows, QP and quick backup check (module docstring).

    ``rows_in``: :func:`aasoatt_rows`' arguments; ``qp_in``: ``(target, lo, hi, scale)``; ``prev``: the previous
    ``(x, keys, z)``; ``gate_in``: ``(pose, u, dt, levels, limit, tol)``; ``gate_block``: the gate's team, pair and
    obstacle block.  Returns ``(solved, passed, rows, qp, avoiding, backup)``: ``rows`` the rows kernel's
    tuple, ``qp = (iterations, n_qp, du, x, z, eta)``, ``avoiding`` the robots with a row of multiplier above
    ``eta_tol``; ``passed``: the quick check finds nothing broken and brakes only robots whose candidate path leaves
    their range limit, so that it is the backup stage's answer ``backup = (du, braking, nudged, margin)`` (as
    :func:`~.backup.gate_with_repair` and :class:`~.backup.BackupLayer` give it: nothing to hold or repair).
    """
    rows = aasoatt_rows(*rows_in)
    ri, rj, Gi, Gj, rhs, pairs, keys, h_min, gap_min = rows
    target, lo, hi, scale = qp_in
    code, used, n_qp, du, x, z, eta = solve_decomposed(rows_in[3], target, lo, hi, scale, ri, rj, Gi, Gj, rhs,
                                                       prev[0], warm_rows(prev[1], prev[2], keys), settings)
    n = du.shape[0]
    avoiding = np.zeros(n, np.bool_)
    for r in range(z.shape[0]):
        if z[r] > eta_tol:
            avoiding[ri[r]] = True
            if rj[r] >= 0:
                avoiding[rj[r]] = True
    solved = code == CLOSED_FORM or code == VERIFIED
    passed, gdu, braking, nudged, margin = False, du, np.zeros(n, np.bool_), np.zeros(n, np.bool_), 0.0
    if solved:
        pose, u, dt, levels, limit, tol = gate_in
        gdu, braking, broken, _, _, out_of_range, _, _, margin = gate_full(pose, u, du, dt, levels, True,
                                                                           *gate_block, limit, tol, False)
        passed = True
        for i in range(n):
            passed = passed and not (broken[i] or (braking[i] and not out_of_range[i]))
            nudged[i] = not braking[i] and (abs(gdu[i, 0] - du[i, 0]) > 1e-9 * scale[i]
                                            or abs(gdu[i, 1] - du[i, 1]) > 1e-9 * scale[i])
    return solved, passed, rows, (used, n_qp, du, x, z, eta), avoiding, (gdu, braking, nudged, margin)
