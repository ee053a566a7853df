"""Bounded memory over long episodes: 50,000 physics steps, memory flat within a few MB.

Uses :func:`benchmarks.bench_memory.measure` (also a script: ``python benchmarks/bench_memory.py``).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

MB = 2**20


def _bench():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_memory.py"
    spec = importlib.util.spec_from_file_location("bench_memory", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_memory", module)  # dataclasses look their module up there
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


@pytest.mark.slow
def test_bare_env_python_heap_is_flat_over_50k_physics_steps() -> None:
    trace = _bench().measure(50_000, robots=4, filtered=False, trace=True)
    assert trace.physics_steps[-1] == 50_000
    assert trace.growth("traced") < 1 * MB, trace.traced
    if trace.rss:
        assert trace.growth("rss") < 4 * MB, trace.rss


@pytest.mark.slow
def test_filtered_env_memory_is_flat_over_50k_physics_steps() -> None:
    trace = _bench().measure(50_000, robots=4, filtered=True, trace=False)
    assert trace.physics_steps[-1] == 50_000
    if not trace.rss:
        pytest.skip("no /proc/self/statm to read the resident set size")
    assert trace.growth("rss") < 4 * MB, [round(r / MB, 2) for r in trace.rss]


def test_trail_is_bounded() -> None:
    from aasoatt_env.sim.env import TRAIL_LENGTH, AASOATTParallelEnv

    env = AASOATTParallelEnv("circle_swap", num_robots=2, max_steps=10**6)
    env.reset(seed=0)
    acts = {a: [0.0, 0.0] for a in env.agents}
    for _ in range(TRAIL_LENGTH + 50):
        env.step(acts)
    assert len(env._trail) == TRAIL_LENGTH
