"""Validated configuration of the safety filter.

Defaults follow ``docs/technical_brief.md`` section 7 (``k1 = k2 = 2``, ``k3 = 1``, ``k4 = 4``,
``zeta = 2``, ``q = -60 deg``, ``D = 3``, ``dt = 0.005``).  Values the paper does
not give are our choices: ``gamma = 1`` (braking SBC), ``varsigma = 2``,
``rho_v = 1``, ``sigma = 0`` (velocity barriers).

Discrete-time safety margin
---------------------------
The CBF guarantee holds in continuous time; with ``du`` held over a step of
``dt`` pairs dip slightly below ``d_s`` (a few millimetres on the crowded
radius-6 circle, exact solves; README, Table II).  ``safety_margin=None`` (default) adds to the safety
distance of each pair

    m_ij = auto_margin(dt) * min(1, |v_ij| / 0.2 m/s),   auto_margin(dt) = 2 dt * 1 m/s

i.e. 1 cm at ``dt = 0.005`` for pairs in relative motion, fading to 0 for pairs
at relative rest.  The fade keeps static packings that are feasible for ``d_s``
reachable: 39 robots of radius 0.48 at their goals on the radius-6 circle are
only 6 mm apart, so a constant 1 cm margin would stop them 2-6 cm short of the
goals (the closed-loop tests and ``benchmarks/safety_campaign.py`` check the
distances).  A float ``safety_margin`` adds that constant instead; ``0`` gives
the paper's exact barrier.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.compiled import KERNELS, available
from aasoatt_env.errors import ConfigError
from aasoatt_env.model.dynamics import DT
from aasoatt_env.model.geometry import row_dot
from aasoatt_env.model.tracking import PAPER_K3, PAPER_K4
from aasoatt_env.safety.barriers import BARRIERS
from aasoatt_env.safety.deadlock import STRATEGIES, TRIGGERS
from aasoatt_env.safety.solvers import get_solver

__all__ = ["GAIN_MAX", "MODES", "FilterConfig", "auto_margin"]

MODES: tuple[str, ...] = ("centralized", "decentralized")
"""Values of :attr:`FilterConfig.mode`."""

GAIN_MAX: float = 1e3
"""Largest accepted barrier/tracking gain (``k1``, ``k2``, ``k3``, ``k4``, ``gamma``,
``varsigma``, ``rho_v``).  Larger gains make the rows so stiff that the QP is
infeasible on most steps (``k1 = 1e10`` left 627 of 2,000 steps without an
answer), so they are rejected rather than silently degraded."""


MARGIN_FADE_SPEED = 0.2
"""Relative speed [m/s] above which the automatic margin is at full size."""


def auto_margin(dt: float) -> float:
    """Default discrete-time margin on ``d_s`` [m] for a step ``dt`` [s]."""
    return 2.0 * dt


@dataclass(frozen=True)
class FilterConfig:
    """Parameters of :class:`aasoatt_env.safety.core.SafetyFilter`.

    Parameters
    ----------
    barrier : str
        Barrier name, see :data:`aasoatt_env.safety.barriers.BARRIERS`.
    deadlock : str
        Deadlock strategy, see :data:`aasoatt_env.safety.deadlock.STRATEGIES`.
    trigger : str
        What switches the deadlock strategy on, see :data:`~aasoatt_env.safety.deadlock.TRIGGERS`.
    solver : str
        QP solver, see :data:`aasoatt_env.safety.solvers.backends.SOLVERS`.
    k1, k2 : float
        Barrier gains of eqn.7 / eqn.7a.
    k3, k4 : float
        Gains of the nominal tracking law eqn.12 that the deadlock corrections
        (eqn.12b, eqn.13) assume; keep them equal to the nominal controller's
        (defaults: the paper's, :data:`aasoatt_env.model.tracking.PAPER_K3` and ``PAPER_K4``).
    zeta : float
        Deadlock gain ``zeta`` of eqn.12b / eqn.13 (``k4 > zeta``, Theorem 2).
    rotation_deg : float
        Rotation angle ``q`` of ``Q`` [deg], in ``[-180, 180]``.
    sensing_range : float
        ``D`` [m]: pairs farther apart get no row.
    gamma : float
        Braking SBC gain (eqn.n4).
    varsigma, rho_v, sigma : float
        Velocity-barrier parameters (eqn.nn5, eqn.n5, eqn.n7).
    gate_range : float or None
        Gate distance of ``gated_distance`` (None: ``sensing_range``).
    safety_margin : float or None
        Added to every safety distance [m]; None: :func:`auto_margin` of ``dt``.
    dt : float
        Control step [s].
    neural_iterations : int
        Projected primal-dual updates per step of the ``neural`` solver.
    active_set : bool
        First try the warm-started exact active-set method
        (:mod:`~aasoatt_env.safety.solvers.active_set`, accepted only when the KKT
        conditions check out; the solver otherwise).  It pays off when consecutive
        QPs share their active set and costs time when the set changes every step
        (``benchmarks/bench_filter.py`` measures both).  On by default.
    mode : {"centralized", "decentralized"}
        ``"centralized"`` (default): one QP for the team (the paper's filter).
        ``"decentralized"``: every robot solves its own 2-variable QP over its
        shares of the pair rows (in proportion to ``Team.max_point_accel``,
        around the pair's nominal answers: the reciprocal split of
        :mod:`aasoatt_env.safety.decentralized`), all at once and exactly;
        ``decompose`` does not apply (``solver`` and ``active_set`` answer the negotiation
        groups only, see ``negotiate``).  A robot whose own QP is infeasible gets
        its least-violation answer (status ``"relaxed"``).  The backup layer
        still runs after it, and it is a team-wide check: it needs every
        neighbour's state and applied input (README: Decentralised filter).
    negotiate : bool
        ``mode="decentralized"`` only: a robot the deadlock trigger flags negotiates, and so
        does every robot it touches (gap below ``negotiate_gap``); the rows between
        negotiating robots are solved whole, jointly, by the negotiation groups they join
        (:mod:`aasoatt_env.safety.decentralized`); every other robot solves its own QP.
        Without it, alike robots that block each other in a crowd can stop for good (README:
        Decentralised filter).  On by default; ``False`` is the per-robot filter alone.  It
        acts only through the trigger, so with ``deadlock="none"`` nobody negotiates.
    negotiate_gap : float
        Gap [m] (distance less the two radii) below which two robots touch, in
        ``[0, sensing_range]`` (default 0.1).
    decompose : bool
        With an exact solver (all but ``neural``): robots in no row are solved in
        closed form (a 2-variable box-constrained least squares each) and the QP
        is built over the robots that share a row only.  The optimum is the same
        (the problem is separable); the QP is smaller.  True by default.
    backup : bool
        The braking backup layer (:mod:`aasoatt_env.safety.gatekeeper`, on by
        default): the QP's answer is applied only where it keeps the team in the
        set of states from which braking keeps every pair ``>= d_s``; elsewhere
        the robots brake.  This is what makes the filter safe for any nominal
        under the robots' real input bounds.  ``False`` gives the paper's filter
        alone (``aasoatt reproduce`` runs it so).
    brake_fraction : float
        The backup's control-point deceleration as a fraction of the robot's
        straight-line braking capability ``rho * max_wheel_accel``, in ``(0, 1]``.
    backup_repair : bool
        Where the backup layer would brake, first nudge the QP's answer toward
        the safe set (the least change that lifts every low backup margin,
        :func:`aasoatt_env.safety.repair.repair`) and check again; keeps crowds
        moving.  On by default.
    speed_margin : float
        Added to the safety distance of a pair in the barrier rows:
        ``speed_margin * (|v_i|^2 + |v_j|^2)`` [s^2/m] (default 0).
    max_wheel_speed : float or None
        Filter-side wheel-speed bound [rad/s] (None: none beyond the robots' own).
        The filter keeps ``|u + du dt| <= max_wheel_speed`` by tightening the box
        on ``du`` (a wheel already beyond it may brake at full acceleration, so the
        box is never empty).  The paper's barrier assumes the rows stay feasible;
        on robots without a wheel-speed limit an adversarial nominal can spin a
        robot up until the drift ``A_dot u`` exceeds what the bounded wheel
        accelerations can cancel, and from there no input keeps the barrier
        (README: known limits).  Set this for such policies; off by default
        because the paper's experiments do not have it.
    eta_tol : float
        A (normalised) multiplier above this marks a row active.
    low_speed : float
        Speed [m/s] below which the ``low_speed`` trigger considers a robot stopped.
    goal_tol : float
        Tracking error [m] above which a stopped robot counts as stuck.
    stall_time : float
        Dwell time [s] of the ``stalled`` trigger.
    stall_distance : float
        Displacement [m] over ``stall_time`` below which a robot is stalled.
    heading_deg : float
        Half-angle [deg] of the ``heading`` trigger's cone.
    kernel : {"auto", "numpy", "numba"}
        Implementation of the backup layer's check and repair, the decentralised
        filter's local solver, the warm active set and the centralised decomposition
        around it, the barrier rows, and the neighbour search (:mod:`aasoatt_env.compiled`):
        ``"auto"`` (default) the compiled kernels when numba is installed (``pip install
        "aasoatt[fast]"``), else the numpy reference; ``"numpy"`` always the reference;
        ``"numba"`` the kernels, or a :class:`~aasoatt_env.errors.ConfigError` when the filter is
        built without numba (a saved configuration still loads).  Both give the same decisions;
        their numbers agree to floating-point rounding.
    """

    barrier: str = "aasoatt"
    deadlock: str = "auxiliary_velocity"
    trigger: str = "multiplier"
    solver: str = "proxsuite"
    k1: float = 2.0
    k2: float = 2.0
    k3: float = PAPER_K3
    k4: float = PAPER_K4
    zeta: float = 2.0
    rotation_deg: float = -60.0
    sensing_range: float = 3.0
    gamma: float = 1.0
    varsigma: float = 2.0
    rho_v: float = 1.0
    sigma: float = 0.0
    gate_range: float | None = None
    safety_margin: float | None = None
    dt: float = DT
    neural_iterations: int = 1
    active_set: bool = True
    mode: str = "centralized"
    negotiate: bool = True
    negotiate_gap: float = 0.1
    decompose: bool = True
    backup: bool = True
    brake_fraction: float = 2.0 / 3.0
    backup_repair: bool = True
    speed_margin: float = 0.0
    max_wheel_speed: float | None = None
    eta_tol: float = 1e-6
    low_speed: float = 0.05
    goal_tol: float = 0.1
    stall_time: float = 0.5
    stall_distance: float = 0.02
    heading_deg: float = 30.0
    kernel: str = "auto"

    def __post_init__(self) -> None:
        for name, registry in (("barrier", BARRIERS), ("deadlock", STRATEGIES), ("trigger", TRIGGERS),
                               ("mode", MODES), ("kernel", KERNELS)):
            check.choice(name, getattr(self, name), registry)
        if not isinstance(self.solver, str):
            raise ConfigError(f"solver: got {self.solver!r}, expected a solver name")
        get_solver(self.solver)  # raises SolverError listing what is available
        gains = ("k1", "k2", "k3", "k4", "gamma", "varsigma", "rho_v")
        for name in gains:
            object.__setattr__(self, name, check.positive(name, getattr(self, name), hi=GAIN_MAX))
        for name in ("sensing_range", "dt", "eta_tol", "low_speed", "goal_tol", "stall_time", "stall_distance"):
            object.__setattr__(self, name, check.positive(name, getattr(self, name)))
        object.__setattr__(self, "dt", check.real("dt", self.dt, lo=1e-6, hi=0.1))
        object.__setattr__(self, "heading_deg", check.real("heading_deg", self.heading_deg, lo=0.0, hi=180.0,
                                                           lo_open=True))
        object.__setattr__(self, "zeta", check.real("zeta", self.zeta, lo=0.0, hi=GAIN_MAX))
        object.__setattr__(self, "sigma", check.real("sigma", self.sigma, lo=-GAIN_MAX, hi=GAIN_MAX))
        object.__setattr__(self, "rotation_deg", check.real("rotation_deg", self.rotation_deg, lo=-180.0, hi=180.0))
        for name in ("gate_range", "max_wheel_speed"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, check.positive(name, getattr(self, name)))
        if self.safety_margin is not None:
            object.__setattr__(self, "safety_margin", check.real("safety_margin", self.safety_margin, lo=0.0, hi=1.0))
        object.__setattr__(self, "brake_fraction", check.real("brake_fraction", self.brake_fraction, lo=0.0,
                                                              hi=1.0, lo_open=True))
        object.__setattr__(self, "speed_margin", check.real("speed_margin", self.speed_margin, lo=0.0, hi=1.0))
        object.__setattr__(self, "negotiate_gap", check.real("negotiate_gap", self.negotiate_gap, lo=0.0,
                                                             hi=self.sensing_range))
        for flag in ("active_set", "negotiate", "decompose", "backup", "backup_repair"):
            check.boolean(flag, getattr(self, flag))
        object.__setattr__(self, "neural_iterations",
                           check.integer("neural_iterations", self.neural_iterations, lo=1, hi=1_000_000))
        if STRATEGIES[self.deadlock].active and not self.k4 > self.zeta:
            raise ConfigError(
                f"k4 must exceed zeta (Theorem 2's convergence condition k4 > zeta): "
                f"got k4={self.k4}, zeta={self.zeta}, expected k4 > {self.zeta}"
            )

    @classmethod
    def merged(cls, config: FilterConfig | Mapping[str, Any] | None = None, /, **options: Any) -> FilterConfig:
        """The one rule for combining a configuration with explicit options.

        Start from ``config`` (a :class:`FilterConfig`, a mapping of its fields
        as read from TOML/JSON/the command line, or None for the defaults); every
        explicit keyword in ``options`` replaces that field.  Unknown names raise
        ``TypeError`` listing the fields; values are validated once.
        """
        known = [f.name for f in fields(cls)]
        if config is None:
            base = cls()
        elif isinstance(config, FilterConfig):
            base = config
        elif isinstance(config, Mapping):
            check.reject_unknown("FilterConfig", config, known)
            base = cls(**dict(config))
        else:
            raise ConfigError(
                f"config: got {type(config).__name__}, expected a FilterConfig, a mapping of its fields or None"
            )
        check.reject_unknown("FilterConfig", options, known)
        return replace(base, **options) if options else base

    @property
    def margin(self) -> float:
        """Largest margin added to a safety distance [m]."""
        return auto_margin(self.dt) if self.safety_margin is None else float(self.safety_margin)

    def pair_margin(self, v_rel: np.ndarray) -> np.ndarray | float:
        """Margin of each pair ``(P,)`` from the relative velocities ``(P, 2)`` (module docstring)."""
        if self.safety_margin is not None:
            return float(self.safety_margin)
        speed = np.sqrt(row_dot(v_rel, v_rel))
        return auto_margin(self.dt) * np.minimum(1.0, speed / MARGIN_FADE_SPEED)

    @property
    def compiled(self) -> bool:
        """Whether the filter runs the compiled kernels (:attr:`kernel` resolved)."""
        return self.kernel != "numpy" and available()
