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

The closed loops differ by more than the nominal: at magnitudes beyond the box the robots drive at full
acceleration, so their traffic (and how often a step's rows are infeasible) is another.  The second table
isolates the nominal: the inputs of the magnitude-1 loops replayed to a fresh filter with every nominal
multiplied by the magnitude (same states, same warm-start history up to the filter's own answers).
Every solver call's work is bounded by an iteration count (:data:`~aasoatt_env.safety.solvers.backends.ITER_LIMIT`,
the warm active set's budgets), so the slowest step is a property of the problem size.

Usage: ``python benchmarks/bench_deadline.py [--sizes 8,32,100] [--steps 600] [--page docs/...]``
"""

from __future__ import annotations

import argparse
import gc
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


def episode(n: int, mode: str, magnitude: float, adversary: str, steps: int,
            record: list | None = None) -> tuple[list[float], int]:
    """Each filter call's wall time [s] and the most iterations of a step, over one episode.

    ``record``: gets the filter, then a copy of each call's ``(input, nominal)``.
    """
    env = make_env("random_goals", num_robots=n, filter={"mode": mode}, max_steps=10**9)
    obs, _ = env.reset(seed=5158)
    filt, times, iters = env.unwrapped.control_filter, [], [0]
    call = type(filt).__call__

    def timed(inp, nominal):
        if record is not None:
            record.append((_copied(inp), nominal.copy()))
        t = time.perf_counter()
        res = call(filt, inp, nominal)
        times.append(time.perf_counter() - t)
        iters[0] = max(iters[0], res.iterations)
        return res

    if record is not None:
        record.append(filt)

    env.unwrapped.set_control_filter(None)
    env.unwrapped.set_control_filter(timed_filter(filt, timed))
    agent = _agent(adversary)
    if hasattr(agent, "reset"):
        agent.reset(env)
    for _ in range(steps):
        act = agent.act(obs, env)
        obs, *_ = env.step({a: v * np.float32(magnitude) for a, v in act.items()})
    _settle()
    return times[1:], iters[0]  # (the first call loads the compiled kernels)


def _settle() -> None:
    """Collect, then move what is kept (the recorded inputs) out of the collector's way: a later step's time is the
    filter's, not a full collection's over the benchmark's own records."""
    gc.collect()
    gc.freeze()


def replay(record: list, magnitude: float) -> list[float]:
    """Each call's wall time [s] of a fresh filter (the recorded one's configuration) on the recorded inputs, every
    nominal multiplied by ``magnitude``."""
    filt, calls = record[0], record[1:]
    fresh = type(filt)(filt.team, config=filt.config)
    times = []
    for inp, nominal in calls:
        t = time.perf_counter()
        fresh(inp, nominal * magnitude)
        times.append(time.perf_counter() - t)
    _settle()
    return times[1:]


def _copied(x: object) -> object:
    """A copy of an input's arrays (named tuples of arrays, nested)."""
    if isinstance(x, np.ndarray):
        return x.copy()
    if isinstance(x, tuple):
        items = [_copied(v) for v in x]
        return type(x)(*items) if hasattr(x, "_fields") else tuple(items)
    return x


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
    same = [f"{'N':>4} {'mode':>14} {'magnitude':>9} {'median':>8} {'p99':>8} {'slowest':>8} {'p99/p99(1)':>10}"
            "   (ms per filter step: the magnitude-1 loops' inputs, nominals x magnitude)"]
    warm_up()  # (as a control loop would before its first step: the kernels compiled or loaded from the cache)
    for n in (int(v) for v in args.sizes.split(",")):
        for mode in ("centralized", "decentralized"):
            base, records = None, []
            for mag in MAGNITUDES:
                ts, its = [], 0
                for adv in args.adversaries.split(","):
                    records.append([] if mag == 1.0 else None)
                    t, i = episode(n, mode, mag, adv, args.steps, records[-1])
                    ts += t
                    its = max(its, i)
                base = _row(lines, f"{n:>4} {mode:>14} {mag:>9.0e}", ts, base, f" {its:>10d}")
            base, records = None, [r for r in records if r is not None]
            for mag in MAGNITUDES:
                base = _row(same, f"{n:>4} {mode:>14} {mag:>9.0e}", [t for r in records for t in replay(r, mag)],
                            base)
    print("\n".join(same))
    write_page(args, "Filter step times under adversarial nominals", "```\n" + "\n".join(lines) + "\n```\n\n```\n"
               + "\n".join(same) + "\n```\n\n" + __doc__.split("Usage")[0])


def _row(lines: list[str], head: str, times: list[float], base: float | None, tail: str = "") -> float:
    """Append (and print) a row of the times' median, p99, slowest and p99 ratio; returns the base p99."""
    ms = np.array(times) * 1e3
    p99 = float(np.percentile(ms, 99))
    base = p99 if base is None else base
    lines.append(f"{head} {np.median(ms):8.2f} {p99:8.2f} {ms.max():8.1f} {p99 / base:10.2f}{tail}")
    print(lines[-1], flush=True)
    return base


if __name__ == "__main__":
    main()
