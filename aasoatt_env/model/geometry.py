"""Neighbour search on disc robots: the one home of every distance query in the library.

The observations (k nearest robots), the safety filter (pairs within the
sensing range), the metrics (smallest gap at every recorded step) and the
adversarial agents (nearest neighbour) all call these functions.

Three back-ends of :func:`robot_pairs` give identical answers:

* brute force over the ``N x N`` distance matrix (one complex subtraction) for
  teams below :data:`KDTREE_MIN_ROBOTS`;
* from :data:`KDTREE_MIN_ROBOTS` robots on (``O(N + pairs)`` memory, so 10,000
  robots are cheap): a compiled grid of cells
  (:func:`aasoatt_env.model.geometry_kernel.cell_pairs`) where numba imports,
  else :class:`scipy.spatial.cKDTree`.

Pairs are returned sorted lexicographically with ``i < j`` so that the order
of barrier rows is deterministic and independent of the back-end.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from aasoatt_env import compiled as _compiled

__all__ = [
    "KDTREE_MIN_ROBOTS",
    "brute_candidates",
    "k_nearest",
    "min_gaps",
    "obstacle_gaps",
    "obstacle_pairs",
    "pair_components",
    "pairwise_distances",
    "robot_pairs",
    "row_dot",
]

KDTREE_MIN_ROBOTS: int = 200
"""Team size from which a k-d tree answers instead of the full distance matrix
(``docs/technical_brief.md`` section 4: the tree beats ``N x N`` broadcasting from about 200 robots)."""

_FULL_SORT_MAX = 64
"""Up to this many points a full row sort beats ``argpartition`` + a partial sort."""


@functools.lru_cache(maxsize=16)
def _upper_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    iu, ju = np.triu_indices(n, k=1)
    iu, ju = iu.astype(np.intp), ju.astype(np.intp)
    iu.flags.writeable = ju.flags.writeable = False
    return iu, ju


_LABELLING_CACHES: dict[str, dict[bytes, Any]] = {"pairs": {}, "size": {}}


def _per_labelling(kind: str, groups: np.ndarray, make: Callable[[np.ndarray], Any]) -> Any:
    """``make(groups)``, cached per labelling (the filter asks for the same one at every physics step)."""
    store = _LABELLING_CACHES[kind]
    key = np.ascontiguousarray(groups).tobytes()
    hit = store.get(key)
    if hit is None:
        if len(store) >= 16:
            store.clear()
        hit = store[key] = make(groups)
    return hit


def _make_group_pairs(groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    iu, ju = _upper_pairs(groups.shape[0])
    same = groups[iu] == groups[ju]
    iu, ju = iu[same], ju[same]
    iu.flags.writeable = ju.flags.writeable = False
    return iu, ju


def _group_pairs(groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``i < j`` of :func:`_upper_pairs` with ``groups[i] == groups[j]`` (cached per labelling)."""
    return _per_labelling("pairs", groups, _make_group_pairs)


def _group_size(groups: np.ndarray) -> int:
    """Robots per group (``N // labels``), cached per labelling."""
    return _per_labelling("size", groups, lambda g: g.shape[0] // max(int(np.unique(g).size), 1))


def brute_candidates(n: int, groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The candidate pairs ``(iu, ju)`` of :func:`robot_pairs`' brute force (cached, read-only).

    Every pair ``i < j`` (of one label with ``groups``) in lexicographic order;
    :func:`robot_pairs` keeps those with ``d0 d0 + d1 d1 <= radius * radius``
    (``d = p_i - p_j``).
    """
    return _upper_pairs(n) if groups is None else _group_pairs(groups)


def uses_brute_force(n: int, groups: np.ndarray | None = None) -> bool:
    """Whether :func:`robot_pairs` with ``method="auto"`` picks its brute force for ``n`` points.

    That is, with fewer than :data:`KDTREE_MIN_ROBOTS` points per group (the grid of cells can
    fall back to the brute force too, and fewer than two points have no pairs).
    """
    return (n if groups is None else _group_size(groups)) < KDTREE_MIN_ROBOTS


def row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products ``(P,)`` of two ``(P, 2)`` arrays: ``a0 b0 + a1 b1``.

    The numbers of ``np.einsum("ij,ij->i", a, b)`` (the same two products added in
    the same order; only a zero's sign may differ, einsum's sum starting from
    ``+0.0``), without its per-call set-up, which dominates on these short rows.
    Only the first two columns are read: the callers pass ``(P, 2)`` arrays.
    """
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]


def pairwise_distances(p: np.ndarray) -> np.ndarray:
    """Centre distances ``(N, N)`` of points ``(N, 2)`` (one complex subtraction)."""
    z = np.ascontiguousarray(p, dtype=np.float64).view(np.complex128)[:, 0]
    return np.abs(z[:, None] - z[None, :])


def robot_pairs(p: np.ndarray, radius: float, *, method: str = "auto", groups: np.ndarray | None = None,
                compiled: bool | None = None) -> np.ndarray:
    """Index pairs ``(i, j)``, ``i < j``, with ``|p_i - p_j| <= radius`` (and, with ``groups``, of one group).

    Parameters
    ----------
    p : numpy.ndarray
        Positions, shape ``(N, 2)``.
    radius : float
        Search radius (the sensing range ``D``).
    method : {"auto", "brute", "kdtree", "cells"}
        Back-end; ``"auto"`` picks brute force below :data:`KDTREE_MIN_ROBOTS`
        (counted per group with ``groups``), above it the compiled grid of cells
        where numba imports, else the k-d tree.  ``"cells"`` without numba:
        ``ImportError``.
    compiled : bool, optional
        For ``"auto"``: ``False`` never picks the compiled cells (the filter's
        ``kernel="numpy"``); None: where numba imports.
    groups : numpy.ndarray, optional
        ``(N,)`` labels (:attr:`aasoatt_env.model.params.Team.group`): only
        pairs of one label are returned.

    Returns
    -------
    numpy.ndarray
        Integer array of shape ``(P, 2)``, sorted lexicographically.
    """
    n = p.shape[0]
    if groups is not None and np.shape(groups) != (n,):
        raise ValueError(f"groups: got shape {np.shape(groups)}, expected one label per point ({n},)")
    if n < 2:
        return np.empty((0, 2), dtype=np.intp)
    if method == "auto":
        use = _compiled.available() if compiled is None else compiled
        method = "brute" if uses_brute_force(n, groups) else "cells" if use else "kdtree"
    if method == "cells":
        if not (radius > 0 and np.isfinite(radius)):
            method = "brute"  # no cell width: the brute force answers (only coincident points at radius 0)
        else:
            has = groups is not None
            if has and not np.issubdtype(np.asarray(groups).dtype, np.integer):  # any labels: their classes
                groups = np.unique(groups, return_inverse=True)[1].reshape(-1)
            g = np.ascontiguousarray(groups, dtype=np.int64) if has else np.zeros(1, np.int64)
            pairs, fine = _compiled.kernels("geometry").cell_pairs(_compiled.c64(p), float(radius), g, has)
            if fine:
                return pairs.astype(np.intp, copy=False)
            method = "brute" if n <= 4000 else "kdtree"  # more cells than int64 keys hold (absurd spreads)
    if method == "brute":
        iu, ju = brute_candidates(n, groups)
        d = p[iu] - p[ju]
        with np.errstate(over="ignore", invalid="ignore"):  # a squared distance of inf is far; NaN pairs nothing
            keep = np.flatnonzero(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] <= radius * radius)
        return np.stack((iu[keep], ju[keep]), axis=1)
    if method != "kdtree":
        raise ValueError(f"method: got {method!r}, expected 'auto', 'brute', 'kdtree' or 'cells'")
    pairs = cKDTree(p).query_pairs(radius, output_type="ndarray").astype(np.intp)
    if groups is not None and pairs.shape[0]:
        pairs = pairs[groups[pairs[:, 0]] == groups[pairs[:, 1]]]
    if pairs.shape[0] == 0:
        return np.empty((0, 2), dtype=np.intp)
    pairs.sort(axis=1)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


def obstacle_gaps(p: np.ndarray, radii: np.ndarray, centers: np.ndarray, obstacle_radii: np.ndarray) -> np.ndarray:
    """Surface gaps robot-obstacle ``(N, M)``: ``|p_i - c_k| - r_i - R_k``."""
    dx = p[:, 0:1] - centers[:, 0]
    dy = p[:, 1:2] - centers[:, 1]
    return np.sqrt(dx * dx + dy * dy) - radii[:, None] - obstacle_radii[None, :]


def obstacle_pairs(p: np.ndarray, centers: np.ndarray, radii: np.ndarray, radius: float, *,
                   groups: np.ndarray | None = None, obstacle_groups: np.ndarray | None = None) -> np.ndarray:
    """Pairs ``(i, k)`` of robot ``i`` and disc obstacle ``k`` whose surface lies within ``radius``.

    The distance is measured from the robot's point to the obstacle centre minus
    the obstacle radius, so large obstacles are sensed from their rim.

    Parameters
    ----------
    p : numpy.ndarray
        Robot positions, ``(N, 2)``.
    centers : numpy.ndarray
        Obstacle centres, ``(M, 2)``.
    radii : numpy.ndarray
        Obstacle radii, ``(M,)``.
    radius : float
        Search radius.
    groups, obstacle_groups : numpy.ndarray, optional
        Labels ``(N,)`` and ``(M,)`` (as in :func:`robot_pairs`): with both,
        only pairs of one label are returned; unlabelled obstacles are every
        group's.

    Returns
    -------
    numpy.ndarray
        Integer array ``(P, 2)`` of (robot, obstacle) indices, sorted.
    """
    if centers.shape[0] == 0 or p.shape[0] == 0:
        return np.empty((0, 2), dtype=np.intp)
    near = obstacle_gaps(p, np.zeros(p.shape[0]), centers, radii) <= radius
    if groups is not None and obstacle_groups is not None:
        near &= np.asarray(groups)[:, None] == np.asarray(obstacle_groups)[None, :]
    i, k = np.nonzero(near)
    return np.stack((i, k), axis=1).astype(np.intp)


def k_nearest(p: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Indices ``(N, k)`` and distances ``(N, k)`` of each point's ``k`` nearest other points.

    Brute force below :data:`KDTREE_MIN_ROBOTS` points (then the full distance
    matrix is returned too, else None); a k-d tree above.  Missing neighbours
    (fewer than ``k`` others) get index -1 and distance inf.
    """
    n = p.shape[0]
    kk = min(k, n - 1)
    if kk <= 0:
        return np.full((n, k), -1, dtype=np.intp), np.full((n, k), np.inf), None
    if n < KDTREE_MIN_ROBOTS:
        d = pairwise_distances(p)
        d.flat[:: n + 1] = np.inf
        rows = np.arange(n)[:, None]
        if n <= _FULL_SORT_MAX or kk >= n - 1:
            order = np.argsort(d, axis=1)[:, :kk]
        else:
            part = np.argpartition(d, kk - 1, axis=1)[:, :kk]
            order = part[rows, np.argsort(d[rows, part], axis=1)]
        dk = d[rows, order]
        if kk == k:
            return order, dk, d
        idx = np.full((n, k), -1, dtype=np.intp)
        dist = np.full((n, k), np.inf)
        idx[:, :kk], dist[:, :kk] = order, dk
        return idx, dist, d
    idx = np.full((n, k), -1, dtype=np.intp)
    dist = np.full((n, k), np.inf)
    dd, ii = cKDTree(p).query(p, k=kk + 1)
    idx[:, :kk], dist[:, :kk] = ii[:, 1:], dd[:, 1:]
    return idx, dist, None


def min_gaps(
    p: np.ndarray, radii: np.ndarray, centers: np.ndarray, obstacle_radii: np.ndarray, *, k: int = 6
) -> np.ndarray:
    """Clearance ``(N,)``: each robot's surface gap to the nearest robot or obstacle.

    Exact below :data:`KDTREE_MIN_ROBOTS` robots (all pairs); above, taken over
    the ``k`` nearest centres (exact for equal radii).  ``inf`` for a lone robot.
    """
    n = p.shape[0]
    gap = np.full(n, np.inf)
    if n > 1:
        if n < KDTREE_MIN_ROBOTS:
            if radii.min() == radii.max():  # equal radii: the nearest centre gives the clearance
                d = pairwise_distances(p)
                d.flat[:: n + 1] = np.inf
                gap = np.minimum.reduce(d, axis=1) - 2.0 * radii
            else:
                g = pairwise_distances(p) - radii[:, None] - radii[None, :]
                g.flat[:: n + 1] = np.inf
                gap = g.min(axis=1)
        else:
            idx, dist, _ = k_nearest(p, k)
            valid = idx >= 0
            gap = np.where(valid, dist - radii[:, None] - radii[np.where(valid, idx, 0)], np.inf).min(axis=1)
    if centers.shape[0]:
        gap = np.minimum(gap, obstacle_gaps(p, radii, centers, obstacle_radii).min(axis=1))
    return gap


def pair_components(n: int, ri: np.ndarray, rj: np.ndarray, *, compiled: bool | None = None) -> np.ndarray:
    """Connected-component label ``(n,)`` of ``n`` robots, edges ``(ri[k], rj[k])`` (none where ``rj < 0``: obstacles).

    Robots of one component share the label of its smallest index.  Union-find in
    the compiled kernel (:func:`aasoatt_env.model.geometry_kernel.components`;
    ``compiled=None``: where numba imports), else min-label propagation with
    pointer jumping (vectorised; a handful of passes for the contact graphs met
    here): the same labels.  Edge ends outside ``[0, n)``: ``ValueError``.
    """
    ri, rj = np.asarray(ri), np.asarray(rj)
    if not (np.issubdtype(ri.dtype, np.integer) and np.issubdtype(rj.dtype, np.integer)) and ri.size:
        raise ValueError(f"ri/rj: edge ends must be integer robot indices, got {ri.dtype}/{rj.dtype}")
    rr = rj >= 0
    a, b = ri[rr], rj[rr]
    if a.size and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= n):
        raise ValueError(f"ri/rj: edge ends must be robot indices in [0, {n})")
    if _compiled.available() if compiled is None else compiled:
        lab = _compiled.kernels("geometry").components(int(n), np.ascontiguousarray(a, np.int64),
                                                      np.ascontiguousarray(b, np.int64))
        return lab.astype(np.intp, copy=False)
    lab = np.arange(n)
    while True:
        low = np.minimum(lab[a], lab[b])
        new = lab.copy()
        np.minimum.at(new, a, low)
        np.minimum.at(new, b, low)
        np.minimum.at(new, lab[a], low)  # hook the old roots too
        np.minimum.at(new, lab[b], low)
        new = new[new]
        if np.array_equal(new, lab):
            return lab
        lab = new
