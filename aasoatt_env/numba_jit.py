"""The one ``numba.njit`` configuration of the library's compiled kernels (imports numba).

Imported only by the kernel modules, which :mod:`aasoatt_env.compiled` loads on
first use, so ``import aasoatt_env`` never imports numba.
"""

from __future__ import annotations

import warnings

import numba

__all__ = ["jit", "jit_reassoc"]


def jit(fn, **flags):
    """``numba.njit`` with an on-disk cache, or without one where no cache folder is writable."""
    try:
        return numba.njit(cache=True, nogil=True, error_model="numpy", **flags)(fn)
    except RuntimeError as err:  # e.g. a read-only install without a writable user cache
        warnings.warn(f"aasoatt: numba cannot cache the compiled kernels here ({err}); they are compiled "
                      "again in every process", RuntimeWarning, stacklevel=2)
        return numba.njit(cache=False, nogil=True, error_model="numpy", **flags)(fn)


def jit_reassoc(fn):
    """:func:`jit` letting LLVM reorder sums (``fastmath`` ``reassoc``, ``contract``: vectorised reductions).

    NaN and inf keep their meaning (no ``nnan``/``ninf``); the sums' last bits depend on the order.
    """
    return jit(fn, fastmath={"reassoc", "contract"})
