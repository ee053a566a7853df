"""The backup layer as the filter's last stage: check the QP's answer, repair it, brake where needed.

:func:`gate_with_repair` is the order in which the filter asks the gatekeeper
(:mod:`~aasoatt_env.safety.backup.gate`): a quick check of the QP's answer; where it brakes
someone for a pair, per group of robots within sensing range of each other, the repair
(:mod:`~aasoatt_env.safety.backup.repair`) and a check of it, and the full check of the QP's
answer only where the repaired one still brakes someone; where it brakes someone only for the
range limit, the full check; outside the safe set, best effort.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from aasoatt_env.model.geometry import pair_components, robot_pairs
from aasoatt_env.model.params import Team
from aasoatt_env.safety.backup.gate import GateResult, gatekeeper, validate
from aasoatt_env.safety.backup.paths import point
from aasoatt_env.safety.backup.repair import repair
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.stages import StepInput
from aasoatt_env.sim.env import FILTERED_MIN_COLLISION_TOLERANCE

__all__ = ["GATE_TOL", "BackupAnswer", "BackupLayer", "gate_with_repair"]

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
                     pairs: np.ndarray | None = None, *, checked: bool = False) -> GateResult:
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
    where nobody brakes keeps the QP's answer.  ``checked``: the caller vouches for every shape and
    pair index (the filter's own arrays).

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
    if not checked:
        pairs = validate(team, pose, obstacles, pairs, u=u, du=du, lo=lo, hi=hi)
    gate_kw = dict(sensing_range=cfg.sensing_range, brake_fraction=cfg.brake_fraction, obstacles=obstacles,
                   compiled=cfg.compiled, checked=True)
    # the filter's pairs within D, where given, are every check's candidate pairs (one neighbour
    # search per step; found from the same points up to rounding: a pair that rounding moves
    # across D is D apart, and the paths of its robots, within D / 2 - r of their starts, keep it
    # d_s apart)
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
        p0 = point(team, pose)
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




class BackupAnswer(NamedTuple):
    """What the backup layer did to the QP's answer."""

    du: np.ndarray
    """``(N, 2)`` the inputs to apply."""
    braking: np.ndarray
    """``(N,)`` robots blended toward, or put on, the braking backup."""
    nudged: np.ndarray
    """``(N,)`` robots whose inputs the repair moved (and that do not brake)."""
    margin: float
    """Smallest ``distance - d_s`` [m] along the backup horizon of the applied inputs."""
    safe: bool
    """The state was brake-safe: the applied inputs keep the team in the safe set."""


def axle_pose(team: Team, p: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Axle poses ``(N, 3)`` from control points and headings."""
    pose = np.empty((p.shape[0], 3))
    pose[:, 2] = theta
    if team.is_diff_drive:
        pose[:, 0] = p[:, 0] - team.offset * np.cos(theta)
        pose[:, 1] = p[:, 1] - team.offset * np.sin(theta)
    else:
        pose[:, :2] = p
    return pose


@dataclass(frozen=True)
class BackupLayer:
    """The backup stage: ``stage(step, du_qp, robot_pairs) -> BackupAnswer``."""

    cfg: FilterConfig

    def __call__(self, s: StepInput, du_qp: np.ndarray, pairs: np.ndarray) -> BackupAnswer:
        """Check (and repair) the QP's answer; robots the check finds broken keep the QP's answer (best effort)."""
        gate = gate_with_repair(s.team, axle_pose(s.team, s.p, s.theta), s.u, du_qp, s.lo, s.hi, self.cfg,
                                s.obstacles, pairs, checked=True)
        broken = gate.broken
        du = np.where(broken[:, None], du_qp, gate.du)
        braking = gate.braking & ~broken
        nudged = ~braking & ~broken & (np.abs(du - du_qp) > 1e-9 * s.scale[:, None]).any(axis=1)
        return BackupAnswer(du, braking, nudged, gate.margin, gate.safe)
