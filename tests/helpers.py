"""An environment-free closed loop of the safety filter, for tests that drive ``SafetyFilter`` directly.

The layout and reference come from the library's own circle-swap scenario; the
nominal is the paper's tracking law, clipped to the bounds.  Also the mark of tests
that need the compiled kernels (``needs_numba``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pytest

from aasoatt_env import compiled
from aasoatt_env.model.dynamics import DT, input_bounds, integrate, kinematics, pose_from_point
from aasoatt_env.model.tracking import point_accel_to_du, tracking_accel
from aasoatt_env.sim.scenarios import CircleSwap, Layout

needs_numba = pytest.mark.skipif(not compiled.available(), reason="numba not installed (aasoatt[fast])")
"""Mark of a test (or parameter) that runs the compiled kernels."""


def circle_layout(n: int, radius: float = 6.0, duration: float = 12.0, robots: object = "paper") -> Layout:
    """The circle-swap layout (team, starts, headings, reference) of ``n`` robots."""
    return CircleSwap(n, radius=radius, duration=duration, settle_time=0.0, robots=robots).build(
        np.random.default_rng(0))


def tracking_nominal(kin, p_d, v_d, a_d, lo, hi):  # noqa: ANN001, ANN201
    """Nominal ``du`` of eqn.12 (paper gains), clipped to ``[lo, hi]``."""
    return np.clip(point_accel_to_du(kin, tracking_accel(kin.p, kin.v, p_d, v_d, a_d)), lo, hi)


@dataclass
class LoopResult:
    """A recorded closed loop."""

    min_distance: float
    final_error: np.ndarray
    statuses: dict[str, int]
    p: np.ndarray
    snapshots: list = field(default_factory=list)


def closed_loop(
    layout: Layout, filt: object, t_end: float, dt: float = DT, record: Callable[[int], bool] | None = None
) -> LoopResult:
    """Run ``filt`` (a ``SafetyFilter``) in closed loop for ``t_end`` seconds.

    ``record(k)`` selects steps whose filter inputs are kept in ``snapshots``.
    """
    team = layout.team
    pose, u = pose_from_point(team, layout.starts, layout.headings), np.zeros((team.n, 2))
    dmin = np.inf
    statuses: dict[str, int] = {}
    snaps = []
    iu, ju = np.triu_indices(team.n, 1)
    for k in range(int(round(t_end / dt))):
        kin = kinematics(team, pose, u)
        p_d, v_d, a_d = layout.reference(k * dt)
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
    return LoopResult(dmin, np.linalg.norm(p - layout.reference.goals, axis=1), statuses, p, snaps)


def tiny_train_config(out_dir: object, **overrides: object):  # noqa: ANN201
    """A :class:`~train.config.TrainConfig` of a run of ~100 agent-steps (seconds), for tests that need a run."""
    from train.config import TrainConfig

    base = dict(num_robots=3, n_envs=2, n_steps=16, batch_size=48, n_epochs=1, total_timesteps=100, net_arch=[8, 8],
                out_dir=str(out_dir), progress_bar=False, tensorboard=False, checkpoint_freq=0, max_steps=20)
    return TrainConfig(**{**base, **overrides})
