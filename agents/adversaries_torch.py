"""The adversaries of :mod:`agents.adversaries` for the torch env (:mod:`aasoatt_env.tensor`), every team at once.

Team ``b`` runs adversary ``kind[b]`` of :data:`ADVERSARIES`, the same behaviours in torch: ``spin_up`` (spin 200
steps, then full throttle), ``burst`` (rest 100 steps, then full throttle), ``bang_bang`` (random +-1 per wheel held
20 steps), ``chase_nearest`` and ``chase_target`` (full point acceleration toward the nearest / a random robot), and
``uniform_noise``; seeded by a ``torch.Generator``.
"""

from __future__ import annotations

import torch

__all__ = ["ADVERSARIES", "adversary_actions"]

ADVERSARIES: tuple[str, ...] = ("spin_up", "burst", "bang_bang", "chase_nearest", "chase_target", "uniform_noise")


def _toward(env, target: torch.Tensor) -> torch.Tensor:
    """Wheel actions of full point acceleration toward ``target`` ``(B, N, 2)``, saturated to [-1, 1]."""
    k, team = env.kin, env.team
    d = target - k.p
    d = d / torch.clamp(torch.sqrt((d * d).sum(-1, keepdim=True)), min=1e-12)
    a = team.max_point_accel[:, None] * d - k.adot
    A = torch.stack((torch.stack((k.a00, k.a01), -1), torch.stack((k.a10, k.a11), -1)), -2)
    return torch.clamp(torch.linalg.solve(A, a[..., None])[..., 0] / team.max_wheel_accel[:, None], -1.0, 1.0)


def adversary_actions(env, t: int, kind: torch.Tensor, gen: torch.Generator, state: dict) -> torch.Tensor:
    """Every team's adversary's wheel actions at step ``t`` (``kind`` ``(B,)``: index into :data:`ADVERSARIES`)."""
    B, N = env.num_envs, env.num_robots
    one = torch.ones(B, N, 2, dtype=env.dtype)
    spin = one * torch.tensor([1.0, -1.0], dtype=env.dtype) if t < 200 else one
    burst = one * (0.0 if t < 100 else 1.0)
    if t % 20 == 0:
        state["signs"] = torch.randint(0, 2, (B, N, 2), generator=gen).to(env.dtype) * 2.0 - 1.0
    nearest = env.dist.argmin(-1)
    chase_n = _toward(env, env.kin.p.gather(1, nearest[..., None].expand(B, N, 2)))
    chase_t = _toward(env, env.kin.p.gather(1, state["target"][..., None].expand(B, N, 2)))
    noise = torch.rand(B, N, 2, generator=gen, dtype=env.dtype) * 2.0 - 1.0
    acts = torch.stack((spin, burst, state["signs"], chase_n, chase_t, noise))
    return acts.gather(0, kind[None, :, None, None].expand(1, B, N, 2))[0]
