"""Memory over a long episode: is it flat?

Runs one long episode (default 50,000 physics steps of 5 ms, i.e. 250 s of
simulated time) bare and behind the safety filter and samples, every
``--every`` physics steps, the Python heap (``tracemalloc``, only with
``--tracemalloc``: it slows the run 2-3x) and the resident set size (RSS, from
``/proc/self/statm``; it also sees the C/C++ allocations of numpy, scipy and the
QP solvers).  Memory is "flat" when the growth from the first sample after
warm-up to the last one stays within a few MB.

The env keeps a bounded trail (:data:`aasoatt_env.sim.env.TRAIL_LENGTH` positions
for rendering) and nothing else per step; recording an episode
(:class:`aasoatt_env.analysis.recording.RecordEpisode`) grows with it by design
and is not part of this check.

Usage: ``python benchmarks/bench_memory.py [--physics-steps 50000] [--robots 4] [--tracemalloc]``
"""

from __future__ import annotations

import argparse
import gc
import os
import time
import tracemalloc
from dataclasses import dataclass

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from aasoatt_env.api.factory import make_env  # noqa: E402
from agents import TrackingController  # noqa: E402

__all__ = ["MemoryTrace", "measure", "rss_bytes"]


def rss_bytes() -> int | None:
    """Resident set size of this process [bytes] (None where ``/proc`` is not available)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


@dataclass
class MemoryTrace:
    """Samples of one long episode."""

    physics_steps: list[int]
    traced: list[int]
    """``tracemalloc`` current size [bytes] (empty without tracemalloc)."""
    rss: list[int]
    """Resident set size [bytes] (empty where unavailable)."""
    wall_s: float

    def growth(self, which: str, warmup: float = 0.2) -> float:
        """Growth [bytes] from the first sample after ``warmup`` (fraction of the run) to the last."""
        values = getattr(self, which)
        if not values:
            return float("nan")
        k = min(int(len(values) * warmup), len(values) - 1)
        return float(values[-1] - values[k])


def measure(
    physics_steps: int = 50_000,
    robots: int = 4,
    filtered: bool = True,
    solver: str = "proxsuite",
    decision_interval: int = 50,
    every: int = 2_500,
    trace: bool = False,
) -> MemoryTrace:
    """Run one episode of ``physics_steps`` physics steps and sample memory every ``every`` of them.

    The circle swap with ``robots`` robots (the tracking controller; behind the
    filter with ``solver`` if ``filtered``), horizon extended to the whole run.
    """
    env_steps = max(1, physics_steps // decision_interval)
    env = make_env("circle_swap", num_robots=robots, radius=max(2.0, 0.3 * robots), duration=10.0,
                   decision_interval=decision_interval, max_steps=env_steps,
                   filter={"solver": solver} if filtered else None)
    ctrl = TrackingController(saturate=not filtered)
    obs, _ = env.reset(seed=0)
    ctrl.reset(env)
    steps, traced, rss = [], [], []
    sample_every = max(1, every // decision_interval)
    if trace:
        tracemalloc.start()
    t0 = time.perf_counter()
    try:
        for k in range(1, env_steps + 1):
            obs, *_ = env.step(ctrl.act(obs, env))
            if k % sample_every == 0 or k == env_steps:
                gc.collect()
                steps.append(k * decision_interval)
                if trace:
                    traced.append(tracemalloc.get_traced_memory()[0])
                r = rss_bytes()
                if r is not None:
                    rss.append(r)
    finally:
        if trace:
            tracemalloc.stop()
    wall = time.perf_counter() - t0
    env.close()
    return MemoryTrace(steps, traced, rss, wall)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--physics-steps", type=int, default=50_000)
    parser.add_argument("--robots", type=int, default=4)
    parser.add_argument("--solver", default="proxsuite")
    parser.add_argument("--tracemalloc", action="store_true", help="also trace the Python heap (slower)")
    args = parser.parse_args()
    mb = 1 / 2**20
    print(f"{'run':>9} {'physics steps':>14} {'wall [s]':>9} {'RSS start [MB]':>15} {'RSS growth [MB]':>16} "
          f"{'heap growth [MB]':>17}")
    for filtered in (False, True):
        tr = measure(args.physics_steps, args.robots, filtered, args.solver, trace=args.tracemalloc)
        start = tr.rss[int(len(tr.rss) * 0.2)] * mb if tr.rss else float("nan")
        print(f"{'filtered' if filtered else 'bare':>9} {tr.physics_steps[-1]:>14} {tr.wall_s:>9.1f} {start:>15.1f} "
              f"{tr.growth('rss') * mb:>16.2f} {tr.growth('traced') * mb:>17.3f}")
        if tr.rss:
            print("          RSS [MB] at samples:", " ".join(f"{r * mb:.1f}" for r in tr.rss))
    _ = np  # numpy is imported first for OMP_NUM_THREADS to take effect


if __name__ == "__main__":
    main()
