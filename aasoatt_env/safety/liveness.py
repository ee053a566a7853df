"""The ``yield`` deadlock strategy: eqn.13 plus right of way by priority, the yielder retracing its own trail.

It changes the QP's target only (the barrier rows, hence safety, stay the filter's); its rules (numbered here as
there), lengths and reasons: ``docs/liveness.md``.  Every decision is a function of the step's state, the pairs in
sensing range and this memory (no clock, no randomness), so the decentralised filter runs it unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from aasoatt_env.safety.detour import ROUTE_POINTS, plan_route

if TYPE_CHECKING:  # pragma: no cover
    from aasoatt_env.safety.deadlock import TargetContext

__all__ = ["CONTACT_GAP", "ESCAPE_TIME", "HOLD_TIME", "KEEP_GAP", "LOOKAHEAD", "PUSH_GAP", "REFERENCE_RADIUS",
           "ROUTE_SEEN", "STALL_DISTANCE", "STALL_ERROR", "STALL_TIME", "TRAIL_STEP", "YieldMemory", "yield_target"]

REFERENCE_RADIUS: float = 0.48
"""[m] The lengths below are for a robot of this radius (the paper's); each robot's scale with its radius."""
STALL_TIME: float = 2.0  #: [s] without leaving a disc of :data:`STALL_DISTANCE`: stalled
STALL_DISTANCE: float = 0.1  #: [m]
STALL_ERROR: float = 0.5  #: [m] a robot closer than this to its reference point is tracking, not stalled
PUSH_GAP: float = 2.0  #: [m] surface gap under which an oncoming robot ahead blocks
CONTACT_GAP: float = 0.3  #: [m] surface gap under which an obstacle, or a robot done at its goal, ahead blocks
KEEP_GAP: float = 2.0  #: [m] a yielder keeps yielding while its pusher is this close
HOLD_TIME: float = 5.0  #: [s] a yielder keeps yielding after its last push
ESCAPE_TIME: float = 6.0  #: [s] a robot stalled at an obstacle slides along it this long
TRAIL_STEP: float = 0.25  #: [m] spacing of the trail's points
LOOKAHEAD: float = 0.6  #: [m] a yielder drops the trail points closer than this
ROUTE_SEEN: int = 5  #: route points ahead (ROUTE_STEP apart) a robot on a detour looks for the farthest in sight
TRAIL_POINTS: int = 256  #: points kept per robot (the oldest are dropped)
_COS_AHEAD = 0.5  # cos(60 deg)


@dataclass
class YieldMemory:
    """What the ``yield`` rule remembers per robot between steps."""

    anchor: np.ndarray  #: ``(N, 2)`` where the stall clock started
    still: np.ndarray  #: ``(N,)`` steps spent within STALL_DISTANCE of ``anchor``
    rank: np.ndarray  #: ``(N,)`` the inherited priority of a yielder (``inf``: not yielding)
    hold: np.ndarray  #: ``(N,)`` steps of yielding left
    away: np.ndarray  #: ``(N, 2)`` unit vector from the last pusher toward the yielder
    trail: np.ndarray  #: ``(N, TRAIL_POINTS, 2)``
    count: np.ndarray  #: ``(N,)`` trail points in use
    cursor: np.ndarray  #: ``(N,)`` where on its trail a robot is (``count``: at its end, tracking its reference)
    escape: np.ndarray  #: ``(N,)`` steps of following obstacles left
    slide: np.ndarray  #: ``(N, 2)`` the direction it follows them in
    hand: np.ndarray  #: ``(N,)`` +1: obstacles on its left, -1: on its right
    tries: np.ndarray  #: ``(N,)`` follows since the robot last tracked its reference closely
    aside: np.ndarray  #: ``(N,)`` a yielder pushed while done at its goal: it steps aside instead of back
    spot: np.ndarray  #: ``(N, 2)`` where such a yielder steps to (off its pusher's line of travel)
    hit: np.ndarray  #: ``(N,)`` distance to its reference point where a robot began to follow obstacles
    route: np.ndarray  #: ``(N, ROUTE_POINTS, 2)`` a detour's points (rule 5b)
    stop: np.ndarray  #: ``(N,)`` route points in use
    leg: np.ndarray  #: ``(N,)`` the route point tracked (``stop``: none, tracking its reference)

    @classmethod
    def empty(cls, p: np.ndarray) -> YieldMemory:
        """No history: the stall clocks start now, no trail, nobody yielding."""
        n = p.shape[0]
        return cls(p.copy(), np.zeros(n, np.int64), np.full(n, np.inf), np.zeros(n, np.int64), np.zeros((n, 2)),
                   np.zeros((n, TRAIL_POINTS, 2)), np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, np.int64),
                   np.zeros((n, 2)), np.zeros(n), np.zeros(n, np.int64), np.zeros(n, dtype=bool), np.zeros((n, 2)),
                   np.zeros(n), np.zeros((n, ROUTE_POINTS, 2)), np.zeros(n, np.int64), np.zeros(n, np.int64))

    def forget(self, rows: np.ndarray) -> None:
        """Start robots ``rows`` afresh (their team starts an episode; the stall clock restarts at the next step)."""
        self.anchor[rows], self.still[rows], self.rank[rows] = np.nan, 0, np.inf
        self.hold[rows], self.count[rows], self.cursor[rows], self.escape[rows], self.tries[rows] = 0, 0, 0, 0, 0
        self.aside[rows], self.stop[rows], self.leg[rows] = False, 0, 0


def _unit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    norm = np.sqrt(x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1])
    return x / np.maximum(norm, 1e-12)[:, None], norm


def _record(m: YieldMemory, p: np.ndarray, yielding: np.ndarray, scale: np.ndarray) -> None:
    """Append ``p`` to the trail of robots on it (cursor at its end, not yielding) that moved TRAIL_STEP from it."""
    rows = np.arange(p.shape[0])
    last = m.trail[rows, np.maximum(m.count - 1, 0)]
    rec = ~yielding & (m.cursor == m.count) & ((m.count == 0) | (_unit(p - last)[1] >= TRAIL_STEP * scale))
    full = rec & (m.count == TRAIL_POINTS)
    if full.any():
        m.trail[full] = np.roll(m.trail[full], -1, axis=1)
        m.count[full] -= 1
        m.cursor[full] -= 1
    m.trail[rows[rec], m.count[rec]] = p[rec]
    m.count[rec] += 1
    m.cursor[rec] = m.count[rec]


def _robot_pairs(c: TargetContext) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robot pairs in both orders ``(i, j)``, the unit vectors from ``i`` to ``j`` and the surface gaps."""
    robots = c.robot_pairs
    i, j = np.concatenate((robots[:, 0], robots[:, 1])), np.concatenate((robots[:, 1], robots[:, 0]))
    u, dist = _unit(c.p[j] - c.p[i])
    return i, j, u, dist - c.radius[i] - c.radius[j]


def _push(m: YieldMemory, c: TargetContext, want: np.ndarray, stalled: np.ndarray, done: np.ndarray,
          home: np.ndarray, hold_steps: int) -> np.ndarray:
    """Rules 2 and 3: who yields, with which priority, away from whom; the robots crowded (rule 5 leaves them be).

    Crowded: pushing, or with a robot ahead within twice CONTACT_GAP in the lane they sweep going their way.
    """
    n = want.shape[0]
    prio = np.arange(n) + n * done
    yielding = m.hold > 0
    eff = np.where(yielding, np.minimum(m.rank, prio), prio)
    i, j, u, gap = _robot_pairs(c)
    pushed_rank = np.full(n, np.inf)
    ahead = np.einsum("ij,ij->i", u, want[i])
    facing = np.einsum("ij,ij->i", want[i], want[j])
    si = c.radius[i] / REFERENCE_RADIUS
    blocks = ((facing < 0.0) & (gap < PUSH_GAP * si)) | (done[j] & (gap < CONTACT_GAP * si))
    across = np.abs(u[:, 0] * want[i][:, 1] - u[:, 1] * want[i][:, 0]) * (gap + c.radius[i] + c.radius[j])
    in_way = across < c.radius[i] + c.radius[j]  # (j overlaps the lane i sweeps going its way)
    contact = ~home[i] & home[j] & in_way & (gap < CONTACT_GAP * si)  # (a robot home in the way, whoever comes)
    new = (ahead > _COS_AHEAD) & ~m.aside[i] & (((stalled[i] | yielding[i]) & blocks) | contact)
    keep = (gap < KEEP_GAP * si) & (ahead > 0.0) & yielding[j] & (eff[i] <= m.rank[j])
    # its own pusher keeps a yielder yielding while obstacles leave it no room to step aside (a passage)
    boxed = keep & ~yielding[i] & (eff[i] == m.rank[j])
    if boxed.any():
        q = np.flatnonzero(boxed)
        boxed[q] = _side_spots(c, want[i[q]], i[q], j[q])[1].all(axis=0)
    hit = ((eff[i] < eff[j]) & (new | keep)) | boxed
    np.minimum.at(pushed_rank, j[hit], eff[i][hit])
    strongest = hit & (eff[i] == pushed_rank[j])
    m.away[j[strongest]] = u[strongest]
    pushed = np.isfinite(pushed_rank)
    _aside(m, c, want, i[strongest], j[strongest], home, yielding)
    m.rank = np.where(pushed, np.minimum(np.where(yielding, m.rank, np.inf), pushed_rank), m.rank)
    m.hold = np.where(pushed, hold_steps, np.maximum(m.hold - 1, 0))
    m.rank[m.hold == 0] = np.inf
    m.aside &= m.hold > 0
    crowded = np.zeros(n, dtype=bool)  # pushing, or behind a robot, one in its lane
    crowded[i[in_way & (hit | ((ahead > _COS_AHEAD) & (gap < 2.0 * CONTACT_GAP * si)))]] = True
    return crowded


def _side_spots(c: TargetContext, lane: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(spots (2, P, 2), taken (2, P))``: where ``j[k]`` steps off ``i[k]``'s line of travel ``lane[k]``.

    Two radii and CONTACT_GAP off that line, on ``j``'s side first (on the line: its right), then on the other;
    ``taken``: an obstacle takes the spot.
    """
    left = np.stack((-lane[:, 1], lane[:, 0]), axis=1)
    off = np.einsum("ij,ij->i", c.p[j] - c.p[i], left)  # j's offset from i's line, + on its left
    clear = c.radius[i] + c.radius[j] + CONTACT_GAP * c.radius[j] / REFERENCE_RADIUS
    side = np.where(off > 0.0, 1.0, -1.0)
    spots = np.stack([c.p[j] + (s * clear - off)[:, None] * left for s in (side, -side)])
    taken = np.zeros((2, j.shape[0]), dtype=bool)
    if c.obstacles is not None and c.obstacle_pairs.shape[0]:
        r, o = c.obstacle_pairs[:, 0], c.obstacle_pairs[:, 1]
        k, q = np.nonzero(j[:, None] == r[None, :])  # (the few pushed robots' obstacle pairs)
        reach = c.radius[j[k]] + c.obstacles[1][o[q]]
        for s in range(2):
            taken[s, k[_unit(spots[s, k] - c.obstacles[0][o[q]])[1] < reach]] = True
    return spots, taken


def _aside(m: YieldMemory, c: TargetContext, want: np.ndarray, i: np.ndarray, j: np.ndarray, home: np.ndarray,
           yielding: np.ndarray) -> None:
    """Rule 3b: robot ``j`` home (or stepping aside), pushed by ``i``, steps off ``i``'s line (:func:`_side_spots`)."""
    spots, taken = _side_spots(c, want[i], i, j)
    free = ~taken[0] | ~taken[1]
    keep = (home[j] & free) | (m.aside[j] & yielding[j])
    m.spot[j[keep & free]] = np.where(taken[0][:, None], spots[1], spots[0])[keep & free]
    m.aside[j] = keep


def _trail_point(m: YieldMemory, p: np.ndarray, p_d: np.ndarray, yielding: np.ndarray, scale: np.ndarray
                 ) -> np.ndarray:
    """Rule 4: the point each robot tracks: a yielder back along its trail, then forward again to where it began."""
    rows, ahead = np.arange(p.shape[0]), LOOKAHEAD * scale
    for _ in range(2):  # (a point or two per step: the points are TRAIL_STEP apart)
        back, fwd = np.maximum(m.cursor - 1, 0), np.minimum(m.cursor, TRAIL_POINTS - 1)
        m.cursor -= yielding & (m.cursor > 0) & (_unit(p - m.trail[rows, back])[1] < ahead)
        m.cursor += ~yielding & (m.cursor < m.count) & (_unit(p - m.trail[rows, fwd])[1] < ahead)
    back, fwd = np.maximum(m.cursor - 1, 0), np.minimum(m.cursor, TRAIL_POINTS - 1)
    side = p + ahead[:, None] * np.stack((m.away[:, 1], -m.away[:, 0]), axis=1)
    trail = m.trail[rows, back]
    back_ok = yielding & (m.cursor > 0) & (np.einsum("ij,ij->i", trail - p, m.away) >= 0.0)  # (not toward the push)
    out = np.where(back_ok[:, None], trail, side)
    out = np.where((~yielding & (m.cursor < m.count))[:, None], m.trail[rows, fwd], out)
    return np.where((~yielding & (m.cursor == m.count))[:, None], p_d, out)


def _escape(m: YieldMemory, c: TargetContext, want: np.ndarray, stuck: np.ndarray, steps: int,
            far: np.ndarray) -> np.ndarray:
    """Rule 5: a robot stalled at an obstacle, pushing nobody, follows the boundary (``far``: Bug2's distance)."""
    if c.obstacles is not None and c.obstacle_pairs.shape[0]:
        i, k = c.obstacle_pairs[:, 0], c.obstacle_pairs[:, 1]
        u, dist = _unit(c.obstacles[0][k] - c.p[i])
        gap = dist - c.radius[i] - c.obstacles[1][k]
        near = np.full(want.shape[0], np.inf)
        np.minimum.at(near, i, gap)
        nearest, right = gap == near[i], np.stack((u[:, 1], -u[:, 0]), axis=1)
        ahead = np.einsum("ij,ij->i", u, want[i])
        touch = gap < CONTACT_GAP * c.radius[i] / REFERENCE_RADIUS
        score = np.where(stuck[i] & (m.escape[i] == 0) & touch & (ahead > 0.0), ahead, -np.inf)
        best = np.full(want.shape[0], -np.inf)
        np.maximum.at(best, i, score)
        first = np.isfinite(score) & (score == best[i])  # the obstacle most in the way among those in contact
        front = np.zeros(want.shape[0], dtype=bool)
        front[i[touch & (ahead > 0.0)]] = True
        m.escape[~front & (far < m.hit - STALL_ERROR * c.radius / REFERENCE_RADIUS)] = 0
        m.hit[i[first]] = far[i[first]]
        hand = np.where(np.einsum("ij,ij->i", right, want[i]) >= 0.0, 1.0, -1.0) * (1 - 2 * (m.tries[i] % 2))
        m.hand[i[first]] = hand[first]
        m.escape[i[first]] = steps << np.minimum(m.tries[i[first]], 3)
        _detour(m, c, np.unique(i[first]), want)
        m.tries[i[first]] += 1
        follow = (m.escape[i] > 0) & nearest
        m.slide[i[follow]] = _unit(m.hand[i[follow], None] * right[follow] + 0.3 * u[follow])[0]
        # an inner corner: another obstacle within CONTACT_GAP across that tangent; follow that one instead
        across = np.where((m.escape[i] > 0) & touch, np.einsum("ij,ij->i", u, m.slide[i]), -np.inf)
        most = np.full(want.shape[0], -np.inf)
        np.maximum.at(most, i, across)
        turn = (across > 0.3) & (across == most[i])
        m.slide[i[turn]] = _unit(m.hand[i[turn], None] * right[turn] + 0.3 * u[turn])[0]
    m.escape = np.maximum(m.escape - 1, 0)
    return m.escape > 0


def _detour(m: YieldMemory, c: TargetContext, starters: np.ndarray, want: np.ndarray) -> None:
    """Rule 5b: robots ``starters`` plan a route round the static obstacles they sense (robots: rule 3).

    A robot with a route follows it instead of the boundary, its stall clock and its trail's return dropped.
    """
    p_d = c.reference[0]  # type: ignore[index]
    for k in starters:  # (the few robots that begin to escape at this step)
        sensed = c.obstacle_pairs[c.obstacle_pairs[:, 0] == k, 1]
        pts = plan_route(c.p[k], p_d[k], float(c.radius[k]), c.obstacles[0][sensed], c.obstacles[1][sensed],
                         int(m.tries[k]), float(c.radius[k] / REFERENCE_RADIUS), want[k])
        if pts is None:
            continue
        m.route[k, :len(pts)], m.stop[k], m.leg[k] = pts, len(pts), 0
        m.escape[k], m.cursor[k], m.anchor[k], m.still[k] = 0, m.count[k], c.p[k], 0


def _route_point(m: YieldMemory, c: TargetContext, g: np.ndarray, scale: np.ndarray, yielding: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Rule 5b: the route point each robot on a detour tracks (``g`` for the others), and who is on one.

    Points within LOOKAHEAD are dropped; of the next ROUTE_SEEN the farthest in sight is tracked (no sensed obstacle
    or robot nearer its segment than to the robot; none: the first).  Yielding or returning, a robot leaves its route.
    """
    n, seen = c.p.shape[0], np.arange(ROUTE_SEEN)
    rows = np.arange(n)
    for _ in range(2):  # (a point or two per step: the points are ROUTE_STEP apart)
        m.leg += (m.leg < m.stop) & ~yielding & (m.cursor == m.count) & (
            _unit(c.p - m.route[rows, np.minimum(m.leg, ROUTE_POINTS - 1)])[1] < LOOKAHEAD * scale)
    on = (m.leg < m.stop) & ~yielding & (m.cursor == m.count)
    pts = m.route[rows[:, None], np.clip(np.minimum(m.leg[:, None] + seen, m.stop[:, None] - 1), 0, None)]
    hits = np.zeros((n, ROUTE_SEEN), np.int64)
    if on.any():
        i, j = _robot_pairs(c)[:2]
        r, centre, size = i, c.p[j], c.radius[j]
        if c.obstacles is not None and c.obstacle_pairs.shape[0]:
            o = c.obstacle_pairs[:, 1]
            r = np.concatenate((i, c.obstacle_pairs[:, 0]))
            centre, size = np.vstack((centre, c.obstacles[0][o])), np.concatenate((size, c.obstacles[1][o]))
        mine = on[r]
        r, centre, size = r[mine], centre[mine], size[mine]
        d, w = pts[r] - c.p[r][:, None], (centre - c.p[r])[:, None]  # (Q, S, 2), (Q, 1, 2)
        t = np.clip(np.sum(w * d, axis=2) / np.maximum(np.sum(d * d, axis=2), 1e-12), 0.0, 1.0)
        closest = np.sqrt(np.sum((w - t[:, :, None] * d) ** 2, axis=2))
        now = np.sqrt(np.sum(w * w, axis=2))
        np.add.at(hits, r, (closest < (size + c.radius[r])[:, None]) & (closest < now - 1e-9))
    clear = np.cumprod(hits == 0, axis=1).astype(bool)
    far = np.maximum(ROUTE_SEEN - 1 - np.argmax(clear[:, ::-1], axis=1), 0) * clear.any(axis=1)
    return np.where(on[:, None], pts[rows, far], g), on


def yield_target(target: np.ndarray, zeta: np.ndarray, Q: np.ndarray, c: TargetContext) -> np.ndarray:
    """The ``yield`` strategy's target (``docs/liveness.md``'s rules); updates ``c.memory.liveness``."""
    p_d, v_d = c.reference  # type: ignore[misc]
    n = c.p.shape[0]
    m = c.memory.liveness if c.memory is not None else None  # type: ignore[union-attr]
    if m is None or m.anchor.shape[0] != n:
        m = YieldMemory.empty(c.p)
        if c.memory is not None:
            c.memory.liveness = m
    steps = lambda seconds: max(1, int(round(seconds / c.cfg.dt)))  # noqa: E731
    scale = c.radius / REFERENCE_RADIUS
    left = ~(_unit(c.p - m.anchor)[1] <= STALL_DISTANCE * scale)  # (NaN anchor: forgotten)
    m.anchor[left], m.still = c.p[left], np.where(left, 0, m.still + 1)
    done = (_unit(c.p - p_d)[1] <= c.cfg.goal_tol) & (_unit(v_d)[1] < c.cfg.low_speed)
    tracking = _unit(c.p - p_d)[1] <= STALL_ERROR * scale
    home = tracking & (_unit(v_d)[1] < c.cfg.low_speed)  # (near its goal, its reference at rest there)
    stalled = (m.still >= steps(STALL_TIME)) & ~tracking
    m.tries[tracking] = 0
    yielding = m.hold > 0
    _record(m, c.p, yielding, scale)
    want = _unit(_route_point(m, c, _trail_point(m, c.p, p_d, yielding, scale), scale, yielding)[0] - c.p)[0]
    crowded = _push(m, c, want, stalled, done, home, steps(HOLD_TIME))
    m.stop[stalled & ~crowded] = 0  # (stalled on a detour, pushing nobody: rule 5 may plan another)
    yielding = m.hold > 0
    g = _trail_point(m, c.p, p_d, yielding, scale)
    to_spot, gap = _unit(m.spot - c.p)
    g = np.where((m.aside & yielding)[:, None], c.p + to_spot * np.minimum(gap, LOOKAHEAD * scale)[:, None], g)
    sliding = _escape(m, c, want, stalled & ~yielding & ~crowded, steps(ESCAPE_TIME), _unit(c.p - p_d)[1])
    sliding &= ~yielding
    g, routed = _route_point(m, c, g, scale, yielding)
    g = np.where(sliding[:, None], c.p + (LOOKAHEAD * scale)[:, None] * m.slide, g)
    off = yielding | (m.cursor < m.count) | sliding | routed
    g_v = np.where(off[:, None], 0.0, v_d)
    toward = -(c.k3 + c.k4) * c.v - c.k3 * c.k4 * (c.p - g) - c.adot  # the tracking law toward g at rest there
    out = np.where(off[:, None], toward, target)
    e = c.v - g_v + c.k3 * (c.p - g)
    return out - zeta[:, None] * np.einsum("ij,nj->ni", Q, e)
