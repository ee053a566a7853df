"""Compile the filter's kernels before a control loop starts.

numba compiles each kernel the first time it runs (and caches it on disk): from a
cold cache a centralised filter's first two steps take seconds, a decentralised
filter's first step too (README: *The braking backup layer*, Implementation).  A
robot that starts its control loop on such a step misses its deadlines.
:func:`warm_up` runs every compiled part once on a tiny problem, with the argument
types the filter passes, so the first real step runs at speed.
"""

from __future__ import annotations

import numpy as np

from aasoatt_env import compiled
from aasoatt_env.compiled import KERNELS, NUMBA_MISSING
from aasoatt_env.errors import ConfigError
from aasoatt_env.model.dynamics import DT, input_bounds, kinematics
from aasoatt_env.model.geometry import brute_candidates, pair_components, robot_pairs
from aasoatt_env.model.params import make_team
from aasoatt_env.safety.decomposition import solve_centralized
from aasoatt_env.safety.gatekeeper import gatekeeper
from aasoatt_env.safety.problem import box_least_squares, build_problem
from aasoatt_env.safety.repair import repair
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers.active_set import solve_active_set_parts
from aasoatt_env.safety.solvers.local import solve_local_qps

__all__ = ["warm_up"]


def warm_up(kernel: str = "auto") -> bool:
    """Compile (or load from numba's cache) every kernel a filter with ``kernel`` can run.

    Parameters
    ----------
    kernel : {"auto", "numpy", "numba"}
        :attr:`~aasoatt_env.safety.config.FilterConfig.kernel`.

    Returns
    -------
    bool
        Whether kernels were run: ``False`` for ``"numpy"``, and for ``"auto"`` without numba.

    Raises
    ------
    ConfigError
        ``kernel`` unknown, or ``"numba"`` without numba.
    """
    if kernel not in KERNELS:
        raise ConfigError(f"kernel: got {kernel!r}, expected one of {list(KERNELS)}")
    if kernel == "numpy" or not compiled.available():
        if kernel == "numba":
            raise ConfigError(f"kernel: {NUMBA_MISSING}")
        return False
    # two robots driving at each other, 1.5 m apart: pairs, rows, braking paths, a repair
    team = make_team("paper", 2)
    pose = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, np.pi]])
    u = np.full((2, 2), 5.0)
    du = np.zeros((2, 2))
    lo, hi = input_bounds(team, u, DT)
    layer = dict(sensing_range=3.0, brake_fraction=2.0 / 3.0, compiled=True)
    gatekeeper(team, pose, u, du, DT, quick=True, **layer)
    repair(team, pose, u, du, DT, lo, hi, **layer)
    pairs = robot_pairs(pose[:, :2], 3.0, method="cells")
    pair_components(2, pairs[:, 0], pairs[:, 1], compiled=True)
    # one robot's QP that is infeasible (its relaxation too), and a two-robot QP with a warm start
    eye = np.eye(2)[None]
    solve_local_qps(eye, np.zeros((1, 2)), -np.ones((1, 2)), np.ones((1, 2)), np.zeros(2, np.intp),
                    np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([-2.0, -2.0]), relax=True, compiled=True)
    prob = build_problem(np.tile(np.eye(2), (2, 1, 1)), np.array([[1.0, 0.0], [-1.0, 0.0]]), -np.ones((2, 2)),
                         np.ones((2, 2)), np.ones(2), np.array([0]), np.array([1]), np.array([[1.0, 0.0]]),
                         np.array([[-1.0, 0.0]]), np.array([0.1]))
    solve_active_set_parts(prob, np.zeros(4), np.ones(1), None, compiled=True)
    # the same two robots' closed forms (the decentralised split's), and through the centralised step's
    # compiled decomposition
    policy = SolverPolicy("proxsuite", active_set=True, compiled=True)
    solve_centralized(policy, np.tile(np.eye(2), (2, 1, 1)), np.array([[1.0, 0.0], [-1.0, 0.0]]), -np.ones((2, 2)),
                      np.ones((2, 2)), np.ones(2), np.array([0]), np.array([1]), np.array([[1.0, 0.0]]),
                      np.array([[-1.0, 0.0]]), np.array([0.1]), np.zeros((2, 2)), np.ones(1), compiled=True)
    box_least_squares(np.tile(np.eye(2), (2, 1, 1)), np.ones((2, 2)), -np.ones((2, 2)), np.ones((2, 2)), compiled=True)
    # the barrier rows of the pair (the filter's argument types: rows_kernel)
    kin = kinematics(team, pose, u)
    c64 = compiled.c64
    compiled.kernels("rows").aasoatt_rows(c64(kin.p), c64(kin.v), c64(kin.adot_u), c64(kin.A), c64(team.radius),
                                          *brute_candidates(2), 9.0, 1.0, 1.0, np.nan, 0.01, 0.2, 0.0, 3, 3.0)
    # the whole step (step_kernel): a filter's second step, warm-started from its first, with the layer and without
    from aasoatt_env.safety.core import SafetyFilter  # (core imports this module)

    for backup in (True, False):
        filt = SafetyFilter(team, backup=backup, kernel="numba")
        for _ in range(2):
            filt.from_state(pose, u, du, reference=(kin.p, np.zeros((2, 2))))
    return True
