"""PPO training throughput (agent-steps/s) with and without the safety filter in the loop.

    python benchmarks/bench_training.py [--timesteps 6144] [--robots 6] [--solver proxsuite]

Each configuration trains PPO (TrainConfig defaults: 4 envs x N robots,
decision_interval 20, n_steps 128) for ``--timesteps`` agent-steps after one
warm-up update and prints a table: rollout collection plus PPO updates, i.e.
what a training run sees.  Single torch thread.
"""

from __future__ import annotations

import argparse
import time

import torch

from train.config import TrainConfig
from train.train import build_model, make_vec_env


def bench(filtered: bool, timesteps: int, robots: int, solver: str | None, n_envs: int) -> tuple[float, int]:
    kw = {"filter_kwargs": {"solver": solver}} if (filtered and solver) else {}
    cfg = TrainConfig(num_robots=robots, n_envs=n_envs, filter=filtered, progress_bar=False, tensorboard=False,
                      checkpoint_freq=0, batch_size=256, **kw)
    venv = make_vec_env(cfg)
    model = build_model(cfg, venv)
    per_update = cfg.n_steps * venv.num_envs
    model.learn(per_update)  # warm-up
    t0 = time.perf_counter()
    model.learn(max(timesteps, per_update), reset_num_timesteps=False)
    dt = time.perf_counter() - t0
    steps = model.num_timesteps - per_update
    venv.close()
    return steps / dt, steps


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--timesteps", type=int, default=6144)
    p.add_argument("--robots", type=int, default=6)
    p.add_argument("--n-envs", type=int, default=4)
    p.add_argument("--solver", default=None, help="filter QP solver (default: the filter's default)")
    args = p.parse_args()
    torch.set_num_threads(1)
    rows = [("bare", False), (f"filter ({args.solver or 'default solver'})", True)]
    print(f"PPO throughput, {args.robots} robots x {args.n_envs} envs, decision_interval 20 (dt 0.005)\n")
    print("| loop | agent-steps | agent-steps/s | physics steps/s |")
    print("|---|---:|---:|---:|")
    for name, filtered in rows:
        rate, steps = bench(filtered, args.timesteps, args.robots, args.solver, args.n_envs)
        print(f"| {name} | {steps} | {rate:,.0f} | {rate / args.robots * 20:,.0f} |", flush=True)


if __name__ == "__main__":
    main()
