"""The safety filter: nominal wheel accelerations in, safe ones out.

:class:`SafetyFilter` needs no environment: :meth:`SafetyFilter.step` takes the
team's kinematics (:class:`aasoatt_env.model.dynamics.Kinematics`), wheel
speeds, headings, the nominal ``du`` and its bounds, builds one barrier row per
pair inside the sensing range (:mod:`~aasoatt_env.safety.barriers`), applies the
deadlock strategy (:mod:`~aasoatt_env.safety.deadlock`) and solves the QP by
independent components (:mod:`~aasoatt_env.safety.decomposition`, solvers in
:mod:`~aasoatt_env.safety.solvers`), warm-started from the previous step.  It
also implements the env's control-filter protocol
(:class:`aasoatt_env.sim.protocol.ControlFilter`): ``reset(team)`` and
``filter(FilterInput, du_nominal) -> FilterResult``.

Discrete-time safety: the barrier is continuous-time; the default
``FilterConfig.safety_margin=None`` adds up to ``2 dt * 1 m/s`` to ``d_s`` for
pairs in relative motion (see :mod:`aasoatt_env.safety.config`).

Which solver answers which QP (fallbacks, relaxation of infeasible rows, the
exact path after a stall) is decided in one place,
:class:`aasoatt_env.safety.solvers.SolverPolicy`; ``FilterResult.message``
says which solver answered.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from aasoatt_env.compiled import NUMBA_MISSING, c64, kernels
from aasoatt_env.compiled import available as compiled_available
from aasoatt_env.errors import ConfigError, StateError, UsageError
from aasoatt_env.model.dynamics import Kinematics, input_bounds, kinematics, speed_box
from aasoatt_env.model.geometry import brute_candidates, obstacle_pairs, robot_pairs, row_dot, uses_brute_force
from aasoatt_env.model.params import Team
from aasoatt_env.safety.barriers import PairGeometry, barrier_rows, get_barrier
from aasoatt_env.safety.config import MARGIN_FADE_SPEED, FilterConfig, auto_margin
from aasoatt_env.safety.deadlock import (
    STRATEGIES,
    TRIGGERS,
    TRIGGERS_WITHOUT_PAIRS,
    DeadlockState,
    Strategy,
    TargetContext,
    TriggerContext,
    rotation,
)
from aasoatt_env.safety.decentralized import GROUP_ONE_CHANGE_ITER, decentralized_step, negotiation_rows
from aasoatt_env.safety.decomposition import CentralAnswer, row_values, solve_centralized
from aasoatt_env.safety.gatekeeper import BLEND_LEVELS, GateResult, _levels, _team_block
from aasoatt_env.safety.inputs import MIN_BRAKING_ROOM, check_inputs, check_team, refuse_rows_beyond
from aasoatt_env.safety.problem import ROW_NORM_MIN
from aasoatt_env.safety.repair import GATE_TOL, gate_with_repair
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers.active_set import (
    BOUND_TIGHT,
    DENSE_MAX_CELLS,
    DENSE_MAX_VARS,
    PDAS_ITER,
    VERIFIED_MESSAGE,
    WARM_FLOOR,
    WARM_REL,
    one_change_budget,
)
from aasoatt_env.safety.solvers.active_set import TOL as AS_TOL
from aasoatt_env.safety.warm_up import warm_up
from aasoatt_env.sim.protocol import FilterInput

__all__ = ["MIN_BRAKING_ROOM", "STATUSES", "FilterResult", "SafetyFilter"]

STATUSES: tuple[str, ...] = ("solved", "relaxed", "backup", "failed", "unsafe")
"""Filter statuses from best to worst (:attr:`FilterResult.status`)."""

_BARRIER_TOL = 1e-6
"""A barrier value below this counts as outside the barrier's safe set (backup layer off)."""
COLLISION_TOL: float = 1e-3
"""Overlap [m] beyond which a pair counts as colliding (the metrics' tolerance): without the backup
layer the status is ``"unsafe"`` then, whatever the barrier's value."""


class _Rows(NamedTuple):
    """A step's rows: ``Gi du_ri + Gj du_rj <= rhs``, their pairs and warm-start keys, and the barrier's minima."""

    ri: np.ndarray
    rj: np.ndarray
    pr: np.ndarray  # the robot pairs within range
    pairs_out: np.ndarray  # every row's pair (an obstacle row's as (i, -1 - k))
    Gi: np.ndarray
    Gj: np.ndarray
    rhs: np.ndarray
    keys: np.ndarray
    barrier_min: float
    gap_min: float
    increasing: bool = False  # keys known to increase (the brute force's pairs): no check before keeping them


_NO_PAIRS = np.empty((0, 2), dtype=np.intp)
"""A trigger context's pairs where the trigger reads none (``deadlock.TRIGGERS_WITHOUT_PAIRS``)."""
_MULTIPLIER = TRIGGERS["multiplier"]
"""The registry's own ``multiplier`` trigger, which the compiled step computes (``deadlock_kernel``)."""
_QUICK_LEVELS = np.array(_levels(BLEND_LEVELS))
_QUICK_LEVELS.flags.writeable = False
"""The levels of the backup layer's quick check (the gatekeeper's default blend levels)."""
_NO_POSE = np.empty((0, 3))
"""The compiled step's poses without the backup layer (not read)."""
_NO_OBSTACLES = (np.empty(0, dtype=np.complex128), np.empty(0), np.empty(0, dtype=np.int64), False)
"""The compiled check's obstacle block without obstacles (centres, radii, groups, has groups)."""


def _safe_without_layer(barrier_min: float, gap_min: float) -> bool:
    """Without the backup layer: every pair inside the barrier's safe set and none overlapping beyond the tolerance."""
    return not (barrier_min < -_BARRIER_TOL or gap_min < -COLLISION_TOL)


def _scale(team: Team, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per-robot scale ``(N,)`` of the QP's scaled variables: the largest input bound, 1 where that is 0."""
    bound = np.maximum(np.abs(lo), np.abs(hi))
    scale = np.maximum(team.max_wheel_accel, np.maximum(bound[:, 0], bound[:, 1]))
    return np.where(scale > 0, scale, 1.0)


def _axle_pose(team: Team, p: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Axle poses ``(N, 3)`` from control points and headings."""
    pose = np.empty((p.shape[0], 3))
    pose[:, 2] = theta
    if team.is_diff_drive:  # p - offset (cos, sin), column by column
        pose[:, 0] = p[:, 0] - team.offset * np.cos(theta)
        pose[:, 1] = p[:, 1] - team.offset * np.sin(theta)
    else:
        pose[:, :2] = p
    return pose


def _numpy_rows(cfg: FilterConfig, A: np.ndarray, v: np.ndarray, g: PairGeometry, p_true: np.ndarray,
                pairs: np.ndarray, key_base: int, gap_initial: float) -> tuple:
    """The step's rows in numpy (the reference of :mod:`~aasoatt_env.safety.rows_kernel`).

    ``g``: the pairs' geometry with the safety distances ``r_i + r_j`` (``p`` as the deadlock
    strategy left it, ``p_true`` as it is); ``pairs`` ``(P, 2)`` the result's pairs.  Adds the
    discrete-time and speed margins, and returns ``(ri, rj, pairs, G_i, G_j, rhs, keys,
    barrier_min, gap_min)`` of the kept rows: the barrier's smallest value with the true geometry
    and safety distance (what "inside the safe set" refers to), the smallest gap ``|p_ij| - d_s``
    (``gap_initial`` without pairs), and the warm-start key ``i * key_base + j`` of a robot pair
    (``i * key_base + N + k`` of obstacle ``k``).
    """
    ri, rj, ds, n = g.i, g.j, g.d_s, v.shape[0]
    margin = cfg.pair_margin(g.v)
    if cfg.speed_margin:
        sp2 = row_dot(v, v)
        margin = margin + cfg.speed_margin * (sp2[ri] + np.where(rj >= 0, sp2[np.maximum(rj, 0)], 0.0))
    h = get_barrier(cfg.barrier).value(g._replace(p=p_true), cfg)
    barrier_min = float(h.min(initial=np.inf))
    gap_min = float((np.sqrt(row_dot(p_true, p_true)) - ds).min(initial=gap_initial))
    c, rhs, keep = barrier_rows(cfg.barrier, g._replace(d_s=ds + margin), cfg)
    ri, rj, pairs = ri[keep], rj[keep], pairs[keep]
    Gi = np.einsum("pki,pk->pi", A[ri], c)
    Gj = -np.einsum("pki,pk->pi", A[np.maximum(rj, 0)], c)
    keys = ri.astype(np.int64) * key_base + np.where(rj >= 0, rj, n - 1 - pairs[:, 1])
    return ri, rj, pairs, Gi, Gj, rhs, keys, barrier_min, gap_min


@dataclass(frozen=True)
class FilterResult:
    """What one :meth:`SafetyFilter.step` did.

    Attributes
    ----------
    du : numpy.ndarray
        The safe wheel accelerations ``(N, 2)`` (within the bounds).
    status : str
        The worst of what happened, by severity (:data:`STATUSES`): ``"solved"``
        (the QP's optimum applied), ``"relaxed"`` (infeasible rows loosened by
        ``slack``; bounds kept), ``"backup"`` (the backup layer changed some
        robots' inputs: braked them, or nudged them toward brake-safety; see
        ``backup`` and the message), ``"failed"`` (the QP solver gave no answer) or ``"unsafe"``
        (the team is outside the safe set: with the backup layer, the state was
        not brake-safe; without it, some pair has a barrier value ``h < 0`` or
        overlaps by more than :data:`COLLISION_TOL`).
        ``"solved"``, ``"relaxed"`` and ``"backup"`` all mean: inside the safe set.
    safe : bool
        The team is inside the safe set after this step (``status != "unsafe"``).
    backup : numpy.ndarray
        ``(N,)``: robots the backup layer braked (blended toward or put on braking; robots it
        only nudged are not flagged, the status and the message count them).
    margin : float
        With the backup layer: the smallest ``distance - d_s`` [m] of any pair
        along the backup horizon of the applied inputs (at most the reach limit
        ``(D - max d_s) / 2`` when no pair is near).  Without it: the smallest
        surface gap ``|p_ij| - d_s`` of the pairs in range (``D - max d_s`` if none).
    barrier_min : float
        Smallest barrier value ``h`` over the rows, without the discrete-time
        margins (``inf`` without rows).
    message : str
        Solver detail.
    eta : numpy.ndarray
        Multiplier of each row ``(n_rows,)`` in the units of eqn.8 (``>= 0``).
    pairs : numpy.ndarray
        Row pairs ``(n_rows, 2)``: ``(i, j)`` robots, or ``(i, -1 - k)`` for obstacle ``k``.
    avoiding : numpy.ndarray
        ``(N,)``: robot has a row with a positive multiplier (in collision avoidance).
    triggered : numpy.ndarray
        ``(N,)``: deadlock strategy active this step.
    slack : float
        Largest violation of a row by the returned ``du`` (eqn.8 units; 0 when solved).
    correction : numpy.ndarray
        ``|du_safe - du_nominal|`` per robot ``(N,)``.
    intervened : numpy.ndarray
        ``(N,)``: the filter changed the robot's nominal.
    iterations : int
        Solver iterations.
    solve_time : float
        Wall time of the whole step [s].
    n_rows : int
        Number of barrier rows.
    n_qp_rows : int
        Rows passed to the QP solver (with ``decompose``: those of the components
        with a row the closed-form answer violates; 0 when no QP was needed).
    """

    du: np.ndarray
    status: str
    safe: bool
    backup: np.ndarray
    margin: float
    barrier_min: float
    message: str
    eta: np.ndarray
    pairs: np.ndarray
    avoiding: np.ndarray
    triggered: np.ndarray
    slack: float
    correction: np.ndarray
    intervened: np.ndarray
    iterations: int
    solve_time: float
    n_rows: int
    n_qp_rows: int = 0

    @property
    def obstacle_rows(self) -> np.ndarray:
        """Boolean ``(n_rows,)``: row is a robot-obstacle row."""
        return self.pairs[:, 1] < 0


class SafetyFilter:
    """CBF-QP safety filter for a team (see module docstring).

    Parameters
    ----------
    team : Team, optional
        Robot parameters; may be given later with :meth:`reset` (the env does).
    config : FilterConfig or mapping, optional
        Configuration (default :class:`FilterConfig`).
    **options
        Fields of :class:`FilterConfig`; they replace those of ``config``
        (:meth:`FilterConfig.merged`, the one rule).
    """

    keeps_input_bounds: bool = True
    """Every ``du`` returned lies within the given bounds (protocol attribute)."""

    def __init__(self, team: Team | None = None, config: FilterConfig | None = None, **options: Any) -> None:
        cfg = FilterConfig.merged(config, **options)
        if cfg.kernel == "numba" and not compiled_available():
            raise ConfigError(f"kernel: {NUMBA_MISSING}")
        self.config = cfg
        if STRATEGIES[cfg.deadlock].rotates_rows:
            warnings.warn(
                f"deadlock={cfg.deadlock!r} rotates the relative positions in the barrier rows (eqn.12c), so the "
                "paper's barrier does not protect those pairs while it is active"
                + ("; the braking backup layer still keeps the team collision-free" if cfg.backup else
                   " and, with backup=False, nothing else does (a 2-robot head-on swap overlapped by 0.8 m)"),
                UserWarning, stacklevel=2,
            )
        self.team: Team | None = None
        self._Q = rotation(cfg.rotation_deg)
        self._strategy = STRATEGIES[cfg.deadlock]
        self._trigger = TRIGGERS[cfg.trigger]
        # the paper's rows of robot pairs in one compiled call (aasoatt_env.safety.rows_kernel)
        self._fused = cfg.compiled and cfg.barrier == "aasoatt" and not self._strategy.rotates_rows
        # (the decentralised mode's is for its negotiation groups: the exact path first, SolverPolicy's docstring,
        # with a larger budget for the warm active set, GROUP_ONE_CHANGE_ITER's docstring)
        decentral = cfg.mode == "decentralized"
        self._solver = SolverPolicy(cfg.solver, active_set=cfg.active_set,
                                    options={"iterations": cfg.neural_iterations}, compiled=cfg.compiled,
                                    exact_first=decentral, one_change_iter=GROUP_ONE_CHANGE_ITER if decentral else None)
        # the step from the rows on in one compiled call (aasoatt_env.safety.step_kernel), where every part
        # it runs is what this configuration runs: the fused rows, the centralised decomposition with the
        # compiled warm active set, a trigger that reads no pairs
        self._whole_step = (self._fused and cfg.mode == "centralized" and cfg.decompose and self._solver.exact
                            and cfg.active_set and cfg.trigger in TRIGGERS_WITHOUT_PAIRS)
        # there, the default trigger and the target by one compiled call (deadlock_kernel), where the strategy
        # acts (a strategy that leaves the target alone has no trigger to evaluate); the registry's own entries
        # only (a trigger registered under that name, or a Strategy subclass, is called as registered)
        self._compiled_trigger = (self._whole_step and self._trigger is _MULTIPLIER and self._strategy.active
                                  and type(self._strategy) is Strategy)
        self.reset(team)

    def warm_up(self) -> bool:
        """Compile this filter's kernels now (:func:`aasoatt_env.safety.warm_up.warm_up`), before a control loop.

        Returns whether kernels were run (``False`` with ``kernel="numpy"`` or without numba).
        """
        return warm_up(self.config.kernel)

    def reset(self, team: Team | None = None) -> None:
        """Forget the warm start, the deadlock memory and the solver's path state; bind ``team`` if given."""
        if team is not None:
            if not isinstance(team, Team):
                raise ConfigError(f"team: got {type(team).__name__}, expected aasoatt_env.model.params.Team")
            check_team(team, self.config)
            self.team = team
        self._dl = DeadlockState()
        self._x: np.ndarray | None = None
        self._keys = np.empty(0, dtype=np.int64)
        self._key_robots = np.empty((0, 2), dtype=np.intp)
        self._z = np.empty(0)
        self._solver.reset()

    def grouped(self, filters: Sequence[object]) -> SafetyFilter | None:
        """One filter for the stack of several teams, each behind a filter of this configuration.

        The stack's ``team.group`` keeps the teams apart (no pair between them),
        so the answer is each team's own up to rounding; the batch calls it once
        per physics step instead of once per team
        (:class:`~aasoatt_env.sim.protocol.GroupableFilter`).  None when some
        filter is not a :class:`SafetyFilter` of the same configuration.
        """
        if all(type(f) is type(self) and f.config == self.config for f in filters):  # type: ignore[attr-defined]
            return type(self)(config=self.config)
        return None

    def reset_rows(self, rows: np.ndarray, team: Team) -> None:
        """Forget the memory of robots ``rows`` (their team started an episode) and bind ``team``.

        What a fresh filter of that team would have: no deadlock memory, no
        warm start for their rows and pairs.  The solver's switch state is
        shared by the stack (it picks between exact paths only).  A team of a
        different size is bound with a full :meth:`reset`.
        """
        if self.team is None or not isinstance(team, Team) or team.n != self.team.n:
            self.reset(team)
            return
        check_team(team, self.config)
        self.team = team
        rows = np.asarray(rows, dtype=np.intp)
        if self._dl.avoiding is not None:
            avoiding = self._dl.avoiding.copy()
            avoiding[rows] = False
            self._dl.avoiding = avoiding
        for h in self._dl.history:  # a position never seen: the stall trigger waits for a full dwell
            h[rows] = np.nan
        if self._x is not None:
            x = self._x.reshape(-1, 2).copy()
            x[rows] = 0.0
            self._x = x.ravel()
        hit = np.isin(self._key_robots, rows).any(axis=1)
        if hit.any():
            self._z = np.where(hit, 0.0, self._z)

    # ------------------------------------------------------------------ API
    def __call__(self, inp: FilterInput, nominal_du: np.ndarray) -> FilterResult:
        """The control-filter protocol (:mod:`aasoatt_env.sim.protocol`): one physics step."""
        if abs(inp.dt - self.config.dt) > 1e-12 * self.config.dt:
            raise ConfigError(f"dt: the env steps {inp.dt:g} s but the filter was configured for {self.config.dt:g} s")
        p_d, v_d, _ = inp.reference
        obstacles = None
        if inp.obstacle_radii.size:
            obstacles = (inp.obstacle_centers, inp.obstacle_radii)
            if inp.obstacle_groups is not None:
                obstacles = (*obstacles, inp.obstacle_groups)
        _, result = self.step(inp.kin, inp.u, inp.theta, nominal_du, inp.lo, inp.hi, reference=(p_d, v_d),
                              obstacles=obstacles)
        return result

    def from_state(
        self,
        pose: np.ndarray,
        u: np.ndarray,
        nominal_du: np.ndarray,
        **kwargs: Any,
    ) -> tuple[np.ndarray, FilterResult]:
        """:meth:`step` from axle poses ``(N, 3)`` and wheel speeds; bounds from :func:`input_bounds`."""
        team = self._bound_team()
        pose, u = np.asarray(pose, dtype=np.float64), np.asarray(u, dtype=np.float64)
        for name, a, shape in (("pose", pose, (team.n, 3)), ("u", u, (team.n, 2))):
            if a.shape != shape:
                raise StateError(f"{name}: got shape {a.shape}, expected {shape}")
            refuse_rows_beyond(name, a, "robot")
        kin = kinematics(team, pose, u)
        lo, hi = input_bounds(team, u, self.config.dt)
        return self.step(kin, u, pose[:, 2], nominal_du, lo, hi, **kwargs)

    def step(
        self,
        kin: Kinematics,
        u: np.ndarray,
        theta: np.ndarray,
        nominal_du: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
        *,
        reference: tuple[np.ndarray, np.ndarray] | None = None,
        obstacles: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, FilterResult]:
        """Safe wheel accelerations ``(N, 2)`` and a :class:`FilterResult`.

        Parameters
        ----------
        kin : Kinematics
            ``p, v, A, adot_u`` of the team.
        u : numpy.ndarray
            Wheel speeds ``(N, 2)``.
        theta : numpy.ndarray
            Headings ``(N,)``.
        nominal_du : numpy.ndarray
            Nominal wheel accelerations ``(N, 2)``; NaN/inf raise :class:`~aasoatt_env.errors.StateError`.
        lo, hi : numpy.ndarray
            Bounds on ``du`` ``(N, 2)``, kept hard.
        reference : tuple of numpy.ndarray, optional
            ``(p_d, v_d)``, each ``(N, 2)``; needed by ``auxiliary_velocity`` and
            ``rotate_reference_velocity``.
        obstacles : tuple of numpy.ndarray, optional
            ``(centers (M, 2), radii (M,))`` of static disc obstacles, or
            ``(centers, radii, groups (M,))`` for a grouped team
            (:attr:`~aasoatt_env.model.params.Team.group`): an obstacle acts on
            the robots of its group only.
        """
        t0 = time.perf_counter()
        cfg, team = self.config, self._bound_team()
        n = team.n
        kin, u, theta, nominal_du, lo, hi, reference, obstacles = check_inputs(
            n, kin, u, theta, nominal_du, lo, hi, reference, obstacles, compiled=cfg.compiled)
        if cfg.max_wheel_speed is not None:
            lo, hi = speed_box(lo, hi, u, cfg.max_wheel_speed, cfg.dt)
        strategy = self._strategy
        if strategy.needs_reference and reference is None:
            raise ConfigError(f"deadlock strategy {cfg.deadlock!r} needs reference=(p_d, v_d); got None")
        p, v, A, adot = kin.p, kin.v, kin.A, kin.adot_u

        # neighbours and pair geometry -------------------------------------------------
        m_obs = n + (0 if obstacles is None else int(np.asarray(obstacles[1]).size))
        gap_initial = cfg.sensing_range - 2.0 * float(team.radius.max(initial=0.0))
        fused = self._fused and obstacles is None
        brute = False  # the brute force's candidates: in (i, j) order, so the rows' keys increase
        if fused:  # the pairs in range and their rows in one compiled call (rows_kernel's docstring)
            brute = uses_brute_force(n, team.group)
            if brute:  # robot_pairs' brute force, its distance test in the kernel
                (ci, cj), range2 = brute_candidates(n, team.group), cfg.sensing_range * cfg.sensing_range
            else:
                found = robot_pairs(p, cfg.sensing_range, groups=team.group, compiled=cfg.compiled)
                (ci, cj), range2 = (np.ascontiguousarray(found[:, 0]), np.ascontiguousarray(found[:, 1])), np.inf
                ci.flags.writeable = cj.flags.writeable = False  # (the brute force's are: one compiled type)
            rows_args = (c64(p), c64(v), c64(adot), c64(A), c64(team.radius), ci, cj, range2, cfg.k1, cfg.k2,
                         np.nan if cfg.safety_margin is None else float(cfg.safety_margin), auto_margin(cfg.dt),
                         MARGIN_FADE_SPEED, cfg.speed_margin, m_obs + 1, gap_initial)
            if self._whole_step and self._x is not None and self._solver.compiled:
                # the rest of the step's compiled parts in one call (step_kernel's docstring): the trigger
                # reads no pairs here, so it and the target come first
                if self._compiled_trigger:
                    triggered, target = self._triggered_target(rows_args[3], nominal_du, rows_args[1], rows_args[0],
                                                               reference)
                else:
                    triggered = self._triggered(TriggerContext(p, v, theta, reference, _NO_PAIRS, _NO_PAIRS, cfg))
                    target = self._target(A, nominal_du, lo, hi, triggered, v, p, reference)
                return self._step_compiled(t0, rows_args, brute, u, theta, nominal_du, lo, hi, A, p, triggered,
                                           target)
            pr, geo_p_true, Gi, Gj, rhs, keys, barrier_min, gap_min = kernels("rows").aasoatt_rows(*rows_args)
            barrier_min, gap_min = float(barrier_min), float(gap_min)
        else:
            pr = robot_pairs(p, cfg.sensing_range, groups=team.group, compiled=cfg.compiled)
        ri, rj = pr[:, 0], pr[:, 1]
        pairs_out = pr
        if not fused:
            rad, amax = team.radius, team.max_point_accel
            state = np.concatenate((p, v, adot), axis=1)  # one gather per side instead of three
            rel = state[ri] - state[rj]
            geo_p, geo_v, geo_a = rel[:, 0:2], rel[:, 2:4], rel[:, 4:6]
            ds, rsum, ap = rad[ri] + rad[rj], rad[ri] + rad[rj], amax[ri] + amax[rj]
            if obstacles is not None:
                oc = np.asarray(obstacles[0], float).reshape(-1, 2)
                orad = np.asarray(obstacles[1], float).reshape(-1)
                po = obstacle_pairs(p, oc, orad, cfg.sensing_range, groups=team.group,
                                    obstacle_groups=obstacles[2] if len(obstacles) > 2 else None)
                oi, ok = po[:, 0], po[:, 1]
                geo_p = np.concatenate((geo_p, p[oi] - oc[ok]))
                geo_v = np.concatenate((geo_v, v[oi]))
                geo_a = np.concatenate((geo_a, adot[oi]))
                rs = rad[oi] + orad[ok]
                ds, rsum, ap = np.concatenate((ds, rs)), np.concatenate((rsum, rs)), np.concatenate((ap, amax[oi]))
                ri = np.concatenate((ri, oi))
                rj = np.concatenate((rj, np.full(oi.shape[0], -1, dtype=np.intp)))
                pairs_out = np.concatenate((pr, np.stack((oi, -1 - ok), axis=1)))
            geo_p_true = geo_p

        # deadlock trigger and strategy -----------------------------------------------
        pair_idx = pr if ri.shape[0] == pr.shape[0] else np.stack((ri, rj), axis=1)  # (robot pairs only: pr)
        triggered = self._triggered(TriggerContext(p, v, theta, reference, pair_idx, -geo_p_true, cfg))
        target = self._target(A, nominal_du, lo, hi, triggered, v, p, reference)

        # rows --------------------------------------------------------------------------
        if not fused:
            geo = PairGeometry(ri, rj, strategy.rotate_rows(geo_p, triggered[ri] | ((rj >= 0) & triggered[np.maximum(
                rj, 0)]), self._Q), geo_v, geo_a, ds, rsum, ap)
            ri, rj, pairs_out, Gi, Gj, rhs, keys, barrier_min, gap_min = _numpy_rows(
                cfg, A, v, geo, geo_p_true, pairs_out, m_obs + 1, gap_initial)
        rows = _Rows(ri, rj, pr, pairs_out, Gi, Gj, rhs, keys, barrier_min, gap_min, brute)
        pose = _axle_pose(team, p, theta) if cfg.backup else None
        # the decentralised mode's negotiation groups (aasoatt_env.safety.decentralized): the rows of touching
        # robots around the triggered ones, solved whole
        whole = (negotiation_rows(triggered, p, team.radius, ri, rj, cfg.negotiate_gap)
                 if cfg.mode == "decentralized" and cfg.negotiate else None)
        return self._solve_and_check(t0, rows, u, pose, nominal_du, lo, hi, A, obstacles, triggered, target,
                                     _scale(team, lo, hi), whole=whole)

    def _triggered(self, context: TriggerContext) -> np.ndarray:
        """``(N,)`` bool: the robots the deadlock strategy acts on at this step (none when it is off)."""
        if self._strategy.active:
            return self._trigger(self._dl, context)
        return np.zeros(context.p.shape[0], dtype=bool)

    def _target(self, A: np.ndarray, nominal_du: np.ndarray, lo: np.ndarray, hi: np.ndarray, triggered: np.ndarray,
                v: np.ndarray, p: np.ndarray, reference: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """The QP's target control-point accelerations ``(N, 2)``: the nominal's, after the deadlock strategy."""
        cfg = self.config
        zeta = np.where(triggered, cfg.zeta, 0.0)
        # a robot alone saturates its own nominal: the decentralised QPs start from what each robot would do
        nom_t = np.minimum(np.maximum(nominal_du, lo), hi) if cfg.mode == "decentralized" else nominal_du
        return self._corrected_target(np.einsum("nij,nj->ni", A, nom_t), zeta, v, p, reference, nominal_du)

    def _corrected_target(self, target: np.ndarray, zeta: np.ndarray, v: np.ndarray, p: np.ndarray,
                          reference: tuple[np.ndarray, np.ndarray] | None, nominal_du: np.ndarray) -> np.ndarray:
        """The strategy's target from ``A du_nom``, refused unless float64 of the nominal's shape.

        (A registered strategy's answer: the compiled parts read it without bounds checks.)
        """
        cfg = self.config
        target = self._strategy.correct_target(target, zeta, self._Q, TargetContext(v, p, reference, cfg.k3, cfg.k4))
        if not (isinstance(target, np.ndarray) and target.shape == nominal_du.shape and target.dtype == np.float64):
            raise ConfigError(f"deadlock strategy {self.config.deadlock!r}: its target has shape "
                              f"{np.shape(target)} (dtype {getattr(target, 'dtype', type(target).__name__)}), "
                              f"expected float64 of shape {nominal_du.shape}")
        return target

    def _triggered_target(self, A: np.ndarray, nominal_du: np.ndarray, v: np.ndarray, p: np.ndarray,
                          reference: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_triggered` and :meth:`_target` of the ``multiplier`` trigger in the centralised mode.

        The trigger and ``A du_nom`` by one compiled call (:mod:`~aasoatt_env.safety.deadlock_kernel`, the
        same numbers); the strategy's correction of the triggered robots as in :meth:`_target`.  ``A``,
        ``v``, ``p`` as :func:`~aasoatt_env.compiled.c64` gives them (the rows' arguments); the others
        are given to the kernel so too (one compiled specialisation whatever the caller's layouts).
        """
        cfg = self.config
        avoiding = self._dl.avoiding
        avoiding = np.zeros(p.shape[0], dtype=bool) if avoiding is None else np.ascontiguousarray(avoiding, bool)
        p_d, v_d = (p, v) if reference is None else (c64(reference[0]), c64(reference[1]))
        triggered, zeta, target, anyone = kernels("deadlock").multiplier_target(
            avoiding, p, v, p_d, v_d, reference is not None, A, c64(nominal_du), cfg.zeta, cfg.low_speed,
            cfg.goal_tol)
        if anyone:
            target = self._corrected_target(target, zeta, v, p, reference, nominal_du)
        return triggered, target

    def _step_compiled(self, t0: float, rows_args: tuple, increasing: bool, u: np.ndarray, theta: np.ndarray,
                       nominal_du: np.ndarray, lo: np.ndarray, hi: np.ndarray, A: np.ndarray, p: np.ndarray,
                       triggered: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, FilterResult]:
        """The step from the rows on by :func:`~aasoatt_env.safety.step_kernel.filter_step`.

        Where the kernel stops early the step goes on in :meth:`_solve_and_check` with what it made
        (the same code as without the kernel, so the same answer); so does a verified answer the
        solver policy needs the problem for (its timing probe, :meth:`SolverPolicy.needs_problem`), as
        :func:`~aasoatt_env.safety.decomposition.solve_centralized` hands such an answer on.
        """
        cfg, team, k = self.config, self.team, kernels("step")
        n = team.n  # type: ignore[union-attr]
        pose = _axle_pose(team, p, theta) if cfg.backup else None  # type: ignore[arg-type]
        kernel_pose = _NO_POSE if pose is None else pose
        block, limit = _team_block(team, cfg.brake_fraction, cfg.sensing_range)  # type: ignore[arg-type]
        diff, offset, cols, tg, amax, adec, _, group, has_group, sensing_range = block
        t_call = time.perf_counter()
        (stage, pairs, keys, barrier_min, gap_min, qp_code, used, n_qp, n_vars, n_parts, x, z, eta, avoiding, braking,
         broken, rounds, n_pairs, margin, du, correction, intervened, nudged, floats, flags) = k.filter_step(
            *rows_args, c64(target), c64(lo), c64(hi), c64(team.max_wheel_accel), c64(nominal_du),  # type: ignore
            c64(self._x.reshape(n, 2)), self._keys, c64(self._z), PDAS_ITER,
            one_change_budget(self._solver.one_change_iter), AS_TOL,  # type: ignore
            WARM_REL, WARM_FLOOR, BOUND_TIGHT, ROW_NORM_MIN, DENSE_MAX_VARS, DENSE_MAX_CELLS, cfg.eta_tol,
            bool(cfg.backup), kernel_pose, c64(u), float(cfg.dt), _QUICK_LEVELS, diff, offset, cols, tg, amax, adec,
            group, has_group, sensing_range, *_NO_OBSTACLES, limit, GATE_TOL)
        barrier_min, gap_min = float(barrier_min), float(gap_min)
        elapsed = time.perf_counter() - t_call  # (the policy's timing: the call, rows and quick check included)
        probe = qp_code == k.VERIFIED and self._solver.needs_problem(int(n_vars), elapsed)
        if stage == k.ROWS or probe:
            # the numpy path, from what the compiled decomposition handed on (solve_centralized's _compiled)
            rows, scale, z_warm, _, xs, zs, _, _, _, done, _ = self._unpacked(
                k, floats, flags, pairs, keys, barrier_min, gap_min, increasing)
            parts = (xs[:n_vars], zs[:n_qp], done[:n_parts], int(used)) if qp_code == k.PARTS else None
            return self._solve_and_check(t0, rows, u, pose, nominal_du, lo, hi, A, None, triggered, target, scale,
                                         tried=True, kernel_parts=parts, z_warm=z_warm)
        if qp_code == k.CLOSED_FORM:
            message, iterations, n_qp = "closed form: no row binds", 0, 0
        else:
            self._solver.note_answer(int(n_vars), elapsed)
            message, iterations, n_qp = VERIFIED_MESSAGE, int(used), int(n_qp)
        if stage == k.DONE:  # nobody brakes, or only for the range limit
            self._remember(x, z, keys, pairs, increasing, avoiding)
            if cfg.backup:
                safe, margin = not bool(broken.any()), float(margin)
            else:
                braking, safe, margin = np.zeros(n, dtype=bool), _safe_without_layer(barrier_min, gap_min), gap_min
            return self._result(t0, du, "solved", message, safe, braking, nudged, margin, barrier_min, eta, pairs,
                                avoiding, triggered, 0.0, correction, intervened, iterations, keys.shape[0], n_qp)
        # (stage QP) the quick check brakes someone for a pair: the repair or the full check follows
        rows, scale, _, du_qp, _, _, gdu, share, robot_margin, _, out_of_range = self._unpacked(
            k, floats, flags, pairs, keys, barrier_min, gap_min, increasing)
        ans = CentralAnswer(du_qp, x, z, eta, "solved", message, iterations, n_qp)
        quick = GateResult(gdu, braking, float(margin), not bool(broken.any()), broken, share, int(rounds),
                           int(n_pairs), robot_margin, out_of_range)
        return self._solve_and_check(t0, rows, u, pose, nominal_du, lo, hi, A, None, triggered, target, scale,
                                     answer=ans, avoiding=avoiding, quick=quick)

    @staticmethod
    def _unpacked(k: Any, floats: np.ndarray, flags: np.ndarray, pairs: np.ndarray, keys: np.ndarray,
                  barrier_min: float, gap_min: float, increasing: bool) -> tuple:
        """Where the compiled step stops early: its rows, and what it packed (``step_kernel.unpack``), as views.

        ``(rows, scale, z_warm, du_qp, xs, zs, gate_du, share, robot_margin, done, out_of_range)``.
        """
        Gi, Gj, rhs, *rest = k.unpack(floats, flags, flags.shape[0] // 2, keys.shape[0])  # (n robots, m rows)
        return (_Rows(pairs[:, 0], pairs[:, 1], pairs, pairs, Gi, Gj, rhs, keys, barrier_min, gap_min, increasing),
                *rest)

    def _result(self, t0: float, du: np.ndarray, status: str, message: str, safe: bool, braking: np.ndarray,
                nudged: np.ndarray, margin: float, barrier_min: float, eta: np.ndarray, pairs: np.ndarray,
                avoiding: np.ndarray, triggered: np.ndarray, slack: float, correction: np.ndarray,
                intervened: np.ndarray, iterations: int, n_rows: int, n_qp: int) -> tuple[np.ndarray, FilterResult]:
        """The step's :class:`FilterResult`: the backup layer's messages, the worst status, braked robots avoiding."""
        n_braked, n_nudged = np.count_nonzero(braking), np.count_nonzero(nudged)
        if n_braked:
            message = f"{message}; backup braked {n_braked} robot(s)"
        if n_nudged:
            message = f"{message}; backup nudged {n_nudged} robot(s) toward brake-safety"
        if not safe:
            status = "unsafe"
        elif (n_braked or n_nudged) and STATUSES.index(status) < STATUSES.index("backup"):
            status = "backup"
        return du, FilterResult(
            du=du, status=status, safe=safe, backup=braking, margin=margin, barrier_min=barrier_min,
            # (avoiding | braking: a new array, the deadlock memory keeps its own)
            message=message, eta=eta, pairs=pairs, avoiding=avoiding | braking,
            triggered=triggered, slack=slack, correction=correction, intervened=intervened, iterations=iterations,
            solve_time=time.perf_counter() - t0, n_rows=n_rows, n_qp_rows=n_qp,
        )

    def _remember(self, x: np.ndarray, z: np.ndarray, keys: np.ndarray, robots: np.ndarray, increasing: bool,
                  avoiding: np.ndarray) -> None:
        """The next step's warm start (point, row keys, their robots and multipliers) and the deadlock memory.

        The rows are kept in increasing key order (sorted here where they are not: ``increasing`` says
        they are known to be), so the next step maps them by binary search.
        """
        # (an obstacle row's (i, -1 - k) names robot i alone, as (i, -1) would)
        if not increasing and keys.shape[0] > 1 and not bool((keys[1:] > keys[:-1]).all()):
            order = np.argsort(keys, kind="stable")
            keys, z, robots = keys[order], z[order], robots[order]
        self._x, self._keys, self._z = x.ravel(), keys, z
        self._key_robots = robots.copy()
        self._dl.avoiding = avoiding

    def _solve_and_check(self, t0: float, rows: _Rows, u: np.ndarray, pose: np.ndarray | None,
                         nominal_du: np.ndarray, lo: np.ndarray, hi: np.ndarray, A: np.ndarray,
                         obstacles: tuple[np.ndarray, ...] | None, triggered: np.ndarray, target: np.ndarray,
                         scale: np.ndarray, *, answer: CentralAnswer | None = None, avoiding: np.ndarray | None = None,
                         quick: GateResult | None = None, tried: bool = False, kernel_parts: tuple | None = None,
                         z_warm: np.ndarray | None = None, whole: np.ndarray | None = None
                         ) -> tuple[np.ndarray, FilterResult]:
        """The QP (unless ``answer`` is given, with its ``avoiding``), the backup layer and the result.

        ``pose``: the axle poses (None without the backup layer); ``quick``: the backup layer's first check,
        where the compiled step made it; ``tried``: the compiled step's decomposition ran on these rows and did
        not answer, ``kernel_parts`` what it handed on, ``z_warm`` the warm start it mapped onto them;
        ``whole``: the rows the decentralised mode's negotiation groups solve whole.
        """
        cfg, team = self.config, self._bound_team()
        n = team.n
        ri, rj, pr, pairs_out, Gi, Gj, rhs, keys, barrier_min, gap_min, _ = rows
        m = rhs.shape[0]
        decentral = cfg.mode == "decentralized"
        if answer is not None:
            ans = answer
        elif decentral:  # every robot its own QP over its halves of the rows: no team QP below
            warm = whole is not None and self._x is not None and bool(whole.any())
            ans = decentralized_step(A, target, lo, hi, ri, rj, Gi, Gj, rhs, team.max_point_accel, scale=scale,
                                     compiled=cfg.compiled, whole=whole, policy=self._solver,
                                     x_warm=self._x.reshape(n, 2) if warm else None,  # type: ignore[union-attr]
                                     z_warm=self._map_warm(keys) if warm else None)
        else:
            ans = solve_centralized(self._solver, A, target, lo, hi, scale, ri, rj, Gi, Gj, rhs,
                                    None if self._x is None else self._x.reshape(n, 2),
                                    (lambda: self._map_warm(keys)) if z_warm is None else z_warm,
                                    decompose=cfg.decompose, compiled=cfg.compiled, checked=True,
                                    tried=tried, kernel_parts=kernel_parts)
        if decentral:
            du, x_full = ans.du.copy(), ans.du / scale[:, None]
            z, eta, iterations, n_qp = ans.z, ans.eta, ans.iterations, m
            status = max("relaxed" if ans.n_relaxed else "solved", ans.group_status, key=STATUSES.index)
            message = (f"decentralized: {n - int(ans.grouped.sum())} local QPs"
                       + (f", {ans.n_relaxed} infeasible (relaxed)" if ans.n_relaxed else "")
                       + (f", {ans.n_groups} negotiation group(s) of {int(ans.grouped.sum())} robots (largest "
                          f"{ans.largest_group})"
                          f"{'' if ans.group_status == 'solved' else ': ' + ans.group_status}"
                          if ans.n_groups else ""))
        else:
            du, x_full, z, eta = ans.du, ans.x, ans.z, ans.eta
            status, message, iterations, n_qp = ans.status, ans.message, ans.iterations, ans.n_qp
        if avoiding is None:
            avoiding = np.zeros(n, dtype=bool)
            if decentral:  # a robot avoids when its own half of a row binds
                active_i, active_j = ans.z_half[:, 0] > cfg.eta_tol, ans.z_half[:, 1] > cfg.eta_tol
                avoiding[ri[active_i]] = True
                avoiding[rj[active_j & (rj >= 0)]] = True
            else:
                active = z > cfg.eta_tol
                avoiding[ri[active]] = True
                avoiding[rj[active & (rj >= 0)]] = True
        self._remember(x_full, z, rows.keys, rows.pairs_out, rows.increasing, avoiding)
        # (the decentralised local solver is exact; a negotiation group's answer is its solver's)
        exact = self._solver.exact or (decentral and not ans.grouped.any())  # type: ignore[union-attr]
        slack = 0.0
        if status != "solved" or not exact:  # (a solved exact answer meets every row: nothing to measure)
            slack = float(max(0.0, np.max(row_values(Gi, Gj, ri, rj, du) - rhs, initial=0.0)))

        # backup layer -----------------------------------------------------------------
        braking = nudged = np.zeros(n, dtype=bool)
        if pose is not None:
            gate = gate_with_repair(team, pose, u, du, lo, hi, cfg, obstacles, pr, quick=quick)
            # robots the gate still marks broken (beyond the range limit when braking): best effort, the QP
            du_qp, broken = du, gate.broken
            du = np.where(broken[:, None], du_qp, gate.du)
            braking, margin, safe = gate.braking & ~broken, gate.margin, gate.safe
            # the repair moved their inputs (beyond the rounding of the gate's level arithmetic)
            nudged = ~braking & ~broken & (np.abs(du - du_qp) > 1e-9 * scale[:, None]).any(axis=1)
        else:
            margin, safe = gap_min, _safe_without_layer(barrier_min, gap_min)
        d = du - nominal_du
        correction = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])  # (np.linalg.norm(d, axis=1)'s numbers)
        return self._result(t0, du, status, message, safe, braking, nudged, margin, barrier_min, eta, pairs_out,
                            avoiding, triggered, slack, correction, correction > 1e-9 * scale, iterations, int(m),
                            int(n_qp))

    # ------------------------------------------------------------------ helpers
    def _bound_team(self) -> Team:
        if self.team is None:
            raise UsageError("SafetyFilter: no team yet; pass team= or call reset(team) first")
        return self.team

    def _map_warm(self, keys: np.ndarray) -> np.ndarray | None:
        if self._x is None:
            return None
        z0 = np.zeros(keys.shape[0])
        if self._keys.shape[0] and keys.shape[0]:
            sk, zk = self._keys, self._z  # (kept in increasing key order: _remember)
            if self.config.compiled:
                kernels("decomposition").search_rows(sk, zk, keys, z0)
                return z0
            pos = np.minimum(np.searchsorted(sk, keys), sk.shape[0] - 1)
            hit = sk[pos] == keys
            z0[hit] = zk[pos[hit]]
        return z0
