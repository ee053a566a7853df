"""Neighbour search: robot pairs and robot-obstacle pairs within the sensing range.

Only pairs with ``|p_i - p_j| <= D`` get a barrier row (SPEC section 3).  Two
back-ends return the same set of pairs:

* brute force broadcasting of the ``N x N`` distance matrix for small teams
  (fast below about 150 robots, ``O(N^2)`` memory);
* :meth:`scipy.spatial.cKDTree.query_pairs` with ``output_type="ndarray"``
  above :data:`KDTREE_THRESHOLD` robots (``O(N + pairs)`` memory, so
  N = 1000+ is cheap).

Pairs are returned sorted lexicographically with ``i < j`` so that the row
order is deterministic and independent of the back-end.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["KDTREE_THRESHOLD", "obstacle_pairs", "robot_pairs"]

KDTREE_THRESHOLD: int = 150
"""Team size from which :func:`robot_pairs` uses a k-d tree."""


@functools.lru_cache(maxsize=16)
def _upper_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    iu, ju = np.triu_indices(n, k=1)
    iu, ju = iu.astype(np.intp), ju.astype(np.intp)
    iu.flags.writeable = ju.flags.writeable = False
    return iu, ju


def robot_pairs(p: np.ndarray, radius: float, *, method: str = "auto") -> np.ndarray:
    """Index pairs ``(i, j)``, ``i < j``, with ``|p_i - p_j| <= radius``.

    Parameters
    ----------
    p : numpy.ndarray
        Positions, shape ``(N, 2)``.
    radius : float
        Sensing range ``D``.
    method : {"auto", "brute", "kdtree"}
        Back-end; ``"auto"`` picks brute force below :data:`KDTREE_THRESHOLD`.

    Returns
    -------
    numpy.ndarray
        Integer array of shape ``(P, 2)``, sorted lexicographically.
    """
    n = p.shape[0]
    if n < 2:
        return np.empty((0, 2), dtype=np.intp)
    if method == "auto":
        method = "kdtree" if n >= KDTREE_THRESHOLD else "brute"
    if method == "brute":
        iu, ju = _upper_pairs(n)
        d = p[iu] - p[ju]
        keep = np.flatnonzero(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] <= radius * radius)
        return np.stack((iu[keep], ju[keep]), axis=1)
    if method != "kdtree":
        raise ValueError(f"method: got {method!r}, expected 'auto', 'brute' or 'kdtree'")
    pairs = cKDTree(p).query_pairs(radius, output_type="ndarray").astype(np.intp)
    if pairs.shape[0] == 0:
        return np.empty((0, 2), dtype=np.intp)
    pairs.sort(axis=1)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


def obstacle_pairs(p: np.ndarray, centers: np.ndarray, radii: np.ndarray, radius: float) -> np.ndarray:
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
        Sensing range ``D``.

    Returns
    -------
    numpy.ndarray
        Integer array ``(P, 2)`` of (robot, obstacle) indices, sorted.
    """
    if centers.shape[0] == 0 or p.shape[0] == 0:
        return np.empty((0, 2), dtype=np.intp)
    d = np.sqrt(np.sum((p[:, None, :] - centers[None, :, :]) ** 2, axis=-1)) - radii[None, :]
    i, k = np.nonzero(d <= radius)
    return np.stack((i, k), axis=1).astype(np.intp)
