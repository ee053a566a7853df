"""Safety campaign of the torch filter: the adversaries of :mod:`agents.adversaries`, batched teams, both dtypes.

Every team of a batch is driven by one adversary (team ``b``: adversary ``b % 6`` of :data:`ADVERSARIES`, seeded by
its team), the same behaviours as :mod:`agents.adversaries` written in torch: ``spin_up`` (spin 200 steps, then
full throttle), ``burst`` (rest 100 steps, then full throttle), ``bang_bang`` (random +-1 per wheel held 20 steps),
``chase_nearest`` and ``chase_target`` (full point acceleration toward the nearest / a random robot), and
``uniform_noise``.  Teams: RandomGoals N = 8 and 16 with 4 random obstacles, the radius-6 circle N = 39.  The torch
env behind the filter's defaults (``backup=True``, negotiation groups), once per ``--stages``: ``compiled``, the
env's compiled CPU stages (:mod:`aasoatt_env.tensor.compiled`: the numpy filter and its backup layer); the torch
stages with the numpy filter's backup layer (``numpy``) or the torch braking check (``torch``,
:mod:`aasoatt_env.tensor.backup`); ``--steps`` physics steps; every step's smallest surface gap (robot-robot and
robot-obstacle) is recorded.  A pair closer than ``d_s - 1 mm`` is a violation.

Usage: ``python benchmarks/tensor_safety.py [--steps 400] [--episodes 8:512,16:384,39:128] [--batch 128]
[--stages compiled,numpy,torch] [--page docs/benchmarks/tensor_safety.md]``
"""

from __future__ import annotations

import argparse
import time

import torch
from page import add_page_options, check_page, printed_page  # noqa: E402

from aasoatt_env.tensor.env import make_tensor_env
from aasoatt_env.tensor.filter import BACKUP_CHECKS
from agents.adversaries_torch import ADVERSARIES, adversary_actions

TOL = 1e-3
STAGES = ("compiled", *BACKUP_CHECKS)  #: ``--stages`` (module docstring)


def run(n: int, episodes: int, batch: int, steps: int, dtype: torch.dtype, stages: str) -> dict:
    """Worst gap and counts of ``episodes`` team-episodes of ``n`` robots, in batches of ``batch`` teams."""
    scen = dict(scenario="circle_swap", radius=6.0) if n == 39 else dict(scenario="random_goals", random_obstacles=4)
    worst, bad, braked, unsafe, done, t0 = float("inf"), 0, 0, 0, 0, time.perf_counter()
    per_adv = {a: float("inf") for a in ADVERSARIES}
    while done < episodes:
        B = min(batch, episodes - done)
        compiled = stages == "compiled"
        env = make_tensor_env(num_envs=B, num_robots=n, dtype=dtype, max_steps=steps + 1, compiled=compiled,
                              backup_check=None if compiled else stages, **scen)
        env.reset(seed=done)
        gen = torch.Generator().manual_seed(done)
        kind = torch.arange(done, done + B) % len(ADVERSARIES)
        state = {"target": (torch.arange(n)[None] + torch.randint(1, max(n, 2), (B, n), generator=gen)) % n}
        low = torch.full((B,), float("inf"), dtype=torch.float64)
        with torch.no_grad():
            for t in range(steps):
                _, _, _, _, info = env.step(adversary_actions(env, t, kind, gen, state))
                low = torch.minimum(low, info["clearance"].amin(-1).double())
                braked += int(info["backup"].any(-1).sum())
                unsafe += int(((info["status"] & 8) > 0).any(-1).sum())
        worst = min(worst, float(low.min()))
        bad += int((low < -TOL).sum())
        for i, a in enumerate(ADVERSARIES):
            if bool((kind == i).any()):
                per_adv[a] = min(per_adv[a], float(low[kind == i].min()))
        done += B
    return dict(worst=worst, bad=bad, braked=braked, unsafe=unsafe, per_adv=per_adv, time=time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--episodes", default="8:512,16:384,39:128", help="N:team-episodes, comma-separated")
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--dtypes", default="float64,float32")
    parser.add_argument("--stages", default=",".join(STAGES), help="the env's stages (module docstring), "
                        "comma-separated")
    add_page_options(parser)
    args = parser.parse_args()
    check_page(args)
    torch.set_num_threads(1)
    plan = [tuple(int(x) for x in s.split(":")) for s in args.episodes.split(",")]
    with printed_page(args, "Torch filter safety campaign", notes=__doc__):
        print("```")
        print(f"{'stages':>8} {'dtype':>8} {'N':>4} {'episodes':>9} {'worst gap [m]':>14} {'< -1 mm':>8} "
              f"{'team-steps braked':>18} {'unsafe':>7} {'time [s]':>9}   worst gap per adversary [m]")
        for stages in args.stages.split(","):
            if stages not in STAGES:
                parser.error(f"--stages: got {stages!r}, expected some of {list(STAGES)}")
            for name in args.dtypes.split(","):
                for n, episodes in plan:
                    r = run(n, episodes, args.batch, args.steps, getattr(torch, name), stages)
                    adv = " ".join(f"{a}={v:.4f}" for a, v in r["per_adv"].items())
                    print(f"{stages:>8} {name:>8} {n:>4} {episodes:>9} {r['worst']:>14.6f} {r['bad']:>8} "
                          f"{r['braked']:>18} {r['unsafe']:>7} {r['time']:>9.0f}   {adv}", flush=True)
        print("```")


if __name__ == "__main__":
    main()
