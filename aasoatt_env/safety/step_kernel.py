"""A centralised filter step's compiled parts in one call (numba; through :mod:`aasoatt_env.compiled`).

:func:`filter_step` runs, for one physics step, the kernels that
:meth:`aasoatt_env.safety.core.SafetyFilter.step` calls one by one, and the
small array operations between them, in one call: each of those Python-level
calls and operations costs microseconds whatever the team's size, which is
most of a small team's step and of a training stack's.

1. the pairs within range and their rows (:func:`~aasoatt_env.safety.rows_kernel.aasoatt_rows`);
2. the previous multipliers mapped onto these rows by their keys (the filter's
   warm start, kept in key order: :func:`~aasoatt_env.safety.decomposition_kernel.search_rows`);
3. the per-robot scale of the scaled variables;
4. the QP by the compiled decomposition
   (:func:`~aasoatt_env.safety.decomposition_kernel.solve_decomposed`);
5. the robots with a binding row (``avoiding``);
6. the backup layer's quick check (:func:`~aasoatt_env.safety.numba_kernels.gate_full`);
7. where nobody brakes, or only robots too fast for the range limit (the
   check's answer is then the layer's): the applied inputs, each robot's
   correction and whether it intervened or was nudged.

It stops where the Python step has more to decide and says where
(:data:`ROWS`: the QP was not answered here; :data:`QP`: the check braked
someone for a pair), returning what it made so far; the Python step goes on from there
with the same code it runs without this kernel.  Every number is the one the
separate calls give, bit for bit: the same kernels on the same arrays, and the
operations between them in numpy's order (no ``fastmath``); the deadlock
trigger, the target and the axle poses (numpy's ``cos``/``sin``) stay in numpy
before the call.  ``tests/test_compiled.py`` runs filtered episodes with and
without it and compares every step.
"""

from __future__ import annotations

import numpy as np

from aasoatt_env.numba_jit import jit, nmin
from aasoatt_env.safety.decomposition_kernel import (
    CLOSED_FORM,
    PARTS,
    VERIFIED,
    search_rows,
    solve_decomposed,
)
from aasoatt_env.safety.numba_kernels import gate_full
from aasoatt_env.safety.rows_kernel import aasoatt_rows

# (the decomposition's codes too: the caller reads them here, where numba is already imported)
__all__ = ["CLOSED_FORM", "DONE", "PARTS", "QP", "ROWS", "VERIFIED", "filter_step", "unpack"]

ROWS = 0
"""Stopped after the rows and the scale: the QP was not answered here (the decomposition's other codes)."""
QP = 1
"""Stopped after the QP and the quick check, which brakes someone for a pair (the repair or the full check follows)."""
DONE = 2
"""The whole step: nobody brakes, or only for the range limit (or the backup layer is off)."""


@jit
def filter_step(p, v, adot, A, radius, cand_i, cand_j, range2, k1, k2, fixed_margin, auto_margin, fade_speed,
                speed_margin, key_base, gap_initial, target, lo, hi, max_wheel_accel, nominal, x_prev, prev_keys,
                prev_z, max_iter, one_change_iter, tol, warm_rel, warm_floor, bound_tight, row_norm_min,
                dense_max_vars, dense_max_cells, eta_tol, backup, pose, u, dt, levels, diff, offset, cols, tg, amax,
                adec, group, has_group, sensing_range, oc, orad, ogroup, has_ogroup, limit, gate_tol):
    """One centralised step's compiled parts (module docstring).

    Parameters
    ----------
    p, ..., gap_initial
        :func:`~aasoatt_env.safety.rows_kernel.aasoatt_rows`' arguments.
    target, lo, hi : numpy.ndarray
        The QP's target control-point accelerations and bounds ``(n, 2)``.
    max_wheel_accel : numpy.ndarray
        ``(n,)``, for the scale.
    nominal : numpy.ndarray
        The nominal ``du`` ``(n, 2)`` (the correction is measured from it).
    x_prev, prev_keys, prev_z : numpy.ndarray
        The previous step's scaled point ``(n, 2)``, row keys (non-decreasing: the filter keeps them
        sorted) and multipliers.
    max_iter, ..., dense_max_cells
        :func:`~aasoatt_env.safety.decomposition_kernel.solve_decomposed`'s constants.
    eta_tol : float
        A row binds where its multiplier exceeds this.
    backup : bool
        Run the backup layer's quick check.
    pose, ..., gate_tol
        :func:`~aasoatt_env.safety.numba_kernels.gate_full`'s arguments (``quick``, no hold; the
        candidate pairs are this step's pairs).

    Returns
    -------
    tuple
        ``(stage, pairs, keys, barrier_min, gap_min, qp_code, iterations, n_qp, n_vars, n_parts, x, z, eta,
        avoiding, braking, broken, rounds, n_pairs, margin, du, correction, intervened, nudged, floats,
        flags)``; ``stage`` (:data:`ROWS`, :data:`QP`, :data:`DONE`) says which are made (the others are
        empty, or, after :data:`ROWS`, the decomposition's buffers, not to be read unless ``qp_code`` is its
        :data:`PARTS`); ``qp_code`` is the decomposition's.  What only the stages before :data:`DONE` read
        is packed into two arrays where it stops early (empty after :data:`DONE`; each array returned
        costs the call a Python object):
        ``floats`` holds ``Gi, Gj (m, 2), rhs (m,), scale (n,), z_warm (m,), du_qp (n, 2), xs (2n,),
        zs (m,), gate_du (n, 2), share (n,), robot_margin (n,)`` one after the other (:func:`unpack`),
        ``flags`` ``done (n,)`` and ``out_of_range (n,)`` (the gate's entries only where it ran).
    """
    n = p.shape[0]
    pairs, _, Gi, Gj, rhs, keys, h_min, gap_min = aasoatt_rows(
        p, v, adot, A, radius, cand_i, cand_j, range2, k1, k2, fixed_margin, auto_margin, fade_speed, speed_margin,
        key_base, gap_initial)
    m = rhs.shape[0]
    scale = np.empty(n)
    for g in range(n):  # max(max_wheel_accel, |lo|, |hi|), 1 where that is 0
        b0 = max(abs(lo[g, 0]), abs(hi[g, 0]))
        b1 = max(abs(lo[g, 1]), abs(hi[g, 1]))
        s = max(max_wheel_accel[g], max(b0, b1))
        scale[g] = s if s > 0 else 1.0
    ri = pairs[:, 0].copy()
    rj = pairs[:, 1].copy()
    z0 = np.zeros(m)  # the filter's _map_warm: the previous multipliers on these rows by key, 0 where none
    if prev_keys.shape[0] and m:
        search_rows(prev_keys, prev_z, keys, z0)
    du_qp, x, z, eta = np.empty((n, 2)), np.empty((n, 2)), np.empty(m), np.empty(m)
    xs, zs, done = np.empty(2 * n), np.empty(m), np.empty(n, dtype=np.bool_)
    code, used, n_qp, n_vars, n_parts = solve_decomposed(
        A, target, lo, hi, scale, ri, rj, Gi, Gj, rhs, x_prev, z0, max_iter, one_change_iter, tol, warm_rel,
        warm_floor, bound_tight, row_norm_min, dense_max_vars, dense_max_cells, du_qp, x, z, eta, xs, zs, done)
    e2, eb, ei = np.empty((0, 2)), np.empty(0, dtype=np.bool_), np.empty(0)
    if code != CLOSED_FORM and code != VERIFIED:
        floats, flags = _packed(Gi, Gj, rhs, scale, z0, du_qp, xs, zs, done)
        return (ROWS, pairs, keys, h_min, gap_min, code, used, n_qp, n_vars, n_parts, x, z, eta, eb, eb, eb, 0, 0,
                0.0, e2, ei, eb, eb, floats, flags)
    avoiding = np.zeros(n, dtype=np.bool_)
    for q in range(m):
        if z[q] > eta_tol:
            avoiding[ri[q]] = True
            if rj[q] >= 0:
                avoiding[rj[q]] = True
    if not backup:
        gdu, braking, broken, share, robot_margin, out_of_range = e2, eb, np.zeros(n, dtype=np.bool_), ei, ei, eb
        rounds, n_pairs, margin = 0, 0, gap_min
    else:
        gdu, braking, broken, share, robot_margin, out_of_range, rounds, n_pairs, margin = gate_full(
            pose, u, du_qp, dt, levels, True, diff, offset, cols, tg, amax, adec, radius, group, has_group,
            sensing_range, pairs, oc, orad, ogroup, has_ogroup, limit, gate_tol, False)
        brakes, beyond, other, any_broken = False, False, False, False
        for g in range(n):
            brakes |= braking[g]
            beyond |= out_of_range[g]
            other |= braking[g] and not out_of_range[g]
            any_broken |= broken[g]
        if brakes:
            if not beyond or any_broken or other:  # the repair or the full check may follow
                floats, flags = _packed(Gi, Gj, rhs, scale, z0, du_qp, xs, zs, done)
                floats[7 * m + 5 * n:7 * m + 7 * n] = gdu.ravel()
                floats[7 * m + 7 * n:7 * m + 8 * n] = share
                floats[7 * m + 8 * n:7 * m + 9 * n] = robot_margin
                flags[n:2 * n] = out_of_range
                return (QP, pairs, keys, h_min, gap_min, code, used, n_qp, n_vars, n_parts, x, z, eta, avoiding,
                        braking, broken, rounds, n_pairs, margin, e2, ei, eb, eb, floats, flags)
            # every robot that brakes does so for the range limit alone, nothing broken: the quick check is
            # the layer's answer (gate_with_repair's first return), its margin as _merged takes it
            for g in range(n):
                margin = nmin(margin, robot_margin[g])
    du = np.empty((n, 2))
    correction = np.empty(n)
    intervened = np.zeros(n, dtype=np.bool_)
    nudged = np.zeros(n, dtype=np.bool_)
    for g in range(n):
        tiny = 1e-9 * scale[g]
        for k in range(2):
            du[g, k] = du_qp[g, k] if (not backup or broken[g]) else gdu[g, k]
            if backup and not broken[g] and not braking[g] and abs(du[g, k] - du_qp[g, k]) > tiny:
                nudged[g] = True  # (the check's level arithmetic only rounds: the repair moves inputs)
        d0, d1 = du[g, 0] - nominal[g, 0], du[g, 1] - nominal[g, 1]
        correction[g] = np.sqrt(d0 * d0 + d1 * d1)
        intervened[g] = correction[g] > tiny
    return (DONE, pairs, keys, h_min, gap_min, code, used, n_qp, n_vars, n_parts, x, z, eta, avoiding, braking,
            broken, rounds, n_pairs, margin, du, correction, intervened, nudged, ei, eb)


@jit
def _packed(Gi, Gj, rhs, scale, z0, du_qp, xs, zs, done):
    """What the early stops read, in :func:`unpack`'s layout; the gate's entries NaN and False, to be filled."""
    n, m = scale.shape[0], rhs.shape[0]
    floats = np.empty(7 * m + 9 * n)
    floats[7 * m + 5 * n:] = np.nan
    flags = np.zeros(2 * n, dtype=np.bool_)
    floats[0:2 * m] = Gi.ravel()
    floats[2 * m:4 * m] = Gj.ravel()
    floats[4 * m:5 * m] = rhs
    floats[5 * m:5 * m + n] = scale
    floats[5 * m + n:6 * m + n] = z0
    floats[6 * m + n:6 * m + 3 * n] = du_qp.ravel()
    floats[6 * m + 3 * n:6 * m + 5 * n] = xs
    floats[6 * m + 5 * n:7 * m + 5 * n] = zs
    flags[0:n] = done
    return floats, flags


def unpack(floats: np.ndarray, flags: np.ndarray, n: int, m: int) -> tuple:
    """:func:`filter_step`'s packed arrays as views.

    Parameters
    ----------
    floats, flags : numpy.ndarray
        :func:`filter_step`'s last two returns.
    n, m : int
        Its robots and rows.

    Returns
    -------
    tuple
        ``(Gi, Gj, rhs, scale, z_warm, du_qp, xs, zs, gate_du, share, robot_margin, done,
        out_of_range)``, views into ``floats`` and ``flags``; the gate's entries (``gate_du`` to
        ``robot_margin``, ``out_of_range``) are NaN and False unless the quick check ran.
    """
    f = floats
    return (f[0:2 * m].reshape(m, 2), f[2 * m:4 * m].reshape(m, 2), f[4 * m:5 * m], f[5 * m:5 * m + n],
            f[5 * m + n:6 * m + n], f[6 * m + n:6 * m + 3 * n].reshape(n, 2), f[6 * m + 3 * n:6 * m + 5 * n],
            f[6 * m + 5 * n:7 * m + 5 * n], f[7 * m + 5 * n:7 * m + 7 * n].reshape(n, 2),
            f[7 * m + 7 * n:7 * m + 8 * n], f[7 * m + 8 * n:7 * m + 9 * n], flags[0:n], flags[n:2 * n])
