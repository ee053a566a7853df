"""Elementary functions that give the same bits on every x86-64 CPU with AVX2 and FMA.

numpy picks per-CPU SIMD kernels for ``arctan2``, ``exp``, ``log`` and ``power`` (AVX-512 ones differ from AVX2 ones in
the last bit), and OpenBLAS picks per-CPU kernels for ``linalg.solve`` and ``dot``.  A closed-loop rollout amplifies a
last-bit difference into another trajectory, so the simulation avoids those calls: it uses these instead, ``x * x * x``
for cubes, and ``einsum`` (numpy's own loops) for products.  ``tests/test_filter_determinism.py`` checks this by
running the same rollouts with the kernels of other CPUs.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["atan2", "solve2"]

_atan2 = np.frompyfunc(math.atan2, 2, 1)


def atan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``np.arctan2`` by the C library's ``atan2`` (one kernel on every AVX2 + FMA CPU), as float64."""
    return np.asarray(_atan2(np.asarray(y, dtype=np.float64), np.asarray(x, dtype=np.float64)), dtype=np.float64)


def solve2(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x`` with ``A x = b`` for stacks of 2x2 systems ``A (..., 2, 2)``, ``b (..., 2)``, by Cramer's rule."""
    a, c, d, e = A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1]
    det = a * e - c * d
    out = np.empty(np.broadcast_shapes(A.shape[:-1], b.shape))
    out[..., 0] = (b[..., 0] * e - c * b[..., 1]) / det
    out[..., 1] = (a * b[..., 1] - d * b[..., 0]) / det
    return out
