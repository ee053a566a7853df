"""``tracking``: one robot on a straight, sine or circle reference (Table I)."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.model.params import RobotParams, make_team
from aasoatt_env.sim.references import FunctionReference, Reference, as_reference
from aasoatt_env.sim.scenarios.base import Layout, Scenario, bounds_around, check_quantity, heading_of

__all__ = ["Tracking"]


class Tracking(Scenario):
    """One robot tracking a straight, sine or circle reference (Table I).

    ``trajectory``: ``"straight"``, ``p_d = (v t, v t / 2)``; ``"sine"``, ``p_d = (v t, A sin(w t))``; ``"circle"``,
    ``p_d = R (cos(v t / R), sin(v t / R))``, with ``speed`` ``v`` [m/s], ``amplitude`` ``A`` [m], ``frequency`` ``w``
    [rad/s], ``circle_radius`` ``R`` [m]; ``reference``: a user reference (object or callable) instead.
    """

    name = "tracking"
    TRAJECTORIES: ClassVar[tuple[str, ...]] = ("straight", "sine", "circle")

    def __init__(self, trajectory: str = "circle", speed: float = 0.5, amplitude: float = 1.0, frequency: float = 0.5,
                 circle_radius: float = 2.0, duration: float = 12.0, robots: str | RobotParams = "paper",
                 reference: Any = None) -> None:
        check.choice("trajectory", trajectory, self.TRAJECTORIES)  # checked even when `reference` replaces it
        self.trajectory = trajectory
        self.speed = check_quantity("speed", speed)
        self.amplitude = check_quantity("amplitude", amplitude)
        self.frequency = check_quantity("frequency", frequency)
        self.circle_radius = check_quantity("circle_radius", circle_radius)
        self.duration = check_quantity("duration", duration)
        self.robots = robots
        self._team = make_team(robots, 1)
        self._user_reference = reference

    def _reference(self) -> Reference:
        if self._user_reference is not None:
            return as_reference(self._user_reference, 1, self.duration)
        v, A, w, R = self.speed, self.amplitude, self.frequency, self.circle_radius
        om = v / R
        p, dp, ddp = {  # position, velocity and acceleration of each trajectory
            "straight": (lambda t: np.array([[v * t, 0.5 * v * t]]), lambda t: np.array([[v, 0.5 * v]]),
                         lambda t: np.zeros((1, 2))),
            "sine": (lambda t: np.array([[v * t, A * math.sin(w * t)]]),
                     lambda t: np.array([[v, A * w * math.cos(w * t)]]),
                     lambda t: np.array([[0.0, -A * w * w * math.sin(w * t)]])),
            "circle": (lambda t: R * np.array([[math.cos(om * t), math.sin(om * t)]]),
                       lambda t: R * om * np.array([[-math.sin(om * t), math.cos(om * t)]]),
                       lambda t: -R * om * om * np.array([[math.cos(om * t), math.sin(om * t)]])),
        }[self.trajectory]
        return FunctionReference(p, self.duration, velocity=dp, acceleration=ddp)

    def build(self, rng: np.random.Generator) -> Layout:
        """Start on the reference, at rest, heading along the reference velocity."""
        ref = self._reference()
        p0, v0, _ = ref(0.0)
        pts = np.concatenate([ref(t)[0] for t in np.linspace(0.0, self.duration, 64)])
        return Layout(team=self._team, starts=p0, headings=heading_of(v0, np.zeros(1)), reference=ref,
                      horizon=self.duration, bounds=bounds_around(pts))
