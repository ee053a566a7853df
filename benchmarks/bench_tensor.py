"""Robot-steps per second of the torch env (:mod:`aasoatt_env.tensor`) beside the numpy batched env, one CPU thread.

Each row steps ``B`` random_goals teams of ``N`` paper robots with the paper's tracking law (``k3 = 1``, ``k4 = 4``)
as actions, from ``reset(seed=0)`` after a few warm-up steps, and reports ``B N`` over the median step's time.
``filt``: behind the paper's filter (decentralised, ``backup=False``, ``negotiate=False``: each robot's own QP);
``defaults``: behind the filter's defaults (negotiation groups and the backup stage).  The first four columns are the
env's CPU default, its compiled stages (``compiled=True``: the numpy env's kernels and the numpy filter, no gradient);
``torch``: the torch stages (``compiled=False``: what runs on a GPU and with ``differentiable=True``) behind the
paper's filter and the defaults, with the numpy backup layer (``torch dflt``, a CPU's default) or the torch braking
check (``torch brake``, :mod:`aasoatt_env.tensor.backup`);
``numpy filt``: the numpy :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv` behind the paper's filter (one grouped
filter call for all teams).  The GPU column is measured only where
``torch.cuda.is_available()`` (the torch stages, float32); otherwise it is empty (never estimated).

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


def _torch_actions(env):
    k = env.kin
    A = torch.stack((torch.stack((k.a00, k.a01), -1), torch.stack((k.a10, k.a11), -1)), -2)
    a = 1.0 * (env.ref[0] - k.p) + 4.0 * (env.ref[1] - k.v) - k.adot
    return torch.linalg.solve(A, a[..., None])[..., 0] / env.team.max_wheel_accel[:, None]


def torch_rate(B: int, N: int, filtered: bool, dtype: torch.dtype, steps: int, device: str = "cpu",
               compiled: bool | None = None, defaults: bool = False, check: str | None = None) -> float:
    """Robot-steps/s of the torch env (``defaults``: behind the filter's defaults, with backup check ``check``)."""
    env = make_tensor_env("random_goals", B, N, device=device, dtype=dtype, filter=filtered,
                          clip_actions=not filtered,  # (the tracking law's nominal leaves [-1, 1] without a filter)
                          compiled=compiled, **({"backup_check": check} if defaults else FILTER))
    env.reset(seed=0)
    times = []
    with torch.no_grad():
        for k in range(3 + steps):
            act = _torch_actions(env)
            if device == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            env.step(act)
            if device == "cuda":
                torch.cuda.synchronize()
            if k >= 3:
                times.append(time.perf_counter() - t0)
    return B * N / float(np.median(times))


def numpy_rate(B: int, N: int, steps: int) -> float:
    """Robot-steps/s of the numpy batched env behind the numpy decentralised filter (one grouped call)."""
    env = make_batched_env(B, "random_goals", num_robots=N, filter=dict(mode="decentralized", **FILTER))
    env.reset(seed=0)

    def act():
        kin, (p_d, v_d, _) = env._kin, env._ref_now
        a = 1.0 * (p_d - kin.p) + 4.0 * (v_d - kin.v) - kin.adot_u
        return (np.linalg.solve(kin.A, a[..., None])[..., 0] / 60.0).reshape(B, N, 2)

    times = []
    for k in range(2 + steps):
        a = act()
        t0 = time.perf_counter()
        env.step(a)
        if k >= 2:
            times.append(time.perf_counter() - t0)
    return B * N / float(np.median(times))


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
        cols = ("bare f32", "filt f32", "filt f64", "defaults", "torch filt", "torch dflt", "torch brake", "numpy filt")
        print(f"{'B':>5} {'N':>5} " + " ".join(f"{c:>11}" for c in cols)
              + f" {'GPU filt f32':>13}   (robot-steps/s, one CPU thread)")
        for B, N in args.sizes:
            robots = B * N
            steps = max(5, min(60, 400_000 // robots)) // (4 if args.quick else 1) or 2
            slow = max(3, min(30, 100_000 // robots)) // (2 if args.quick else 1) or 2  # (the torch stages)
            rates = (torch_rate(B, N, False, torch.float32, steps), torch_rate(B, N, True, torch.float32, steps),
                     torch_rate(B, N, True, torch.float64, steps),
                     torch_rate(B, N, True, torch.float32, steps, defaults=True),
                     torch_rate(B, N, True, torch.float32, slow, compiled=False),
                     torch_rate(B, N, True, torch.float32, slow, compiled=False, defaults=True),
                     torch_rate(B, N, True, torch.float32, slow, compiled=False, defaults=True, check="torch"),
                     numpy_rate(B, N, slow))
            g = f"{torch_rate(B, N, True, torch.float32, steps, 'cuda'):>13.0f}" if gpu else f"{'':>13}"
            print(f"{B:>5} {N:>5} " + " ".join(f"{r:>11.0f}" for r in rates) + f" {g}", flush=True)
        print("```")
        print("\nGPU: " + ("measured on " + torch.cuda.get_device_name() if gpu else
                           "no CUDA device on the measuring machine (torch.cuda.is_available() is False); column "
                           "left empty"))


if __name__ == "__main__":
    main()
