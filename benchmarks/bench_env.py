"""Bare environment throughput: env steps per second vs team size.

Prints a table of median steps/s over several repeats for N = 4, 20, 100 with
``decision_interval=1`` (one 5 ms physics step per env step), zero actions,
single thread.  The "physics only" column times the dynamics alone (kinematics
+ bounds + exact-arc integration) as the baseline the env overhead is measured
against, in the same run.

Usage: ``python benchmarks/bench_env.py [--quick]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from aasoatt_env import AASOATTParallelEnv
from aasoatt_env.model import dynamics  # noqa: E402


def _env_rate(n: int, steps: int) -> float:
    env = AASOATTParallelEnv("circle_swap", num_robots=n, radius=max(6.0, 0.2 * n), max_steps=10**9)
    env.reset(seed=0)
    acts = {a: np.zeros(2, np.float32) for a in env.agents}
    t = time.perf_counter()
    for _ in range(steps):
        env.step(acts)
    return steps / (time.perf_counter() - t)


def _physics_rate(n: int, steps: int) -> float:
    env = AASOATTParallelEnv("circle_swap", num_robots=n, radius=max(6.0, 0.2 * n))
    env.reset(seed=0)
    team, pose, u, du = env.team, env.poses, env.wheel_speeds, np.zeros((n, 2))
    t = time.perf_counter()
    for _ in range(steps):
        dynamics.kinematics(team, pose, u)
        dynamics.input_bounds(team, u, 0.005)
        pose, u = dynamics.integrate(team, pose, u, du, 0.005)
    return steps / (time.perf_counter() - t)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    repeats = 3 if args.quick else 7
    print(f"{'N':>5} {'env steps/s':>12} {'agent-steps/s':>14} {'physics steps/s':>16} {'env/physics':>12}")
    for n in (4, 20, 100):
        steps = (300 if args.quick else 2000) if n < 100 else (100 if args.quick else 500)
        env_r = statistics.median(_env_rate(n, steps) for _ in range(repeats))
        phys_r = statistics.median(_physics_rate(n, steps) for _ in range(repeats))
        print(f"{n:>5} {env_r:>12.0f} {env_r * n:>14.0f} {phys_r:>16.0f} {env_r / phys_r:>12.2f}")


if __name__ == "__main__":
    main()
