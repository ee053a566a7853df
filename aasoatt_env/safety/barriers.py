"""Pairwise barrier functions, each turned into rows ``c^T (w_i - w_j) <= rhs``, ``w = A du``, ``c = -p_ij`` (eqn.8).

An obstacle (``j = -1``) stands still: its robot carries the whole row.  ``aasoatt``: eqn.7c's typo corrected
(``- A_dot_j u_j``); ``braking``: ``r - d_s`` clamped at 1e-6; ``gated_distance``: eqn.nn5 while the pair approaches
within ``gate_range`` (eqn.n6's printed gate acts only after a collision).  The velocity barriers apply to the next-step
velocity ``v + (A du + A_dot u) dt``, divided by ``2 dt``.  See ``docs/technical_brief.md`` section 3.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from aasoatt_env.errors import ConfigError
from aasoatt_env.model.geometry import namespace, row_dot, row_norm, safe_sqrt

if TYPE_CHECKING:  # pragma: no cover
    from aasoatt_env.safety.config import FilterConfig

__all__ = ["BARRIERS", "Barrier", "PairGeometry", "barrier_rows", "get_barrier"]


class PairGeometry(NamedTuple):
    """Relative quantities of P pairs (robot-robot and robot-obstacle), each ``(P,)`` or ``(P, 2)``."""

    i: np.ndarray
    j: np.ndarray  #: ``-1`` for an obstacle
    p: np.ndarray  #: ``p_i - p_j`` (obstacle: ``p_i - c_k``)
    v: np.ndarray
    adot: np.ndarray  #: the drift accelerations ``A_dot_i u_i - A_dot_j u_j``
    d_s: np.ndarray  #: the safety distance, margin included
    r_sum: np.ndarray  #: ``r_i + r_j`` without margin (eqn.n7's ``r``)
    a_plus: np.ndarray  #: the maximum point accelerations ``a_i+ + a_j+``


#: ``f(geometry, config) -> (rhs, keep)``; ``keep`` is a boolean mask or None (all rows)
BarrierFn = Callable[[PairGeometry, "FilterConfig"], "tuple[np.ndarray, np.ndarray | None]"]
ValueFn = Callable[[PairGeometry, "FilterConfig"], np.ndarray]  #: ``h(geometry, config) -> (P,)``; safe: ``h >= 0``


@dataclass(frozen=True)
class Barrier:
    """A registered barrier: its rows and the barrier function whose set ``h >= 0`` the rows keep invariant."""

    rows: BarrierFn
    value: ValueFn
    equation: str
    kernel: str = ""  #: its compiled rows, a function of :mod:`~.rows_kernel` (empty: numpy only)
    #: its functions use only the array namespace of their inputs (:func:`~aasoatt_env.model.geometry.namespace`),
    #: so they also run on torch tensors (the torch filter refuses a barrier without it)
    array_api: bool = False


def _common(g: PairGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``|p|`` (at least 1e-9), ``p.v``, ``v.v``, ``p.adot``."""
    xp = namespace(g.p)
    return xp.maximum(row_norm(g.p), 1e-9), row_dot(g.p, g.v), row_dot(g.v, g.v), row_dot(g.p, g.adot)


def _aasoatt_h(g: PairGeometry, q: FilterConfig) -> np.ndarray:
    r, pv, _, _ = _common(g)
    return pv / r + q.k1 * (r - g.d_s)


def _braking_h(g: PairGeometry, q: FilterConfig) -> np.ndarray:
    r, pv, _, _ = _common(g)
    gap = r - g.d_s
    xp = namespace(gap)
    return xp.sign(gap) * safe_sqrt(2.0 * g.a_plus * xp.abs(gap)) + pv / r


def _distance_h(g: PairGeometry, q: FilterConfig) -> np.ndarray:
    r, pv, _, _ = _common(g)
    return q.varsigma * (r * r - g.d_s * g.d_s) + 2.0 * pv


def _aasoatt(g: PairGeometry, q: FilterConfig) -> tuple[np.ndarray, None]:
    r, pv, vv, pa = _common(g)
    return vv - pv * pv / (r * r) + (q.k1 + q.k2) * pv + q.k1 * q.k2 * r * (r - g.d_s) + pa, None


def _braking(g: PairGeometry, q: FilterConfig) -> tuple[np.ndarray, None]:
    r, pv, vv, pa = _common(g)
    xp = namespace(r)
    root = xp.sqrt(2.0 * g.a_plus * xp.maximum(r - g.d_s, 1e-6))
    h = root + pv / r
    return q.gamma * h * h * h * r + vv - pv * pv / (r * r) + g.a_plus * pv / root + pa, None


def _velocity_rhs(g: PairGeometry, q: FilterConfig, d: np.ndarray) -> np.ndarray:
    r, pv, _, pa = _common(g)
    return (q.varsigma * (r * r - d * d) + 2.0 * pv) / (2.0 * q.dt) + pa


def _distance(g: PairGeometry, q: FilterConfig) -> tuple[np.ndarray, None]:
    return _velocity_rhs(g, q, g.d_s), None


def _gated_distance(g: PairGeometry, q: FilterConfig) -> tuple[np.ndarray, np.ndarray]:
    gate = q.sensing_range if q.gate_range is None else q.gate_range
    r, pv, _, _ = _common(g)
    return _velocity_rhs(g, q, g.d_s), (pv < 0.0) & (r < gate)


def _adaptive_distance(g: PairGeometry, q: FilterConfig) -> tuple[np.ndarray, None]:
    pv = row_dot(g.p, g.v)
    D, margin = q.sensing_range, g.d_s - g.r_sum
    d = 0.5 * (D + g.r_sum) + (D - g.r_sum) / math.pi * namespace(pv).atan(-q.rho_v * pv + q.sigma) + margin
    return _velocity_rhs(g, q, d), None


BARRIERS: dict[str, Barrier] = {
    "aasoatt": Barrier(_aasoatt, _aasoatt_h, "eqn.7-8", kernel="aasoatt_rows", array_api=True),
    "braking": Barrier(_braking, _braking_h, "eqn.n4", array_api=True),
    "distance": Barrier(_distance, _distance_h, "eqn.nn5", array_api=True),
    "gated_distance": Barrier(_gated_distance, _distance_h, "eqn.n5/n6", array_api=True),
    "adaptive_distance": Barrier(_adaptive_distance, _distance_h, "eqn.n7", array_api=True),
}
"""Barrier registry: name -> :class:`Barrier` (adding one: its rows, its ``h`` and a line here).  The velocity
barriers share ``h = varsigma (r^2 - d_s^2) + 2 p^T v`` (eqn.n7's larger distance keeps a subset of its set)."""


def get_barrier(name: str) -> Barrier:
    """Return the barrier registered as ``name`` or raise :class:`ConfigError`."""
    try:
        return BARRIERS[name]
    except (KeyError, TypeError):
        raise ConfigError(f"barrier: got {name!r}, expected one of {sorted(BARRIERS)}") from None


def barrier_rows(name: str, g: PairGeometry, params: FilterConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of barrier ``name`` for the pairs of ``g``: ``c = -p_ij`` ``(P', 2)``, ``rhs``, the kept pairs' indices."""
    rhs, keep = get_barrier(name).rows(g, params)
    if keep is None:
        return -g.p, rhs, np.arange(rhs.shape[0])
    idx = np.flatnonzero(keep)
    return -g.p[idx], rhs[idx], idx
