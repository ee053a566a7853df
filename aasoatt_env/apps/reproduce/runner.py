"""One simulation run of a reproduction experiment, and a (parallel) runner over many.

A :class:`RunSpec` names a scenario, a nominal controller and an optional
safety-filter configuration.  :func:`run_spec` simulates it and returns a
:class:`RunResult`: the episode's metrics (over the paper's time window) and a
light, down-sampled copy of the trajectories for figures, so that results are
cheap to send back from worker processes.  :func:`run_many` runs a list of
specs, serially or over ``jobs`` processes, with a tqdm progress bar; results
come back in the order of the specs and do not depend on ``jobs`` (every run is
deterministic).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aasoatt_env.analysis.metrics import pairwise_min_distance, summarize
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.api.factory import make_env
from aasoatt_env.safety.config import FilterConfig
from agents.baselines import PDController, TrackingController

__all__ = ["RunResult", "RunSpec", "run_many", "run_spec"]

#: Largest number of time samples kept for figures.
MAX_SAMPLES: int = 800


@dataclass(frozen=True)
class RunSpec:
    """What to simulate.

    Parameters
    ----------
    key : str
        Unique label of the run inside its experiment (e.g. ``"ours/N=20"``).
    scenario : str
        Scenario name (see :data:`aasoatt_env.sim.scenarios.SCENARIOS`).
    scenario_kwargs : dict
        Scenario parameters (``num_robots``, ``radius``, ``duration``, ...).
    controller : {"tracking", "pd"}
        Nominal controller: the paper's law (eqn.11-12) or SBC's PD law.
    k3, k4 : float
        Controller gains.
    filter : FilterConfig or None
        The safety filter's configuration; None runs the bare env with saturated actions.
    seed : int
        Reset seed (the circle scenarios are deterministic anyway).
    window : float or None
        Paper metrics are computed over ``[0, window]`` s (None: whole episode).
    meta : dict
        Free-form labels copied into the result row (method, N, ...).
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
    """Metrics and down-sampled traces of one run.

    Attributes
    ----------
    spec : RunSpec
        What was run.
    metrics : dict
        :func:`aasoatt_env.analysis.metrics.summarize` over the metric window, plus
        ``min_center_distance_full`` (whole episode), ``safety_distance`` and
        ``wall_time`` [s].
    traces : dict of numpy.ndarray
        ``times (S,)``, ``positions (S, N, 2)``, ``references (S, N, 2)``,
        ``speeds (S, N)``, ``min_center_distance (S,)`` (minimum over the
        samples it stands for), ``goals (N, 2)``, ``radii (N,)``,
        ``obstacle_centers (M, 2)``, ``obstacle_radii (M,)``.
    """

    spec: RunSpec
    metrics: dict[str, Any]
    traces: dict[str, np.ndarray]


def _make_agent(spec: RunSpec) -> Any:
    saturate = spec.filter is None
    if spec.controller == "tracking":
        return TrackingController(spec.k3, spec.k4, saturate=saturate)
    if spec.controller == "pd":
        return PDController(spec.k3, spec.k4, saturate=saturate)
    raise ValueError(f"controller: got {spec.controller!r}, expected 'tracking' or 'pd'")


def run_spec(spec: RunSpec) -> RunResult:
    """Simulate one :class:`RunSpec` (see module docstring)."""
    t0 = time.perf_counter()
    env = make_env(spec.scenario, filter=spec.filter, **spec.scenario_kwargs)
    rollout, _ = run_episode(env, _make_agent(spec), seed=spec.seed, metadata={"key": spec.key})
    wall = time.perf_counter() - t0

    part = rollout.window(spec.window)
    metrics = summarize(part)
    full = metrics if part is rollout else summarize(rollout)
    for k in ("final_error_mean", "final_error_max", "reach_rate", "n_deadlocked"):
        metrics[f"{k}_end"] = full[k]
    sep = pairwise_min_distance(rollout)
    radii = rollout.radii
    metrics["min_center_distance_full"] = float(np.min(sep.min_center_distance)) if rollout.n_robots > 1 else None
    metrics["min_robot_gap_full"] = float(np.min(sep.min_robot_gap)) if rollout.n_robots > 1 else None
    metrics["safety_distance"] = float(2 * radii.min()) if rollout.n_robots > 1 else None
    metrics["wall_time"] = wall

    stride = max(1, int(np.ceil(rollout.n_steps / MAX_SAMPLES)))
    idx = np.arange(0, rollout.n_steps, stride)
    if idx[-1] != rollout.n_steps - 1:
        idx = np.append(idx, rollout.n_steps - 1)
    dmin = sep.min_center_distance
    # each kept sample carries the minimum over the steps up to the next kept one
    dmin_s = np.minimum.reduceat(dmin, idx) if rollout.n_robots > 1 else np.full(idx.size, np.inf)
    traces = {
        "times": rollout.times[idx],
        "positions": rollout.positions[idx],
        "references": rollout.references[idx],
        "speeds": np.linalg.norm(rollout.velocities[idx], axis=-1),
        "min_center_distance": dmin_s,
        "goals": rollout.goals,
        "radii": radii,
        "obstacle_centers": rollout.obstacle_centers,
        "obstacle_radii": rollout.obstacle_radii,
    }
    if rollout.triggered is not None:
        traces["triggered"] = rollout.triggered[idx]
    return RunResult(spec, metrics, traces)


def _init_worker() -> None:
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover
        pass


def run_many(specs: list[RunSpec], jobs: int = 1, desc: str = "runs", progress: bool = True) -> list[RunResult]:
    """Run ``specs`` (in parallel over ``jobs`` processes when ``jobs > 1``).

    Parameters
    ----------
    specs : list of RunSpec
        Runs to simulate.
    jobs : int
        Worker processes (1: in this process).
    desc : str
        Progress-bar label.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    list of RunResult
        In the order of ``specs``.
    """
    from tqdm import tqdm

    keys = [s.key for s in specs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"run keys must be unique, got {keys}")
    bar = tqdm(total=len(specs), desc=desc, unit="run", disable=not progress, leave=False)
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
            ctx = mp.get_context("spawn")
            with ctx.Pool(min(jobs, len(specs)), initializer=_init_worker) as pool:
                for res in pool.imap(run_spec, specs, chunksize=1):
                    results.append(res)
                    bar.update(1)
    finally:
        bar.close()
    return results
