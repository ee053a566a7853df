"""Validated configuration of the safety filter (:class:`FilterConfig`).

Defaults follow ``docs/technical_brief.md`` section 7 (``k1 = k2 = 2``, ``k3 = 1``, ``k4 = 4``, ``zeta = 2``,
``q = -60 deg``, ``D = 3 m``, ``dt = 5 ms``); where the paper gives no value these are our choices
(``gamma = 1``, ``varsigma = 2``, ``rho_v = 1``, ``sigma = 0``).

Discrete-time margin: the barrier's guarantee is for continuous time; with ``du`` held over ``dt``
pairs dip a few millimetres below ``d_s``.  ``safety_margin=None`` adds to each pair's safety distance
``auto_margin(dt) * min(1, |v_ij| / 0.2 m/s)`` (1 cm at 5 ms for pairs in relative motion, fading to 0 at
relative rest, so packings feasible for ``d_s``, such as 39 robots at their goals on the radius-6 circle,
stay reachable); a float adds that constant instead, ``0`` the paper's exact barrier.
"""

from __future__ import annotations

import functools
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

__all__ = ["GAIN_MAX", "MODES", "NEURAL_ITERATIONS_MAX", "FilterConfig", "auto_margin"]

MODES: tuple[str, ...] = ("centralized", "decentralized")
"""Values of :attr:`FilterConfig.mode`."""

GAIN_MAX: float = 1e3
"""Largest accepted gain (``k1``, ``k2``, ``k3``, ``k4``, ``gamma``, ``varsigma``, ``rho_v``): stiffer rows make
the QP infeasible on most steps, so such gains are refused rather than silently degraded."""
NEURAL_ITERATIONS_MAX: int = 20_000
"""Largest ``neural_iterations``: a step's work is bounded by a number the user sees."""


MARGIN_FADE_SPEED = 0.2
"""Relative speed [m/s] above which the automatic margin is at full size."""


def auto_margin(dt: float) -> float:
    """Default discrete-time margin on ``d_s`` [m] for a step ``dt`` [s]."""
    return 2.0 * dt


@dataclass(frozen=True)
class FilterConfig:
    """Parameters of :class:`~aasoatt_env.safety.core.SafetyFilter` (every field validated when made).

    Parameters
    ----------
    barrier, deadlock, trigger, solver : str
        Registered names: :data:`~aasoatt_env.safety.barriers.BARRIERS`,
        :data:`~aasoatt_env.safety.deadlock.STRATEGIES`, :data:`~aasoatt_env.safety.deadlock.TRIGGERS`,
        :data:`~aasoatt_env.safety.solvers.SOLVERS` (the back-end; :mod:`~aasoatt_env.safety.solvers.policy`
        decides which solver answers each problem).
    k1, k2 : float
        Barrier gains (eqn.7, eqn.7a).
    k3, k4 : float
        The nominal tracking law's gains that eqn.12b and eqn.13 assume (the paper's); ``k4 > zeta`` (Theorem 2).
    zeta, rotation_deg : float
        Deadlock gain and the rotation ``q`` of ``Q`` [deg] (eqn.12-14).
    sensing_range : float
        ``D`` [m]: pairs farther apart get no row.
    gamma, varsigma, rho_v, sigma, gate_range : float
        Braking SBC gain (eqn.n4); velocity barriers (eqn.nn5, eqn.n5/n6 with ``gate_range``, None: ``D``; eqn.n7).
    safety_margin : float or None
        Added to every safety distance [m]; None: the speed-dependent discrete-time margin (module docstring).
    dt : float
        Control step [s].
    neural_iterations : int
        Projected primal-dual updates per step of the ``neural`` solver (at most :data:`NEURAL_ITERATIONS_MAX`).
    active_set : bool
        Try the warm-started exact active set first (accepted only where the KKT conditions hold).
    mode : {"centralized", "decentralized"}
        One QP for the team (the paper's), or every robot's own 2-variable QP over its share of each pair row
        (:mod:`~aasoatt_env.safety.decentralized`); ``decompose`` does not apply to the latter.
    negotiate, negotiate_gap : bool, float
        Decentralised only: robots the deadlock trigger flags, and those touching them (gap below
        ``negotiate_gap`` [m]), solve the rows among them jointly; without it alike robots can block each other
        for good.
    decompose : bool
        Robots in no violated row are answered in closed form, the QP built over the others (the same optimum).
    backup : bool
        The braking backup layer (:mod:`~aasoatt_env.safety.backup`): the QP's answer is applied only where braking
        from the state it leads to keeps every pair apart; this makes the filter safe for any nominal under the
        real input bounds.  ``False``: the paper's filter alone (``aasoatt reproduce`` runs it so).
    brake_fraction : float
        The backup's deceleration as a fraction of the robot's straight-line braking capability, in ``(0, 1]``.
    backup_repair : bool
        Where the layer would brake, first nudge the QP's answer toward brake-safety and check again.
    speed_margin : float
        ``speed_margin * (|v_i|^2 + |v_j|^2)`` [s^2/m] added to a pair's safety distance in the rows.
    max_wheel_speed : float or None
        Filter-side wheel-speed bound [rad/s]: the box on ``du`` is tightened so ``|u + du dt|`` stays within it
        (a policy that spins robots up beyond what the wheels can cancel makes the rows infeasible).
    eta_tol : float
        A normalised multiplier above this marks a row active (the ``multiplier`` trigger).
    low_speed, goal_tol, stall_time, stall_distance, heading_deg : float
        Thresholds of the triggers (:mod:`~aasoatt_env.safety.deadlock`).
    kernel : {"auto", "numpy", "numba"}
        The stages' implementation (:mod:`aasoatt_env.compiled`): compiled where numba is installed
        (``"auto"``), the numpy reference (``"numpy"``), or compiled or an error (``"numba"``).
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
                           check.integer("neural_iterations", self.neural_iterations, lo=1, hi=NEURAL_ITERATIONS_MAX))
        if STRATEGIES[self.deadlock].active and not self.k4 > self.zeta:
            raise ConfigError(
                f"k4 must exceed zeta (Theorem 2's convergence condition k4 > zeta): "
                f"got k4={self.k4}, zeta={self.zeta}, expected k4 > {self.zeta}"
            )

    @classmethod
    def merged(cls, config: FilterConfig | Mapping[str, Any] | None = None, /, **options: Any) -> FilterConfig:
        """``config`` (a FilterConfig, a mapping of its fields, None: defaults) with ``options`` replacing fields.

        The one rule for combining a configuration with explicit options; unknown names raise ``TypeError``
        listing the fields.
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

    @functools.cached_property
    def compiled(self) -> bool:
        """Whether the filter runs the compiled kernels (:attr:`kernel` resolved)."""
        return self.kernel != "numpy" and available()
