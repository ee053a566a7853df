"""The inputs stage's number checks in one compiled loop (numba; :func:`~aasoatt_env.safety.inputs.check_step`)."""

from __future__ import annotations

import numpy as np

from aasoatt_env.numba_jit import jit

__all__ = ["numbers"]


@jit
def numbers(flat, n, bound, amax):
    """``(ok, scale)``: every number finite within ``bound`` and ``lo <= hi``; per robot ``max(amax, |lo|, |hi|)``.

    ``flat``: a step's arrays concatenated, ``nominal_du, lo, hi`` first (``(n, 2)`` each).  numpy's numbers.
    """
    ok = True
    for x in flat:
        ok = ok and abs(x) <= bound  # (NaN fails too)
    lo, hi = flat[2 * n: 4 * n].reshape(n, 2), flat[4 * n: 6 * n].reshape(n, 2)
    scale = np.empty(n)
    for i in range(n):
        s = amax[i]
        for c in range(2):
            ok = ok and lo[i, c] <= hi[i, c]
            s = max(s, abs(lo[i, c]), abs(hi[i, c]))
        scale[i] = s
    return ok, scale
