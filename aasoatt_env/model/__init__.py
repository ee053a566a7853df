"""The model layer: robot parameters, dynamics, neighbour geometry and the tracking law (no envs, filters, learning)."""

from aasoatt_env.model.dynamics import DT, Kinematics, input_bounds, integrate, kinematics, pose_from_point
from aasoatt_env.model.params import PRESETS, RobotParams, Team, make_team
from aasoatt_env.model.tracking import PAPER_K3, PAPER_K4, tracking_accel

__all__ = ["DT", "PAPER_K3", "PAPER_K4", "PRESETS", "Kinematics", "RobotParams", "Team", "input_bounds", "integrate",
           "kinematics", "make_team", "pose_from_point", "tracking_accel"]
