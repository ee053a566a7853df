"""Which implementation runs: the numpy reference or the compiled kernels.

These parts are loops over small arrays whose numpy form spends a step's time
in the overhead of its calls rather than in arithmetic
(``benchmarks/bench_filter.py --calls``):

- the backup layer's check (:func:`~aasoatt_env.safety.gatekeeper.gatekeeper`)
  and repair (:func:`~aasoatt_env.safety.repair.repair`): rounds of sampling each
  robot's candidate or braking path, taking every close pair's smallest distance
  along both paths, demoting the members of failing pairs
  (:mod:`aasoatt_env.safety.numba_kernels`);
- the decentralised filter's local solver
  (:func:`~aasoatt_env.safety.solvers.local.solve_local_qps`): every robot's
  2-variable QP, its active set, checks and least-violation relaxation
  (:mod:`aasoatt_env.safety.solvers.local_kernel`);
- the neighbour search and contact components of
  :mod:`aasoatt_env.model.geometry` (:mod:`aasoatt_env.model.geometry_kernel`:
  the same pairs and labels, exactly);
- the centralised filter's warm active set on small dense parts
  (:func:`~aasoatt_env.safety.solvers.active_set.solve_active_set_parts`): each
  independent part's working-set rules, equality points and KKT check
  (:mod:`aasoatt_env.safety.solvers.active_set_kernel`), and a warm-started
  centralised step's whole decomposition around it (each robot's closed form,
  the violated rows' components, the scaled problem, the active set:
  :mod:`aasoatt_env.safety.decomposition_kernel`, which answers only where it
  verifies every component, with the numbers of the numpy decomposition around
  the compiled active set, bit for bit, up to a zero's or a NaN's sign in a
  robot's closed form);
- the paper's barrier rows of every robot pair
  (:mod:`aasoatt_env.safety.rows_kernel`: the pair geometry, the discrete-time
  margins, the barrier's value, the rows in wheel coordinates and the warm-start
  keys, the numpy step's numbers bit for bit);
- a centralised step from the rows on (:mod:`aasoatt_env.safety.step_kernel`:
  the kernels above and the operations between them in one call, stopping
  where the Python step has more to decide; the parts' step bit for bit);
- the test of a step's input numbers (:mod:`aasoatt_env.safety.inputs_kernel`:
  finite, within the magnitude bound, ``lo <= hi``; the errors stay numpy's);
- the default deadlock trigger and the nominal's target
  (:mod:`aasoatt_env.safety.deadlock_kernel`: the numpy step's numbers bit for bit).

The kernels are the same loops compiled with numba (``pip install
"aasoatt[fast]"``), imported only when first used.  The numpy code stays the
reference and the fallback.  The kernels make its decisions (which robots brake,
the blend shares, the broken pairs, the rounds, the pairs checked; each robot's
active constraints, feasibility and loosened rows; each part's working sets
and verification, but see the kernel's docstring); numbers agree to
floating-point rounding, not bit for bit: numba's ``sin``/``cos``/``exp`` and
numpy's vectorised ones may differ in the last bit, and sums may be added in
another order.  The repair divides by a squared finite-difference gradient,
which is small where a pair is closest at its first step, so its answers agree
less closely than the check's (README: *The braking backup layer*).
``tests/test_compiled.py`` checks them on random states and along adversarial
episodes.  Selection: :attr:`~aasoatt_env.safety.config.FilterConfig.kernel` for
the filter's parts, the geometry's included (the filter passes its choice);
called directly, ``robot_pairs`` and ``pair_components`` use their kernels
wherever numba imports (their answers are the reference's exactly), or as their
``compiled=`` says.  The kernel modules take their ``numba.njit`` settings from
:mod:`aasoatt_env.numba_jit`.
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
    "backup": "aasoatt_env.safety.numba_kernels",
    "local": "aasoatt_env.safety.solvers.local_kernel",
    "active_set": "aasoatt_env.safety.solvers.active_set_kernel",
    "geometry": "aasoatt_env.model.geometry_kernel",
    "decomposition": "aasoatt_env.safety.decomposition_kernel",
    "rows": "aasoatt_env.safety.rows_kernel",
    "step": "aasoatt_env.safety.step_kernel",
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
