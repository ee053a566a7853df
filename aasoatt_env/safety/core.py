"""The safety filter: nominal wheel accelerations in, safe ones out, as a pipeline of named stages.

Each stage (inputs, pairs, deadlock, rows, solve, backup, result: the table of ``docs/design.md`` gives what it
does, its module and its compiled form) has one numpy reference and at most one compiled implementation, chosen when
the filter is built (``FilterConfig.kernel``) and never changed during a step; :meth:`describe` says which runs.
Where rows, solve and backup all run compiled (the default centralised filter), :mod:`.fused` runs them in one call
on a warm step; a stage it does not answer runs from its start.  No decision reads the clock: a filter is a function
of the team's state and the nominal (as a Robotarium barrier certificate), plus its memory of the previous step (the
warm start and the deadlock trigger's state).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from aasoatt_env.compiled import NUMBA_MISSING, kernels
from aasoatt_env.compiled import available as compiled_available
from aasoatt_env.errors import ConfigError, StateError, UsageError
from aasoatt_env.model.dynamics import Kinematics, input_bounds, kinematics
from aasoatt_env.model.params import Team
from aasoatt_env.safety.backup import BackupLayer
from aasoatt_env.safety.barriers import get_barrier
from aasoatt_env.safety.centralized import Centralized
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.deadlock import (
    STRATEGIES,
    TRIGGERS,
    TRIGGERS_WITHOUT_PAIRS,
    DeadlockState,
    TargetContext,
    TriggerContext,
    rotation,
)
from aasoatt_env.safety.decentralized import GROUP_ONE_CHANGE_ITER, Decentralized
from aasoatt_env.safety.fused import FusedStep, fusable
from aasoatt_env.safety.inputs import MIN_BRAKING_ROOM, bound_nominal, check_step, check_team, refuse_rows_beyond
from aasoatt_env.safety.result import STATUSES, FilterResult, result
from aasoatt_env.safety.rows import CompiledRows, Pairs, Rows, find_pairs, numpy_rows
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.stages import Answer, StepInput, Warm
from aasoatt_env.safety.warm_up import warm_up
from aasoatt_env.sim.protocol import FilterInput

__all__ = ["MIN_BRAKING_ROOM", "STATUSES", "FilterResult", "SafetyFilter", "StepInput"]

_NO_PAIRS = np.empty((0, 2), dtype=np.intp)
_MULTIPLIER = TRIGGERS["multiplier"]
"""The registry's own ``multiplier`` trigger, whose compiled form the deadlock stage runs (``rows_kernel``)."""


class SafetyFilter:
    """CBF-QP safety filter for a team (module docstring).

    Parameters
    ----------
    team : Team, optional
        Robot parameters; may be given later with :meth:`reset` (the env does).
    config : FilterConfig or mapping, optional
        Configuration (default :class:`FilterConfig`).
    **options
        Fields of :class:`FilterConfig`; they replace those of ``config`` (:meth:`FilterConfig.merged`).
    """

    keeps_input_bounds: bool = True
    """Every ``du`` returned lies within the given bounds (protocol attribute)."""

    def __init__(self, team: Team | None = None, config: FilterConfig | None = None, **options: Any) -> None:
        cfg = FilterConfig.merged(config, **options)
        if cfg.kernel == "numba" and not compiled_available():
            raise ConfigError(f"kernel: {NUMBA_MISSING}")
        self.config = cfg
        self._strategy, self._trigger, self._Q = STRATEGIES[cfg.deadlock], TRIGGERS[cfg.trigger], rotation(
            cfg.rotation_deg)
        if self._strategy.rotates_rows:
            warnings.warn(
                f"deadlock={cfg.deadlock!r} rotates the relative positions in the barrier rows (eqn.12c), so the "
                "paper's barrier does not protect those pairs while it is active"
                + ("; the braking backup layer still keeps the team collision-free" if cfg.backup else
                   " and, with backup=False, nothing else does"), UserWarning, stacklevel=2)
        compiled = cfg.compiled
        self._multiplier = (kernels("deadlock").multiplier_target if compiled and self._strategy.active
                            and self._trigger is _MULTIPLIER else None)
        self._rows_compiled = compiled and bool(get_barrier(cfg.barrier).kernel) and not self._strategy.rotates_rows
        self._rows = CompiledRows(cfg) if self._rows_compiled else numpy_rows
        decentral = cfg.mode == "decentralized"
        policy = SolverPolicy(cfg.solver, active_set=cfg.active_set, compiled=compiled,
                              one_change_iter=GROUP_ONE_CHANGE_ITER if decentral else None,
                              iterations=cfg.neural_iterations)
        self._solve = (Decentralized(policy, cfg.negotiate, cfg.negotiate_gap, cfg.eta_tol, compiled) if decentral
                       else Centralized(policy, cfg.decompose, cfg.eta_tol, compiled))
        self._backup = BackupLayer(cfg) if cfg.backup else None
        self._warm_rows = not decentral or cfg.negotiate  # the QP reads the previous step's multipliers
        self._fused = (FusedStep(cfg, policy, self._rows) if fusable(cfg, self._strategy.rotates_rows, policy.exact)
                       else None)
        self.reset(team)

    def describe(self) -> str:
        """The filter's stages, and which implementation runs each (numpy reference or compiled kernel)."""
        cfg, kernel = self.config, "compiled" if self.config.compiled else "numpy"
        lines = [f"SafetyFilter(mode={cfg.mode}, barrier={cfg.barrier}, deadlock={cfg.deadlock}, "
                 f"trigger={cfg.trigger}, solver={cfg.solver}, backup={cfg.backup})",
                 f"  inputs    {'numpy shapes, compiled number checks' if cfg.compiled else 'numpy'}",
                 f"  pairs     numpy brute force (< 200 robots a group), "
                 f"{'compiled grid of cells' if cfg.compiled else 'k-d tree'} above",
                 f"  deadlock  {'compiled' if self._multiplier is not None else 'numpy'} ({cfg.trigger}, "
                 f"{cfg.deadlock}; the strategy's correction numpy)",
                 f"  rows      {'compiled' if self._rows_compiled else 'numpy'} ({cfg.barrier}"
                 + ("" if self._rows_compiled or not cfg.compiled else ": the strategy rotates the rows"
                    if self._strategy.rotates_rows else ": no compiled form") + ")",
                 f"  solve     {cfg.mode}: " + (f"local QPs {kernel}, " if cfg.mode == "decentralized" else "")
                 + (f"warm active set {kernel}, " if cfg.active_set else "") + f"then {cfg.solver} (solvers.route)",
                 f"  backup    {kernel if cfg.backup else 'off'}",
                 "  result    numpy"]
        if self._fused is not None:
            lines.append("  fused     a warm step's rows, solve and backup check in one compiled call; a stage it "
                         "does not answer runs as above")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.describe()

    def warm_up(self) -> bool:
        """Compile this filter's kernels now (:func:`~aasoatt_env.safety.warm_up.warm_up`), before a control loop."""
        return warm_up(self.config.kernel)

    def reset(self, team: Team | None = None) -> None:
        """Forget the warm start and the deadlock memory; bind ``team`` if given."""
        if team is not None:
            if not isinstance(team, Team):
                raise ConfigError(f"team: got {type(team).__name__}, expected aasoatt_env.model.params.Team")
            check_team(team, self.config)
            self.team: Team | None = team
        elif not hasattr(self, "team"):
            self.team = None
        self._dl = DeadlockState()
        self._fuse, self._relaxed = True, False
        self._x: np.ndarray | None = None
        self._keys = np.empty(0, dtype=np.int64)
        self._key_robots = np.empty((0, 2), dtype=np.intp)
        self._z = np.empty(0)

    def grouped(self, filters: Sequence[object]) -> SafetyFilter | None:
        """One filter for the stack of several teams behind filters of this configuration (None if they differ).

        The stack's ``team.group`` keeps the teams apart, so each team's answer is its own up to
        rounding (:class:`~aasoatt_env.sim.protocol.GroupableFilter`).
        """
        if all(type(f) is type(self) and f.config == self.config for f in filters):  # type: ignore[attr-defined]
            return type(self)(config=self.config)
        return None

    def reset_rows(self, rows: np.ndarray, team: Team) -> None:
        """Forget the memory of robots ``rows`` (their team starts an episode) and bind ``team`` (same size)."""
        if self.team is None or not isinstance(team, Team) or team.n != self.team.n:
            self.reset(team)
            return
        check_team(team, self.config)
        self.team = team
        rows = np.asarray(rows, dtype=np.intp)
        if self._dl.avoiding is not None:
            self._dl.avoiding = self._dl.avoiding.copy()
            self._dl.avoiding[rows] = False
        for h in self._dl.history:  # a position never seen: the stall trigger waits for a full dwell
            h[rows] = np.nan
        if self._dl.liveness is not None:
            self._dl.liveness.forget(rows)
        if self._x is not None:
            self._x = self._x.copy()
            self._x[rows] = 0.0
        hit = np.isin(self._key_robots, rows).any(axis=1)
        if hit.any():
            self._z = np.where(hit, 0.0, self._z)

    # ------------------------------------------------------------------ API
    def __call__(self, inp: FilterInput, nominal_du: np.ndarray) -> FilterResult:
        """The control-filter protocol (:mod:`aasoatt_env.sim.protocol`): one physics step."""
        if abs(inp.dt - self.config.dt) > 1e-12 * self.config.dt:
            raise ConfigError(f"dt: the env steps {inp.dt:g} s but the filter was configured for {self.config.dt:g} s")
        obstacles = None
        if inp.obstacle_radii.size:
            obstacles = (inp.obstacle_centers, inp.obstacle_radii, inp.obstacle_groups)
        return self.step(inp.kin, inp.u, inp.theta, nominal_du, inp.lo, inp.hi, reference=inp.reference[:2],
                         obstacles=obstacles)[1]

    def from_state(self, pose: np.ndarray, u: np.ndarray, nominal_du: np.ndarray,
                   **kwargs: Any) -> tuple[np.ndarray, FilterResult]:
        """:meth:`step` from axle poses ``(N, 3)`` and wheel speeds; bounds from :func:`input_bounds`."""
        team = self._bound_team()
        pose, u = np.asarray(pose, dtype=np.float64), np.asarray(u, dtype=np.float64)
        for name, a, shape in (("pose", pose, (team.n, 3)), ("u", u, (team.n, 2))):
            if a.shape != shape:
                raise StateError(f"{name}: got shape {a.shape}, expected {shape}")
            refuse_rows_beyond(name, a, "robot")
        lo, hi = input_bounds(team, u, self.config.dt)
        return self.step(kinematics(team, pose, u), u, pose[:, 2], nominal_du, lo, hi, **kwargs)

    def step(self, kin: Kinematics, u: np.ndarray, theta: np.ndarray, nominal_du: np.ndarray, lo: np.ndarray,
             hi: np.ndarray, *, reference: tuple[np.ndarray, np.ndarray] | None = None,
             obstacles: tuple[np.ndarray, ...] | None = None) -> tuple[np.ndarray, FilterResult]:
        """Safe wheel accelerations ``(N, 2)`` and a :class:`FilterResult`.

        Parameters
        ----------
        kin : Kinematics
            ``p, v, A, adot_u`` of the team.
        u, theta : numpy.ndarray
            Wheel speeds ``(N, 2)`` and headings ``(N,)``.
        nominal_du : numpy.ndarray
            Nominal wheel accelerations ``(N, 2)``.
        lo, hi : numpy.ndarray
            Bounds on ``du`` ``(N, 2)``, kept hard.
        reference : tuple of numpy.ndarray, optional
            ``(p_d, v_d)``, each ``(N, 2)``; needed by ``auxiliary_velocity`` and ``rotate_reference_velocity``.
        obstacles : tuple of numpy.ndarray, optional
            ``(centres (M, 2), radii (M,))`` of static discs, or ``(centres, radii, groups (M,))`` for a
            grouped team (an obstacle acts on the robots of its group only).
        """
        t0 = time.perf_counter()
        cfg, team = self.config, self._bound_team()
        s = check_step(team, cfg, kin, u, theta, nominal_du, lo, hi, reference, obstacles)
        if self._strategy.needs_reference and s.reference is None:
            raise ConfigError(f"deadlock strategy {cfg.deadlock!r} needs reference=(p_d, v_d); got None")
        pairs = find_pairs(team, s.p, cfg.sensing_range, s.obstacles, cfg.compiled)
        triggered, target = self._deadlock(s, pairs)
        fused = None
        if self._fused is not None and self._x is not None and self._fuse:
            fused = self._fused(s, pairs, target, self._x, self._keys, self._z)
        if fused is None:
            rows = self._rows(cfg, s, pairs, triggered)
            ans, backup = self._solve(s, rows, target, triggered, self._warm(rows)), None
        else:
            rows, ans, backup = fused
        # (the fused call is tried after a step the compiled stages answered: after one the solvers' route
        # answered, it would most likely not answer either; the answers are the same either way)
        self._fuse = ans.warm_verified
        self._remember(rows, ans)
        if backup is None and self._backup is not None:
            backup = self._backup(s, ans.du, pairs.robots)
        res = result(s.nominal, s.scale, rows, ans, backup, triggered, time.perf_counter() - t0)
        return res.du, res

    # ------------------------------------------------------------------ stages
    def _triggered(self, s: StepInput, pairs: Pairs) -> np.ndarray:
        """``(N,)`` bool: the robots the deadlock trigger flags at this step (none when the strategy is off)."""
        if not self._strategy.active:
            return np.zeros(s.p.shape[0], dtype=bool)
        if self.config.trigger in TRIGGERS_WITHOUT_PAIRS:
            idx, vec = _NO_PAIRS, _NO_PAIRS
        else:
            idx, vec = pairs.index(), pairs.vectors(s.p, None if s.obstacles is None else s.obstacles[0])
        return self._trigger(self._dl, TriggerContext(s.p, s.v, s.theta, s.reference, idx, vec, self.config))

    def _deadlock(self, s: StepInput, pairs: Pairs) -> tuple[np.ndarray, np.ndarray]:
        """The robots the deadlock strategy acts on ``(N,)`` and the QP's target ``(N, 2)``: ``A du_nom`` after it.

        A nominal far outside the bounds is first pulled in (:func:`~aasoatt_env.safety.inputs.bound_nominal`);
        in the decentralised mode each robot saturates its own nominal to its bounds.
        """
        cfg = self.config
        if cfg.mode == "decentralized":
            nominal = np.minimum(np.maximum(s.nominal, s.lo), s.hi)
        else:
            nominal = s.nominal if s.near else bound_nominal(s.nominal, s.lo, s.hi, s.scale, s.team.max_wheel_accel)
        if self._multiplier is not None:  # the registry's multiplier trigger and A du_nom, compiled
            avoiding = self._dl.avoiding if self._dl.avoiding is not None else np.zeros(s.p.shape[0], dtype=bool)
            ref = s.reference if s.reference is not None else (s.p, s.v)  # (not read without a reference)
            triggered, zeta, target, anyone = self._multiplier(avoiding, s.p, s.v, *ref, s.reference is not None, s.A,
                                                               nominal, cfg.zeta, cfg.low_speed, cfg.goal_tol)
        else:
            triggered = self._triggered(s, pairs)
            target = np.einsum("nij,nj->ni", s.A, nominal)
            anyone = bool(triggered.any())
            zeta = np.where(triggered, cfg.zeta, 0.0) if anyone else None
        if not (anyone or self._strategy.stateful):  # (a strategy corrects the triggered robots only)
            return triggered, target
        if self._strategy.stateful:
            ctx = TargetContext(s.v, s.p, s.reference, cfg.k3, cfg.k4, self._dl, pairs.robots, pairs.obstacles,
                                None if s.obstacles is None else s.obstacles[:2], s.team.radius, s.adot, cfg)
            zeta = zeta if zeta is not None else np.zeros(s.p.shape[0])
        else:
            ctx = TargetContext(s.v, s.p, s.reference, cfg.k3, cfg.k4)
        target = self._strategy.correct_target(target, zeta, self._Q, ctx)
        if not (isinstance(target, np.ndarray) and target.shape == s.nominal.shape and target.dtype == np.float64
                and np.isfinite(target).all()):
            raise ConfigError(f"deadlock strategy {cfg.deadlock!r}: its target has shape {np.shape(target)} "
                              f"(dtype {getattr(target, 'dtype', type(target).__name__)}), expected finite float64 "
                              f"of shape {s.nominal.shape}")
        return triggered, target

    def _warm(self, rows: Rows) -> Warm:
        """The previous answer on this step's rows (a row new at this step starts at 0)."""
        if self._x is None:
            return Warm(None, None)
        if not self._warm_rows:  # (each robot's own QP, exactly: no warm start)
            return Warm(self._x, None)
        z0 = np.zeros(rows.m)
        if self._keys.shape[0] and rows.m:
            pos = np.minimum(np.searchsorted(self._keys, rows.keys), self._keys.shape[0] - 1)
            hit = self._keys[pos] == rows.keys
            z0[hit] = self._z[pos[hit]]
        # (the fused step's QP is the compiled solve's)
        return Warm(self._x, z0, self._fuse and self._fused is None, self._relaxed)

    def _remember(self, rows: Rows, ans: Answer) -> None:
        """The next step's warm start (rows in increasing key order) and the deadlock memory."""
        keys, z, robots = rows.keys, ans.z, rows.pairs
        if keys.shape[0] > 1 and not bool((keys[1:] > keys[:-1]).all()):
            order = np.argsort(keys, kind="stable")
            keys, z, robots = keys[order], z[order], robots[order]
        self._x, self._keys, self._z, self._key_robots = ans.x, keys, z, robots
        self._relaxed = ans.status == "relaxed"
        self._dl.avoiding = ans.avoiding

    def _bound_team(self) -> Team:
        if self.team is None:
            raise UsageError("SafetyFilter: no team yet; pass team= or call reset(team) first")
        return self.team
