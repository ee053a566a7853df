"""The ``yield`` strategy's detour (rule 5b): a stalled robot's way round the static obstacles it senses.

Boundary following slides along one disc at a time and gets caught in pockets between close discs; a route sees the
whole cluster: the shortest 8-connected way (Dijkstra) on a grid of the free space (the discs grown by the robot's
radius), steps near obstacles weighed up.  Its rules and lengths: ``docs/liveness.md``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ROUTE_BACK", "ROUTE_CELL", "ROUTE_CLEARANCE", "ROUTE_COST", "ROUTE_MARGIN", "ROUTE_PAD", "ROUTE_POINTS",
           "ROUTE_STEP", "plan_route"]

ROUTE_CELL: float = 0.1  #: [m] grid spacing (for the reference radius; lengths scale with the robot's)
ROUTE_CLEARANCE: float = 0.03  #: [m] least clearance of a passable cell, times ``1 + tries``
ROUTE_MARGIN: float = 0.3  #: [m] a step this close to an obstacle costs up to ``1 + ROUTE_COST`` times its length
ROUTE_COST: float = 4.0
ROUTE_BACK: float = 0.6  #: [m] how far round the robot it may back out of the grown band
ROUTE_PAD: float = 1.0  #: [m] the grid covers the robot, its goal and the grown discs, and this much round them
ROUTE_STEP: float = 0.25  #: [m] spacing of the route's points
ROUTE_POINTS: int = 64  #: points kept (a longer route is cut; the robot plans again if it stalls again)
_MAX_CELLS = 40_000  # a larger box is planned on a coarser grid


def plan_route(p: np.ndarray, goal: np.ndarray, radius: float, centres: np.ndarray, radii: np.ndarray,
               tries: int, scale: float, ahead: np.ndarray) -> np.ndarray | None:
    """Points ``(K, 2)`` every ROUTE_STEP from near ``p`` to ``goal`` round the discs ``(centres, radii)``.

    None when the grid has no way (the caller follows the boundary instead).  ``scale``: the robot's radius over
    the reference radius; ``ahead``: the unit direction it was blocked in.
    """
    from scipy.sparse import coo_matrix  # (here: importing the library does not load scipy.sparse)
    from scipy.sparse.csgraph import dijkstra

    reach = (radii + radius)[:, None]
    lo = np.min(np.vstack((p, goal, centres - reach)), axis=0) - ROUTE_PAD * scale
    hi = np.max(np.vstack((p, goal, centres + reach)), axis=0) + ROUTE_PAD * scale
    h = max(ROUTE_CELL * scale, float(np.sqrt(np.prod(hi - lo) / _MAX_CELLS)))
    nx, ny = (np.ceil((hi - lo) / h).astype(int) + 1).tolist()
    gx, gy = np.meshgrid(lo[0] + h * np.arange(nx), lo[1] + h * np.arange(ny), indexing="ij")
    clear = np.min(np.sqrt((gx[..., None] - centres[:, 0]) ** 2 + (gy[..., None] - centres[:, 1]) ** 2) - radii
                   - radius, axis=2, initial=np.inf)  # (cells x the few discs the robot senses)
    start, end = (np.clip(np.round((q - lo) / h).astype(int), 0, [nx - 1, ny - 1]) for q in (p, goal))
    own = np.min(np.sqrt(np.sum((centres - p) ** 2, axis=1)) - radii - radius, initial=np.inf)
    dx, dy = gx - p[0], gy - p[1]  # near the robot, not ahead: its own clearance less a cell (back out, not on)
    back = (dx * dx + dy * dy <= (ROUTE_BACK * scale) ** 2) & (dx * ahead[0] + dy * ahead[1] <= 0.5 * h) \
        & (clear >= own - h)
    near = np.zeros((nx, ny), dtype=bool)  # its cell and those within two of its goal: passable regardless
    near[tuple(start)] = True
    near[max(end[0] - 2, 0):end[0] + 3, max(end[1] - 2, 0):end[1] + 3] = True
    free = (clear >= ROUTE_CLEARANCE * scale * (1 + min(tries, 3))) | back | near
    weight = 1.0 + ROUTE_COST * np.clip(1.0 - clear / (ROUTE_MARGIN * scale), 0.0, 1.0)
    ids = np.arange(nx * ny).reshape(nx, ny)
    rows, cols, vals = [], [], []
    for dx, dy in ((1, 0), (0, 1), (1, 1), (1, -1)):  # (the four directions; the graph is undirected)
        a = (slice(0, nx - dx), slice(max(-dy, 0), ny - max(dy, 0)))
        b = (slice(dx, nx), slice(max(dy, 0), ny - max(-dy, 0)))
        ok = free[a] & free[b]
        rows.append(ids[a][ok])
        cols.append(ids[b][ok])
        vals.append(np.hypot(dx, dy) * h * 0.5 * (weight[a][ok] + weight[b][ok]))
    graph = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(nx * ny,) * 2)
    s, t = int(ids[tuple(start)]), int(ids[tuple(end)])
    dist, pred = dijkstra(graph.tocsr(), directed=False, indices=t, return_predecessors=True)
    if not np.isfinite(dist[s]):
        return None
    chain = [s]
    while chain[-1] != t:  # (one cell a step: at most the path's length in cells)
        chain.append(int(pred[chain[-1]]))
    cells = np.stack((gx.ravel()[chain], gy.ravel()[chain]), axis=1)
    cells[0], cells[-1] = p, goal
    seg = np.sqrt(np.sum(np.diff(cells, axis=0) ** 2, axis=1))
    run = np.concatenate(([0.0], np.cumsum(seg)))
    at = np.append(np.arange(ROUTE_STEP * scale, run[-1], ROUTE_STEP * scale), run[-1])[:ROUTE_POINTS]
    return np.stack((np.interp(at, run, cells[:, 0]), np.interp(at, run, cells[:, 1])), axis=1)
