"""The repair: the least nudge of a QP answer toward brake-safety, so the gatekeeper rarely has to brake."""

from __future__ import annotations

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.params import Team
from aasoatt_env.safety.backup import gate, paths

__all__ = ["repair"]


def repair(team: Team, pose: np.ndarray, u: np.ndarray, du_c: np.ndarray, dt: float, lo: np.ndarray, hi: np.ndarray,
           *, sensing_range: float, brake_fraction: float, obstacles: tuple[np.ndarray, ...] | None = None,
           target: float = 2e-4, rounds: int = 3, eps: float = 1.0, near_pairs: np.ndarray | None = None,
           compiled: bool = False, checked: bool = False) -> np.ndarray:
    """Nudge a candidate toward brake-safety: the least change that lifts every low backup margin.

    For every pair whose margin along :func:`~aasoatt_env.safety.backup.candidate_paths` is below ``target`` [m], both
    inputs move by the least-norm change that lifts the margin to ``2 target``, linearised by finite differences (step
    ``eps``) at its closest step; the changes add up and are clipped to ``[lo, hi]``, ``rounds`` times.  Safety still
    comes from the gatekeeper, whose ``near_pairs``, ``compiled``, ``checked`` these are.
    """
    if not checked:
        near_pairs = gate.validate(team, pose, obstacles, near_pairs, u=u, du_c=du_c, lo=lo, hi=hi)
    if compiled:
        block = gate.kernel_args(team, pose, brake_fraction, sensing_range, obstacles, near_pairs)
        pose, u, du_c, lo, hi = (c64(a) for a in (pose, u, du_c, lo, hi))
        return kernels().repair_full(pose, u, du_c, lo, hi, float(dt), *block, float(target), int(rounds),
                                     float(eps), gate.CLOSEST_TIE)
    du = np.minimum(np.maximum(du_c, lo), hi)
    n = pose.shape[0]
    p0 = paths.point(team, pose)
    cache = _PathCache(team, pose, u, dt, brake_fraction)
    for _ in range(rounds):
        # reach first (O(N)): only robots with a pair that could come close need sampled paths
        R = paths.candidate(team, p0, pose[:, 2], u, du, dt, brake_fraction).reach + eps * dt * dt
        i, j, ds = gate.pairs_near(team, p0, R, sensing_range, 2.0 * target, near_pairs)
        oc, oi, ok, ods = gate.obstacles_near(team, p0, R, obstacles, 2.0 * target)
        if i.size + oi.size == 0:
            break
        S = np.unique(np.concatenate((i, j, oi)))  # rows of the paths: these robots, in this order
        loc = np.full(n, -1, dtype=np.intp)
        loc[S] = np.arange(S.size)
        P, D, need = cache.get(S, du)
        low = gate.bucketed_margins(P, D, need, loc[i], loc[j], ds) < target
        i, j, ds = i[low], j[low], ds[low]
        if oi.size:
            lowo = gate.bucketed_margins(P, D, need, loc[oi], ok, ods, centers=oc) < target
            oi, ok, ods = oi[lowo], ok[lowo], ods[lowo]
        if i.size + oi.size == 0:
            break
        step = _lifts(team, pose, u, du, dt, brake_fraction, target, eps, (P, D), loc, (i, j, ds), (oc, oi, ok, ods))
        if not step.any():
            break
        moved_du = np.minimum(np.maximum(du + step, lo), hi)
        cache.forget(np.flatnonzero((moved_du != du).any(axis=1)))
        du = moved_du
    return du


def _lifts(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, dt: float, brake_fraction: float,
           target: float, eps: float, base: tuple, loc: np.ndarray, pairs: tuple, obst: tuple) -> np.ndarray:
    """The summed least-norm lifts ``(n, 2)`` of the low pairs, by finite differences at their closest steps."""
    (P, D), (i, j, ds), (oc, oi, ok, ods) = base, pairs, obst
    n = pose.shape[0]
    step = np.zeros((n, 2))
    U = np.unique(np.concatenate((i, j, oi)))  # every robot of a low pair with each input moved: rows 2 q + d
    at = np.full(n, -1, dtype=np.intp)
    at[U] = 2 * np.arange(U.size)
    R2 = np.repeat(U, 2)
    sub = (team.subset(R2), pose[R2], u[R2], du[R2] + eps * np.tile(np.eye(2), (U.size, 1)), dt, brake_fraction)
    if i.size:
        li, lj = loc[i], loc[j]
        m0, k = gate.pair_margins(P[li], P[lj], D[li], D[lj], ds, closest=True)
        s4 = np.tile(k[:, None] + np.arange(2), (4, 1))
        fix = np.concatenate((lj, lj, li, li))
        pm, dm = paths.candidate_samples_at(*sub, s4, rows=np.concatenate((at[i], at[i] + 1, at[j], at[j] + 1)))
        mg = gate.pair_margins(pm, P[fix[:, None], s4], dm[:, :1], D[fix, s4[:, 0]][:, None], np.tile(ds, 4))
        mg = mg.reshape(4, -1)
        gi = ((mg[0:2] - m0) / eps).T
        gj = ((mg[2:4] - m0) / eps).T
        lift = (2.0 * target - m0) / np.maximum((gi * gi).sum(1) + (gj * gj).sum(1), 1e-12)
        np.add.at(step, i, lift[:, None] * gi)
        np.add.at(step, j, lift[:, None] * gj)
    if oi.size:
        lo_ = loc[oi]
        m0, k = gate.pair_margins(P[lo_], oc[ok][:, None], D[lo_], 0.0, ods, closest=True)
        s2 = np.tile(k[:, None] + np.arange(2), (2, 1))
        pm, dm = paths.candidate_samples_at(*sub, s2, rows=np.concatenate((at[oi], at[oi] + 1)))
        mg = gate.pair_margins(pm, oc[np.tile(ok, 2)][:, None], dm[:, :1], 0.0, np.tile(ods, 2)).reshape(2, -1)
        go = ((mg - m0) / eps).T
        lift = (2.0 * target - m0) / np.maximum((go * go).sum(1), 1e-12)
        np.add.at(step, oi, lift[:, None] * go)
    return step


class _PathCache:
    """Candidate paths of a team's robots, kept until the robot's input changes (a shorter row rests at its end)."""

    def __init__(self, team: Team, pose: np.ndarray, u: np.ndarray, dt: float, brake_fraction: float) -> None:
        self.team, self.pose, self.u, self.dt, self.brake_fraction = team, pose, u, dt, brake_fraction
        n = pose.shape[0]
        self.p = np.zeros((n, 2), dtype=np.complex128)
        self.delta = np.zeros((n, 1))
        self.length = np.zeros(n, dtype=np.int64)
        self.valid = np.zeros(n, dtype=bool)

    def get(self, rows: np.ndarray, du: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Samples ``(R, L)``, deviations ``(R, L-1)``, sample counts ``(R,)`` of robots ``rows`` (sorted) at ``du``."""
        new = rows[~self.valid[rows]]
        if new.size:
            t = paths.candidate_paths(self.team.subset(new), self.pose[new], self.u[new], du[new], self.dt,
                                self.brake_fraction)
            width = t.p.shape[1]
            if width > self.p.shape[1]:  # every row rests beyond its own horizon
                grow = width - self.p.shape[1]
                self.p = np.concatenate((self.p, np.repeat(self.p[:, -1:], grow, axis=1)), axis=1)
                self.delta = np.concatenate((self.delta, np.zeros((self.delta.shape[0], grow))), axis=1)
            self.p[new, :width], self.p[new, width:] = t.p, t.p[:, -1:]
            self.delta[new, : width - 1], self.delta[new, width - 1:] = t.delta, 0.0
            self.length[new] = t.length
            self.valid[new] = True
        L = max(int(self.length[rows].max(initial=0)), 2)
        return self.p[rows, :L], self.delta[rows, : L - 1], self.length[rows]

    def forget(self, rows: np.ndarray) -> None:
        """Robots whose input changed: their paths are made again when asked for."""
        self.valid[rows] = False
