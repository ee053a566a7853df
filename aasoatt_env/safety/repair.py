"""The repair of a QP answer toward brake-safety, and the backup layer's decision for it.

:func:`~aasoatt_env.safety.gatekeeper.gatekeeper` alone keeps the team safe: it puts
every robot whose candidate is not brake-safe on the braking backup.  Braking
costs liveness, so before the gatekeeper decides, :func:`repair` nudges the
QP's answer toward brake-safety (the least change that lifts every low backup
margin, like backup-barrier rows in the QP), and :func:`gate_with_repair` is
the order in which the filter asks: a quick check of the QP's answer, then, in
each group of robots within sensing range of each other where it brakes
someone for a pair, the repair and a check of it, the full check of the QP's
answer only where the repaired one still brakes someone; where it brakes
someone only for the range limit, the full check; outside the safe set, best
effort.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.geometry import pair_components, robot_pairs
from aasoatt_env.model.params import Team
from aasoatt_env.safety.backup import (
    _brake,
    _candidate_reach,
    _first_step,
    _point,
    candidate_paths,
    candidate_samples_at,
)
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.gatekeeper import (
    CLOSEST_TIE,
    GateResult,
    _bucketed,
    _kernel_args,
    _obstacles_near,
    _pairs_near,
    gatekeeper,
    pair_margins,
)
from aasoatt_env.sim.env import FILTERED_MIN_COLLISION_TOLERANCE

__all__ = ["GATE_TOL", "gate_with_repair", "repair"]

GATE_TOL: float = 0.5 * FILTERED_MIN_COLLISION_TOLERANCE
"""Overlap [m] the backup check forgives: half the env's smallest collision tolerance behind a filter
(:data:`aasoatt_env.sim.env.FILTERED_MIN_COLLISION_TOLERANCE`), the other half left for the rounding between
the check's closed-form paths and the simulator's steps, which grows with the coordinates (~``eps P``:
1e-10 m at ``P`` = 1e6 m, the largest a scenario takes).  With the whole 1e-9 m forgiven, an adversarial
tester's exactly touching packs pushed together 1e3-1e6 m from the origin passed 4-33 pm beyond it
(2026-12-02).  Twice what a scenario's start may overlap (:data:`aasoatt_env.sim.scenarios.base.TOUCH_TOL`),
so a touching team at rest, its positions rounded, is brake-safe."""


def gate_with_repair(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     cfg: FilterConfig, obstacles: tuple[np.ndarray, ...] | None,
                     pairs: np.ndarray | None = None, quick: GateResult | None = None) -> GateResult:
    """The backup layer's decision for the QP's answer ``du``: the gatekeeper, with the repair if it brakes.

    Every answer comes from :func:`~aasoatt_env.safety.gatekeeper.gatekeeper`
    (safety is its invariant).  Whether the QP's answer passes for every robot
    is decided by the first round, which is the same with or without the blend
    levels, so it is checked first without them (``quick=True``: fewer rounds)
    unless a robot is too fast for the range limit (then the blends are its
    only way short of braking, and that first check is the full one).  When it
    brakes someone, the rest is decided per connected
    component of the robots within the sensing range ``D`` of each other
    (``pairs``: those pairs, as the filter found them; found here when None;
    a safety input: every check, the quick one included, takes its candidate pairs from
    it, so it must hold every pair of one group within ``D`` at the control points; None:
    each call searches itself),
    each as if it were alone: the gatekeeper never couples robots farther apart
    than ``D``, so a stack of teams decides as each team alone, and a component
    where nobody brakes keeps the QP's answer.  ``quick``: that first check's
    result, where the caller made it (the compiled step,
    :mod:`~aasoatt_env.safety.step_kernel`, with ``pairs``).

    - A component whose invariant was already broken (a pair failing when both
      brake: a start that was not brake-safe, an assumption violated) gets the
      best effort of ``hold_violations``, and the result says unsafe.
    - One where a robot brakes for a pair is nudged by :func:`repair` and checked
      again with the blend levels; the full check of the QP's answer is made
      only where the repaired one still brakes someone, and of the two the one
      that brakes fewer robots is kept (the repaired one on a tie, the QP's when
      its check finds the component broken).
    - The others (the braking robots only too fast for the range limit, which no
      nudge of a pair margin changes; a robot beyond the range limit even when
      braking; the repair off) get the full check of the QP's answer.
    """
    gate_kw = dict(sensing_range=cfg.sensing_range, brake_fraction=cfg.brake_fraction, obstacles=obstacles,
                   compiled=cfg.compiled)
    # the filter's pairs within D, where given, are every check's candidate pairs (one neighbour
    # search per step; found from the same points up to rounding: a pair that rounding moves
    # across D is D apart, and the paths of its robots, within D / 2 - r of their starts, keep it
    # d_s apart)
    if quick is None:
        quick = gatekeeper(team, pose, u, du, cfg.dt, tol=GATE_TOL, quick=True, near_pairs=pairs, **gate_kw)
    if not quick.braking.any():
        return quick
    full_check = bool(quick.out_of_range.any())  # the quick check used the blend levels: it is the full one
    if full_check and not quick.broken.any() and not (quick.braking & ~quick.out_of_range).any():
        # every robot that brakes does so for the range limit alone, and nothing is broken: nothing is
        # held or repaired, and the full check is the one made (what the branches below would return)
        return _merged(quick, [], unsafe=False)
    n = pose.shape[0]
    if pairs is None:
        p0 = _point(team, pose)
        pairs = robot_pairs(np.stack((p0.real, p0.imag), axis=1), cfg.sensing_range, groups=team.group,
                            compiled=cfg.compiled)
    label = pair_components(n, pairs[:, 0], pairs[:, 1], compiled=cfg.compiled)

    def per_component(flags: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: the robot's component has a robot with ``flags``."""
        hit = np.zeros(n, dtype=bool)
        hit[label[flags]] = True
        return hit[label]


    def sub(rows: np.ndarray) -> tuple[Team, np.ndarray, np.ndarray]:
        """The team, poses and speeds of robots ``rows`` (the arrays themselves when that is everyone)."""
        return (team, pose, u) if rows.size == n else (team.subset(rows), pose[rows], u[rows])

    def near_of(rows: np.ndarray) -> np.ndarray:
        """``pairs`` within robots ``rows`` (unions of components), in their numbering."""
        if rows.size == n:
            return pairs
        loc = np.full(n, -1, dtype=np.intp)
        loc[rows] = np.arange(rows.size)
        q = loc[pairs]
        return q[(q >= 0).all(axis=1)]

    def gate_on(rows: np.ndarray, cand: np.ndarray, **kw) -> GateResult:
        return gatekeeper(*sub(rows), cand, cfg.dt, tol=GATE_TOL, near_pairs=near_of(rows), **gate_kw, **kw)

    broken = per_component(quick.broken)
    held = broken & per_component(quick.robot_margin < 0.0)
    fixing = per_component(quick.braking & ~quick.out_of_range) & ~broken & cfg.backup_repair
    full = per_component(quick.braking) & ~held & ~fixing
    parts: list[tuple[np.ndarray, GateResult]] = []
    if held.any():
        # best effort outside the safe set: every pair held to its own margin under braking, so no
        # pair gets closer than braking would bring it while robots may still move apart; the
        # caller's bounds stay hard (they bind only when tighter than the robots' own, which the
        # backup respects)
        rows = np.flatnonzero(held)
        g = gate_on(rows, du[rows], hold_violations=True)
        parts.append((rows, g._replace(du=np.minimum(np.maximum(g.du, lo[rows]), hi[rows]))))
    if full.any() and not full_check:
        rows = np.flatnonzero(full)
        parts.append((rows, gate_on(rows, du[rows])))
    if fixing.any():
        # nudge the QP's answer toward brake-safety, then check again (usually nobody brakes then)
        rows = np.flatnonzero(fixing)
        repaired = repair(*sub(rows), du[rows], cfg.dt, lo[rows], hi[rows], near_pairs=near_of(rows), **gate_kw)
        second = gate_on(rows, repaired)
        parts.append((rows, second))
        again = np.zeros(n, dtype=bool)
        again[rows] = second.braking
        again = per_component(again)
        if again.any():
            # the full check of the QP's answer there; of the two, per component, the repaired
            # answer unless the QP's brakes fewer robots (or the QP's check finds the state broken)
            rows_a = np.flatnonzero(again)
            first = _rows_of(quick, rows_a) if full_check else gate_on(rows_a, du[rows_a])
            nb2, nb1, bad1 = (np.zeros(n, dtype=np.int64) for _ in range(3))
            np.add.at(nb2, label[rows], second.braking)
            np.add.at(nb1, label[rows_a], first.braking)
            np.add.at(bad1, label[rows_a], first.broken)
            take_first = ~((bad1 == 0) & (nb2 <= nb1))[label[rows_a]]
            parts.append((rows_a[take_first], _rows_of(first, np.flatnonzero(take_first))))
    return _merged(quick, parts, unsafe=bool(held.any()))


def _rows_of(g: GateResult, at: np.ndarray) -> GateResult:
    """The per-robot entries ``at`` of a gate result (scalars kept)."""
    return g._replace(du=g.du[at], braking=g.braking[at], broken=g.broken[at], share=g.share[at],
                      robot_margin=g.robot_margin[at], out_of_range=g.out_of_range[at])


def _merged(base: GateResult, parts: list[tuple[np.ndarray, GateResult]], unsafe: bool) -> GateResult:
    """``base`` with the robots ``rows`` of each part replaced by that part's answers (later parts win).

    ``n_pairs`` and ``out_of_range`` stay the first check's (the whole team's pairs and candidate).
    """
    du, braking, broken = base.du.copy(), base.braking.copy(), base.broken.copy()
    share, robot_margin = base.share.copy(), base.robot_margin.copy()
    for rows, g in parts:
        du[rows], braking[rows], broken[rows], share[rows], robot_margin[rows] = (
            g.du, g.braking, g.broken, g.share, g.robot_margin)
    return GateResult(du, braking, float(robot_margin.min(initial=base.margin)), not (unsafe or broken.any()), broken,
                      share, base.rounds + sum(g.rounds for _, g in parts), base.n_pairs, robot_margin,
                      base.out_of_range)


def repair(
    team: Team,
    pose: np.ndarray,
    u: np.ndarray,
    du_c: np.ndarray,
    dt: float,
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    sensing_range: float,
    brake_fraction: float,
    obstacles: tuple[np.ndarray, np.ndarray] | None = None,
    target: float = 2e-4,
    rounds: int = 3,
    eps: float = 1.0,
    near_pairs: np.ndarray | None = None,
    compiled: bool = False,
) -> np.ndarray:
    """Nudge a candidate toward brake-safety: the least change that lifts every low backup margin.

    For every pair whose margin along :func:`~aasoatt_env.safety.backup.candidate_paths` is below
    ``target`` [m], the margin's gradient with respect to both robots' inputs is
    taken by finite differences at the pair's closest step (step ``eps`` in input
    units; the two samples of that step in closed form,
    :func:`~aasoatt_env.safety.backup.candidate_samples_at`), and the two
    inputs move by the least-norm change that lifts the linearised margin to
    ``2 target``; changes from several pairs add up, and the result is clipped
    to ``[lo, hi]``.  ``rounds`` rounds.  This acts like backup-barrier rows in
    the QP (a small, local correction toward the safe set), so the gatekeeper
    rarely has to brake; safety still comes from :func:`~aasoatt_env.safety.gatekeeper.gatekeeper` alone.
    ``near_pairs``: candidate pairs as in the gatekeeper (one search for every round).
    ``compiled``: run it in the compiled kernel of :mod:`aasoatt_env.compiled` (``ImportError``
    without numba; the same answer up to rounding, which the division by the squared gradient
    amplifies: see that module).
    """
    if compiled:
        block = _kernel_args(team, pose, brake_fraction, sensing_range, obstacles, near_pairs, u=u, du_c=du_c,
                             lo=lo, hi=hi)
        pose, u, du_c, lo, hi = (c64(a) for a in (pose, u, du_c, lo, hi))
        return kernels().repair_full(pose, u, du_c, lo, hi, float(dt), *block, float(target), int(rounds),
                                     float(eps), CLOSEST_TIE)
    du = np.minimum(np.maximum(du_c, lo), hi)
    n = pose.shape[0]
    eye = np.eye(2)
    p0 = _point(team, pose)
    paths = _PathCache(team, pose, u, dt, brake_fraction)
    for _ in range(rounds):
        # reach first (O(N)): only robots with a pair that could come close need sampled paths
        p1, d1, theta1, u1 = _first_step(team, p0, pose[:, 2], u, du, dt)
        R = _candidate_reach(p0, p1, d1, _brake(team, theta1, u1, dt, brake_fraction)) + eps * dt * dt
        i, j, ds = _pairs_near(team, p0, R, sensing_range, 2.0 * target, near_pairs)
        oc, oi, ok, ods = _obstacles_near(team, p0, R, obstacles, 2.0 * target)
        if i.size + oi.size == 0:
            break
        S = np.unique(np.concatenate((i, j, oi)))  # rows of `base`: these robots, in this order
        loc = np.full(n, -1, dtype=np.intp)
        loc[S] = np.arange(S.size)
        base = paths.get(S, du)
        m = _bucketed(base.p, base.delta, base.length, loc[i], loc[j], ds)
        low = m < target
        i, j, ds = i[low], j[low], ds[low]
        if oi.size:
            mo = _bucketed(base.p, base.delta, base.length, loc[oi], ok, ods, centers=oc)
            lowo = mo < target
            oi, ok, ods = oi[lowo], ok[lowo], ods[lowo]
        if i.size + oi.size == 0:
            break
        # the gradient of each low margin at its closest step (the envelope of the minimum): that
        # step's two samples of one member's path with one input moved by eps, in closed form
        step = np.zeros((n, 2))
        # every robot of a low pair with each input moved by eps: rows 2 q + d of `moved`
        U = np.unique(np.concatenate((i, j, oi)))
        at = np.full(n, -1, dtype=np.intp)
        at[U] = 2 * np.arange(U.size)
        R2 = np.repeat(U, 2)
        sub_team, sub_pose, sub_u = team.subset(R2), pose[R2], u[R2]
        moved = du[R2] + eps * np.tile(eye, (U.size, 1))
        if i.size:
            li, lj = loc[i], loc[j]
            m0, k = pair_margins(base.p[li], base.p[lj], base.delta[li], base.delta[lj], ds, closest=True)
            s4 = np.tile(k[:, None] + np.arange(2), (4, 1))
            fix = np.concatenate((lj, lj, li, li))
            pm, dm = candidate_samples_at(sub_team, sub_pose, sub_u, moved, dt, brake_fraction, s4,
                                          rows=np.concatenate((at[i], at[i] + 1, at[j], at[j] + 1)))
            mg = pair_margins(pm, base.p[fix[:, None], s4], dm[:, :1], base.delta[fix, s4[:, 0]][:, None],
                              np.tile(ds, 4)).reshape(4, -1)
            gi = ((mg[0:2] - m0) / eps).T
            gj = ((mg[2:4] - m0) / eps).T
            lift = (2.0 * target - m0) / np.maximum((gi * gi).sum(1) + (gj * gj).sum(1), 1e-12)
            np.add.at(step, i, lift[:, None] * gi)
            np.add.at(step, j, lift[:, None] * gj)
        if oi.size:
            lo_ = loc[oi]
            m0, k = pair_margins(base.p[lo_], oc[ok][:, None], base.delta[lo_], 0.0, ods, closest=True)
            s2 = np.tile(k[:, None] + np.arange(2), (2, 1))
            pm, dm = candidate_samples_at(sub_team, sub_pose, sub_u, moved, dt, brake_fraction, s2,
                                          rows=np.concatenate((at[oi], at[oi] + 1)))
            mg = pair_margins(pm, oc[np.tile(ok, 2)][:, None], dm[:, :1], 0.0, np.tile(ods, 2)).reshape(2, -1)
            go = ((mg - m0) / eps).T
            lift = (2.0 * target - m0) / np.maximum((go * go).sum(1), 1e-12)
            np.add.at(step, oi, lift[:, None] * go)
        if not step.any():
            break
        moved_du = np.minimum(np.maximum(du + step, lo), hi)
        paths.forget(np.flatnonzero((moved_du != du).any(axis=1)))
        du = moved_du
    return du


class _Paths(NamedTuple):
    """Paths as in :class:`~aasoatt_env.safety.backup.Trajectories`, without the reach bound.

    Samples ``(R, L)``, deviation bounds ``(R, L-1)`` and sample counts ``(R,)``.
    """

    p: np.ndarray
    delta: np.ndarray
    length: np.ndarray


class _PathCache:
    """Candidate paths of a team's robots, each made once and kept until the robot's input changes.

    :func:`~aasoatt_env.safety.backup.candidate_paths`, row by row: a repair round moves only the
    robots of low pairs, so the others keep their paths.  Rows are made only for robots asked
    for; a row shorter than the others is extended with its rest position (deviation 0), which
    is what a longer horizon gives for it, sample for sample.
    """

    def __init__(self, team: Team, pose: np.ndarray, u: np.ndarray, dt: float, brake_fraction: float) -> None:
        self.team, self.pose, self.u, self.dt, self.brake_fraction = team, pose, u, dt, brake_fraction
        n = pose.shape[0]
        self.p = np.zeros((n, 2), dtype=np.complex128)
        self.delta = np.zeros((n, 1))
        self.length = np.zeros(n, dtype=np.int64)
        self.valid = np.zeros(n, dtype=bool)

    def get(self, rows: np.ndarray, du: np.ndarray) -> _Paths:
        """The paths of robots ``rows`` (sorted) with inputs ``du[rows]``, ``L`` their longest horizon."""
        new = rows[~self.valid[rows]]
        if new.size:
            t = candidate_paths(self.team.subset(new), self.pose[new], self.u[new], du[new], self.dt,
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
        return _Paths(self.p[rows, :L], self.delta[rows, : L - 1], self.length[rows])

    def forget(self, rows: np.ndarray) -> None:
        """Robots whose input changed: their paths are made again when asked for."""
        self.valid[rows] = False
