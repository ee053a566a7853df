"""Liveness of the torch filter beside the numpy one: the same teams and nominal laws, robots home at the end.

RandomGoals teams of ``--robots`` (held-out seeds ``2**32 + b``, as training's evaluation), 100 ms decisions of
point accelerations (clipped to the bound) from two nominal laws: ``track``, a PD law on the moving reference
(``a_d + 4 (v_d - v) + (p_d - p)``), and ``goal``, a PD law on the goal (``3 (goal - p) - 3 v``, saturating: it drives
at the bound and leaves the reference behind). Each team runs one episode behind the torch filter (float64, defaults:
negotiation groups; with the numpy backup layer, with the torch braking check and its repair, and with that check
alone, ``backup_repair=False``) and behind the numpy decentralised filter (defaults: negotiation groups and the backup
layer with its repair). Columns: robots within the goal tolerance
(0.1 m) at the end, robot-decisions on the backup (braked by the torch check; braked by the numpy layer, its
``backup`` flag: a robot its repair nudged instead is not counted), robots that collided.

Usage: ``python benchmarks/tensor_liveness.py [--teams 32] [--robots 6] [--page docs/benchmarks/tensor_liveness.md]``
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from page import add_page_options, check_page, printed_page  # noqa: E402

from aasoatt_env import make_env
from aasoatt_env.tensor.env import make_tensor_env

SEED = 2**32
TOL = 0.1
LAWS = ("track", "goal")


def law(kind: str, p, v, p_d, v_d, a_d, goal):
    """The nominal point acceleration [m/s^2] of ``kind`` (module docstring); numpy or torch."""
    if kind == "track":
        return a_d + 4.0 * (v_d - v) + 1.0 * (p_d - p)
    return 3.0 * (goal - p) - 3.0 * v


def torch_run(kind: str, teams: int, n: int, check: str, repair: bool = True) -> tuple[float, float, int]:
    """Success, backup share and robots collided of ``teams`` teams behind the torch filter (the torch stages) with
    ``check``."""
    env = make_tensor_env("random_goals", teams, n, decision_interval=20, action_mode="point", dtype=torch.float64,
                          backup_repair=repair, backup_check=check, compiled=False)  # (the torch stages)
    env.autoreset = False
    env.reset(seed=SEED)
    amax = env.team.max_point_accel[:, None]
    done = torch.zeros(teams, dtype=torch.bool)
    home = torch.zeros(teams, n, dtype=torch.bool)
    collided = torch.zeros(teams, n, dtype=torch.bool)
    braked = total = 0
    with torch.no_grad():
        while not bool(done.all()):
            p_d, v_d, a_d = env.ref
            a = law(kind, env.kin.p, env.kin.v, p_d, v_d, a_d, env.goals) / amax
            _, _, _, trunc, info = env.step(a.clamp(-1.0, 1.0))
            live = ~done[:, None].expand(teams, n)
            braked += int((info["backup"] & live).sum())
            total += int(live.sum())
            collided |= live & (info["clearance"] < -env.collision_tolerance)
            end = trunc[:, 0] & ~done
            at_goal = torch.sqrt(((env.kin.p - env.goals) ** 2).sum(-1)) < TOL
            home[end] = at_goal[end]
            done |= trunc[:, 0]
    return float(home.float().mean()), braked / total, int(collided.sum())


def numpy_run(kind: str, teams: int, n: int) -> tuple[float, float, int]:
    """The same behind the numpy decentralised filter, one PettingZoo env per team."""
    home, braked, total, collided = [], 0, 0, 0
    for b in range(teams):
        env = make_env("random_goals", num_robots=n, decision_interval=20, action_mode="point",
                       filter={"mode": "decentralized"})
        env.reset(seed=SEED + b)
        base = env.unwrapped
        hit = np.zeros(n, dtype=bool)
        while env.agents:
            kin, (p_d, v_d, a_d) = base.kinematics, base.reference
            a = law(kind, kin.p, kin.v, p_d, v_d, a_d, base.goals) / base.team.max_point_accel[:, None]
            a = np.clip(a, -1.0, 1.0).astype(np.float32)
            _, _, _, _, info = env.step({ag: a[i] for i, ag in enumerate(env.agents)})
            braked += sum(bool(i["filter"]["backup"]) for i in info.values())
            total += len(info)
            hit |= np.array([info[ag]["collision"] for ag in env.possible_agents])
        home.append(np.hypot(*(base.positions - base.goals).T) < TOL)
        collided += int(hit.sum())
    return float(np.mean(home)), braked / total, collided


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--teams", type=int, default=32)
    ap.add_argument("--robots", type=int, default=6)
    add_page_options(ap)
    args = ap.parse_args()
    check_page(args)
    torch.set_num_threads(1)
    with printed_page(args, "Torch filter liveness", notes=__doc__):
        print("```")
        print(f"{'law':>6} {'filter':>24} {'robots home':>12} {'on the backup':>14} {'robots collided':>16}")
        for kind in LAWS:
            for name, run in (("torch, numpy check", lambda *a: torch_run(*a, "numpy")),
                              ("torch, torch check", lambda *a: torch_run(*a, "torch")),
                              ("torch check, no repair", lambda *a: torch_run(*a, "torch", repair=False)),
                              ("numpy decentralised", numpy_run)):
                s, share, hit = run(kind, args.teams, args.robots)
                print(f"{kind:>6} {name:>24} {s:>12.3f} {share:>14.3f} {hit:>16}", flush=True)
        print("```")


if __name__ == "__main__":
    main()
