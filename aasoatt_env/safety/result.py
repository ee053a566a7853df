"""What one filter step did: :class:`FilterResult` (the pipeline's last stage, :func:`result`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aasoatt_env.safety.backup import BackupAnswer
from aasoatt_env.safety.rows import Rows
from aasoatt_env.safety.stages import BACKUP, GROUPED, RELAXED, UNSAFE, Answer

__all__ = ["BACKUP", "COLLISION_TOL", "GROUPED", "RELAXED", "STATUSES", "UNSAFE", "FilterResult", "result"]

STATUSES: tuple[str, ...] = ("solved", "relaxed", "backup", "failed", "unsafe")  #: from best to worst
#: overlap [m] beyond which a pair counts as colliding (the metrics' tolerance; without the backup layer: unsafe)
COLLISION_TOL: float = 1e-3
_BARRIER_TOL = 1e-6  # a barrier value below this is outside the barrier's safe set (backup layer off)


@dataclass(frozen=True)
class FilterResult:
    """What one :meth:`~aasoatt_env.safety.core.SafetyFilter.step` did (multipliers in eqn.8's units)."""

    du: np.ndarray  #: ``(N, 2)`` safe wheel accelerations, within the bounds
    #: the worst of what happened (:data:`STATUSES`): ``"solved"`` (the QP's optimum), ``"relaxed"`` (infeasible
    #: rows loosened by ``slack``, bounds kept), ``"backup"`` (the backup layer braked or nudged robots),
    #: ``"failed"`` (no solver answered) or ``"unsafe"`` (outside the safe set: with the backup layer, the state
    #: was not brake-safe; without it, some pair has ``h < 0`` or overlaps by more than :data:`COLLISION_TOL`)
    status: str
    safe: bool  #: ``status != "unsafe"``
    backup: np.ndarray  #: ``(N,)`` the backup layer braked the robot (nudged ones are counted in the message only)
    #: with the backup layer, the smallest ``distance - d_s`` [m] of any pair along the backup horizon of the
    #: applied inputs; without it, the smallest surface gap of the pairs in range
    margin: float
    barrier_min: float  #: the rows' smallest ``h`` without the discrete-time margins (``inf`` without rows)
    message: str  #: which solver answered, and what the backup layer did
    eta: np.ndarray  #: ``(m,)`` each row's multiplier
    pairs: np.ndarray  #: ``(m, 2)`` the rows' pairs: ``(i, j)``, or ``(i, -1 - k)`` for obstacle ``k``
    avoiding: np.ndarray  #: ``(N,)`` a row of the robot binds (or it brakes)
    triggered: np.ndarray  #: ``(N,)`` the deadlock strategy acts on the robot
    slack: float  #: the largest violation of a row by ``du`` (eqn.8's units; 0 when solved)
    correction: np.ndarray  #: ``(N,)`` ``|du - du_nominal|``
    intervened: np.ndarray  #: ``(N,)`` the robot's nominal was changed
    iterations: int
    solve_time: float  #: wall time of the step [s] (reported only: no decision reads it)
    n_rows: int
    n_qp_rows: int = 0  #: the rows the QP solver saw (0 where the closed form answered)
    #: ``(N,)`` per-robot bits (:data:`RELAXED`, :data:`GROUPED`: the decentralised mode's; :data:`BACKUP`,
    #: :data:`UNSAFE`: the backup layer's)
    flags: np.ndarray | None = None

    @property
    def obstacle_rows(self) -> np.ndarray:
        """``(n_rows,)`` bool: the row is a robot-obstacle row."""
        return self.pairs[:, 1] < 0


def result(nominal: np.ndarray, scale: np.ndarray, rows: Rows, ans: Answer, backup: BackupAnswer | None,
           triggered: np.ndarray, solve_time: float) -> FilterResult:
    """The step's :class:`FilterResult` from its stages' answers (``backup`` None: the layer is off)."""
    status, message = ans.status, ans.message
    n = ans.du.shape[0]
    flags = np.zeros(n, dtype=np.int8) if ans.flags is None else ans.flags.astype(np.int8)
    if backup is None:
        du, braking, margin = ans.du, np.zeros(n, dtype=bool), rows.gap_min
        safe = not (rows.barrier_min < -_BARRIER_TOL or rows.gap_min < -COLLISION_TOL)
    else:
        du, braking, margin, safe = backup.du, backup.braking, backup.margin, backup.safe
        flags |= np.where(braking, BACKUP, 0).astype(np.int8)
        if backup.unsafe is not None:
            flags |= np.where(backup.unsafe, UNSAFE, 0).astype(np.int8)
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
                        ans.iterations, solve_time, rows.m, ans.n_qp, flags)
