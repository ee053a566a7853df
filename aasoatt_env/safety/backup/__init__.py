"""The braking backup layer: keeps the team collision-free for any nominal, under the real input bounds.

A gatekeeper (Agrawal and Panagou), a backup-set barrier (Gurriet et al.): :mod:`.paths`, the backup's paths in closed
form; :mod:`.gate`, the gatekeeper and the repair; :mod:`.layer`, the filter's stage; :mod:`.kernels`, compiled.
"""

from aasoatt_env.safety.backup.gate import CLOSEST_TIE, GateResult, gatekeeper, pair_margins
from aasoatt_env.safety.backup.layer import GATE_TOL, BackupAnswer, BackupLayer, backup_answer, gate_with_repair
from aasoatt_env.safety.backup.paths import (
    MAX_BRAKE_STEPS,
    Trajectories,
    brake_decel,
    brake_time,
    braking_du,
    braking_trajectory,
    candidate_paths,
    candidate_samples_at,
    reach_limit,
)

__all__ = ["CLOSEST_TIE", "GATE_TOL", "MAX_BRAKE_STEPS", "BackupAnswer", "BackupLayer", "GateResult", "Trajectories",
           "backup_answer", "brake_decel", "brake_time", "braking_du", "braking_trajectory", "candidate_paths",
           "candidate_samples_at", "gate_with_repair", "gatekeeper", "pair_margins", "reach_limit"]
