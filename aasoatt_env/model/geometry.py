"""Neighbour search on disc robots: the one home of every distance query in the library.

:func:`robot_pairs`: brute force below :data:`KDTREE_MIN_ROBOTS` robots, above a compiled grid of cells where numba
imports, else a k-d tree (the same sorted pairs ``i < j``); :func:`neighbourhood`: several equal teams stacked.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np

from aasoatt_env import compiled as _compiled

__all__ = ["KDTREE_MIN_ROBOTS", "Proximity", "brute_candidates", "k_nearest", "kdtree", "min_gaps", "neighbourhood",
           "namespace", "obstacle_pairs", "pair_components", "robot_pairs", "row_dot", "row_norm", "safe_sqrt",
           "uses_brute_force"]

KDTREE_MIN_ROBOTS: int = 200
"""Team size from which a tree (or grid) answers instead of the full distance matrix."""


@functools.lru_cache(maxsize=16)
def _upper_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    iu, ju = np.triu_indices(n, k=1)
    iu, ju = iu.astype(np.intp), ju.astype(np.intp)
    iu.flags.writeable = ju.flags.writeable = False
    return iu, ju


def _key(groups: np.ndarray) -> tuple[bytes, str]:
    groups = np.asarray(groups)
    if groups.dtype.kind == "O":  # labels of any kind: their classes
        groups = np.unique(groups, return_inverse=True)[1].reshape(-1)
    return np.ascontiguousarray(groups).tobytes(), groups.dtype.str


@functools.lru_cache(maxsize=16)
def _group_pairs(key: bytes, dtype: str) -> tuple[np.ndarray, np.ndarray]:
    """Every pair ``i < j`` of one label, sorted: each group's upper triangle (memory of the pairs, not of ``n^2``)."""
    groups = np.frombuffer(key, dtype=dtype)
    order = np.argsort(groups, kind="stable")  # (a group's robots in ascending order)
    _, start, counts = np.unique(groups[order], return_index=True, return_counts=True)
    iu, ju = [np.empty(0, np.intp)], [np.empty(0, np.intp)]
    for size in np.unique(counts[counts > 1]):  # (groups of one size at once)
        a, b = np.triu_indices(int(size), k=1)
        first = start[counts == size][:, None]
        iu.append(order[(first + a).ravel()])
        ju.append(order[(first + b).ravel()])
    iu, ju = np.concatenate(iu), np.concatenate(ju)
    o = np.lexsort((ju, iu))
    iu, ju = iu[o].astype(np.intp), ju[o].astype(np.intp)
    iu.flags.writeable = ju.flags.writeable = False
    return iu, ju


@functools.lru_cache(maxsize=16)
def _group_size(key: bytes, dtype: str) -> int:
    groups = np.frombuffer(key, dtype=dtype)
    return groups.shape[0] // max(int(np.unique(groups).size), 1)


def brute_candidates(n: int, groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The candidate pairs ``(iu, ju)`` of :func:`robot_pairs`' brute force: every ``i < j`` (of one label), sorted."""
    return _upper_pairs(n) if groups is None else _group_pairs(*_key(groups))


def uses_brute_force(n: int, groups: np.ndarray | None = None) -> bool:
    """Whether :func:`robot_pairs` picks its brute force: fewer than :data:`KDTREE_MIN_ROBOTS` points per group."""
    return (n if groups is None else _group_size(*_key(groups))) < KDTREE_MIN_ROBOTS


def row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products ``(...,)`` of two ``(..., 2)`` arrays: ``a0 b0 + a1 b1``."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def row_norm(a: Any) -> Any:
    """Row-wise lengths ``(...,)`` of ``(..., 2)`` arrays, ``sqrt(a0 a0 + a1 a1)`` (:func:`safe_sqrt`)."""
    return safe_sqrt(row_dot(a, a))


def safe_sqrt(s: Any) -> Any:
    """``sqrt(s)`` of ``s >= 0``; on a tensor that records a graph, gradient 0 at 0 instead of NaN (same values)."""
    xp = namespace(s)
    if not getattr(s, "requires_grad", False):
        return xp.sqrt(s)
    pos = s > 0
    return xp.where(pos, xp.sqrt(xp.where(pos, s, xp.ones_like(s))), xp.zeros_like(s))


def namespace(*arrays: Any) -> Any:
    """The array namespace of ``arrays``: numpy for numpy arrays and Python scalars, else array-api-compat's.

    Code written against it (``xp.sqrt``, ``xp.maximum``, ...) runs on numpy arrays unchanged and on torch tensors
    (``array-api-compat``, installed with the ``train`` extra beside torch).
    """
    if all(isinstance(a, (np.ndarray, np.generic, float, int)) for a in arrays):
        return np
    from array_api_compat import array_namespace

    return array_namespace(*(a for a in arrays if not isinstance(a, (float, int))))


def robot_pairs(p: np.ndarray, radius: float, *, method: str = "auto", groups: np.ndarray | None = None,
                compiled: bool | None = None) -> np.ndarray:
    """Index pairs ``(P, 2)``, ``i < j``, sorted, with ``|p_i - p_j| <= radius`` (of one of the ``(N,)`` ``groups``).

    ``method``: ``"brute"``, ``"kdtree"``, ``"cells"`` (numba's grid; ``ImportError`` without numba) or ``"auto"``
    (module docstring; ``compiled=False``: never the cells).
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
    pairs = kdtree(p).query_pairs(radius, output_type="ndarray").astype(np.intp)
    if groups is not None and pairs.shape[0]:
        pairs = pairs[groups[pairs[:, 0]] == groups[pairs[:, 1]]]
    if pairs.shape[0] == 0:
        return np.empty((0, 2), dtype=np.intp)
    pairs.sort(axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _obstacle_gaps(p: np.ndarray, radii: np.ndarray, centers: np.ndarray, obstacle_radii: np.ndarray,
                   teams: int) -> np.ndarray:
    """Robot-obstacle surface gaps ``(K N, M)`` of ``teams`` stacked teams, each with its ``M`` obstacles."""
    m = centers.shape[-2]
    if m == 0:
        return np.zeros((p.shape[0], 0))
    n = p.shape[0] // teams
    c, r = centers.reshape(teams, 1, m, 2), radii.reshape(teams, n, 1)
    p3 = p.reshape(teams, n, 1, 2)
    dx = p3[..., 0] - c[..., 0]
    dy = p3[..., 1] - c[..., 1]
    return (np.sqrt(dx * dx + dy * dy) - r - obstacle_radii.reshape(teams, 1, m)).reshape(teams * n, m)


def obstacle_pairs(p: np.ndarray, centers: np.ndarray, radii: np.ndarray, radius: float, *,
                   groups: np.ndarray | None = None, obstacle_groups: np.ndarray | None = None) -> np.ndarray:
    """Sorted pairs ``(P, 2)`` of robot ``i`` and obstacle ``k`` (of one label) whose rim is within ``radius``."""
    if centers.shape[0] == 0 or p.shape[0] == 0:
        return np.empty((0, 2), dtype=np.intp)
    near = _obstacle_gaps(p, np.zeros(p.shape[0]), centers, radii, 1) <= radius
    if groups is not None and obstacle_groups is not None:
        near &= np.asarray(groups)[:, None] == np.asarray(obstacle_groups)[None, :]
    i, k = np.nonzero(near)
    return np.stack((i, k), axis=1).astype(np.intp)


@functools.lru_cache(maxsize=16)
def _rows(n: int) -> np.ndarray:  # arange(n)[:, None], read-only
    rows = np.arange(n)[:, None]
    rows.flags.writeable = False
    return rows


def _distances(p: np.ndarray, teams: int) -> np.ndarray:
    """Centre distances within each of ``teams`` equal consecutive blocks of ``p``: ``(K, N, N)``, inf diagonal.

    ``sqrt(dx dx + dy dy)``: correctly rounded operations, the same bits on every machine and in the kernel.
    """
    n = p.shape[0] // teams
    q = np.asarray(p, dtype=np.float64).reshape(teams, n, 2)
    dx = q[:, :, None, 0] - q[:, None, :, 0]
    dy = q[:, :, None, 1] - q[:, None, :, 1]
    d = np.sqrt(dx * dx + dy * dy)
    d.reshape(teams, -1)[:, :: n + 1] = np.inf
    return d


def _nearest(d: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's ``k`` nearest in ``d (K, N, N)``: stack indices, distances ``(K N, k)`` (-1, inf: none).

    Nearest first, the lower index on a tie.
    """
    teams, n = d.shape[0], d.shape[1]
    kk = min(k, n - 1)
    if kk <= 0:
        return np.full((teams * n, k), -1, dtype=np.intp), np.full((teams * n, k), np.inf)
    d2 = d.reshape(teams * n, n)
    order = d2.argsort(axis=1, kind="stable")[:, :kk]  # (stable: the same order on every machine)
    dk = d2[_rows(teams * n), order]
    if teams > 1:
        order = order + np.repeat(np.arange(teams) * n, n)[:, None]
    if kk == k:
        return order, dk
    idx, dist = np.full((teams * n, k), -1, dtype=np.intp), np.full((teams * n, k), np.inf)
    idx[:, :kk], dist[:, :kk] = order, dk
    return idx, dist


def _robot_gaps(d: np.ndarray, radii: np.ndarray, equal: np.ndarray | None = None) -> np.ndarray:
    """Surface gap ``(K N,)`` of each robot to the nearest of its team (``equal (K,)``: a team's radii are equal)."""
    teams, n = d.shape[0], d.shape[1]
    if n <= 1:
        return np.full(teams * n, np.inf)
    r = radii.reshape(teams, n)
    if equal is None:
        equal = np.array([radii.min() == radii.max()]) if teams == 1 else r.min(axis=1) == r.max(axis=1)
    if teams == 1 and equal[0]:
        return np.minimum.reduce(d[0], axis=1) - 2.0 * radii
    if equal.all():
        return (np.minimum.reduce(d, axis=2) - 2.0 * r).ravel()
    gap = (d - r[:, :, None] - r[:, None, :]).min(axis=2)
    if equal.any():
        gap = np.where(equal[:, None], np.minimum.reduce(d, axis=2) - 2.0 * r, gap)
    return gap.ravel()


def _listed_gaps(idx: np.ndarray, dist: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Surface gap ``(N,)`` to the nearest of the neighbours ``idx`` (-1: none) at centre distances ``dist``."""
    valid = idx >= 0
    return np.where(valid, dist - radii[:, None] - radii[np.where(valid, idx, 0)], np.inf).min(axis=1)


def k_nearest(p: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Indices, distances ``(N, k)`` of each point's ``k`` nearest (-1, inf: none), the matrix (brute force) or None."""
    n = p.shape[0]
    kk = min(k, n - 1)
    if kk <= 0:
        return np.full((n, k), -1, dtype=np.intp), np.full((n, k), np.inf), None
    if n < KDTREE_MIN_ROBOTS:
        d = _distances(p, 1)
        return (*_nearest(d, k), d[0])
    idx, dist = np.full((n, k), -1, dtype=np.intp), np.full((n, k), np.inf)
    dd, ii = kdtree(p).query(p, k=kk + 1)
    idx[:, :kk], dist[:, :kk] = ii[:, 1:], dd[:, 1:]
    return idx, dist, None


def min_gaps(p: np.ndarray, radii: np.ndarray, centers: np.ndarray, obstacle_radii: np.ndarray, *, k: int = 6
             ) -> np.ndarray:
    """Clearance ``(N,)``: each robot's surface gap to the nearest robot or obstacle (``inf``: none).

    Exact below :data:`KDTREE_MIN_ROBOTS` robots; above, over the ``k`` nearest centres (exact for equal radii).
    """
    return neighbourhood(p, radii, centers, obstacle_radii, 0, clear_k=k)[3]


class Proximity(NamedTuple):
    """Each robot's ``k`` nearest robots ``idx``/``dist (N, k)`` (-1/inf: none), nearest first, obstacle gaps.

    ``obstacle_gaps (N, M)``: surface gaps; ``clearance (N,)``: to the nearest of either (negative: overlap).
    """

    idx: np.ndarray
    dist: np.ndarray
    obstacle_gaps: np.ndarray
    clearance: np.ndarray


def neighbourhood(p: np.ndarray, radii: np.ndarray, centers: np.ndarray, obstacle_radii: np.ndarray, k: int,
                  teams: int = 1, equal_radii: np.ndarray | None = None, clear_k: int = 6,
                  compiled: bool = False) -> Proximity:
    """The :class:`Proximity` of ``teams`` equal teams stacked in ``p (K N, 2)`` (stack indices).

    Each robot's ``k`` nearest of its team, its gaps to its team's obstacles ``(K, M, 2)``, ``(K, M)`` and its
    clearance (as :func:`min_gaps`).  ``compiled``: below :data:`KDTREE_MIN_ROBOTS` a team, the nearest and the
    gaps by the compiled kernel (the same numbers).
    """
    n = p.shape[0] // teams
    if compiled and n < KDTREE_MIN_ROBOTS:
        if equal_radii is None:
            r = radii.reshape(teams, n)
            equal_radii = r.min(axis=1) == r.max(axis=1)
        idx, dist, gap = _compiled.kernels("geometry").nearest(_compiled.c64(p), _compiled.c64(radii), teams, k,
                                                              np.asarray(equal_radii, dtype=bool))
        idx = idx.astype(np.intp, copy=False)
    elif n < KDTREE_MIN_ROBOTS:
        d = _distances(p, teams)
        idx, dist = _nearest(d, k) if k else (np.empty((p.shape[0], 0), np.intp), np.empty((p.shape[0], 0)))
        gap = _robot_gaps(d, radii, equal_radii)
    else:  # (a tree per team: large teams)
        near = [k_nearest(p[t * n:(t + 1) * n], max(k, clear_k))[:2] for t in range(teams)]
        idx = np.concatenate([np.where(i >= 0, i + t * n, -1) for t, (i, _) in enumerate(near)])
        dist = np.concatenate([d for _, d in near])
        gap = _listed_gaps(idx, dist, radii)
        idx, dist = idx[:, :k], dist[:, :k]
    og = _obstacle_gaps(p, radii, centers, obstacle_radii, teams)
    if og.shape[1]:
        gap = np.minimum(gap, og.min(axis=1))
    return Proximity(idx, dist, og, gap)


def pair_components(n: int, ri: np.ndarray, rj: np.ndarray, *, compiled: bool | None = None) -> np.ndarray:
    """Connected-component label ``(n,)`` (its smallest index) of robots under edges ``(ri[k], rj[k])`` (``rj >= 0``).

    Union-find in the compiled kernel (``compiled=None``: where numba imports), else min-label propagation.
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


def kdtree(p: np.ndarray) -> object:
    """The points' ``scipy.spatial.cKDTree`` (imported here: large teams only, not at import time)."""
    from scipy.spatial import cKDTree

    return cKDTree(p)
