"""Which implementation of the backup layer runs: the numpy reference or the compiled kernels.

The backup layer's check (:func:`~aasoatt_env.safety.gatekeeper.gatekeeper`)
and repair (:func:`~aasoatt_env.safety.repair.repair`) are loops of rounds over
small arrays: sample each robot's candidate or braking path, take every close
pair's smallest distance along both paths, demote the members of failing pairs,
again.  In numpy each round is dozens of calls on arrays of a few hundred
numbers, so a step's time is the overhead of those calls rather than arithmetic
(``benchmarks/bench_filter.py --calls``).  :mod:`aasoatt_env.safety.numba_kernels`
is the same loops compiled with numba (``pip install "aasoatt[fast]"``),
imported only when first used.

The numpy code stays the reference and the fallback.  The kernels make its
decisions (which robots brake, the blend shares, the broken pairs, the rounds,
the pairs checked); numbers agree to floating-point rounding, not bit for bit:
numba's ``sin``/``cos``/``exp`` and numpy's vectorised ones may differ in the
last bit.  The repair divides by a squared finite-difference gradient, which is
small where a pair is closest at its first step, so its answers agree less
closely than the check's (README: *The braking backup layer*).
``tests/test_compiled.py`` checks both on random states and along adversarial
episodes.  Selection: :attr:`~aasoatt_env.safety.config.FilterConfig.kernel`.
"""

from __future__ import annotations

import functools
from types import ModuleType

__all__ = ["KERNELS", "NUMBA_MISSING", "available", "kernels"]

KERNELS: tuple[str, ...] = ("auto", "numpy", "numba")
"""Values of :attr:`~aasoatt_env.safety.config.FilterConfig.kernel`."""

NUMBA_MISSING = (
    'the backup layer\'s compiled kernels (kernel="numba", compiled=True) need numba, which is not installed '
    'or does not import: pip install "aasoatt[fast]" (kernel="auto" falls back to the numpy reference, '
    'kernel="numpy" always uses it)'
)


@functools.cache
def _load() -> ModuleType | None:
    try:
        from aasoatt_env.safety import numba_kernels
    except ImportError:  # numba missing, or a numba that does not import with this numpy
        return None
    return numba_kernels


def available() -> bool:
    """Whether the compiled kernels can be used (numba imports; the first call imports it)."""
    return _load() is not None


def kernels() -> ModuleType:
    """The module of compiled kernels.

    Raises
    ------
    ImportError
        numba is missing (:data:`NUMBA_MISSING`).
    """
    mod = _load()
    if mod is None:
        raise ImportError(NUMBA_MISSING)
    return mod
