"""MAPPO (or IPPO) with TorchRL on the torch env behind the torch filter: many teams in one call, no PettingZoo.

The robots of a team are one TorchRL agent group (:class:`~aasoatt_env.tensor.torchrl_env.TorchRLTensorEnv`); the
policy is one shared MLP per robot (its own observation in, a Gaussian over its normalised control-point
accelerations out, with a state-independent standard deviation starting at ``e^-1``; ``action_mode="point"``, as
``aasoatt train``'s recipe; ``--action-mode wheel`` for wheel accelerations; the env gets each sample clipped to
``[-1, 1]``, the loss the sample itself, as SB3's PPO), the critic a shared MLP over the whole team's observations
(MAPPO; ``--ippo``: each robot's own), both behind observations standardised by the statistics of a random-action
rollout (:func:`observation_stats`). Clipped PPO with GAE; the advantages are standardised over each minibatch's
robots together (as SB3 does over ``aasoatt train``'s agents; TorchRL's multi-agent PPO tutorial does not
standardise them); 32 teams x 64 decisions per iteration and 12 minibatches, as ``aasoatt train``'s rollouts.
Every ``--eval-every`` iterations, and at the end, the deterministic policy is evaluated on held-out seeds (teams
``seed >= 2**32``, as ``aasoatt train``'s) for one episode per team: success (robots within ``goal_tolerance`` of
their goal at the end), collisions (robot-steps with a surface gap below ``-collision_tolerance``), the filter's
mean correction; the report is written as JSON (atomically) with the wall times.

The filter is the torch env's defaults; ``--backup-check`` picks its backup stage (``numpy``: the numpy filter's
layer, a CPU's default; ``torch``: the batched braking check) and ``--no-negotiate`` answers every robot by its own QP.

Usage: ``python -m train.torchrl_mappo [--frames 204800] [--teams 32] [--steps 64] [--robots 6] [--ippo]
[--backup-check numpy|torch] [--no-negotiate] [--out runs/torchrl_mappo]``
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data.replay_buffers import ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.data.replay_buffers.storages import LazyTensorStorage
from torchrl.envs import TransformedEnv
from torchrl.envs.transforms import ClipTransform
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import IndependentNormal, MultiAgentMLP, ProbabilisticActor
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from aasoatt_env.cli_support import OutputPlan, Parser, add_common_options, atomic_write, int_option, run_guarded
from aasoatt_env.errors import ConfigError
from aasoatt_env.tensor.filter import BACKUP_CHECKS
from aasoatt_env.tensor.torchrl_env import TorchRLTensorEnv
from train.config import HELDOUT_SEED, TRAIN_REWARD

__all__ = ["Normalise", "build", "evaluate", "main", "observation_stats", "train"]

GROUP = "agents"


def make_env(teams: int, robots: int, seed: int, **options: Any) -> TransformedEnv:
    """``teams`` RandomGoals teams of ``robots`` behind the decentralised torch filter, 100 ms decisions."""
    options = {"action_mode": "point", **options}
    env = TorchRLTensorEnv("random_goals", num_envs=teams, num_robots=robots, decision_interval=20,
                           reward=dict(TRAIN_REWARD), **options)
    env.set_seed(seed)
    # the env gets the sampled action clipped to [-1, 1]; the loss, the sample itself (as SB3's PPO)
    return TransformedEnv(env, ClipTransform(in_keys_inv=[(GROUP, "action")], low=-1.0, high=1.0))


class Normalise(nn.Module):
    """Observations standardised by fixed statistics (``(x - loc) / scale``), the first layer of both networks."""

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("loc", loc)
        self.register_buffer("scale", scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(x - loc) / scale``."""
        return (x - self.loc) / self.scale


@torch.no_grad()
def observation_stats(env: TransformedEnv, steps: int = 20) -> Normalise:
    """Per-entry mean and standard deviation (at least 0.01) of the observations of ``steps`` uniform random actions."""
    td = env.rollout(steps, break_when_any_done=False)  # (random actions; finished teams reset)
    obs = torch.cat((td[GROUP, "observation"][:, :1], td["next", GROUP, "observation"]), 1).transpose(0, 1)
    obs = obs.reshape(-1, obs.shape[-1])  # (time-major)
    return Normalise(obs.mean(0), obs.std(0).clamp(min=0.01))


def build(env: TransformedEnv, centralised: bool, width: int = 128, norm: Normalise | None = None,
          log_std: float = -1.0) -> tuple[ProbabilisticActor, TensorDictModule]:
    """The shared per-robot Gaussian policy (``log_std``: its initial log standard deviation) and the critic."""
    n, obs = env.env.num_robots, env.env.obs_dim
    norm = norm if norm is not None else nn.Identity()
    net = nn.Sequential(norm, MultiAgentMLP(obs, 2, n, centralised=False, share_params=True, depth=2,
                                            num_cells=width, activation_class=nn.Tanh),
                        AddStateIndependentNormalScale(2, init_value=log_std))
    actor = ProbabilisticActor(
        TensorDictModule(net, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "loc"), (GROUP, "scale")]),
        spec=env.action_spec[GROUP, "action"], in_keys=[(GROUP, "loc"), (GROUP, "scale")],
        out_keys=[(GROUP, "action")], distribution_class=IndependentNormal, return_log_prob=True,
        log_prob_key=(GROUP, "log_prob"))
    critic = TensorDictModule(nn.Sequential(norm, MultiAgentMLP(obs, 1, n, centralised=centralised, share_params=True,
                                                                depth=2, num_cells=width, activation_class=nn.Tanh)),
                              in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "state_value")])
    return actor, critic


@torch.no_grad()
def evaluate(actor: ProbabilisticActor, teams: int, robots: int, seed: int = HELDOUT_SEED,
             **options: Any) -> dict[str, float]:
    """One episode of ``teams`` held-out teams with the policy's mean action (module docstring)."""
    env = make_env(teams, robots, seed, **options)
    tol = env.env.reward_config.goal_tolerance
    td = env.reset()
    collided, home = (torch.zeros(teams, robots, dtype=torch.bool) for _ in range(2))
    live = torch.ones(teams, 1, dtype=torch.bool)  # (each team's own episode: their lengths differ)
    corr, steps = 0.0, 0
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        while bool(live.any()):
            nxt = env.step(actor(td))["next"]
            collided |= (nxt[GROUP, "clearance"] < -env.env.collision_tolerance) & live
            corr, steps = corr + float(nxt[GROUP, "correction"][live[:, 0]].sum()), steps + int(live.sum()) * robots
            ends = live & nxt["done"]
            home |= ends & (torch.sqrt(((env.env.kin.p - env.env.goals) ** 2).sum(-1)) < tol)
            live &= ~ends
            td = env.reset(nxt.set("_reset", nxt["done"].clone())) if bool(nxt["done"].any()) else nxt
    return {"success": float(home.float().mean()), "robots_collided": int(collided.sum()),
            "correction": corr / max(steps, 1), "teams": teams}


def train(frames: int, teams: int, robots: int, seed: int, centralised: bool, eval_every: int,
          eval_teams: int = 64, log: Any = print, epochs: int = 10, minibatches: int = 12,
          reward_scale: float = 0.1, steps: int = 64, **options: Any) -> dict[str, Any]:
    """Train from scratch; returns the report (per-iteration rewards, in the env's units, and the evaluations).

    ``reward_scale``: the rewards the value function learns are the env's times this (returns of order 1-10, fitted
    by a squared loss); ``options``: the env's (:func:`make_env`), e.g. ``max_steps`` for short episodes.
    """
    torch.manual_seed(seed)
    env = make_env(teams, robots, seed, **options)
    actor, critic = build(env, centralised, norm=observation_stats(env))
    start_params = [p.detach().clone() for p in actor.parameters()]
    per_batch = teams * steps  # decisions of 100 ms per team per iteration
    collector = Collector(env, actor, frames_per_batch=per_batch, total_frames=frames,
                          auto_register_policy_transforms=False)  # (a feed-forward policy: no InitTracker)
    buffer = ReplayBuffer(storage=LazyTensorStorage(per_batch), sampler=SamplerWithoutReplacement(),
                          batch_size=max(1, per_batch // minibatches))
    loss = ClipPPOLoss(actor_network=actor, critic_network=critic, clip_epsilon=0.2, entropy_coeff=1e-3,
                       normalize_advantage=True, loss_critic_type="l2")
    loss.set_keys(reward=(GROUP, "reward"), action=(GROUP, "action"), sample_log_prob=(GROUP, "log_prob"),
                  value=(GROUP, "state_value"), done=(GROUP, "done"), terminated=(GROUP, "terminated"))
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
    report: dict[str, Any] = {"frames": frames, "teams": teams, "robots": robots, "seed": seed,
                              "critic": "centralised" if centralised else "independent", "epochs": epochs,
                              "minibatches": minibatches, "steps": steps, "reward_scale": reward_scale,
                              "options": options,
                              "iterations": [],
                              "evaluations": [{"iteration": 0, **evaluate(actor, eval_teams, robots, **options)}]}
    log(f"iteration 0: held-out {report['evaluations'][0]}")
    start = time.perf_counter()
    for it, data in enumerate(collector, 1):
        shape = data.get_item_shape(("next", GROUP, "reward"))
        for key in ("done", "terminated"):  # the team's end is each robot's
            data.set(("next", GROUP, key), data.get(("next", key)).unsqueeze(-1).expand(shape))
        reward = float(data["next", GROUP, "reward"].mean())
        data.set(("next", GROUP, "reward"), data.get(("next", GROUP, "reward")) * reward_scale)
        with torch.no_grad():
            loss.value_estimator(data, params=loss.critic_network_params,
                                 target_params=loss.target_critic_network_params)
        buffer.extend(data.reshape(-1))
        for _ in range(epochs):
            for _ in range(minibatches):
                with warnings.catch_warnings():  # (over the robots too, on purpose: module docstring)
                    warnings.filterwarnings("ignore", "You requested advantage normalization", UserWarning)
                    out = loss(buffer.sample())
                total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                optim.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
                optim.step()
        collector.update_policy_weights_()
        report["iterations"].append({"iteration": it, "frames": it * per_batch, "mean_reward": reward,
                                     "wall_s": time.perf_counter() - start})
        if it % eval_every == 0:
            report["evaluations"].append({"iteration": it, **evaluate(actor, eval_teams, robots, **options)})
            log(f"iteration {it}: mean reward {reward:.3f}, held-out {report['evaluations'][-1]}")
    collector.shutdown()
    final = evaluate(actor, eval_teams, robots, **options)
    report["evaluations"].append({"iteration": len(report["iterations"]), **final})
    report["wall_s"] = time.perf_counter() - start
    report["policy_change"] = float(sum(float(((p.detach() - q) ** 2).sum()) for p, q in
                                        zip(actor.parameters(), start_params)) ** 0.5)  # (L2 over the weights)
    log(f"final: held-out {report['evaluations'][-1]}, wall {report['wall_s']:.0f} s")
    return report


def main(argv: list[str] | None = None) -> int:
    """The command line (module docstring): a user error is one line and exit status 2."""
    argv = list(sys.argv[1:] if argv is None else argv)
    return run_guarded("python -m train.torchrl_mappo", argv, _main)


def _main(argv: list[str]) -> int:
    ap = Parser(prog="python -m train.torchrl_mappo", description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int_option(1), default=204_800, help="team decisions in total (teams x steps)")
    ap.add_argument("--teams", type=int_option(1), default=32)
    ap.add_argument("--robots", type=int_option(1), default=6)
    ap.add_argument("--steps", type=int_option(1), default=64, help="decisions per team per iteration")
    ap.add_argument("--seed", type=int_option(0), default=0)
    ap.add_argument("--ippo", action="store_true", help="independent critics (IPPO) instead of MAPPO's")
    ap.add_argument("--action-mode", choices=("point", "wheel"), default="point")
    ap.add_argument("--epochs", type=int_option(1), default=10)
    ap.add_argument("--minibatches", type=int_option(1), default=12)
    ap.add_argument("--eval-every", type=int_option(1), default=10)
    ap.add_argument("--eval-teams", type=int_option(1), default=64)
    ap.add_argument("--backup-check", choices=BACKUP_CHECKS, default=None,
                    help="the filter's backup stage (default: numpy on a CPU, torch on a GPU)")
    ap.add_argument("--no-negotiate", action="store_true", help="no negotiation groups: every robot's own QP")
    ap.add_argument("--out", type=Path, default=Path("runs/torchrl_mappo"))
    add_common_options(ap)  # --debug, --overwrite
    a = ap.parse_args(argv)
    try:  # (before training)
        path = OutputPlan(a.overwrite).file(a.out / "report.json", "--out")
    except ConfigError as exc:
        ap.error(str(exc))
    torch.set_num_threads(1)
    report = train(a.frames, a.teams, a.robots, a.seed, not a.ippo, a.eval_every, a.eval_teams, epochs=a.epochs,
                   minibatches=a.minibatches, steps=a.steps, action_mode=a.action_mode, backup_check=a.backup_check,
                   negotiate=not a.no_negotiate)
    atomic_write(path, lambda temp: temp.write_text(json.dumps(report, indent=1)))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
