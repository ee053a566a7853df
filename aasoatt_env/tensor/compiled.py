"""The torch env's compiled CPU stages: the numpy env's kernels and the numpy filter on the tensors' memory.

:class:`CompiledStages` is chosen when a :class:`~aasoatt_env.tensor.env.TensorEnv` is built (``compiled``): on a
CPU, without ``differentiable``, with the numpy backup layer, where numba imports.  Each stage is the numpy env's
own: kinematics and the exact-arc step (:mod:`aasoatt_env.model.dynamics_kernel`), the neighbour table and clearance
(:func:`~aasoatt_env.model.geometry.neighbourhood`), observations (:mod:`aasoatt_env.sim.observations_kernel`), and
one numpy :class:`~aasoatt_env.safety.core.SafetyFilter` for all teams (a stacked team, each team its own group, as
:class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`'s grouped filter), which keeps its warm start and trigger memory
and forgets a team's when the team starts an episode.  They compute in float64; the env stores their results in its
dtype.  No gradient: the torch stages are the differentiable ones.
"""

from __future__ import annotations

import numpy as np
import torch

from aasoatt_env.model import dynamics
from aasoatt_env.model.geometry import Proximity, neighbourhood
from aasoatt_env.model.params import Team
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.core import SafetyFilter
from aasoatt_env.sim.observations import build_observations
from aasoatt_env.tensor.filter import FilterOut
from aasoatt_env.tensor.model import TensorKinematics, stacked_team

__all__ = ["CompiledStages", "as_numpy"]


def as_numpy(x: torch.Tensor, width: int) -> np.ndarray:
    """``x`` ``(B, N, ...)`` as a float64 ``(B N, width)`` array (the tensor's memory where it is float64 already)."""
    return x.detach().to(torch.float64).reshape(-1, width).numpy()


class CompiledStages:
    """The stages of ``B`` teams of ``team`` (a numpy :class:`Team`) behind ``config`` (None: bare) in ``dtype``."""

    def __init__(self, team: Team, num_envs: int, config: FilterConfig | None, dtype: torch.dtype) -> None:
        self.B, self.N, self.dtype = num_envs, team.n, dtype
        self.team = stacked_team(team, num_envs)
        self.filter = None if config is None else SafetyFilter(self.team, config)
        self.equal_radii = np.full(num_envs, team.radius.min() == team.radius.max())
        self.kin: dynamics.Kinematics | None = None
        self.pose = self.u = np.empty(0)  # the state of the last kinematics(), float64 (B N, .)
        self.prox: Proximity | None = None

    def _t(self, a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(a).reshape(self.B, self.N, *a.shape[1:]).to(self.dtype)

    def restart(self, teams: np.ndarray) -> None:
        """Forget the filter's memory of ``teams``, whose episodes start."""
        if self.filter is not None:
            self.filter.reset_rows((teams[:, None] * self.N + np.arange(self.N)).ravel(), self.team)

    def kinematics(self, pose: torch.Tensor, u: torch.Tensor) -> TensorKinematics:
        """:func:`~aasoatt_env.model.dynamics.kinematics` (kept, and the state, for the other stages)."""
        self.pose, self.u = as_numpy(pose, 3), as_numpy(u, 2)
        self.kin = k = dynamics.kinematics(self.team, self.pose, self.u, True)
        A = self._t(k.A.reshape(-1, 4))
        return TensorKinematics(self._t(k.p), self._t(k.v), self._t(k.adot_u), *A.unbind(-1))

    def clearance(self, oc: torch.Tensor, orad: torch.Tensor, k: int) -> torch.Tensor:
        """Each robot's clearance ``(B, N)`` (its ``k`` nearest kept for :meth:`observations`)."""
        self.prox = neighbourhood(self.kin.p, self.team.radius, oc.detach().double().numpy(),
                                  orad.detach().double().numpy(), k, self.B, self.equal_radii, compiled=True)
        return torch.from_numpy(self.prox.clearance).reshape(self.B, self.N).to(self.dtype)

    def observations(self, ref: tuple[torch.Tensor, ...], goals: torch.Tensor,
                     oc: torch.Tensor, orad: torch.Tensor, sensing_range: float, k_robots: int,
                     k_obstacles: int) -> torch.Tensor:
        """:func:`~aasoatt_env.sim.observations.build_observations` of every robot ``(B, N, obs_dim)`` float32."""
        m = orad.shape[-1]
        obs = build_observations(
            p=self.kin.p, v=self.kin.v, theta=self.pose[:, 2], u=self.u,
            p_d=as_numpy(ref[0], 2), v_d=as_numpy(ref[1], 2), a_d=as_numpy(ref[2], 2), goals=as_numpy(goals, 2),
            radii=self.team.radius, obstacle_centers=as_numpy(oc, 2), obstacle_radii=as_numpy(orad, 1)[:, 0],
            sensing_range=sensing_range, k_robots=k_robots, k_obstacles=k_obstacles, prox=self.prox,
            obstacle_offset=np.repeat(np.arange(self.B) * m, self.N) if m and self.B > 1 else None, compiled=True)
        return torch.from_numpy(obs).reshape(self.B, self.N, -1)

    def step_filter(self, nominal: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, p_d: torch.Tensor,
                    v_d: torch.Tensor, oc: torch.Tensor, orad: torch.Tensor) -> FilterOut:
        """The numpy filter's step of every team at the last state.

        ``FilterOut.avoiding``: the numpy result's (a binding row, or braking); ``gap`` None (the env reports
        ``clearance``).
        """
        m = orad.shape[-1]
        obstacles = (as_numpy(oc, 2), as_numpy(orad, 1)[:, 0], np.repeat(np.arange(self.B), m)) if m else None
        du, res = self.filter.step(self.kin, self.u, self.pose[:, 2], as_numpy(nominal, 2),
                                   as_numpy(lo, 2), as_numpy(hi, 2), reference=(as_numpy(p_d, 2), as_numpy(v_d, 2)),
                                   obstacles=obstacles)
        shape = (self.B, self.N)
        return FilterOut(self._t(du), torch.from_numpy(res.flags.astype(np.int64)).reshape(shape),
                         torch.from_numpy(res.avoiding).reshape(shape), torch.from_numpy(res.triggered).reshape(shape),
                         self._t(res.correction), torch.from_numpy(res.intervened).reshape(shape), None)

    def integrate(self, du: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`~aasoatt_env.model.dynamics.integrate` (the exact arc) of every robot from the last state."""
        new_pose, new_u = dynamics.integrate(self.team, self.pose, self.u, as_numpy(du, 2), dt, True)
        return self._t(new_pose), self._t(new_u)
