"""Validated configuration of the safety filter (:class:`FilterConfig`).

Defaults follow ``docs/technical_brief.md`` section 7 (``k1 = k2 = 2``, ``k3 = 1``, ``k4 = 4``, ``zeta = 2``,
``q = -60 deg``, ``D = 3 m``, ``dt = 5 ms``); ``gamma``, ``varsigma``, ``rho_v``, ``sigma`` (not in the paper) are ours.
``safety_margin=None`` adds ``auto_margin(dt) * min(1, |v_ij| / 0.2 m/s)`` to each pair's safety distance
(``docs/design.md``); a float adds that constant instead, ``0`` the paper's exact barrier.
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
from aasoatt_env.model.geometry import namespace, row_norm
from aasoatt_env.model.tracking import PAPER_K3, PAPER_K4
from aasoatt_env.safety.barriers import BARRIERS
from aasoatt_env.safety.deadlock import STRATEGIES, TRIGGERS
from aasoatt_env.safety.solvers import get_solver

__all__ = ["GAIN_MAX", "MODES", "NEURAL_ITERATIONS_MAX", "FilterConfig", "auto_margin"]

MODES: tuple[str, ...] = ("centralized", "decentralized")  #: values of :attr:`FilterConfig.mode`
#: largest accepted gain (``k1``-``k4``, ``gamma``, ``varsigma``, ``rho_v``): stiffer rows make most QPs infeasible
GAIN_MAX: float = 1e3
NEURAL_ITERATIONS_MAX: int = 20_000  #: a step's work is bounded by a number the user sees
MARGIN_FADE_SPEED = 0.2  #: relative speed [m/s] above which the automatic margin is at full size
_OPTIONAL = ("gate_range", "max_wheel_speed", "safety_margin")


def auto_margin(dt: float) -> float:
    """Default discrete-time margin on ``d_s`` [m] for a step ``dt`` [s]."""
    return 2.0 * dt


@dataclass(frozen=True)
class FilterConfig:
    """Parameters of :class:`~aasoatt_env.safety.core.SafetyFilter`, each validated when the config is made."""

    barrier: str = "aasoatt"  #: a name in :data:`~.barriers.BARRIERS`
    deadlock: str = "auxiliary_velocity"  #: a name in :data:`~.deadlock.STRATEGIES`
    trigger: str = "multiplier"  #: a name in :data:`~.deadlock.TRIGGERS`
    #: the back-end, a name in :data:`~.solvers.SOLVERS` (:mod:`~.solvers.policy` decides which solver answers)
    solver: str = "proxsuite"
    k1: float = 2.0  #: barrier gain (eqn.7)
    k2: float = 2.0  #: barrier gain (eqn.7a)
    k3: float = PAPER_K3  #: the tracking law's gain that eqn.12b and eqn.13 assume
    k4: float = PAPER_K4  #: the tracking law's gain that eqn.12b and eqn.13 assume; ``k4 > zeta`` (Theorem 2)
    zeta: float = 2.0  #: deadlock gain (eqn.12-13)
    rotation_deg: float = -60.0  #: the rotation ``q`` of ``Q`` [deg] (eqn.14)
    sensing_range: float = 3.0  #: ``D`` [m]: pairs farther apart get no row
    gamma: float = 1.0  #: braking SBC gain (eqn.n4)
    varsigma: float = 2.0  #: the velocity barriers' gain (eqn.nn5, eqn.n5/n6, eqn.n7)
    rho_v: float = 1.0  #: eqn.n7's adaptive distance
    sigma: float = 0.0  #: eqn.n7's adaptive distance
    gate_range: float | None = None  #: eqn.n5/n6's gate [m] (None: ``D``)
    #: added to every safety distance [m]; None: the discrete-time margin (module docstring)
    safety_margin: float | None = None
    dt: float = DT  #: control step [s]
    neural_iterations: int = 1  #: ``neural``'s projected primal-dual updates a step (<= NEURAL_ITERATIONS_MAX)
    active_set: bool = True  #: try the warm-started exact active set first (taken where the KKT conditions hold)
    mode: str = "centralized"  #: one QP for the team (the paper's), or each robot's own (:mod:`~.decentralized`)
    #: decentralised: flagged robots and those touching them (gap below ``negotiate_gap`` [m]) solve jointly;
    #: without it alike robots can block each other for good
    negotiate: bool = True
    negotiate_gap: float = 0.1
    #: centralised: robots in no violated row are answered in closed form, the QP built over the others (same optimum)
    decompose: bool = True
    #: the braking backup layer (:mod:`~.backup`): safe for any nominal under the real input bounds; False: the
    #: paper's filter alone (as ``aasoatt reproduce`` runs it)
    backup: bool = True
    brake_fraction: float = 2.0 / 3.0  #: the backup's deceleration, a fraction of the braking capability, in (0, 1]
    backup_repair: bool = True  #: where the layer would brake, first nudge the answer toward brake-safety
    speed_margin: float = 0.0  #: ``speed_margin * (|v_i|^2 + |v_j|^2)`` [s^2/m] added to a pair's safety distance
    #: wheel-speed bound [rad/s]: ``du``'s box keeps ``|u + du dt|`` within it (spun-up wheels make rows infeasible)
    max_wheel_speed: float | None = None
    eta_tol: float = 1e-6  #: a normalised multiplier above this marks a row active (the ``multiplier`` trigger)
    low_speed: float = 0.05  #: the triggers' thresholds (:mod:`~.deadlock`) [m/s]
    goal_tol: float = 0.1  #: [m]
    stall_time: float = 0.5  #: [s]
    stall_distance: float = 0.02  #: [m]
    heading_deg: float = 30.0  #: [deg]
    #: ``"auto"``: compiled where numba is installed; ``"numpy"``: the reference; ``"numba"``: compiled or an error
    kernel: str = "auto"

    def __post_init__(self) -> None:
        for name, registry in (("barrier", BARRIERS), ("deadlock", STRATEGIES), ("trigger", TRIGGERS),
                               ("mode", MODES), ("kernel", KERNELS)):
            check.choice(name, getattr(self, name), registry)
        if not isinstance(self.solver, str):
            raise ConfigError(f"solver: got {self.solver!r}, expected a solver name")
        get_solver(self.solver)  # raises SolverError listing what is available
        ranges = [*((k, 0, GAIN_MAX, True) for k in ("k1", "k2", "k3", "k4", "gamma", "varsigma", "rho_v")),
                  *((k, 0, None, True) for k in ("sensing_range", "dt", "eta_tol", "low_speed", "goal_tol",
                                                 "stall_time", "stall_distance")),
                  ("dt", 1e-6, 0.1, False), ("heading_deg", 0, 180, True), ("zeta", 0, GAIN_MAX, False),
                  ("sigma", -GAIN_MAX, GAIN_MAX, False), ("rotation_deg", -180, 180, False),
                  ("gate_range", 0, None, True), ("max_wheel_speed", 0, None, True), ("safety_margin", 0, 1, False),
                  ("brake_fraction", 0, 1, True), ("speed_margin", 0, 1, False)]
        for name, lo, hi, lo_open in ranges:
            if name not in _OPTIONAL or getattr(self, name) is not None:
                object.__setattr__(self, name, check.real(name, getattr(self, name), lo=lo, hi=hi, lo_open=lo_open))
        object.__setattr__(self, "negotiate_gap", check.real("negotiate_gap", self.negotiate_gap, lo=0.0,
                                                             hi=self.sensing_range))
        for flag in ("active_set", "negotiate", "decompose", "backup", "backup_repair"):
            check.boolean(flag, getattr(self, flag))
        object.__setattr__(self, "neural_iterations",
                           check.integer("neural_iterations", self.neural_iterations, lo=1, hi=NEURAL_ITERATIONS_MAX))
        if STRATEGIES[self.deadlock].active and not self.k4 > self.zeta:
            raise ConfigError(f"k4 must exceed zeta (Theorem 2's convergence condition k4 > zeta): "
                              f"got k4={self.k4}, zeta={self.zeta}, expected k4 > {self.zeta}")

    @classmethod
    def merged(cls, config: FilterConfig | Mapping[str, Any] | None = None, /, **options: Any) -> FilterConfig:
        """``config`` (a FilterConfig, a mapping of its fields, None: defaults) with ``options`` replacing fields.

        Unknown names raise ``TypeError`` listing the fields.
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
            raise ConfigError(f"config: got {type(config).__name__}, expected a FilterConfig, a mapping of its fields "
                              "or None")
        check.reject_unknown("FilterConfig", options, known)
        return replace(base, **options) if options else base

    @property
    def margin(self) -> float:
        """Largest margin added to a safety distance [m]."""
        return auto_margin(self.dt) if self.safety_margin is None else float(self.safety_margin)

    def pair_margin(self, v_rel: np.ndarray) -> np.ndarray | float:
        """Margin of each pair ``(...,)`` from the relative velocities ``(..., 2)`` (module docstring)."""
        if self.safety_margin is not None:
            return float(self.safety_margin)
        xp = namespace(v_rel)
        return auto_margin(self.dt) * xp.minimum(row_norm(v_rel) / MARGIN_FADE_SPEED, 1.0)

    @functools.cached_property
    def compiled(self) -> bool:
        """Whether the filter runs the compiled kernels (:attr:`kernel` resolved)."""
        return self.kernel != "numpy" and available()
