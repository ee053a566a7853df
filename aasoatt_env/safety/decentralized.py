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

**Negotiation groups** (``whole``; the filter's ``FilterConfig.negotiate``, on by
default).  Split rows keep the team safe but cannot pick which of two alike robots
goes first: in dense crowds robots stop against each other with every half-row
met and nobody yielding (a deadlock the rotation of the deadlock strategy does not
free; README: Decentralised filter).  The filter therefore lets the robots around
a jam agree on one answer (:func:`negotiation_rows`): a robot the deadlock trigger
flags negotiates, and so does every robot it touches; the row between two
negotiating robots is kept whole, and the robots joined by such rows (a *group*, a
connected component of them) solve their QP jointly, the centralised filter's QP
restricted to them (:func:`~aasoatt_env.safety.decomposition.solve_centralized`),
with their halves of every other row as in the split.  Every robot outside a
group solves its own QP as above.  So every pair row is still met (whole by a
group, or by its two halves), and with no robot triggered the step is the
per-robot one exactly.  On real robots a group's QP is solved by one of its
members from what the members send (the nominals the reciprocal split already
exchanges, their states and inputs), or by a distributed QP method among them.
A group's QP can be infeasible where the team's is not (the halves it keeps of
rows to robots outside it box it in, as a lone robot's can): it is answered as
the centralised filter answers an infeasible team, by its least-violation point
(status ``"relaxed"``), and the backup layer keeps the team safe.  (Widening such
a group to its whole connected component of rows instead made the dense scenes'
slowest steps slower, README.)  A group's size is not bounded: where a whole crowd
is jammed (the paper's circle swaps, dense random scenes) it is the crowd, and the
step there is the centralised one (:attr:`DecentralizedResult.largest_group`).
Rows between touching robots only (a tighter rule) left more robots short of their
goals, with more infeasible group QPs (README).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from aasoatt_env.model.geometry import pair_components
from aasoatt_env.safety.centralized import solve_rows
from aasoatt_env.safety.problem import box_least_squares
from aasoatt_env.safety.rows import Rows
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers.local import RELAX_TOL, solve_local_qps
from aasoatt_env.safety.stages import Answer, StepInput, Warm

__all__ = ["GROUP_ONE_CHANGE_ITER", "SPLITS", "Decentralized", "DecentralizedResult", "SplitRows",
           "decentralized_step", "negotiation_rows", "split_rows"]

SPLITS: tuple[str, ...] = ("reciprocal", "authority")
"""Ways of sharing a pair row (module docstring)."""
GROUP_ONE_CHANGE_ITER: int = 200
"""The warm active set's one-change budget on the negotiation groups' QPs (the centralised filter's is
:data:`~aasoatt_env.safety.solvers.active_set.ONE_CHANGE_ITER`).  A group's rows and members change from
step to step, so its warm start is often a dozen or more rows off the optimum, one change per iteration;
with the smaller budget such a step went on to ``ldp``, several times slower on a group of 80 robots."""


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
    """``(N,)``: the robot answered alone and its own QP was infeasible (answered with its least-violation
    point); a robot in a negotiation group is False here (the group's status is ``group_status``)."""
    n_relaxed: int
    """Robots answered alone whose rows were loosened (``infeasible.sum()``)."""
    slack: float
    """Largest violation of a half-row of those robots by ``du`` [eqn.8 units]; 0 when every lone robot's
    QP was feasible (a relaxed group's violation is not in it: the filter measures the pair rows then)."""
    iterations: int
    """Active-set iterations: the local solver's (largest over the robots), or the groups' solver's where
    that is larger."""
    n_enumerated: int
    """Robots the local solver answered by exact enumeration."""
    grouped: np.ndarray
    """``(N,)``: the robot's answer is its negotiation group's (module docstring), not its own QP's."""
    n_groups: int
    """Negotiation groups solved (0 without ``whole`` rows)."""
    largest_group: int
    """Robots in the largest of them (0 without)."""
    group_status: str
    """The groups' QP status (``"solved"``, ``"relaxed"`` or ``"failed"``; ``"solved"`` without groups)."""


def negotiation_rows(triggered: np.ndarray, p: np.ndarray, radius: np.ndarray, ri: np.ndarray, rj: np.ndarray,
                     gap: float) -> np.ndarray:
    """The rows the negotiation groups solve whole (module docstring): every robot row between two negotiating robots.

    A robot negotiates when the deadlock trigger flags it or it touches a robot the trigger flags;
    two robots touch when they share a row and their gap (distance less the two radii) is below
    ``gap`` (a barrier that drops the rows of receding pairs, ``gated_distance``, drops them here too).

    Parameters
    ----------
    triggered : numpy.ndarray
        ``(N,)`` bool: the robots the deadlock trigger flags at this step.
    p : numpy.ndarray
        Control-point positions ``(N, 2)``.
    radius : numpy.ndarray
        Robot radii ``(N,)``.
    ri, rj : numpy.ndarray
        Robots of each row ``(M,)``; ``rj = -1`` for obstacle rows (never whole: an obstacle row is its robot's).
    gap : float
        Touching gap [m].

    Returns
    -------
    numpy.ndarray
        ``(M,)`` bool.
    """
    whole = np.zeros(ri.shape[0], dtype=bool)
    if ri.shape[0] == 0 or not triggered.any():
        return whole
    rob = np.flatnonzero(rj >= 0)
    a, b = ri[rob], rj[rob]
    d = p[a] - p[b]
    touch = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) - (radius[a] + radius[b]) < gap
    member = np.array(triggered, dtype=bool, copy=True)
    member[b[touch & triggered[a]]] = True
    member[a[touch & triggered[b]]] = True
    whole[rob] = member[a] & member[b]
    return whole


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
    whole: np.ndarray | None = None,
    policy: SolverPolicy | None = None,
    x_warm: np.ndarray | None = None,
    z_warm: np.ndarray | None = None,
) -> DecentralizedResult:
    """Every robot's own QP over its half-rows, solved exactly for all robots at once; negotiation groups jointly.

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
    whole : numpy.ndarray, optional
        ``(M,)`` bool: robot-robot rows the negotiation groups solve whole, jointly (:func:`negotiation_rows`;
        module docstring).  None or none set: every robot alone.
    policy : SolverPolicy, optional
        The solver of the groups' QPs (the centralised filter's); required with ``whole``.
    x_warm, z_warm : numpy.ndarray, optional
        Where the groups' solver starts: a scaled point ``(N, 2)`` (``du / scale``; default each robot's
        box-clipped least squares) and a multiplier of each row ``(M,)`` in the units of
        :attr:`DecentralizedResult.z` (default none active; a half-row starts at its row's).  The
        previous step's answer makes the warm active set answer most steps; the answer is the QP's
        optimum either way.

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
    slack = _half_slack(sp, du, infeasible)
    du = np.minimum(np.maximum(du, lo), hi)
    grouped = np.zeros(n, dtype=bool)
    joint = None
    if whole is not None:
        whole = whole & (rj >= 0)  # (an obstacle row is its robot's: never whole)
    if whole is not None and whole.any():
        if policy is None:
            raise ValueError("policy: the negotiation groups' solver is required with whole rows")
        if du0 is None:
            du0 = box_least_squares(A, target, lo, hi, compiled=compiled)
        x0 = du0 / scale[:, None] if x_warm is None else x_warm
        joint, grouped, group_ans, n_groups, largest = _groups(A, target, lo, hi, scale, x0, z_warm, ri, rj, Gi, Gj,
                                                               rhs, sp, whole, policy, compiled)
        lam = np.where(grouped[sp.owner], 0.0, lam)  # the grouped robots' own QPs are not what they apply
        if (infeasible & grouped).any():
            infeasible &= ~grouped
            slack = _half_slack(sp, sol.x, infeasible)
        du[grouped] = group_ans.du
    n_relaxed = int(infeasible.sum())
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
    status, iterations = "solved", sol.iterations
    if joint is None:
        n_groups = largest = 0
    else:  # the groups' multipliers: a whole row's on both of its sides, a kept half's on its side
        k = joint.shape[0]
        eta_half[joint, 0] = eta_half[joint, 1] = group_ans.eta[:k]
        z_half[joint, 0] = z_half[joint, 1] = group_ans.z[:k]
        kept = group_ans.kept
        row, side = sp.row_side(kept)
        eta_half[row, side] = group_ans.eta[k:]
        z_half[row, side] = group_ans.z[k:]
        status, iterations = group_ans.status, max(iterations, group_ans.iterations)
    return DecentralizedResult(
        du=du, eta=np.maximum(eta_half[:, 0], eta_half[:, 1]), eta_half=eta_half,
        z=np.maximum(z_half[:, 0], z_half[:, 1]), z_half=z_half, infeasible=infeasible, n_relaxed=n_relaxed,
        slack=slack, iterations=iterations, n_enumerated=sol.n_enumerated, grouped=grouped, n_groups=n_groups,
        largest_group=largest, group_status=status,
    )


def _half_slack(sp: SplitRows, du: np.ndarray, infeasible: np.ndarray) -> float:
    """Largest violation of a half-row of the relaxed robots by their (unclipped) answers; 0 without any."""
    if not infeasible.any():
        return 0.0
    hr = np.flatnonzero(infeasible[sp.owner])
    o = sp.owner[hr]
    res = sp.G[hr, 0] * du[o, 0] + sp.G[hr, 1] * du[o, 1] - sp.h[hr]
    return float(max(0.0, res.max(initial=0.0)))


class _GroupAnswer(NamedTuple):
    du: np.ndarray
    eta: np.ndarray
    z: np.ndarray
    kept: np.ndarray
    status: str
    iterations: int


def _groups(A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray, scale: np.ndarray, x0: np.ndarray,
            z0: np.ndarray | None, ri: np.ndarray, rj: np.ndarray, Gi: np.ndarray, Gj: np.ndarray, rhs: np.ndarray,
            sp: SplitRows, whole: np.ndarray, policy: SolverPolicy,
            compiled: bool) -> tuple[np.ndarray, np.ndarray, _GroupAnswer, int, int]:
    """The negotiation groups' QP: the whole rows (robot rows only), and the grouped robots' halves of the others.

    Returns the whole rows (indices into the rows), the robots answered by a group (those in a whole
    row), the answer (its ``du`` in the order of those robots; multipliers of the whole rows, then of
    the kept halves ``kept``, indices into ``sp``), the number of groups and the largest one's size.
    """
    n, m = A.shape[0], ri.shape[0]
    joint = np.flatnonzero(whole)
    grouped = np.zeros(n, dtype=bool)
    grouped[ri[joint]] = True
    grouped[rj[joint]] = True
    # a grouped robot's halves of the rows it does not share whole (obstacle rows: whole, its own)
    side_i = grouped[ri] & ~whole
    side_j = grouped[sp.owner[m:]] & ~whole[sp.rr]
    kept = np.concatenate((np.flatnonzero(side_i), m + np.flatnonzero(side_j)))
    sub = np.flatnonzero(grouped)
    remap = np.full(n, -1, dtype=np.intp)
    remap[sub] = np.arange(sub.size)
    k = kept.shape[0]
    g_ri = np.concatenate((remap[ri[joint]], remap[sp.owner[kept]]))
    g_rj = np.concatenate((remap[rj[joint]], np.full(k, -1, dtype=np.intp)))
    g_Gi = np.concatenate((Gi[joint], sp.G[kept]))
    g_Gj = np.concatenate((Gj[joint], np.zeros((k, 2))))
    g_rhs = np.concatenate((rhs[joint], sp.h[kept]))
    if z0 is None:
        g_z = np.zeros(g_rhs.shape[0])
    else:  # (a kept half starts at its row's multiplier)
        g_z = np.concatenate((z0[joint], z0[sp.row_side(kept)[0]]))
    g_rows = Rows(g_ri, g_rj, g_Gi, g_Gj, g_rhs, _NO_PAIRS, _NO_KEYS, np.inf, np.inf)
    du, _, z, eta, sol, _ = solve_rows(policy, A[sub], target[sub], lo[sub], hi[sub], scale[sub], g_rows,
                                       Warm(np.ascontiguousarray(x0[sub]), g_z), compiled=compiled)
    status, iterations = ("solved", 0) if sol is None else (sol.status, sol.iterations)
    label = pair_components(sub.size, g_ri[: joint.shape[0]], g_rj[: joint.shape[0]], compiled=compiled)
    sizes = np.bincount(label, minlength=sub.size)
    return joint, grouped, _GroupAnswer(du, eta, z, kept, status, iterations), \
        int(np.count_nonzero(sizes >= 2)), int(sizes.max(initial=0))


_NO_PAIRS = np.empty((0, 2), dtype=np.intp)
_NO_KEYS = np.empty(0, dtype=np.int64)


@dataclass(frozen=True)
class Decentralized:
    """The decentralised QP stage: ``stage(step, rows, target, triggered, warm) -> Answer`` (module docstring).

    ``target`` is each robot's own: the filter saturates the nominal to the bounds before it.
    """

    policy: SolverPolicy
    negotiate: bool
    negotiate_gap: float
    eta_tol: float
    compiled: bool

    def __call__(self, s: StepInput, rows: Rows, target: np.ndarray, triggered: np.ndarray, warm: Warm) -> Answer:
        """Every robot's own QP, and the negotiation groups' joint ones."""
        n = target.shape[0]
        whole = (negotiation_rows(triggered, s.p, s.team.radius, rows.ri, rows.rj, self.negotiate_gap)
                 if self.negotiate else None)
        grouping = whole is not None and warm.x is not None and bool(whole.any())
        ans = decentralized_step(s.A, target, s.lo, s.hi, rows.ri, rows.rj, rows.Gi, rows.Gj, rows.rhs,
                                 s.team.max_point_accel, scale=s.scale, compiled=self.compiled, whole=whole,
                                 policy=self.policy, x_warm=warm.x if grouping else None,
                                 z_warm=warm.z if grouping else None)
        status = max("relaxed" if ans.n_relaxed else "solved", ans.group_status, key=_SEVERITY.index)
        n_grouped = int(ans.grouped.sum())
        message = f"decentralized: {n - n_grouped} local QPs"
        if ans.n_relaxed:
            message += f", {ans.n_relaxed} infeasible (relaxed)"
        if ans.n_groups:
            message += (f", {ans.n_groups} negotiation group(s) of {n_grouped} robots (largest {ans.largest_group})"
                        + ("" if ans.group_status == "solved" else f": {ans.group_status}"))
        avoiding = np.zeros(n, dtype=bool)  # a robot avoids where its own half of a row binds
        avoiding[rows.ri[ans.z_half[:, 0] > self.eta_tol]] = True
        avoiding[rows.rj[(ans.z_half[:, 1] > self.eta_tol) & (rows.rj >= 0)]] = True
        slack = 0.0
        if status != "solved" or (ans.grouped.any() and not self.policy.exact):
            slack = float(max(0.0, np.max(rows.values(ans.du) - rows.rhs, initial=0.0)))
        return Answer(ans.du.copy(), ans.du / s.scale[:, None], ans.z, ans.eta, avoiding, status, message,
                      ans.iterations, rows.m, slack)


_SEVERITY = ("solved", "relaxed", "failed")
