"""The decentralised QP stage: every robot solves its own 2-variable QP over its share of each pair row.

A pair row is shared by authority ``a`` (``Team.max_point_accel``), ``s_i = a_i / (a_i + a_j)``: ``"reciprocal"``
(default) splits the correction ``Gi du0_i + Gj du0_j - rhs`` of the closed-form answers ``du0``, ``"authority"`` the
bound (``s_i rhs``); an obstacle row is its robot's.  An infeasible robot gets its least-violation answer
(``"relaxed"``).  Robots the trigger flags, and those they touch, solve the rows among them whole (negotiation groups).
Why: ``docs/design.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from aasoatt_env.model.geometry import pair_components
from aasoatt_env.safety.centralized import WARM_MESSAGES, TeamAnswer, avoiding_robots, compiled_settings, solve_team
from aasoatt_env.safety.problem import box_least_squares
from aasoatt_env.safety.rows import Rows
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers.local import RELAX_TOL, solve_local_qps
from aasoatt_env.safety.solvers.policy import SEVERITY
from aasoatt_env.safety.stages import GROUPED, RELAXED, Answer, StepInput, Warm

__all__ = ["GROUP_ONE_CHANGE_ITER", "SPLITS", "Decentralized", "DecentralizedResult", "SplitRows",
           "decentralized_step", "negotiation_rows", "solve_groups", "split_rows"]

SPLITS: tuple[str, ...] = ("reciprocal", "authority")  #: ways of sharing a pair row (module docstring)
#: the warm active set's one-change budget on the negotiation groups' QPs (their warm starts are often far off)
GROUP_ONE_CHANGE_ITER: int = 200


class SplitRows(NamedTuple):
    """The half-rows ``G du_owner <= h``: every row's ``i`` half (an obstacle row whole), then the ``j`` halves."""

    owner: np.ndarray
    G: np.ndarray  #: ``(., 2)``
    h: np.ndarray
    rr: np.ndarray  #: the robot-robot rows, in the order of the ``j`` halves

    def row_side(self, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pair row and side (0: ``i`` half or obstacle, 1: ``j`` half) of half-rows ``half``."""
        m = self.owner.shape[0] - self.rr.shape[0]
        jside = half >= m
        row = half.copy()
        row[jside] = self.rr[half[jside] - m]
        return row, jside.astype(np.intp)


def split_rows(ri: np.ndarray, rj: np.ndarray, Gi: np.ndarray, Gj: np.ndarray, rhs: np.ndarray, authority: np.ndarray,
               du_nominal: np.ndarray | None = None) -> SplitRows:
    """Split every pair row ``(M,)`` between its robots by ``authority`` ``(N,)`` (module docstring).

    ``rj = -1``: an obstacle row (``Gj`` ignored); equal shares where both authorities are 0; ``du_nominal`` ``(N, 2)``:
    split reciprocally around it (None: ``"authority"``).
    """
    ri, rj = np.asarray(ri, np.intp), np.asarray(rj, np.intp)
    rr = np.flatnonzero(rj >= 0)
    rjr, Gjr = rj[rr], Gj[rr]
    a_i, a_j = authority[ri[rr]], authority[rjr]
    tot = a_i + a_j
    pos = tot > 0
    share_i = np.where(pos, a_i / np.where(pos, tot, 1.0), 0.5)
    if du_nominal is None:  # rhs split
        base_i, base_j, need = np.zeros(ri.shape[0]), np.zeros(rr.shape[0]), -rhs
    else:  # the correction of the nominal pair split: h_i = Gi du0_i - v share_i
        base_i = Gi[:, 0] * du_nominal[ri, 0] + Gi[:, 1] * du_nominal[ri, 1]
        base_j = Gjr[:, 0] * du_nominal[rjr, 0] + Gjr[:, 1] * du_nominal[rjr, 1]
        need = base_i - rhs
        need[rr] += base_j
    need_r = need[rr]
    h_i = base_i - need  # obstacle rows whole
    h_i[rr] = base_i[rr] - need_r * share_i
    return SplitRows(owner=np.concatenate((ri, rjr)), G=np.concatenate((Gi, Gjr)),
                     h=np.concatenate((h_i, base_j - need_r * (1.0 - share_i))), rr=rr)


class DecentralizedResult(NamedTuple):
    """What :func:`decentralized_step` did; ``eta`` in eqn.8's units, ``z`` in the centralised filter's scaled ones."""

    du: np.ndarray  #: ``(N, 2)`` within the bounds
    eta: np.ndarray  #: ``(M,)`` the larger of each pair row's two halves' multipliers
    eta_half: np.ndarray  #: ``(M, 2)`` the halves' multipliers (column 1 is 0 on obstacle rows)
    z: np.ndarray  #: ``(M,)`` as ``eta``, the units that ``eta_tol`` reads
    z_half: np.ndarray  #: ``(M, 2)``
    infeasible: np.ndarray  #: ``(N,)`` its own QP was infeasible (its least-violation answer; False if grouped)
    n_relaxed: int
    slack: float  #: largest violation of a half-row of the relaxed robots (eqn.8 units)
    iterations: int  #: the local solver's (largest over the robots), or the groups' solver's where larger
    n_enumerated: int  #: robots the local solver answered by enumeration
    grouped: np.ndarray  #: ``(N,)`` the robot's answer is its negotiation group's
    n_groups: int
    largest_group: int  #: robots in the largest group
    group_status: str  #: ``"solved"`` without groups
    #: the groups' QP was answered by the closed form or the warm active set (True without groups)
    group_warm: bool = True
    #: ``(N,)`` grouped robots in a row their group's answer violates (an inconsistent group; None: no groups)
    group_loose: np.ndarray | None = None


def negotiation_rows(triggered: np.ndarray, p: np.ndarray, radius: np.ndarray, ri: np.ndarray, rj: np.ndarray,
                     gap: float) -> np.ndarray:
    """``(M,)`` bool: the robot rows between robots ``triggered`` or in a row with one at a gap below ``gap`` [m]."""
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


def decentralized_step(A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray, ri: np.ndarray,
                       rj: np.ndarray, Gi: np.ndarray, Gj: np.ndarray, rhs: np.ndarray, authority: np.ndarray, *,
                       split: str = "reciprocal", scale: np.ndarray | None = None, compiled: bool = False,
                       whole: np.ndarray | None = None, policy: SolverPolicy | None = None,
                       x_warm: np.ndarray | None = None, z_warm: np.ndarray | None = None,
                       try_compiled: bool = True) -> DecentralizedResult:
    """Every robot's own QP over its half-rows, exactly and all at once; negotiation groups jointly.

    ``target`` ``(N, 2)``: each robot's ``A du_nom``, its nominal within its (hard) bounds; ``scale`` ``(N,)`` of ``du``
    for ``z`` and the loosening (None: the largest bound); ``whole`` ``(M,)``: the rows the groups solve whole (needs
    ``policy``), from the scaled ``x_warm`` ``(N, 2)`` and ``z_warm`` ``(M,)``; ``try_compiled``: the groups' compiled
    solve first.
    """
    if split not in SPLITS:
        raise ValueError(f"split: got {split!r}, expected one of {list(SPLITS)}")
    if scale is None:
        big = np.maximum(np.abs(lo), np.abs(hi)).max(axis=1)
        scale = np.where(big > 0, big, 1.0)
    H, g = _objective(A, target)
    du0 = box_least_squares(A, target, lo, hi, compiled=compiled) if split == "reciprocal" else None
    sp = split_rows(ri, rj, Gi, Gj, rhs, authority, du0)
    sol = solve_local_qps(H, g, lo, hi, sp.owner, sp.G, sp.h, relax=True, relax_tol=RELAX_TOL * scale,
                          compiled=compiled)
    lam, infeasible = sol.lam, ~sol.feasible
    slack = _half_slack(sp, sol.x, infeasible)
    du = np.minimum(np.maximum(sol.x, lo), hi)
    grouped, joint, group_ans, kept, n_groups, largest = np.zeros(A.shape[0], dtype=bool), None, None, None, 0, 0
    loose = np.zeros_like(grouped)
    if whole is not None and (whole := whole & (rj >= 0)).any():  # (an obstacle row is never whole)
        if policy is None:
            raise ValueError("policy: the negotiation groups' solver is required with whole rows")
        if du0 is None:
            du0 = box_least_squares(A, target, lo, hi, compiled=compiled)
        x0 = du0 / scale[:, None] if x_warm is None else x_warm
        joint, grouped, group_ans, kept, n_groups, largest = _groups(A, target, lo, hi, scale, Warm(x0, z_warm,
                                                                     try_compiled), ri, rj, Gi, Gj, rhs, sp, whole,
                                                                     policy, compiled)
        lam = np.where(grouped[sp.owner], 0.0, lam)  # the grouped robots' own QPs are not what they apply
        if (infeasible & grouped).any():
            infeasible &= ~grouped
            slack = _half_slack(sp, sol.x, infeasible)
        du[grouped] = group_ans.du
        loose = _loose(du, ri, rj, Gi, Gj, rhs, joint, sp, kept, scale)
    eta_half, z_half = _half_multipliers(sp, lam, H, scale, rhs.shape[0])
    status, iterations = "solved", sol.iterations
    if joint is not None:  # the groups' multipliers: a whole row's on both of its sides, a kept half's on its side
        k = joint.shape[0]
        eta_half[joint, 0] = eta_half[joint, 1] = group_ans.eta[:k]
        z_half[joint, 0] = z_half[joint, 1] = group_ans.z[:k]
        row, side = sp.row_side(kept)
        eta_half[row, side] = group_ans.eta[k:]
        z_half[row, side] = group_ans.z[k:]
        status, iterations = group_ans.status, max(iterations, group_ans.iterations)
    eta, z = np.maximum(eta_half[:, 0], eta_half[:, 1]), np.maximum(z_half[:, 0], z_half[:, 1])
    return DecentralizedResult(du, eta, eta_half, z, z_half, infeasible, int(infeasible.sum()), slack, iterations,
                               sol.n_enumerated, grouped, n_groups, largest, status,
                               group_ans is None or group_ans.message in WARM_MESSAGES, loose)


def _loose(du: np.ndarray, ri: np.ndarray, rj: np.ndarray, Gi: np.ndarray, Gj: np.ndarray, rhs: np.ndarray,
           joint: np.ndarray, sp: SplitRows, kept: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``(N,)`` the grouped robots of a row their groups' answer ``du`` violates (an inconsistent group's).

    Over ``1e-9`` of the row's scale, as the torch filter's ``_negotiate``: both robots of a whole row, a kept half's
    owner.
    """
    a, b, o = ri[joint], rj[joint], sp.owner[kept]
    whole = Gi[joint, 0] * du[a, 0] + Gi[joint, 1] * du[a, 1] + (Gj[joint, 0] * du[b, 0] + Gj[joint, 1] * du[b, 1])
    half = sp.G[kept, 0] * du[o, 0] + sp.G[kept, 1] * du[o, 1] - sp.h[kept]
    out = np.zeros(du.shape[0], dtype=bool)
    over = whole - rhs[joint] > 1e-9 * np.hypot(Gi[joint, 0], Gi[joint, 1]) * np.maximum(scale[a], scale[b])
    out[a[over]] = out[b[over]] = True
    out[o[half > 1e-9 * np.hypot(sp.G[kept, 0], sp.G[kept, 1]) * scale[o]]] = True
    return out


def _objective(A: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each robot's ``|A du - t|^2 = 0.5 du' H du + g' du + const``: ``H = 2 A'A`` ``(N, 2, 2)``, ``g = -2 A't``."""
    a00, a01, a10, a11 = A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1]
    H = np.empty((A.shape[0], 2, 2))
    H[:, 0, 0] = 2.0 * (a00 * a00 + a10 * a10)
    H[:, 0, 1] = H[:, 1, 0] = 2.0 * (a00 * a01 + a10 * a11)
    H[:, 1, 1] = 2.0 * (a01 * a01 + a11 * a11)
    t0, t1 = target[:, 0], target[:, 1]
    return H, np.stack((-2.0 * (a00 * t0 + a10 * t1), -2.0 * (a01 * t0 + a11 * t1)), axis=1)


def _half_multipliers(sp: SplitRows, lam: np.ndarray, H: np.ndarray, scale: np.ndarray,
                      m: int) -> tuple[np.ndarray, np.ndarray]:
    """The half-rows' multipliers on the pair rows ``(M, 2)``: ``eta`` as given, ``z`` in the centralised units."""
    nz = np.flatnonzero(lam)
    row, side = sp.row_side(nz)
    o = sp.owner[nz]
    s_o = scale[o]
    sigma = s_o * s_o * np.maximum(np.maximum(np.abs(H[o, 0, 0]), np.abs(H[o, 1, 1])), np.abs(H[o, 0, 1]))
    Gn = sp.G[nz]
    eta_half, z_half = np.zeros((m, 2)), np.zeros((m, 2))
    eta_half[row, side] = lam[nz]
    z_half[row, side] = lam[nz] * np.sqrt(Gn[:, 0] ** 2 + Gn[:, 1] ** 2) * s_o / sigma
    return eta_half, z_half


def _half_slack(sp: SplitRows, du: np.ndarray, infeasible: np.ndarray) -> float:
    """Largest violation of a half-row of the relaxed robots by their (unclipped) answers; 0 without any."""
    if not infeasible.any():
        return 0.0
    hr = np.flatnonzero(infeasible[sp.owner])
    o = sp.owner[hr]
    res = sp.G[hr, 0] * du[o, 0] + sp.G[hr, 1] * du[o, 1] - sp.h[hr]
    return float(max(0.0, res.max(initial=0.0)))


def _groups(A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray, scale: np.ndarray, warm: Warm,
            ri: np.ndarray, rj: np.ndarray, Gi: np.ndarray, Gj: np.ndarray, rhs: np.ndarray,
            sp: SplitRows, whole: np.ndarray, policy: SolverPolicy,
            compiled: bool) -> tuple[np.ndarray, np.ndarray, TeamAnswer, np.ndarray, int, int]:
    """The negotiation groups' QP over the whole rows and the grouped robots' halves of the others.

    Returns the whole rows, the robots in them, the QP's answer (multipliers of the whole rows, then of the kept
    halves), the kept halves (indices into ``sp``), the number of groups, the largest's size.
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
    # (a kept half starts at its row's multiplier)
    z0 = warm.z
    g_z = None if z0 is None else np.concatenate((z0[joint], z0[sp.row_side(kept)[0]]))
    ans, n_groups, largest = solve_groups(A, target, lo, hi, scale, Warm(warm.x, g_z, warm.compiled), grouped,
                                          (ri[joint], rj[joint], Gi[joint], Gj[joint], rhs[joint]),
                                          (sp.owner[kept], sp.G[kept], sp.h[kept]), policy, compiled)
    return joint, grouped, ans, kept, n_groups, largest


def solve_groups(A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray, scale: np.ndarray, warm: Warm,
                 grouped: np.ndarray, joint: tuple[np.ndarray, ...], kept: tuple[np.ndarray, ...],
                 policy: SolverPolicy, compiled: bool, teams: np.ndarray | None = None) -> tuple[TeamAnswer, int, int]:
    """The ``grouped`` robots' joint QP over the whole rows ``joint`` and their half-rows ``kept``.

    ``joint = (ri, rj, Gi, Gj, rhs)``, ``kept = (owner, G, h)``; ``warm``: ``x`` of the team (scaled), ``z`` of
    ``joint`` then ``kept`` (None: 0); ``teams`` ``(N,)``: independent teams, in consecutive blocks (their QPs are
    solved in chunks of whole teams of about :data:`GROUP_CHUNK` grouped robots; None: one QP).  Returns the answer
    (the grouped robots', multipliers of ``joint`` then ``kept``), the number of groups and the largest's size.
    """
    sub = np.flatnonzero(grouped)
    remap = np.full(A.shape[0], -1, dtype=np.intp)
    remap[sub] = np.arange(sub.size)
    jri, jrj, jGi, jGj, jrhs = joint
    owner, G, h = kept
    k = owner.shape[0]
    g_ri = np.concatenate((remap[jri], remap[owner]))
    g_rj = np.concatenate((remap[jrj], np.full(k, -1, dtype=np.intp)))
    g_z = np.zeros(jri.shape[0] + k) if warm.z is None else warm.z
    g_rows = Rows(g_ri, g_rj, np.concatenate((jGi, G)), np.concatenate((jGj, np.zeros((k, 2)))),
                  np.concatenate((jrhs, h)), np.empty((0, 2), np.intp), np.empty(0, np.int64), np.inf, np.inf)
    label = pair_components(sub.size, g_ri[: jri.shape[0]], g_rj[: jri.shape[0]], compiled=compiled)
    sizes = np.bincount(label, minlength=sub.size)
    # a stack's teams in chunks of whole teams: each chunk's QP stays about one team's size, on the solvers' dense path
    chunk = np.zeros(sub.size, dtype=np.intp)
    if teams is not None and sub.size > GROUP_CHUNK:
        first = np.unique(teams[sub], return_index=True)[1]
        counts = np.diff(np.append(first, sub.size))
        chunk = np.repeat(np.cumsum(counts) // GROUP_CHUNK, counts)
    x_sub = np.ascontiguousarray(warm.x[sub])
    parts = []
    for c in range(int(chunk.max(initial=0)) + 1):
        robots, rows = np.flatnonzero(chunk == c), np.flatnonzero(chunk[g_ri] == c)
        if robots.size == 0:
            continue
        loc = np.full(sub.size, -1, dtype=np.intp)
        loc[robots] = np.arange(robots.size)
        rj_c = g_rows.rj[rows]
        rows_c = g_rows._replace(ri=loc[g_ri[rows]], rj=np.where(rj_c >= 0, loc[np.maximum(rj_c, 0)], -1),
                                 Gi=g_rows.Gi[rows], Gj=g_rows.Gj[rows], rhs=g_rows.rhs[rows])
        s = sub[robots]
        parts.append((robots, rows, solve_team(policy, A[s], target[s], lo[s], hi[s], scale[s], rows_c,
                                               Warm(x_sub[robots], g_z[rows], warm.compiled), decompose=True,
                                               compiled=compiled, settings=compiled_settings(policy, compiled))))
    return _joined(parts, sub.size, g_ri.shape[0]), int(np.count_nonzero(sizes >= 2)), int(sizes.max(initial=0))


GROUP_CHUNK: int = 64  #: grouped robots of a stack's teams solved in one QP (whole teams: a larger one alone)


def _joined(parts: list[tuple[np.ndarray, np.ndarray, TeamAnswer]], n: int, m: int) -> TeamAnswer:
    """One :class:`TeamAnswer` of independent chunks ``(robots, rows, answer)`` (the worst status and its message)."""
    if len(parts) == 1:
        return parts[0][2]
    du, x, z, eta = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(m), np.zeros(m)
    for robots, rows, a in parts:
        du[robots], x[robots], z[rows], eta[rows] = a.du, a.x, a.z, a.eta
    worst = max((a for _, _, a in parts), key=lambda a: SEVERITY.index(a.status))
    return TeamAnswer(du, x, z, eta, worst.status, worst.message, max(a.iterations for _, _, a in parts),
                      sum(a.n_qp for _, _, a in parts), all(a.exact for _, _, a in parts))


@dataclass(frozen=True)
class Decentralized:
    """The decentralised QP stage; ``target`` is each robot's own (its nominal saturated to its bounds)."""

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
                                 z_warm=warm.z if grouping else None, try_compiled=warm.compiled)
        status = max("relaxed" if ans.n_relaxed else "solved", ans.group_status, key=SEVERITY.index)
        n_grouped = int(ans.grouped.sum())
        message = f"decentralized: {n - n_grouped} local QPs"
        if ans.n_relaxed:
            message += f", {ans.n_relaxed} infeasible (relaxed)"
        if ans.n_groups:
            message += (f", {ans.n_groups} negotiation group(s) of {n_grouped} robots (largest {ans.largest_group})"
                        + ("" if ans.group_status == "solved" else f": {ans.group_status}"))
        binds = ans.z_half > self.eta_tol  # a robot avoids where its own half of a row binds
        avoiding = avoiding_robots(n, rows, binds[:, 0], binds[:, 1])
        checked = status != "solved" or (ans.grouped.any() and not self.policy.exact)
        slack = float(max(0.0, np.max(rows.values(ans.du) - rows.rhs, initial=0.0))) if checked else 0.0
        flags = np.where(ans.infeasible | ans.group_loose, RELAXED, 0) | np.where(ans.grouped, GROUPED, 0)
        return Answer(ans.du.copy(), ans.du / s.scale[:, None], ans.z, ans.eta, avoiding, status, message,
                      ans.iterations, rows.m, slack, ans.group_warm, flags)

