"""Bounded waits: the filter step's time distribution under every adversary, at nominal magnitudes 1, 1e3, 1e6.

A safety filter runs in a control loop with a fixed period (the paper's is 5 ms), so its step time must be
bounded for every input it accepts, not only its median on friendly ones.  For each team size (RandomGoals,
paper robots, seed 5158), mode and magnitude, every adversary of :data:`agents.ADVERSARIES` drives the team
for ``--steps`` physics steps with its actions multiplied by the magnitude (behind the filter the env takes
actions beyond ``[-1, 1]`` as the unclipped nominal; an untrained network without a squashing output, a units
mistake or another action scale produces them), plus the forward/swerve pattern (full forward for 120 steps,
a hard swerve for 30, alternating sides).  After :func:`~aasoatt_env.safety.warm_up`, each ``SafetyFilter`` call
is timed; the table gives the median, p99 and slowest step over all of them, the p99 ratio to magnitude 1, and
the most solver iterations of a step.
Every solver call's work is bounded by an iteration count (:data:`~aasoatt_env.safety.solvers.backends.ITER_LIMIT`,
the warm active set's budgets), so the slowest step is a property of the problem size.

Usage: ``python benchmarks/bench_deadline.py [--sizes 8,32,100] [--steps 600] [--page docs/...]``
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from page import add_page_options, check_page, write_page  # noqa: E402

from aasoatt_env import make_env  # noqa: E402
from aasoatt_env.safety import warm_up  # noqa: E402
from agents import ADVERSARIES  # noqa: E402

MAGNITUDES = (1.0, 1e3, 1e6)


class Swerve:
    """Full forward for 120 steps, a hard swerve for 30, alternating sides."""

    def __init__(self) -> None:
        self.k = -1

    def act(self, obs: dict, env: object) -> dict:
        """The team's actions at the next step."""
        self.k += 1
        k = self.k % 300
        a = [1.0, 1.0] if k < 120 or 150 <= k < 270 else [1.0, -1.0] if k < 150 else [-1.0, 1.0]
        return {agent: np.array(a, np.float32) for agent in env.agents}  # type: ignore[attr-defined]


def _agent(name: str) -> object:
    if name == "swerve":
        return Swerve()
    cls = ADVERSARIES[name]
    try:
        return cls(seed=3)
    except TypeError:
        return cls()


def episode(n: int, mode: str, magnitude: float, adversary: str, steps: int) -> tuple[list[float], int]:
    """Each filter call's wall time [s] and the most iterations of a step, over one episode."""
    env = make_env("random_goals", num_robots=n, filter={"mode": mode}, max_steps=10**9)
    obs, _ = env.reset(seed=5158)
    filt, times, iters = env.unwrapped.control_filter, [], [0]
    call = type(filt).__call__

    def timed(inp, nominal):
        t = time.perf_counter()
        res = call(filt, inp, nominal)
        times.append(time.perf_counter() - t)
        iters[0] = max(iters[0], res.iterations)
        return res

    env.unwrapped.set_control_filter(None)
    env.unwrapped.set_control_filter(timed_filter(filt, timed))
    agent = _agent(adversary)
    if hasattr(agent, "reset"):
        agent.reset(env)
    for _ in range(steps):
        act = agent.act(obs, env)
        obs, *_ = env.step({a: v * np.float32(magnitude) for a, v in act.items()})
    return times[1:], iters[0]  # (the first call loads the compiled kernels)


def timed_filter(filt: object, call: object) -> object:
    """``filt`` with its ``__call__`` replaced by ``call`` (the env's filter protocol)."""
    class Timed:
        keeps_input_bounds = True

        def reset(self, team: object) -> None:
            filt.reset(team)  # type: ignore[attr-defined]

        def __call__(self, inp: object, nominal: np.ndarray) -> object:
            return call(inp, nominal)  # type: ignore[operator]

    return Timed()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="8,32,100", help="team sizes, comma-separated")
    ap.add_argument("--steps", type=int, default=600, help="physics steps per adversary and setting")
    ap.add_argument("--adversaries", default=",".join([*ADVERSARIES, "swerve"]), help="comma-separated")
    add_page_options(ap)
    args = ap.parse_args()
    check_page(args)
    lines = [f"{'N':>4} {'mode':>14} {'magnitude':>9} {'median':>8} {'p99':>8} {'slowest':>8} {'p99/p99(1)':>10} "
             f"{'iterations':>10}   (ms per filter step, {args.steps} steps x each adversary)"]
    print(lines[0], flush=True)
    warm_up()  # (as a control loop would before its first step: the kernels compiled or loaded from the cache)
    for n in (int(v) for v in args.sizes.split(",")):
        for mode in ("centralized", "decentralized"):
            base = None
            for mag in MAGNITUDES:
                ts, its = [], 0
                for adv in args.adversaries.split(","):
                    t, i = episode(n, mode, mag, adv, args.steps)
                    ts += t
                    its = max(its, i)
                ms = np.array(ts) * 1e3
                p99 = float(np.percentile(ms, 99))
                base = p99 if base is None else base
                lines.append(f"{n:>4} {mode:>14} {mag:>9.0e} {np.median(ms):8.2f} {p99:8.2f} {ms.max():8.1f} "
                             f"{p99 / base:10.2f} {its:>10d}")
                print(lines[-1], flush=True)
    write_page(args, "Filter step times under adversarial nominals", "```\n" + "\n".join(lines) + "\n```\n\n"
               + __doc__.split("Usage")[0])


if __name__ == "__main__":
    main()
