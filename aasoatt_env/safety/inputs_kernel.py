"""The filter's per-step check of its input numbers compiled (numba; through :mod:`aasoatt_env.compiled`).

:func:`numbers_ok` is the test :func:`aasoatt_env.safety.inputs.check_inputs` makes on
the numbers of a step once their types and shapes are checked (every value finite
and within ``+-MAGNITUDE_MAX``; ``lo <= hi``), in one pass over the arrays instead of
a concatenation and two reductions: that function's Python-level operations are a
small team's step's cost, not their arithmetic.  It only answers whether the
numbers pass; where they do not, :func:`~aasoatt_env.safety.inputs.check_inputs`
looks for the culprit and raises its error as without this kernel.
"""

from __future__ import annotations

from aasoatt_env.numba_jit import jit

__all__ = ["numbers_ok"]


@jit
def numbers_ok(bound, nominal, lo, hi, u, theta, p, v, A, adot, p_d, v_d):
    """Whether every value of the arrays lies within ``+-bound`` (NaN does not) and ``lo <= hi``.

    Parameters
    ----------
    bound : float
        The magnitude bound (:data:`~aasoatt_env.validation.MAGNITUDE_MAX`).
    nominal, lo, hi, u, p, v, adot, p_d, v_d : numpy.ndarray
        ``(n, 2)`` float64, C-contiguous.
    theta : numpy.ndarray
        ``(n,)``.
    A : numpy.ndarray
        ``(n, 2, 2)``.

    Returns
    -------
    bool
        True where every number passes.  The caller has checked every shape (the arrays are read
        without bounds checks).
    """
    for i in range(theta.shape[0]):
        if not abs(theta[i]) <= bound:
            return False
        for k in range(2):
            if not (abs(nominal[i, k]) <= bound and abs(lo[i, k]) <= bound and abs(hi[i, k]) <= bound
                    and abs(u[i, k]) <= bound and abs(p[i, k]) <= bound and abs(v[i, k]) <= bound
                    and abs(adot[i, k]) <= bound and abs(p_d[i, k]) <= bound and abs(v_d[i, k]) <= bound
                    and abs(A[i, k, 0]) <= bound and abs(A[i, k, 1]) <= bound):
                return False
            if lo[i, k] > hi[i, k]:
                return False
    return True
