"""``TrackingPriorPolicy``: PPO actor-critic whose action mean starts as the tracking law.

What it is
----------
The paper's tracking law (:class:`agents.baselines.TrackingController`)
``a = a_d - (k3 + k4)(v - v_d) - k3 k4 (p - p_d)`` is *linear* in the
observation (entries 0:2 ``p - p_d``, 4:6 ``v``, 10:12 ``v_d``, 12:14 ``a_d``,
see :mod:`aasoatt_env.sim.observations`).  This policy starts as that law, so
it tracks from the first step.  Be clear about what that buys: PPO changes it
little, and in closed loop it behaves like its prior.  It is a baseline and a
starting point for fine-tuning, not a policy learned from scratch; the default recipe
(:class:`train.config.TrainConfig` defaults: a plain MLP, normalised
observations and rewards, 1.23M agent-steps) learns to reach the goals without it.

Here the Gaussian mean is ``W obs + MLP(scale * obs)``: ``W`` is a trainable
linear layer on the raw observation, initialised to the tracking law in
normalised point-acceleration units (``action_mode="point"``, divided by
``max_point_accel``), and the MLP (SB3's ``action_net`` output, initialised
near zero) learns the residual (e.g. reacting to neighbours).  Everything is
trained by PPO; the prior is only the initialisation (a residual /
prior-initialised policy).  The observation must reach the policy *raw*
(``normalize_obs=False``): the MLP and value net see ``scale * obs``, a fixed
scaling instead of running statistics so that ``W`` keeps its meaning.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.distributions import DiagGaussianDistribution, Distribution
from stable_baselines3.common.policies import ActorCriticPolicy

__all__ = ["TrackingPriorPolicy", "tracking_prior_matrix"]


def tracking_prior_matrix(obs_dim: int, k3: float, k4: float, max_point_accel: float) -> np.ndarray:
    """``(2, obs_dim)`` matrix of the tracking law on the observation, in normalised action units."""
    w = np.zeros((2, obs_dim))
    for d in range(2):
        w[d, 0 + d] = -k3 * k4  # p - p_d
        w[d, 4 + d] = -(k3 + k4)  # v
        w[d, 10 + d] = k3 + k4  # v_d
        w[d, 12 + d] = 1.0  # a_d
    return w / float(max_point_accel)


class TrackingPriorPolicy(ActorCriticPolicy):
    """Actor-critic with a linear tracking-law prior on the action mean (module docstring).

    Extra parameters
    ----------------
    prior_matrix : array_like, shape (action_dim, obs_dim)
        Initial ``W`` (:func:`tracking_prior_matrix`).
    input_scale : float
        Fixed scaling of the observation fed to the MLPs.
    """

    def __init__(self, *args: Any, prior_matrix: Any = None, input_scale: float = 1.0 / 3.0, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if not isinstance(self.action_dist, DiagGaussianDistribution):
            raise ValueError("TrackingPriorPolicy needs a Box action space without gSDE")
        obs_dim = int(np.prod(self.observation_space.shape))
        act_dim = int(np.prod(self.action_space.shape))
        self.prior_matrix = None if prior_matrix is None else np.asarray(prior_matrix, dtype=np.float64).tolist()
        self.input_scale = float(input_scale)
        self.prior = th.nn.Linear(obs_dim, act_dim, bias=False)
        with th.no_grad():
            if prior_matrix is None:
                self.prior.weight.zero_()
            else:
                self.prior.weight.copy_(th.as_tensor(np.asarray(prior_matrix), dtype=th.float32))
        self.prior.to(self.device)
        # rebuild the optimizer so that it includes the prior's weights
        self.optimizer = self.optimizer_class(self.parameters(), lr=self._lr0, **self.optimizer_kwargs)
        self._raw_obs: th.Tensor | None = None

    def _build(self, lr_schedule: Any) -> None:
        self._lr0 = lr_schedule(1)
        super()._build(lr_schedule)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(prior_matrix=self.prior_matrix, input_scale=self.input_scale)
        return data

    # the raw observation feeds the prior, the scaled one the MLPs
    def forward(self, obs: th.Tensor, deterministic: bool = False) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Actions, values and log-probabilities (the prior reads the unscaled observation)."""
        self._raw_obs = obs.float()
        return super().forward(obs * self.input_scale, deterministic)

    def evaluate_actions(self, obs: Any, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor | None]:
        """Values, log-probabilities and entropy of ``actions`` (prior on the raw observation)."""
        self._raw_obs = obs.float()
        return super().evaluate_actions(obs * self.input_scale, actions)

    def get_distribution(self, obs: Any) -> Distribution:
        """Action distribution (prior on the raw observation)."""
        self._raw_obs = obs.float()
        return super().get_distribution(obs * self.input_scale)

    def predict_values(self, obs: Any) -> th.Tensor:
        """State values of the scaled observation."""
        return super().predict_values(obs * self.input_scale)

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> Distribution:
        assert self._raw_obs is not None
        mean = self.action_net(latent_pi) + self.prior(self._raw_obs.reshape(len(latent_pi), -1))
        self._raw_obs = None
        return self.action_dist.proba_distribution(mean, self.log_std)
