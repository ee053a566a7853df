"""The fused step: a warm centralised step's rows, QP and backup check in one compiled call.

Chosen when the filter is built where each of those stages runs compiled (:func:`fusable`); it calls their
own kernels, so where it answers, the step is the pipeline's bit for bit (``tests/test_compiled.py``).  It
answers the rows and the solve where the QP is verified, and the backup too where its quick check leaves nothing
to hold or repair (it brakes nobody, or only robots whose path leaves their range limit); a stage it does not
answer runs in the pipeline from its start.  At a few tens of robots a step's cost is mostly the calls between
the stages, which this saves.
"""

from __future__ import annotations

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.dynamics import pose_from_point
from aasoatt_env.safety.backup import GATE_TOL, BackupAnswer
from aasoatt_env.safety.backup.gate import BLEND_LEVELS, kernel_args, levels_of, team_block
from aasoatt_env.safety.centralized import CLOSED_FORM_MESSAGE, kernel_settings
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.rows import CompiledRows, Pairs, Rows, kernel_rows
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers.active_set import VERIFIED_MESSAGE
from aasoatt_env.safety.stages import Answer, StepInput

__all__ = ["FusedStep", "fusable"]


def fusable(cfg: FilterConfig, rotates_rows: bool, exact: bool) -> bool:
    """Whether every stage the fused step replaces runs compiled in this configuration."""
    return (cfg.compiled and cfg.barrier == "aasoatt" and not rotates_rows and cfg.mode == "centralized"
            and cfg.decompose and cfg.active_set and exact and cfg.backup)


class FusedStep:
    """``step(s, pairs, target, x, keys, z) -> (rows, answer, backup or None)`` or None (module docstring)."""

    def __init__(self, cfg: FilterConfig, policy: SolverPolicy, rows: CompiledRows) -> None:
        self.cfg, self._rows = cfg, rows
        self._kernel = kernels("fused").fused_step
        self._settings = kernel_settings(policy)
        self._levels = levels_of(BLEND_LEVELS)

    def __call__(self, s: StepInput, pairs: Pairs, target: np.ndarray, x: np.ndarray, keys: np.ndarray,
                 z: np.ndarray) -> tuple[Rows, Answer, BackupAnswer | None] | None:
        """The step's rows, QP answer and backup answer (None: the backup stage runs), or None (module docstring)."""
        cfg, team = self.cfg, s.team
        limit = team_block(team, cfg.brake_fraction, cfg.sensing_range)[1]
        pose = pose_from_point(team, s.p, s.theta)
        solved, passed, r, qp, avoiding, (gdu, braking, nudged, margin) = self._kernel(
            self._rows.args(cfg, s, pairs), (c64(target), s.lo, s.hi, s.scale), (c64(x), keys, z), self._settings,
            cfg.eta_tol, (pose, s.u, cfg.dt, self._levels, limit, GATE_TOL),
            kernel_args(team, pose, cfg.brake_fraction, cfg.sensing_range, s.obstacles, pairs.robots))
        if not solved:
            return None
        used, n_qp, du, x_new, z_new, eta = qp
        ans = Answer(du, x_new, z_new, eta, avoiding, "solved", VERIFIED_MESSAGE if n_qp else CLOSED_FORM_MESSAGE,
                     int(used), int(n_qp), 0.0, True)
        backup = BackupAnswer(gdu, braking, nudged, float(margin), True) if passed else None
        return kernel_rows(r), ans, backup
