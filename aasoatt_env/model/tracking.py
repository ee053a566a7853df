"""The paper's trajectory-tracking law (eqn.11-12), the one home of the nominal controller's algebra.

With ``ell = p - p_d`` it asks for ``a = a_d - (k3 + k4)(v - v_d) - k3 k4 ell`` (eqn.12), i.e.
``du = A^{-1} (a - A_dot u)``; Theorem 2 keeps the error converging under eqn.13 while ``k4 > zeta``.
"""

from __future__ import annotations

import numpy as np

from aasoatt_env.model.dynamics import Kinematics
from aasoatt_env.model.portable import solve2

__all__ = ["PAPER_K3", "PAPER_K4", "point_accel_to_du", "tracking_accel"]

PAPER_K3: float = 1.0
"""The paper's position gain ``k3`` of eqn.12."""
PAPER_K4: float = 4.0
"""The paper's velocity gain ``k4`` of eqn.12."""


def tracking_accel(p: np.ndarray, v: np.ndarray, p_d: np.ndarray, v_d: np.ndarray, a_d: np.ndarray,
                   k3: float = PAPER_K3, k4: float = PAPER_K4) -> np.ndarray:
    """Control-point accelerations ``(N, 2)`` of eqn.12 (all arrays ``(N, 2)``)."""
    return a_d - (k3 + k4) * (v - v_d) - (k3 * k4) * (p - p_d)


def point_accel_to_du(kin: Kinematics, accel: np.ndarray) -> np.ndarray:
    """Wheel accelerations ``du = A^{-1} (accel - A_dot u)`` realising point accelerations ``(N, 2)``."""
    return solve2(kin.A, accel - kin.adot_u)
