"""Which implementation runs: the numpy reference or a compiled kernel (numba, ``pip install "aasoatt[fast]"``).

The filter's stages are loops over small arrays whose numpy form spends its time in the
overhead of many small calls; each such stage has one compiled form, the same loop compiled
with numba, chosen when the filter is built (:attr:`~aasoatt_env.safety.config.FilterConfig.kernel`):

- the inputs' number checks (:mod:`aasoatt_env.safety.inputs_kernel`);
- the default deadlock trigger and the target (:mod:`aasoatt_env.safety.deadlock_kernel`);
- the barrier rows (:mod:`aasoatt_env.safety.rows_kernel`: the numpy reference's numbers, bit for bit);
- the centralised QP stage on a warm-started step (:mod:`aasoatt_env.safety.centralized_kernel`: the
  numpy stage's numbers, bit for bit, where it answers) and its warm active set
  (:mod:`aasoatt_env.safety.solvers.active_set_kernel`);
- the decentralised local QPs (:mod:`aasoatt_env.safety.solvers.local_kernel`);
- the backup layer's check and repair (:mod:`aasoatt_env.safety.backup.kernels`);
- a warm centralised step's rows, QP and quick backup check in one call, where all three answer
  (:mod:`aasoatt_env.safety.fused_kernel`: those kernels called in turn, the pipeline's numbers);
- the neighbour grid and contact components (:mod:`aasoatt_env.model.geometry_kernel`: the same pairs
  and labels, exactly).

The kernels make the reference's decisions; where their sums run in another order their numbers
agree to rounding (``tests/test_compiled.py``).  numba is imported only when a kernel is first used.
"""

from __future__ import annotations

import functools
import importlib
from types import ModuleType

import numpy as np

__all__ = ["KERNELS", "NUMBA_MISSING", "PARTS", "available", "c64", "kernels"]

KERNELS: tuple[str, ...] = ("auto", "numpy", "numba")
"""Values of :attr:`~aasoatt_env.safety.config.FilterConfig.kernel`."""

NUMBA_MISSING = (
    'the compiled kernels (kernel="numba", compiled=True) need numba, which is not installed '
    'or does not import: pip install "aasoatt[fast]" (kernel="auto" falls back to the numpy reference, '
    'kernel="numpy" always uses it)'
)


PARTS: dict[str, str] = {
    "backup": "aasoatt_env.safety.backup.kernels",
    "local": "aasoatt_env.safety.solvers.local_kernel",
    "active_set": "aasoatt_env.safety.solvers.active_set_kernel",
    "geometry": "aasoatt_env.model.geometry_kernel",
    "rows": "aasoatt_env.safety.rows_kernel",
    "centralized": "aasoatt_env.safety.centralized_kernel",
    "fused": "aasoatt_env.safety.fused_kernel",
    "inputs": "aasoatt_env.safety.inputs_kernel",
    "deadlock": "aasoatt_env.safety.deadlock_kernel",
}
"""The compiled parts and their modules."""


@functools.cache
def _load(name: str) -> ModuleType | None:
    try:
        return importlib.import_module(name)
    except ImportError:  # numba missing, or a numba that does not import with this numpy
        return None


def available() -> bool:
    """Whether the compiled kernels can be used (numba imports; the first call imports it)."""
    return _load("aasoatt_env.numba_jit") is not None


def kernels(part: str = "backup") -> ModuleType:
    """The compiled kernels of ``part`` (:data:`PARTS`).

    Raises
    ------
    ImportError
        numba is missing (:data:`NUMBA_MISSING`).
    """
    mod = _load(PARTS[part])
    if mod is None:
        raise ImportError(NUMBA_MISSING)
    return mod


def c64(a: np.ndarray) -> np.ndarray:
    """``a`` as a C-contiguous, writeable float64 array (one compiled specialisation for every caller's arrays)."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    return a if a.flags.writeable else a.copy()
