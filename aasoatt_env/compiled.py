"""Which implementation runs: the numpy reference or a compiled kernel (numba, ``pip install "aasoatt[fast]"``).

One numba form per filter stage (:data:`PARTS`, ``docs/design.md``); numba is imported when a kernel is first used.
"""

from __future__ import annotations

import functools
import importlib
from types import ModuleType

import numpy as np

__all__ = ["KERNELS", "NUMBA_MISSING", "PARTS", "available", "c64", "kernels"]

KERNELS: tuple[str, ...] = ("auto", "numpy", "numba")
"""Values of :attr:`~aasoatt_env.safety.config.FilterConfig.kernel`."""

NUMBA_MISSING = (  # the ImportError of kernels() without numba
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
    "fused": "aasoatt_env.safety.centralized_kernel",
    "inputs": "aasoatt_env.safety.rows_kernel",
    "deadlock": "aasoatt_env.safety.rows_kernel",
    "observations": "aasoatt_env.sim.observations_kernel",
    "dynamics": "aasoatt_env.model.dynamics_kernel",
}
"""The compiled parts (each a stage's loop, the same numbers or the same decisions) and their modules."""


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
    """The compiled kernels of ``part`` (:data:`PARTS`); ``ImportError`` (:data:`NUMBA_MISSING`) without numba."""
    mod = _load(PARTS[part])
    if mod is None:
        raise ImportError(NUMBA_MISSING)
    return mod


def c64(a: np.ndarray) -> np.ndarray:
    """``a`` as a C-contiguous, writeable float64 array (one compiled specialisation for every caller)."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    return a if a.flags.writeable else a.copy()
