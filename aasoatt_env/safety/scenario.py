"""A minimal circle-swap closed loop (SPEC section 7) for tests and benchmarks.

``N`` robots evenly on a circle of radius ``R``, headings towards the centre,
each tracking the straight line to its antipode over ``T`` seconds; nominal
``du`` from the tracking law eqn.12 (``A du = dzr``) clipped to the bounds.
This is not the environment, only enough of it to exercise the filter.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from aasoatt_env.model.dynamics import input_bounds, integrate, kinematics, pose_from_point
from aasoatt_env.model.params import Team, make_team

__all__ = ["CircleSwap", "Rollout", "rollout", "tracking_nominal"]


@dataclass
class CircleSwap:
    """Initial state and reference of the circle swap."""

    n: int
    radius: float = 6.0
    duration: float = 12.0
    team: Team = field(init=False)
    start: np.ndarray = field(init=False)
    goal: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.team = make_team("paper", self.n)
        ang = 2.0 * np.pi * np.arange(self.n) / self.n
        self.start = self.radius * np.stack((np.cos(ang), np.sin(ang)), axis=1)
        self.goal = -self.start

    def initial(self) -> tuple[np.ndarray, np.ndarray]:
        """Axle poses ``(N, 3)`` (heading to the centre) and zero wheel speeds."""
        theta = np.arctan2(-self.start[:, 1], -self.start[:, 0])
        return pose_from_point(self.team, self.start, theta), np.zeros((self.n, 2))

    def reference(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``p_d, v_d, a_d`` at time ``t`` (linear in time, then held at the goal)."""
        s = min(t / self.duration, 1.0)
        p_d = self.start + s * (self.goal - self.start)
        v_d = (self.goal - self.start) / self.duration if t < self.duration else np.zeros_like(self.start)
        return p_d, v_d, np.zeros_like(self.start)


def tracking_nominal(kin, p_d, v_d, a_d, lo, hi, k3: float = 1.0, k4: float = 4.0) -> np.ndarray:  # noqa: ANN001
    """Nominal ``du = A^-1 dzr`` of eqn.12, clipped to ``[lo, hi]``."""
    dzr = a_d - kin.adot_u - (k3 + k4) * (kin.v - v_d) - k3 * k4 * (kin.p - p_d)
    du = np.linalg.solve(kin.A, dzr[..., None])[..., 0]
    return np.clip(du, lo, hi)


@dataclass
class Rollout:
    """Recorded closed loop."""

    min_distance: float
    final_error: np.ndarray
    statuses: dict[str, int]
    p: np.ndarray
    snapshots: list = field(default_factory=list)


def rollout(
    scen: CircleSwap,
    filt: object,
    t_end: float,
    dt: float = 0.005,
    record: Callable[[int], bool] | None = None,
) -> Rollout:
    """Run the closed loop for ``t_end`` seconds with ``filt`` (a :class:`SafetyFilter`).

    ``record(k)`` selects steps whose filter inputs are stored in ``snapshots``.
    """
    team = scen.team
    pose, u = scen.initial()
    dmin = np.inf
    statuses: dict[str, int] = {}
    snaps = []
    iu, ju = np.triu_indices(scen.n, 1)
    for k in range(int(round(t_end / dt))):
        t = k * dt
        kin = kinematics(team, pose, u)
        p_d, v_d, a_d = scen.reference(t)
        lo, hi = input_bounds(team, u, dt)
        nom = tracking_nominal(kin, p_d, v_d, a_d, lo, hi)
        if record is not None and record(k):
            snaps.append((kin, u.copy(), pose[:, 2].copy(), nom, lo, hi, (p_d, v_d)))
        du, res = filt.step(kin, u, pose[:, 2], nom, lo, hi, reference=(p_d, v_d))
        statuses[res.status] = statuses.get(res.status, 0) + 1
        pose, u = integrate(team, pose, u, du, dt)
        p = kinematics(team, pose, u).p
        d = np.linalg.norm(p[iu] - p[ju], axis=1)
        dmin = min(dmin, float(d.min()) if d.size else np.inf)
    p = kinematics(team, pose, u).p
    return Rollout(dmin, np.linalg.norm(p - scen.goal, axis=1), statuses, p, snaps)
