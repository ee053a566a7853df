"""Exact fallback solver for the safety QP: least-distance programming by NNLS.

In ``w = y + L^{-1} g`` (:class:`~aasoatt_env.safety.solvers.active_set.LeastDistanceForm`) the problem is ``min 0.5
|w|^2  s.t.  Mt w <= hb``; Lawson and Hanson (ch. 23) solve it by one finitely terminating NNLS
(:func:`scipy.optimize.nnls`), so it does not stall on congested problems.  The point is polished by the warm active
set, or returned unpolished where feasible to :data:`FEAS_TOL`.  Dense: up to :data:`MAX_VARS` variables.
"""

from __future__ import annotations

import numpy as np

from aasoatt_env.safety.solvers.active_set import dense_least_distance_form, solve_active_set

__all__ = ["FEAS_TOL", "MAX_VARS", "solve_ldp"]

MAX_VARS: int = 500  #: largest number of variables solved (``E`` is dense, ``(n + 1) x (m + 2n)``)
FEAS_TOL: float = 1e-9  #: largest violation of a normalised row or bound accepted for an unpolished point


def solve_ldp(prob, feas_tol: float = FEAS_TOL) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """Solve ``prob`` exactly: ``(x, z, message)``, ``x``, ``z`` None without an answer (``message`` says why)."""
    n, m = prob.n, prob.m
    if n == 0 or n % 2:
        return None, None, "ldp: needs 2x2 blocks"
    if n > MAX_VARS:
        return None, None, f"ldp: {n} variables > MAX_VARS = {MAX_VARS}"
    form = dense_least_distance_form(prob)
    if form is None:
        return None, None, "ldp: Hessian block not positive definite"
    gt, Mt, b = form.gt, form.Mt, form.b
    finite = np.abs(b) < 1e19  # rows or bounds at +-inf are dropped
    if not np.all(finite):
        Mt, b = Mt[finite], b[finite]
    hb = b + Mt @ gt
    E = -np.vstack((Mt.T, hb[None, :]))
    norms = np.linalg.norm(E, axis=0)
    norms = np.where(norms > 0.0, norms, 1.0)
    f = np.zeros(n + 1)
    f[-1] = 1.0
    from scipy.optimize import nnls  # (scipy.optimize imported where asked: not by ``aasoatt --help``)

    try:
        us, _ = nnls(E / norms, f, maxiter=10 * E.shape[1])
    except RuntimeError as exc:  # iteration limit
        return None, None, f"ldp: {exc}"
    u = us / norms
    r = E @ u - f
    if not np.all(np.isfinite(r)) or -r[-1] <= 1e-14:
        return None, None, "ldp: rows inconsistent (NNLS residual zero)"
    w = -r[:n] / r[-1]
    lam = np.zeros(finite.shape[0])
    lam[finite] = u / (-r[-1])
    x = form.to_x(w - gt)
    z = lam[:m]
    polished = solve_active_set(prob, x, z)
    if polished is not None:
        return polished[0], polished[1], "ldp (KKT verified)"
    x = np.clip(x, prob.lb, prob.ub)
    viol = float(np.max(prob.C @ x - prob.u, initial=0.0))
    if viol > feas_tol or not np.all(np.isfinite(x)):
        return None, None, f"ldp: point violates a row by {viol:.2g}"
    return x, np.maximum(z, 0.0), "ldp (feasible, KKT polish did not converge)"
