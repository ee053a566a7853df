"""Closed-loop safety campaign of the AA-SOATT filter (issue 3's "Must show", long form).

Runs, with the paper's method (TrackingController behind AASOATTFilter, defaults):

* circle swap radius 6, 12 s (+3 s settling), N = 10, 20, 30, 35, 39;
* circle swap radius 10, 20 s (+3 s settling), N = 60 (paper robots) and N = 100
  (robots of radius 0.3, as in ``aasoatt reproduce swarm100``: 100 robots of the
  paper's radius 0.48 do not fit on a radius-10 circle);

and, behind the filter, uniform random actions and a hostile policy (every
robot accelerates at its nearest neighbour) on RandomGoals with 20 robots,
10 seeds x 2,000 steps each.  Prints one table: minimum centre distance minus
``d_s`` (must be >= -1e-3), steps relaxed / failed, largest final distance to
the goal (circle runs: must be <= 0.05), collisions, wall time.

Usage: ``python benchmarks/safety_campaign.py [--quick] [--solver proxsuite] [--only r6|r10|random]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from aasoatt_env import FilterConfig, make_env
from aasoatt_env.analysis.metrics import collisions, pairwise_min_distance
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.model.params import RobotParams
from agents import HostileAgent, RandomAgent, TrackingController


def _row(label: str, rollout, t: float, goal_check: bool) -> str:
    sep = pairwise_min_distance(rollout)
    gap = sep.overall_min_gap
    status = rollout.solver_status
    final = np.linalg.norm(rollout.positions[-1] - rollout.goals, axis=1).max() if goal_check else None
    ok = gap >= -1e-3 and (final is None or final <= 0.05) and not np.any(status == "failed")
    final_txt = "-" if final is None else f"{final:.4f}"  # no goal check for RandomGoals policies
    return (
        f"{label:34s} {gap:+10.5f} {int(np.sum(status == 'relaxed')):8d} {int(np.sum(status == 'failed')):7d} "
        f"{final_txt:>10s} {collisions(rollout).n_robot_pairs:6d} {t:8.1f}  {'ok' if ok else 'FAIL'}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N = 10, 39 and 2 seeds only")
    parser.add_argument("--solver", default="proxsuite")
    parser.add_argument("--wheel-speed-limit", type=float, default=None,
                        help="RandomGoals robots: paper robots with this wheel-speed limit [rad/s] (default: none)")
    parser.add_argument("--filter-speed-limit", type=float, default=None,
                        help="RandomGoals: the filter's max_wheel_speed [rad/s] on the robots (default: none)")
    parser.add_argument("--only", choices=("r6", "r10", "random"),
                        help="run only the radius-6 circles, the radius-10 circles or RandomGoals")
    args = parser.parse_args()
    head = ("run", "min gap", "relaxed", "failed", "final err", "coll.", "time s")
    print(f"{head[0]:34s} " + " ".join(f"{h:>{w}s}" for h, w in zip(head[1:], (10, 8, 7, 10, 6, 8))))
    circles = [(6.0, 12.0, n, None) for n in ((10, 39) if args.quick else (10, 20, 30, 35, 39))]
    if not args.quick:
        circles += [(10.0, 20.0, 60, None), (10.0, 20.0, 100, "paper_small")]
    if args.only is not None:
        circles = [c for c in circles if args.only == f"r{c[0]:g}"]
    for radius, duration, n, robots in circles:
        kwargs = {} if robots is None else {"robots": robots}
        env = make_env("circle_swap", filter=FilterConfig(solver=args.solver), num_robots=n, radius=radius,
                       duration=duration, settle_time=3.0, **kwargs)
        t = time.perf_counter()
        rollout, _ = run_episode(env, TrackingController(), seed=0)
        print(_row(f"circle R={radius:g} N={n}", rollout, time.perf_counter() - t, True), flush=True)
    seeds = range(2 if args.quick else 10) if args.only in (None, "random") else range(0)
    for name, agent in (("random", RandomAgent(seed=0)), ("hostile", HostileAgent())):
        for seed in seeds:
            limit = args.wheel_speed_limit
            robots = {} if limit is None else {"robots": RobotParams(max_wheel_speed=limit)}
            fc = FilterConfig(solver=args.solver, max_wheel_speed=args.filter_speed_limit)
            env = make_env("random_goals", filter=fc, num_robots=20, max_steps=2000, **robots)
            t = time.perf_counter()
            rollout, _ = run_episode(env, agent, seed=seed)
            tag = "" if args.wheel_speed_limit is None else f" |w|<={args.wheel_speed_limit:g}"
            tag += "" if args.filter_speed_limit is None else f" filter |w|<={args.filter_speed_limit:g}"
            print(_row(f"random_goals N=20 {name}{tag} s={seed}", rollout, time.perf_counter() - t, False), flush=True)


if __name__ == "__main__":
    main()
