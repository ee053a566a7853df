"""The inputs stage's number checks in one compiled loop (numba; :func:`~aasoatt_env.safety.inputs.check_step`)."""

from __future__ import annotations

import numpy as np
from numba import literal_unroll

from aasoatt_env.numba_jit import jit

__all__ = ["numbers"]


@jit
def numbers(arrays, bound, amax, reach):
    """``(ok, scale, near)``: numbers within ``bound``, ``lo <= hi``; ``max(amax, |lo|, |hi|)``; no pull-in needed.

    ``near``: :func:`~aasoatt_env.safety.inputs.bound_nominal`'s quick test with ``reach``; ``arrays``: a step's
    arrays, ``nominal_du, lo, hi`` first (``(n, 2)`` each).  numpy's numbers.
    """
    nominal, lo, hi = arrays[0], arrays[1], arrays[2]
    n = lo.shape[0]
    ok, top = True, 0.0
    for a in literal_unroll(arrays):
        for x in a.ravel():
            ok = ok and abs(x) <= bound  # (NaN fails too)
    for x in nominal.ravel():
        top = max(top, abs(x))
    scale = np.empty(n)
    smax, amin = 0.0, np.inf
    for i in range(n):
        s = amax[i]
        for c in range(2):
            ok = ok and lo[i, c] <= hi[i, c]
            s = max(s, abs(lo[i, c]), abs(hi[i, c]))
        scale[i] = s
        smax, amin = max(smax, s), min(amin, amax[i])
    return ok, scale, n > 0 and 1.5 * (top + smax) <= reach * amin
