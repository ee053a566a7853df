"""The backup layer as the filter's last stage: check the QP's answer, repair it, brake where needed."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from aasoatt_env.model.dynamics import pose_from_point
from aasoatt_env.model.geometry import pair_components, robot_pairs
from aasoatt_env.model.params import Team
from aasoatt_env.safety.backup.gate import GateResult, gatekeeper, repair, validate
from aasoatt_env.safety.backup.paths import point
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.stages import StepInput
from aasoatt_env.sim.env import FILTERED_MIN_COLLISION_TOLERANCE

__all__ = ["GATE_TOL", "BackupAnswer", "BackupLayer", "backup_answer", "gate_with_repair"]

GATE_TOL: float = 0.5 * FILTERED_MIN_COLLISION_TOLERANCE
"""Overlap [m] the check forgives: half the env's collision tolerance behind a filter (the other half absorbs the
rounding of closed-form paths), twice a scenario start's (``TOUCH_TOL``): a touching team at rest is brake-safe."""


def gate_with_repair(team: Team, pose: np.ndarray, u: np.ndarray, du: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     cfg: FilterConfig, obstacles: tuple[np.ndarray, ...] | None,
                     pairs: np.ndarray | None = None, *, checked: bool = False) -> GateResult:
    """The backup layer's decision for the QP's answer ``du``: the gatekeeper, with the repair where it brakes.

    The quick check decides whether ``du`` passes.  Where it brakes, each component of robots within ``D`` is decided
    alone: a broken one gets ``hold_violations``' best effort (unsafe), one braking for a pair is repaired and checked
    again (the answer braking fewer robots kept, the repaired on a tie), the others get the full check.
    """
    if not checked:
        pairs = validate(team, pose, obstacles, pairs, u=u, du=du, lo=lo, hi=hi)
    gate_kw = dict(sensing_range=cfg.sensing_range, brake_fraction=cfg.brake_fraction, obstacles=obstacles,
                   compiled=cfg.compiled, checked=True)
    quick = gatekeeper(team, pose, u, du, cfg.dt, tol=GATE_TOL, quick=True, near_pairs=pairs, **gate_kw)
    if not quick.braking.any():
        return quick
    full_check = bool(quick.out_of_range.any())  # the quick check used the blend levels: it is the full one
    if full_check and not quick.broken.any() and not (quick.braking & ~quick.out_of_range).any():
        return _merged(quick, [], None)  # braking for the range limit alone: nothing held or repaired
    if pairs is None:
        p0 = point(team, pose)
        pairs = robot_pairs(np.stack((p0.real, p0.imag), axis=1), cfg.sensing_range, groups=team.group,
                            compiled=cfg.compiled)
    n = pose.shape[0]
    comp = _Components(team, pose, u, pairs, pair_components(n, pairs[:, 0], pairs[:, 1], compiled=cfg.compiled))

    def gate_on(rows: np.ndarray, cand: np.ndarray, **kw) -> GateResult:
        return gatekeeper(*comp.sub(rows), cand, cfg.dt, tol=GATE_TOL, near_pairs=comp.near(rows), **gate_kw, **kw)

    broken = comp.any(quick.broken)
    held = broken & comp.any(quick.robot_margin < 0.0)
    fixing = comp.any(quick.braking & ~quick.out_of_range) & ~broken & cfg.backup_repair
    full = comp.any(quick.braking) & ~held & ~fixing
    parts: list[tuple[np.ndarray, GateResult]] = []
    if held.any():  # best effort outside the safe set; the caller's bounds stay hard
        rows = np.flatnonzero(held)
        g = gate_on(rows, du[rows], hold_violations=True)
        parts.append((rows, g._replace(du=np.minimum(np.maximum(g.du, lo[rows]), hi[rows]))))
    if full.any() and not full_check:
        rows = np.flatnonzero(full)
        parts.append((rows, gate_on(rows, du[rows])))
    if fixing.any():
        rows = np.flatnonzero(fixing)
        repaired = repair(*comp.sub(rows), du[rows], cfg.dt, lo[rows], hi[rows], near_pairs=comp.near(rows),
                          **gate_kw)
        second = gate_on(rows, repaired)
        parts.append((rows, second))
        again = np.zeros(n, dtype=bool)
        again[rows] = second.braking
        again = comp.any(again)
        if again.any():  # per component, the repaired answer unless the QP's brakes fewer robots (or is broken)
            rows_a = np.flatnonzero(again)
            first = _rows_of(quick, rows_a) if full_check else gate_on(rows_a, du[rows_a])
            nb2, nb1, bad1 = (np.zeros(n, dtype=np.int64) for _ in range(3))
            np.add.at(nb2, comp.label[rows], second.braking)
            np.add.at(nb1, comp.label[rows_a], first.braking)
            np.add.at(bad1, comp.label[rows_a], first.broken)
            take_first = ~((bad1 == 0) & (nb2 <= nb1))[comp.label[rows_a]]
            parts.append((rows_a[take_first], _rows_of(first, np.flatnonzero(take_first))))
    return _merged(quick, parts, held if held.any() else None)


class _Components:
    """The team's components of robots within sensing range of each other (``label``), and their sub-teams."""

    def __init__(self, team: Team, pose: np.ndarray, u: np.ndarray, pairs: np.ndarray, label: np.ndarray) -> None:
        self.team, self.pose, self.u, self.pairs, self.label = team, pose, u, pairs, label

    def any(self, flags: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: the robot's component has a robot with ``flags``."""
        hit = np.zeros(self.label.shape[0], dtype=bool)
        hit[self.label[flags]] = True
        return hit[self.label]

    def sub(self, rows: np.ndarray) -> tuple[Team, np.ndarray, np.ndarray]:
        """The team, poses and speeds of robots ``rows`` (the arrays themselves when that is everyone)."""
        if rows.size == self.label.shape[0]:
            return self.team, self.pose, self.u
        return self.team.subset(rows), self.pose[rows], self.u[rows]

    def near(self, rows: np.ndarray) -> np.ndarray:
        """The pairs within robots ``rows`` (unions of components), in their numbering."""
        n = self.label.shape[0]
        if rows.size == n:
            return self.pairs
        loc = np.full(n, -1, dtype=np.intp)
        loc[rows] = np.arange(rows.size)
        q = loc[self.pairs]
        return q[(q >= 0).all(axis=1)]


_PER_ROBOT = ("du", "braking", "broken", "share", "robot_margin", "out_of_range")  # a GateResult's (N,) fields


def _rows_of(g: GateResult, at: np.ndarray) -> GateResult:
    """The per-robot entries ``at`` of a gate result (scalars kept)."""
    return g._replace(**{f: getattr(g, f)[at] for f in _PER_ROBOT})


def _merged(base: GateResult, parts: list[tuple[np.ndarray, GateResult]], held: np.ndarray | None) -> GateResult:
    """``base`` with each part's robots replaced by its answers (later parts win; n_pairs, out_of_range kept)."""
    new = {f: getattr(base, f).copy() for f in _PER_ROBOT[:-1]}
    for rows, g in parts:
        for f, a in new.items():
            a[rows] = getattr(g, f)
    return base._replace(margin=float(new["robot_margin"].min(initial=base.margin)),
                         safe=not (held is not None or new["broken"].any()), held=held,
                         rounds=base.rounds + sum(g.rounds for _, g in parts), **new)


class BackupAnswer(NamedTuple):
    """What the backup layer did: :class:`GateResult`'s ``du``, ``braking``, ``margin``, ``safe``, and ``nudged``."""

    du: np.ndarray
    braking: np.ndarray
    nudged: np.ndarray  #: robots the repair moved (not braking)
    margin: float
    safe: bool
    unsafe: np.ndarray | None = None  #: robots outside the safe set: held (best effort) or broken (the QP's answer)


@dataclass(frozen=True)
class BackupLayer:
    """The backup stage: ``stage(step, du_qp, robot_pairs) -> BackupAnswer``."""

    cfg: FilterConfig

    def __call__(self, s: StepInput, du_qp: np.ndarray, pairs: np.ndarray) -> BackupAnswer:
        """Check (and repair) the QP's answer; robots the check finds broken keep the QP's answer (best effort)."""
        return backup_answer(s.team, pose_from_point(s.team, s.p, s.theta), s.u, du_qp, s.lo, s.hi, s.scale,
                             self.cfg, s.obstacles, pairs, checked=True)


def backup_answer(team: Team, pose: np.ndarray, u: np.ndarray, du_qp: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  scale: np.ndarray, cfg: FilterConfig, obstacles: tuple[np.ndarray, ...] | None, pairs: np.ndarray,
                  checked: bool = False) -> BackupAnswer:
    """The backup stage's answer for the QP's ``du_qp`` (:func:`gate_with_repair`; ``scale`` ``(N,)``: ``nudged``'s)."""
    gate = gate_with_repair(team, pose, u, du_qp, lo, hi, cfg, obstacles, pairs, checked=checked)
    broken = gate.broken
    du = np.where(broken[:, None], du_qp, gate.du)
    braking = gate.braking & ~broken
    nudged = ~braking & ~broken & (np.abs(du - du_qp) > 1e-9 * scale[:, None]).any(axis=1)
    unsafe = broken if gate.held is None else broken | gate.held
    return BackupAnswer(du, braking, nudged, gate.margin, gate.safe, unsafe)
