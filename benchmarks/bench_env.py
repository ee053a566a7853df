"""Environment throughput: env steps per second vs team size, bare and behind the default filter.

One env step is one 5 ms physics step (``decision_interval=1``); the team is
RandomGoals (N = 4, 20, 100, 1,000; 10,000 with ``--large``) driven by the
paper's tracking controller, so the filter sees the rows and QPs of real
traffic.  Columns: bare env steps/s (zero actions: the env alone), the same
with the tracking controller (env + controller), behind the default filter
(env + controller + filter), behind the default filter with uniform random
actions, behind the decentralised filter (``mode="decentralized"``, tracking
controller), agent-steps/s of the filtered env, and the
"physics only" rate (kinematics + bounds + exact-arc integration) as the
baseline the env overhead is measured against, in the same run.  Medians
over repeats, one thread.

``--dense`` instead times every ``env.step`` of one dense scene (100 robots in a
20 m arena with 10 obstacles, tracking controller, seed 0, the first 1,200 physics
steps) behind the centralised and the decentralised filter, in one run: median,
p99, slowest step and steps over 20 ms (the decentralised mode's negotiation groups
are the whole crowd there, and their infeasible steps are its tail).

Usage: ``python benchmarks/bench_env.py [--quick] [--large] [--sizes 20,1000] [--dense] [--page docs/...]``
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from page import add_page_options, check_page, write_page  # noqa: E402

from aasoatt_env import make_env  # noqa: E402
from aasoatt_env.model import dynamics  # noqa: E402
from agents import TrackingController  # noqa: E402


def _rate(n: int, steps: int, filtered: bool | dict, agent: str) -> float:
    """Env steps/s; ``agent``: ``zeros``, ``tracking`` (the paper's controller) or ``random`` (uniform actions)."""
    env = make_env("random_goals", filter=filtered, num_robots=n, max_steps=10**9)
    obs, _ = env.reset(seed=0)
    ctrl = TrackingController()
    rng = np.random.default_rng(0)
    zeros = {a: np.zeros(2, np.float32) for a in env.agents}

    def act(obs):
        if agent == "tracking":
            return ctrl.act(obs, env)
        if agent == "random":  # one draw for the team (the harness's cost, not the env's, stays small)
            return dict(zip(env.agents, rng.uniform(-1, 1, (len(env.agents), 2)).astype(np.float32)))
        return zeros

    for _ in range(3):  # warm-up
        obs, *_ = env.step(act(obs))
    gc.collect()  # the previous env's garbage is not this one's cost
    t = time.perf_counter()
    for _ in range(steps):
        obs, *_ = env.step(act(obs))
    return steps / (time.perf_counter() - t)


def _physics_rate(n: int, steps: int) -> float:
    env = make_env("random_goals", num_robots=n)
    env.reset(seed=0)
    team, pose, u, du = env.team, env.poses, env.wheel_speeds, np.zeros((n, 2))
    t = time.perf_counter()
    for _ in range(steps):
        dynamics.kinematics(team, pose, u)
        dynamics.input_bounds(team, u, 0.005)
        pose, u = dynamics.integrate(team, pose, u, du, 0.005)
    return steps / (time.perf_counter() - t)


def dense(steps: int = 1200) -> list[str]:
    """Step-time distribution of the dense scene (module docstring), both modes."""
    lines = [f"{'mode':>14} {'median':>8} {'p99':>8} {'slowest':>8} {'>20 ms':>7} {'first':>8}   (ms per env.step)"]
    print(lines[0])
    for mode in ("centralized", "decentralized"):
        env = make_env("random_goals", num_robots=100, arena_size=20, random_obstacles=10, filter={"mode": mode},
                       max_steps=10**9)
        obs, _ = env.reset(seed=0)
        ctrl, ts = TrackingController(), []
        for _ in range(steps):
            act = ctrl.act(obs, env)
            t = time.perf_counter()
            obs, *_ = env.step(act)
            ts.append(time.perf_counter() - t)
        ms = np.array(ts) * 1e3
        lines.append(f"{mode:>14} {np.median(ms):8.2f} {np.percentile(ms, 99):8.2f} {ms[1:].max():8.1f} "
                     f"{int((ms[1:] > 20).sum()):7d} {ms[0]:8.1f}")
        print(lines[-1], flush=True)
    lines.append("(slowest and > 20 ms: without the first step, which loads the compiled kernels)")
    print(lines[-1])
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N <= 100, fewer steps and repeats")
    parser.add_argument("--large", action="store_true", help="also N = 10,000")
    parser.add_argument("--sizes", type=lambda v: [int(x) for x in v.split(",")], default=None,
                        help="team sizes, comma-separated (replaces the defaults)")
    parser.add_argument("--dense", action="store_true", help="only the dense scene's step times, both modes")
    add_page_options(parser)
    args = parser.parse_args()
    check_page(args)
    if args.dense:
        lines = dense()
        write_page(args, "Dense scene step times", "```\n" + "\n".join(lines) + "\n```\n\n" + __doc__)
        return
    repeats = 3 if args.quick else 5
    sizes = [4, 20, 100] if args.quick else [4, 20, 100, 1000] + ([10000] if args.large else [])
    sizes = args.sizes or sizes
    lines = [f"{'N':>6} {'bare':>10} {'+control':>10} {'+filter':>10} {'random+f':>10} {'decentral':>10} "
             f"{'agent-st/s':>11} {'physics':>10} {'bare/phys':>10} {'filt/bare':>10}   (env steps/s)"]
    print(lines[0])
    dec = {"mode": "decentralized"}
    for n in sizes:
        steps = 400 if n <= 20 else 150 if n <= 100 else 60 if n <= 1000 else 4
        steps = max(steps // (4 if args.quick else 1), 4)
        fsteps = max(steps // 2, 4)  # windows of >= 0.2 s at N <= 1,000: short ones catch the machine's noise
        bare = statistics.median(_rate(n, steps, False, "zeros") for _ in range(repeats))
        ctrl = statistics.median(_rate(n, steps, False, "tracking") for _ in range(repeats))
        filt = statistics.median(_rate(n, fsteps, True, "tracking") for _ in range(repeats))
        rand = statistics.median(_rate(n, fsteps, True, "random") for _ in range(repeats))
        dcen = statistics.median(_rate(n, fsteps, dec, "tracking") for _ in range(repeats))
        phys = statistics.median(_physics_rate(n, steps) for _ in range(repeats))
        lines.append(f"{n:>6} {bare:>10.0f} {ctrl:>10.0f} {filt:>10.1f} {rand:>10.1f} {dcen:>10.1f} "
                     f"{filt * n:>11.0f} {phys:>10.0f} {bare / phys:>10.2f} {filt / bare:>10.3f}")
        print(lines[-1], flush=True)
    write_page(args, "Environment throughput", "```\n" + "\n".join(lines) + "\n```\n\n" + __doc__)


if __name__ == "__main__":
    main()
