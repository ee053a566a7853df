"""The one ``numba.njit`` configuration of the compiled kernels and their scalar helpers (imports numba)."""

from __future__ import annotations

import math
import warnings

import numba
from numba import types
from numba.extending import intrinsic

__all__ = ["cmul", "fma", "jit", "jit_reassoc", "nclip", "nmax", "nmin"]

_WARNED = [False]


def jit(fn, **flags):
    """``numba.njit`` with an on-disk cache, or without one where no cache folder is writable."""
    try:
        return numba.njit(cache=True, nogil=True, error_model="numpy", **flags)(fn)
    except RuntimeError as err:  # e.g. a read-only install without a writable user cache
        if not _WARNED[0]:  # once, not once per kernel function
            _WARNED[0] = True
            warnings.warn(f"aasoatt: numba cannot cache the compiled kernels here ({err}); they are compiled "
                          "again in every process", RuntimeWarning, stacklevel=2)
        return numba.njit(cache=False, nogil=True, error_model="numpy", **flags)(fn)


def jit_reassoc(fn):
    """:func:`jit` letting LLVM reorder sums (``reassoc``, ``contract``); NaN and inf keep their meaning."""
    return jit(fn, fastmath={"reassoc", "contract"})


@jit
def nmin(a, b):
    """``numpy.minimum`` of two numbers (NaN if either is)."""
    if a != a or b != b:
        return math.nan
    return a if a <= b else b


@jit
def nmax(a, b):
    """``numpy.maximum`` of two numbers (NaN if either is)."""
    if a != a or b != b:
        return math.nan
    return a if a >= b else b


@jit
def nclip(a, lo, hi):
    """``numpy.clip`` (``np.minimum(np.maximum(a, lo), hi)``) of one number."""
    return nmin(nmax(a, lo), hi)


@intrinsic
def fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (LLVM's ``fma``: the instruction on a CPU with FMA)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


@jit
def cmul(ar, ai, br, bi):
    """``(ar + i ai)(br + i bi)`` as numpy's complex multiplication computes it on a CPU with FMA (``(re, im)``)."""
    return fma(ar, br, -(ai * bi)), fma(ar, bi, ai * br)
