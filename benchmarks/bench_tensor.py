"""Robot-steps per second of the torch env (:mod:`aasoatt_env.tensor`) beside the numpy batched env, one CPU thread.

Each row steps ``B`` random_goals teams of ``N`` paper robots with the paper's tracking law (``k3 = 1``, ``k4 = 4``)
as actions, from ``reset(seed=0)`` after a few warm-up steps: bare (no filter) and filtered (the decentralised
filter, ``backup=False``, ``negotiate=False``: the paper's filter, each robot's own QP) in float32 and float64,
and behind the filter's defaults (negotiation groups and the backup stage) in float32 with either backup check
(``+bk numpy``: the numpy filter's layer on the CPU, a CPU's default; ``+bk torch``: the braking check of
:mod:`aasoatt_env.tensor.backup`), and the numpy :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv` with the numpy
decentralised filter of the filtered columns' configuration (one grouped filter call for all teams) measured in the
same run.  ``ratio``: torch float64
filtered over numpy filtered.  The GPU column is measured only where ``torch.cuda.is_available()``; otherwise it
is empty (never estimated).

Usage: ``python benchmarks/bench_tensor.py [--quick] [--sizes 1x20,64x20] [--page docs/benchmarks/tensor.md]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from page import add_page_options, check_page, printed_page

from aasoatt_env.api.factory import make_batched_env
from aasoatt_env.tensor.env import make_tensor_env

SIZES = [(1, 20), (64, 20), (1024, 20), (4096, 20), (16, 1000)]
FILTER = dict(backup=False, negotiate=False)
NUMPY_TEAMS = 1024


def _torch_actions(env):
    k = env.kin
    A = torch.stack((torch.stack((k.a00, k.a01), -1), torch.stack((k.a10, k.a11), -1)), -2)
    a = 1.0 * (env.ref[0] - k.p) + 4.0 * (env.ref[1] - k.v) - k.adot
    return torch.linalg.solve(A, a[..., None])[..., 0] / env.team.max_wheel_accel[:, None]


def torch_rate(B: int, N: int, filtered: bool, dtype: torch.dtype, steps: int, device: str = "cpu",
               check: str | None = None) -> float:
    """Robot-steps/s of the torch env (``check``: behind the filter's defaults with that backup check)."""
    env = make_tensor_env("random_goals", B, N, device=device, dtype=dtype, filter=filtered,
                          clip_actions=not filtered,  # (the tracking law's nominal leaves [-1, 1] without a filter)
                          **(FILTER if check is None else {"backup_check": check}))
    env.reset(seed=0)
    with torch.no_grad():
        for _ in range(3):
            env.step(_torch_actions(env))
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(steps):
            env.step(_torch_actions(env))
        if device == "cuda":
            torch.cuda.synchronize()
    return B * N * steps / (time.perf_counter() - t0)


def numpy_rate(B: int, N: int, steps: int) -> float:
    """Robot-steps/s of the numpy batched env behind the numpy decentralised filter (one grouped call)."""
    env = make_batched_env(B, "random_goals", num_robots=N, filter=dict(mode="decentralized", **FILTER))
    env.reset(seed=0)

    def act():
        kin, (p_d, v_d, _) = env._kin, env._ref_now
        a = 1.0 * (p_d - kin.p) + 4.0 * (v_d - kin.v) - kin.adot_u
        return (np.linalg.solve(kin.A, a[..., None])[..., 0] / 60.0).reshape(B, N, 2)

    for _ in range(2):
        env.step(act())
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(act())
    return B * N * steps / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps")
    parser.add_argument("--sizes", type=lambda v: [tuple(int(x) for x in s.split("x")) for s in v.split(",")],
                        default=SIZES, help="BxN sizes, comma-separated")
    add_page_options(parser)
    args = parser.parse_args()
    check_page(args)
    torch.set_num_threads(1)
    gpu = torch.cuda.is_available()
    with printed_page(args, "Torch env throughput", notes=__doc__):
        print("```")
        print(f"{'B':>5} {'N':>5} {'bare f32':>11} {'filt f32':>11} {'+bk numpy':>11} {'+bk torch':>11} "
              f"{'filt f64':>11} {'numpy filt':>11} "
              f"{'ratio':>7} {'GPU filt f32':>13}   (robot-steps/s, one CPU thread)")
        for B, N in args.sizes:
            robots = B * N
            steps = max(2, min(60, 200_000 // robots)) // (4 if args.quick else 1) or 2
            nsteps = max(2, min(30, 20_000 // robots)) // (2 if args.quick else 1) or 2
            bare = torch_rate(B, N, False, torch.float32, steps)
            f32 = torch_rate(B, N, True, torch.float32, steps)
            bk_np = torch_rate(B, N, True, torch.float32, steps, check="numpy")
            bk_t = torch_rate(B, N, True, torch.float32, steps, check="torch")
            f64 = torch_rate(B, N, True, torch.float64, steps)
            npr = numpy_rate(min(B, NUMPY_TEAMS), N, nsteps)
            g = f"{torch_rate(B, N, True, torch.float32, steps, 'cuda'):>13.0f}" if gpu else f"{'':>13}"
            print(f"{B:>5} {N:>5} {bare:>11.0f} {f32:>11.0f} {bk_np:>11.0f} {bk_t:>11.0f} {f64:>11.0f} {npr:>11.0f} "
                  f"{f64 / npr:>7.1f} {g}",
                  flush=True)
        print("```")
        print("\nGPU: " + ("measured on " + torch.cuda.get_device_name() if gpu else
                           "no CUDA device on the measuring machine (torch.cuda.is_available() is False); column "
                           "left empty"))


if __name__ == "__main__":
    main()
