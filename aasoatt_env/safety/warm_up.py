"""Compile the filter's and the env's kernels before a control loop starts (``aasoatt warm-up``).

numba compiles each kernel the first time it runs and caches it on disk, which from an empty cache takes tens
of seconds; :func:`warm_up` runs every compiled part once on tiny problems with the filter's argument types.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from aasoatt_env import compiled
from aasoatt_env.compiled import KERNELS, NUMBA_MISSING
from aasoatt_env.errors import ConfigError

__all__ = ["warm_up"]


def _scenes() -> list[tuple[str, Callable[[], None]]]:
    """``(name, run)`` of the tiny problems that reach every compiled part, with the filter's argument types."""
    from aasoatt_env.model.dynamics import DT, input_bounds
    from aasoatt_env.model.geometry import pair_components, robot_pairs
    from aasoatt_env.model.params import make_team
    from aasoatt_env.safety.backup.gate import gatekeeper, repair
    from aasoatt_env.safety.core import SafetyFilter  # (core imports this module)
    from aasoatt_env.safety.solvers.local import solve_local_qps

    team = make_team("paper", 2)
    pose, u = np.array([[0.0, 0.0, 0.0], [1.2, 0.05, np.pi]]), np.full((2, 2), 8.0)
    lo, hi = input_bounds(team, u, DT)
    obstacles = (np.array([[0.6, 1.5]]), np.array([0.3]))

    def team_steps(mode: str, backup: bool) -> None:  # rows, the QP stages, the check, with and without obstacles
        for deadlock, ref in (("auxiliary_velocity", (pose[:, :2], np.zeros((2, 2)))), ("rotate_nominal", None)):
            f = SafetyFilter(team, mode=mode, backup=backup, kernel="numba", deadlock=deadlock)
            for k in range(3):
                f.from_state(pose, u, np.full((2, 2), 60.0 * (1 - 2 * (k % 2))), reference=ref,
                             obstacles=obstacles if k else None)

    def backup_layer() -> None:  # the check (quick, full, held) and the repair, as the layer calls them
        layer = dict(sensing_range=3.0, brake_fraction=2.0 / 3.0, compiled=True, checked=True,
                     near_pairs=np.array([[0, 1]]))
        for obs in (None, obstacles):
            for quick, hold in ((True, False), (False, False), (False, True)):
                gatekeeper(team, pose, u, hi, DT, quick=quick, hold_violations=hold, obstacles=obs, **layer)
            repair(team, pose, u, hi, DT, lo, hi, obstacles=obs, **layer)

    def local_qps() -> None:  # one robot's infeasible QP (its relaxation too), and a feasible one
        solve_local_qps(np.tile(np.eye(2), (2, 1, 1)), np.zeros((2, 2)), -np.ones((2, 2)), np.ones((2, 2)),
                        np.array([0, 0, 1]), np.array([[1.0, 0.0], [-1.0, 0.0], [1.0, 1.0]]),
                        np.array([-2.0, -2.0, 0.5]), relax=True, relax_tol=np.full(2, 1e-7), compiled=True)

    def env() -> None:  # the env's kinematics, step and observations, as one team and as stacked teams
        from aasoatt_env.sim.batched import BatchedAASOATTEnv
        from aasoatt_env.sim.env import AASOATTParallelEnv

        def one() -> AASOATTParallelEnv:
            return AASOATTParallelEnv("random_goals", num_robots=3, random_obstacles=1)

        single = one()
        single.reset(seed=0)
        single.step({a: np.ones(2, np.float32) for a in single.agents})
        stacked = BatchedAASOATTEnv([one, one])
        stacked.reset(seed=0)
        stacked.step(np.ones((2, 3, 2), np.float32))

    def geometry() -> None:
        p = np.random.default_rng(0).uniform(0, 5, (8, 2))
        pairs = robot_pairs(p, 3.0, method="cells")
        pair_components(8, pairs[:, 0], pairs[:, 1], compiled=True)

    return [("geometry", geometry), ("env", env), ("backup layer", backup_layer), ("local QPs", local_qps)] + [
        (f"{mode} filter{' + backup' if backup else ''}", lambda mode=mode, backup=backup: team_steps(mode, backup))
        for mode in ("centralized", "decentralized") for backup in (True, False)]


def warm_up(kernel: str = "auto", progress: Callable[[str], None] | None = None) -> bool:
    """Compile (or load from numba's cache) every kernel a filter with ``kernel`` (``FilterConfig.kernel``) runs.

    ``progress`` gets each part's name before it runs.  Returns False for ``"numpy"`` and for ``"auto"`` without numba.
    """
    if kernel not in KERNELS:
        raise ConfigError(f"kernel: got {kernel!r}, expected one of {list(KERNELS)}")
    if kernel == "numpy" or not compiled.available():
        if kernel == "numba":
            raise ConfigError(f"kernel: {NUMBA_MISSING}")
        return False
    for name, run in _scenes():
        if progress is not None:
            progress(name)
        run()
    return True
