"""What one filter step did: :class:`FilterResult` (the pipeline's last stage, :func:`result`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aasoatt_env.safety.backup import BackupAnswer
from aasoatt_env.safety.rows import Rows
from aasoatt_env.safety.stages import Answer

__all__ = ["COLLISION_TOL", "STATUSES", "FilterResult", "result"]

STATUSES: tuple[str, ...] = ("solved", "relaxed", "backup", "failed", "unsafe")
"""Filter statuses from best to worst (:attr:`FilterResult.status`)."""
COLLISION_TOL: float = 1e-3
"""Overlap [m] beyond which a pair counts as colliding (the metrics' tolerance): without the backup layer
the status is ``"unsafe"`` then, whatever the barrier's value."""
_BARRIER_TOL = 1e-6
"""A barrier value below this is outside the barrier's safe set (backup layer off)."""


@dataclass(frozen=True)
class FilterResult:
    """What one :meth:`~aasoatt_env.safety.core.SafetyFilter.step` did.

    Attributes
    ----------
    du : numpy.ndarray
        The safe wheel accelerations ``(N, 2)``, within the bounds.
    status : str
        The worst of what happened (:data:`STATUSES`): ``"solved"`` (the QP's optimum), ``"relaxed"``
        (infeasible rows loosened by ``slack``, bounds kept), ``"backup"`` (the backup layer braked or
        nudged some robots), ``"failed"`` (no solver answered) or ``"unsafe"`` (the team is outside the
        safe set: with the backup layer, the state was not brake-safe; without it, some pair has
        ``h < 0`` or overlaps by more than :data:`COLLISION_TOL`).
    safe : bool
        ``status != "unsafe"``.
    backup : numpy.ndarray
        ``(N,)`` robots the backup layer braked (nudged ones are counted in the message only).
    margin : float
        With the backup layer: the smallest ``distance - d_s`` [m] of any pair along the backup
        horizon of the applied inputs.  Without it: the smallest surface gap of the pairs in range.
    barrier_min : float
        Smallest barrier value ``h`` of the rows, without the discrete-time margins (``inf`` without rows).
    message : str
        Which solver answered, and what the backup layer did.
    eta : numpy.ndarray
        ``(m,)`` multiplier of each row in the units of eqn.8.
    pairs : numpy.ndarray
        ``(m, 2)`` the rows' pairs: ``(i, j)``, or ``(i, -1 - k)`` for obstacle ``k``.
    avoiding, triggered, intervened : numpy.ndarray
        ``(N,)``: a row of the robot binds (or it brakes); the deadlock strategy acts on it; its
        nominal was changed.
    slack : float
        Largest violation of a row by ``du`` (eqn.8 units; 0 when solved).
    correction : numpy.ndarray
        ``(N,)`` ``|du - du_nominal|``.
    iterations : int
        Solver iterations.
    solve_time : float
        Wall time of the step [s] (reported only: no decision reads it).
    n_rows, n_qp_rows : int
        Barrier rows, and those the QP solver saw (0 where the closed form answered).
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
        """``(n_rows,)`` bool: the row is a robot-obstacle row."""
        return self.pairs[:, 1] < 0


def result(nominal: np.ndarray, scale: np.ndarray, rows: Rows, ans: Answer, backup: BackupAnswer | None,
           triggered: np.ndarray, solve_time: float) -> FilterResult:
    """The step's :class:`FilterResult` from its stages' answers (``backup`` None: the layer is off)."""
    status, message = ans.status, ans.message
    if backup is None:
        du, braking = ans.du, np.zeros(ans.du.shape[0], dtype=bool)
        margin = rows.gap_min
        safe = not (rows.barrier_min < -_BARRIER_TOL or rows.gap_min < -COLLISION_TOL)
    else:
        du, braking, margin, safe = backup.du, backup.braking, backup.margin, backup.safe
        n_braked, n_nudged = np.count_nonzero(braking), np.count_nonzero(backup.nudged)
        if n_braked:
            message = f"{message}; backup braked {n_braked} robot(s)"
        if n_nudged:
            message = f"{message}; backup nudged {n_nudged} robot(s) toward brake-safety"
        if (n_braked or n_nudged) and STATUSES.index(status) < STATUSES.index("backup"):
            status = "backup"
    if not safe:
        status = "unsafe"
    d = du - nominal
    correction = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    return FilterResult(du, status, safe, braking, float(margin), rows.barrier_min, message, ans.eta, rows.pairs,
                        ans.avoiding | braking, triggered, ans.slack, correction, correction > 1e-9 * scale,
                        ans.iterations, solve_time, rows.m, ans.n_qp)
