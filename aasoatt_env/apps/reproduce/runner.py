"""One run of a reproduction experiment (metrics, light traces) and a runner over many (the same for any ``jobs``)."""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aasoatt_env.analysis.metrics import pairwise_min_distance, summarize
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.api.factory import make_env
from aasoatt_env.cli_support import progress
from aasoatt_env.safety.config import FilterConfig
from agents.baselines import PDController, TrackingController

__all__ = ["RunResult", "RunSpec", "run_many", "run_spec"]

MAX_SAMPLES: int = 800  # time samples kept for figures, at most


@dataclass(frozen=True)
class RunSpec:
    """What to simulate: ``controller`` ``tracking`` (eqn. 11-12) or SBC's ``pd``; metrics over ``[0, window]`` s.

    ``key`` labels the run in its experiment, ``meta`` goes into its row; ``filter`` None: actions saturated.
    """

    key: str
    scenario: str
    scenario_kwargs: dict[str, Any]
    controller: str = "tracking"
    k3: float = 1.0
    k4: float = 4.0
    filter: FilterConfig | None = None
    seed: int = 0
    window: float | None = None
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class RunResult:
    """Metrics over the window (``*_end``, ``*_full``: the whole episode) and down-sampled traces of one run."""

    spec: RunSpec
    metrics: dict[str, Any]
    traces: dict[str, np.ndarray]


def run_spec(spec: RunSpec) -> RunResult:
    """Simulate one :class:`RunSpec`."""
    controllers = {"tracking": TrackingController, "pd": PDController}
    if spec.controller not in controllers:
        raise ValueError(f"controller: got {spec.controller!r}, expected 'tracking' or 'pd'")
    t0 = time.perf_counter()
    env = make_env(spec.scenario, filter=spec.filter, **spec.scenario_kwargs)
    agent = controllers[spec.controller](spec.k3, spec.k4, saturate=spec.filter is None)
    rollout, _ = run_episode(env, agent, seed=spec.seed, metadata={"key": spec.key})
    wall = time.perf_counter() - t0
    part = rollout.window(spec.window)
    metrics = summarize(part)
    full = metrics if part is rollout else summarize(rollout)
    for k in ("final_error_mean", "final_error_max", "reach_rate", "n_deadlocked"):
        metrics[f"{k}_end"] = full[k]
    sep = pairwise_min_distance(rollout)
    team = rollout.n_robots > 1
    metrics.update(min_center_distance_full=sep.overall_min_center_distance if team else None,
                   min_robot_gap_full=sep.overall_min_robot_gap if team else None,
                   safety_distance=float(2 * rollout.radii.min()) if team else None, wall_time=wall)
    stride = max(1, int(np.ceil(rollout.n_steps / MAX_SAMPLES)))
    idx = np.unique(np.append(np.arange(0, rollout.n_steps, stride), rollout.n_steps - 1))  # the last step too
    traces = {
        "times": rollout.times[idx], "positions": rollout.positions[idx], "references": rollout.references[idx],
        "speeds": np.linalg.norm(rollout.velocities[idx], axis=-1),
        "min_center_distance": np.minimum.reduceat(sep.min_center_distance, idx) if team else np.full(idx.size, np.inf),
        "goals": rollout.goals, "radii": rollout.radii, "obstacle_centers": rollout.obstacle_centers,
        "obstacle_radii": rollout.obstacle_radii,
    }
    return RunResult(spec, metrics, traces)


def _init_worker() -> None:
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)


def run_many(specs: list[RunSpec], jobs: int = 1, desc: str = "runs", show: bool = True) -> list[RunResult]:
    """Run ``specs`` (over ``jobs`` processes when ``jobs > 1``) with a progress bar; results in spec order."""
    keys = [s.key for s in specs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"run keys must be unique, got {keys}")
    bar = progress(len(specs), desc, unit="run", enabled=show, leave=False)
    results: list[RunResult] = []
    try:
        if jobs <= 1 or len(specs) <= 1:
            for spec in specs:
                bar.set_postfix_str(spec.key)
                results.append(run_spec(spec))
                bar.update(1)
        else:
            import multiprocessing as mp

            for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
                os.environ.setdefault(var, "1")
            with mp.get_context("spawn").Pool(min(jobs, len(specs)), initializer=_init_worker) as pool:
                for res in pool.imap(run_spec, specs, chunksize=1):
                    results.append(res)
                    bar.update(1)
                pool.close()  # let the workers exit on their own (terminating them leaks their semaphores)
                pool.join()
    finally:
        bar.close()
    return results
