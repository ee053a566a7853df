"""The decentralised safety filter step: every robot solves its own 2-variable QP.

In the spirit of Wang, Ames and Egerstedt's decentralised safety barrier
certificates, each pair row of the centralised filter (:mod:`~aasoatt_env.safety.core`)

    c^T (w_i - w_j) <= rhs,      w = A du,   i.e.   Gi du_i + Gj du_j <= rhs

is shared between its two robots in proportion to their authority ``a``
(:attr:`aasoatt_env.model.params.Team.max_point_accel`), ``s_i = a_i / (a_i + a_j)``.
Two ways (``split``):

``"authority"`` (Wang-Ames-Egerstedt): the right-hand side is split::

    robot i:   Gi du_i <= s_i rhs          robot j:   Gj du_j <= s_j rhs

``"reciprocal"`` (default; the reciprocal split of ORCA-style collision
avoidance): the correction that the pair's own nominal answers ``du0`` (each
robot's box-clipped least squares, :func:`~aasoatt_env.safety.problem.box_least_squares`)
need, ``v = Gi du0_i + Gj du0_j - rhs``, is split::

    robot i:   Gi du_i <= Gi du0_i - s_i v      robot j:   Gj du_j <= Gj du0_j - s_j v

so a pair whose nominals already keep the row keeps its slack, and a pair
that must change moves each robot by its share from where it wants to go.
It needs the neighbours' nominal accelerations (broadcast in a real team).
With the rhs split a robot at rest next to a neighbour can never accelerate
towards it, whatever the neighbour does: in closed loop on the radius-6 circle
swap (10 robots, tracking nominal, default deadlock strategy and backup layer)
the team froze in a ring around the centre (robots 7.5 m from their goals);
with the reciprocal split all ten reached their goals (within 0.02 m).

The two halves add up to the pair row, so any pair of answers that meet their
halves meets the pair row.  An obstacle row goes wholly to its robot.  Robot
``i`` then solves, with its own data only::

    min |A_i du_i - target_i|^2   s.t.   lo_i <= du_i <= hi_i,   its half-rows

(the centralised objective restricted to the robot), all robots at once with
the exact vectorised solver :func:`aasoatt_env.safety.solvers.local.solve_local_qps`
(it works in the metric of the objective, so ``du`` needs no rescaling).  The
multipliers come back in the units of the centralised filter's ``eta`` and, for
its ``eta_tol`` test, in its scaled normalised units ``z``
(:func:`aasoatt_env.safety.problem.build_problem`).

Halving rows can make a robot's QP infeasible where the joint QP is not (a robot
boxed in by halves it cannot meet with its bounded inputs).  Such a robot gets
the least-violation answer of its own QP, exactly as the centralised policy does
it (:func:`aasoatt_env.safety.solvers.policy.solve_qp`): a phase-1 problem finds
the least violation of each of its rows with the bounds hard
(:func:`~aasoatt_env.safety.solvers.local.least_violation`), the rows are
loosened by it, and the loosened QP is solved exactly.  It is reported
(:attr:`DecentralizedResult.infeasible`); the backup layer that runs after the
QP in the filter keeps the team safe.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.safety.problem import box_least_squares
from aasoatt_env.safety.solvers.local import RELAX_TOL, solve_local_qps

__all__ = ["SPLITS", "DecentralizedResult", "SplitRows", "decentralized_step", "split_rows"]

SPLITS: tuple[str, ...] = ("reciprocal", "authority")
"""Ways of sharing a pair row (module docstring)."""


class SplitRows(NamedTuple):
    """The half-rows of :func:`split_rows`.

    First the ``i`` half of every row (an obstacle row whole), then the ``j`` half
    of every robot-robot row ``rr[k]`` (``M + len(rr)`` half-rows).
    """

    owner: np.ndarray
    """Robot of each half-row."""
    G: np.ndarray
    """Coefficients on the owner's ``du`` ``(., 2)``."""
    h: np.ndarray
    """Right-hand sides."""
    rr: np.ndarray
    """The robot-robot rows, in the order of the ``j`` halves."""

    def row_side(self, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pair row and side (0: ``i`` half or obstacle, 1: ``j`` half) of half-rows ``half``."""
        m = self.owner.shape[0] - self.rr.shape[0]
        jside = half >= m
        row = half.copy()
        row[jside] = self.rr[half[jside] - m]
        return row, jside.astype(np.intp)


def split_rows(
    ri: np.ndarray,
    rj: np.ndarray,
    Gi: np.ndarray,
    Gj: np.ndarray,
    rhs: np.ndarray,
    authority: np.ndarray,
    du_nominal: np.ndarray | None = None,
) -> SplitRows:
    """Split every pair row between its robots by authority (module docstring).

    Parameters
    ----------
    ri, rj : numpy.ndarray
        Robots of each row ``(M,)``; ``rj = -1`` for obstacle rows.
    Gi, Gj : numpy.ndarray
        Row coefficients on ``du_i`` and ``du_j`` ``(M, 2)`` (``Gj`` ignored where ``rj < 0``).
    rhs : numpy.ndarray
        Right-hand sides ``(M,)``.
    authority : numpy.ndarray
        Non-negative authority of each robot ``(N,)`` (equal shares where both are 0).
    du_nominal : numpy.ndarray, optional
        ``(N, 2)``: split reciprocally around these accelerations (``"reciprocal"`` in the
        module docstring) instead of splitting ``rhs`` itself (``"authority"``).
    """
    ri = np.asarray(ri, np.intp)
    rj = np.asarray(rj, np.intp)
    m = ri.shape[0]
    if m == 0 or rj.min() >= 0:  # no obstacle rows
        rr = np.arange(m)
        rjr, Gjr = rj, Gj
        a_i = authority[ri]
    else:
        rr = np.flatnonzero(rj >= 0)
        rjr, Gjr = rj[rr], Gj[rr]
        a_i = authority[ri[rr]]
    a_j = authority[rjr]
    tot = a_i + a_j
    pos = tot > 0
    share_i = np.where(pos, a_i / np.where(pos, tot, 1.0), 0.5)
    full = rr.shape[0] == m
    if du_nominal is None:  # rhs split
        base_i, base_j, need = np.zeros(m), np.zeros(rr.shape[0]), -rhs
    else:  # the correction of the nominal pair split: h_i = Gi du0_i - v share_i
        base_i = Gi[:, 0] * du_nominal[ri, 0] + Gi[:, 1] * du_nominal[ri, 1]
        base_j = Gjr[:, 0] * du_nominal[rjr, 0] + Gjr[:, 1] * du_nominal[rjr, 1]
        need = base_i - rhs
        if full:
            need += base_j
        else:
            need[rr] += base_j
    need_r = need if full else need[rr]
    if full:
        h_i = base_i - need * share_i
    else:
        h_i = base_i - need  # obstacle rows whole
        h_i[rr] = base_i[rr] - need_r * share_i
    return SplitRows(
        owner=np.concatenate((ri, rjr)),
        G=np.concatenate((Gi, Gjr)),
        h=np.concatenate((h_i, base_j - need_r * (1.0 - share_i))),
        rr=rr,
    )


class DecentralizedResult(NamedTuple):
    """What :func:`decentralized_step` did."""

    du: np.ndarray
    """Wheel accelerations ``(N, 2)``, within the bounds."""
    eta: np.ndarray
    """Multiplier of each pair row ``(M,)``: the larger of its two halves' (du units of the objective
    ``|A du - target|^2``, as the centralised filter's ``eta``; equal to it where both robots' optima
    coincide with the centralised optimum)."""
    eta_half: np.ndarray
    """Multipliers of the two halves ``(M, 2)`` (column 1 is 0 on obstacle rows)."""
    z: np.ndarray
    """The larger half multiplier in the centralised filter's normalised units ``(M,)`` (scaled
    coordinates ``x = du / scale``, unit-norm rows, each robot's objective divided by its largest
    scaled Hessian entry): compare with ``FilterConfig.eta_tol``."""
    z_half: np.ndarray
    """``z`` of each half ``(M, 2)``."""
    infeasible: np.ndarray
    """``(N,)``: the robot's own QP was infeasible (answered with its least-violation point)."""
    n_relaxed: int
    """Robots whose rows were loosened (``infeasible.sum()``)."""
    slack: float
    """Largest violation of a half-row by ``du`` [eqn.8 units]; 0 when every robot's QP was feasible."""
    iterations: int
    """Active-set iterations of the local solver (largest over the robots)."""
    n_enumerated: int
    """Robots the local solver answered by exact enumeration."""


def decentralized_step(
    A: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    ri: np.ndarray,
    rj: np.ndarray,
    Gi: np.ndarray,
    Gj: np.ndarray,
    rhs: np.ndarray,
    authority: np.ndarray,
    *,
    split: str = "reciprocal",
    scale: np.ndarray | None = None,
    compiled: bool = False,
) -> DecentralizedResult:
    """Every robot's own QP over its half-rows, solved exactly for all robots at once.

    Parameters
    ----------
    A : numpy.ndarray
        Input matrices ``(N, 2, 2)`` (``w = A du``).
    target : numpy.ndarray
        Desired control-point accelerations ``(N, 2)``, at the scale of what the bounds allow (the
        filter passes the nominal clipped to the bounds): the local solver's tolerance is relative to
        the unconstrained minimiser (:func:`~aasoatt_env.safety.solvers.local.solve_local_qps`, Notes).
    lo, hi : numpy.ndarray
        Bounds on ``du`` ``(N, 2)``, kept hard.
    ri, rj : numpy.ndarray
        Robots of each row ``(M,)``; ``rj = -1`` for obstacle rows.
    Gi, Gj : numpy.ndarray
        Row coefficients on ``du_i`` and ``du_j`` ``(M, 2)``.
    rhs : numpy.ndarray
        Right-hand sides ``(M,)``.
    authority : numpy.ndarray
        Authority of each robot ``(N,)`` (``Team.max_point_accel``).
    split : {"reciprocal", "authority"}
        How a pair row is shared (module docstring).
    scale : numpy.ndarray, optional
        Positive per-robot scale of ``du`` ``(N,)`` used only to express ``z`` and the
        loosening tolerance in the centralised filter's scaled units (default ``max(|lo|, |hi|)``;
        the filter passes its own).
    compiled : bool
        Solve the robots' QPs in the compiled kernel (:func:`~aasoatt_env.safety.solvers.local.solve_local_qps`),
        and their closed forms of the reciprocal split
        (:func:`~aasoatt_env.safety.problem.box_least_squares`, the same numbers).

    Returns
    -------
    DecentralizedResult
    """
    n = A.shape[0]
    m = rhs.shape[0]
    if scale is None:
        big = np.maximum(np.abs(lo), np.abs(hi))
        scale = np.maximum(big[:, 0], big[:, 1])
        scale = np.where(scale > 0, scale, 1.0)
    # robot k: |A du - t|^2 = 0.5 du' H du + g' du + const, H = 2 A'A, g = -2 A't (the solver's
    # half-plane geometry is that of the objective, so du needs no rescaling)
    a00, a01, a10, a11 = A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1]
    H = np.empty((n, 2, 2))
    H[:, 0, 0] = 2.0 * (a00 * a00 + a10 * a10)
    H[:, 0, 1] = H[:, 1, 0] = 2.0 * (a00 * a01 + a10 * a11)
    H[:, 1, 1] = 2.0 * (a01 * a01 + a11 * a11)
    t0, t1 = target[:, 0], target[:, 1]
    g = np.stack((-2.0 * (a00 * t0 + a10 * t1), -2.0 * (a01 * t0 + a11 * t1)), axis=1)
    if split not in SPLITS:
        raise ValueError(f"split: got {split!r}, expected one of {list(SPLITS)}")
    du0 = box_least_squares(A, target, lo, hi, compiled=compiled) if split == "reciprocal" else None
    sp = split_rows(ri, rj, Gi, Gj, rhs, authority, du0)
    sol = solve_local_qps(H, g, lo, hi, sp.owner, sp.G, sp.h, relax=True, relax_tol=RELAX_TOL * scale,
                          compiled=compiled)
    du, lam = sol.x, sol.lam
    infeasible = ~sol.feasible
    n_relaxed = int(infeasible.sum())
    slack = 0.0
    if n_relaxed:
        hr = np.flatnonzero(infeasible[sp.owner])
        o = sp.owner[hr]
        res = sp.G[hr, 0] * du[o, 0] + sp.G[hr, 1] * du[o, 1] - sp.h[hr]
        slack = float(max(0.0, res.max(initial=0.0)))
    du = np.minimum(np.maximum(du, lo), hi)
    # multipliers back on the pair rows; z: scaled (x = du / s), unit-norm row, objective / sigma
    nz = np.flatnonzero(lam)
    row, side = sp.row_side(nz)
    o = sp.owner[nz]
    s_o = scale[o]
    sigma = s_o * s_o * np.maximum(np.maximum(np.abs(H[o, 0, 0]), np.abs(H[o, 1, 1])), np.abs(H[o, 0, 1]))
    Gn = sp.G[nz]
    eta_half = np.zeros((m, 2))
    z_half = np.zeros((m, 2))
    eta_half[row, side] = lam[nz]
    z_half[row, side] = lam[nz] * np.sqrt(Gn[:, 0] ** 2 + Gn[:, 1] ** 2) * s_o / sigma
    return DecentralizedResult(
        du=du, eta=np.maximum(eta_half[:, 0], eta_half[:, 1]), eta_half=eta_half,
        z=np.maximum(z_half[:, 0], z_half[:, 1]), z_half=z_half, infeasible=infeasible, n_relaxed=n_relaxed,
        slack=slack, iterations=sol.iterations, n_enumerated=sol.n_enumerated,
    )
