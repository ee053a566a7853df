"""Experiment scaffolding: declare an :class:`Experiment` of :class:`RunSpec` runs; :func:`run` tabulates it.

One run is :func:`run_spec`, many :func:`run_many` (the same numbers for any ``jobs``); the report puts ours beside
the paper's numbers.  Last, the set-up the experiments share (``docs/technical_brief.md`` section 7; our choices where
the paper is silent).
"""

from __future__ import annotations

import contextlib
import csv
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from aasoatt_env.analysis.metrics import format_value as fmt
from aasoatt_env.analysis.metrics import pairwise_min_distance, summarize
from aasoatt_env.analysis.plotting import new_figure, plot_trajectories
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.api.factory import make_env
from aasoatt_env.cli_support import OutputPlan, progress, staged
from aasoatt_env.safety.config import FilterConfig
from agents.baselines import PDController, TrackingController

__all__ = ["Experiment", "Report", "RunResult", "RunSpec", "Settings", "fmt", "fmt_rel", "md_table", "rel_diff", "run",
           "run_many", "run_spec"]

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


Column = tuple[str, Callable[[dict[str, Any]], str]]  # a table column: its header and the cell of a CSV row
Results = dict[str, RunResult]  # the runs of an experiment by key

#: The CSV columns of a run's metrics, in this order (then the ``*_end`` goal metrics).
CSV_METRICS = ("intervention_time", "rmse", "mae", "std", "max_tracking_error", "min_center_distance_full",
               "min_robot_gap_full", "min_obstacle_gap", "n_collision_pairs", "n_obstacle_collisions",
               "final_error_mean", "final_error_max", "reach_rate", "n_deadlocked", "triggered_fraction",
               "relaxed_fraction", "unsafe_fraction", "failed_fraction", "slack_max", "solve_time_median", "wall_time")

SHORT_NAMES = {"intervention_time": "IT [s]", "rmse": "RMSE", "mae": "MAE", "std": "std"}


@dataclass(frozen=True)
class Settings:
    """The options of ``aasoatt reproduce`` shared by all experiments (``command`` heads the Markdown)."""

    quick: bool = False
    out: Path = Path("results")
    jobs: int = 1
    solver: str = "daqp"
    safety_margin: float = 0.0
    backup: bool = False
    progress: bool = True
    command: str = "aasoatt reproduce"


def rel_diff(ours: float | None, paper: float | None) -> float | None:
    """Relative difference ``(ours - paper) / |paper|`` (None when either is missing)."""
    if ours is None or paper is None or paper == 0 or not math.isfinite(ours):
        return None
    return (ours - paper) / abs(paper)


def fmt_rel(x: float | None) -> str:
    """A relative difference as a signed percentage."""
    return "-" if x is None else f"{100 * x:+.1f}%"


def md_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub Markdown table; cells are formatted with :func:`fmt` unless already strings."""
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(c if isinstance(c, str) else fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def col(header: str, key: str | Callable[[dict[str, Any]], Any], digits: int = 4) -> Column:
    """A column showing the CSV row's ``key`` (or ``key(row)``) with ``digits`` decimals."""
    return header, lambda row: fmt(key(row) if callable(key) else row.get(key), digits)


def compared(metrics: Sequence[str]) -> list[Column]:
    """The paper | ours | relative-difference columns of ``metrics``."""
    return [c for k in metrics for c in (col(f"{SHORT_NAMES[k]} paper", f"paper_{k}"), col(f"{SHORT_NAMES[k]} ours", k),
                                         ("rel.", lambda row, k=k: fmt_rel(row[f"rel_{k}"])))]


class Experiment:
    """One experiment of the paper, declared by overriding the hooks that apply.

    ``_specs``: the runs in table order; ``_paper``: a run's numbers in the paper; ``_extra``: more CSV fields;
    ``_columns``, ``_notes``, ``_sections``, ``_findings``: the Markdown; ``_figures``: ``(figure, file, caption)``.
    """

    name: ClassVar[str]
    title: ClassVar[str]
    metrics: ClassVar[tuple[str, ...]] = ()
    heading: ClassVar[str] = "## Results (paper | ours | relative difference)"
    sizes: ClassVar[dict[bool, Any]] = {}
    columns: ClassVar[list[Column]] = []  # the results table, unless it depends on the settings (_columns)

    def size(self, s: Settings) -> Any:
        """The scenario sizes for ``s``."""
        return self.sizes[s.quick]

    def _specs(self, s: Settings) -> list[RunSpec]:
        raise NotImplementedError

    def _columns(self, s: Settings) -> list[Column]:
        return self.columns

    def _paper(self, spec: RunSpec) -> dict[str, Any] | None:
        return None

    def _extra(self, s: Settings, spec: RunSpec, result: RunResult) -> dict[str, Any]:
        return {}

    def _notes(self, s: Settings) -> list[str]:
        return []

    def _sections(self, s: Settings, res: Results) -> list[Any]:
        return []

    _findings = _figures = _sections  # no findings, no figures unless overridden


def result_row(exp: str, res: RunResult, ref: dict[str, Any] | None, metrics: Sequence[str]) -> dict[str, Any]:
    """One CSV row: the run's labels, metrics, the paper's numbers and the relative differences."""
    row: dict[str, Any] = {"experiment": exp, "key": res.spec.key, **res.spec.meta}
    row.update({k: res.metrics[k] for k in CSV_METRICS if k in res.metrics})
    row.update({k: v for k, v in res.metrics.items() if k.endswith("_end")})
    for k in metrics:
        p = None if ref is None else ref.get(k)
        row[f"paper_{k}"], row[f"rel_{k}"] = p, rel_diff(res.metrics.get(k), p)
    return row


def run(exp: Experiment, s: Settings) -> Report:
    """Run ``exp`` and tabulate its results."""
    specs = exp._specs(s)
    res = {r.spec.key: r for r in run_many(specs, jobs=s.jobs, desc=exp.name, show=s.progress)}
    rows = [{**result_row(exp.name, res[sp.key], exp._paper(sp), exp.metrics), **exp._extra(s, sp, res[sp.key])}
            for sp in specs]
    cols = exp._columns(s)
    table = md_table([h for h, _ in cols], [[cell(row) for _, cell in cols] for row in rows])
    findings = "\n".join(f"- {line}" for line in exp._findings(s, res))
    sections = [f"{exp.heading}\n\n{table}", *exp._sections(s, res), *([f"## Findings\n\n{findings}"] * bool(findings))]
    return Report(exp.name, exp.title, s.out, rows, exp._notes(s), sections, exp._figures(s, res))


@dataclass
class Report:
    """One experiment's rows, settings, Markdown sections and figures, ready to write."""

    name: str
    title: str
    out: Path
    rows: list[dict[str, Any]]
    settings: list[str]
    sections: list[str]
    figures: list[tuple[Any, str, str]]

    @property
    def dir(self) -> Path:
        """The experiment's folder, ``<out>/<name>``."""
        return Path(self.out) / self.name

    def body(self) -> list[str]:
        """The Markdown of the settings and sections (what a results page shows of this experiment)."""
        return (["## Settings", "", *(f"- {s}" for s in self.settings), ""] if self.settings else []) + [
            line for s in self.sections for line in (s.strip(), "")]

    def write(self, wall_time: float, command: str) -> tuple[Path, Path]:
        """Write ``<name>.csv``, ``README.md`` and the figures (all or none); return the CSV and README paths."""
        csv_path, md_path = self.dir / f"{self.name}.csv", self.dir / "README.md"
        md = [f"# {self.title}", "", f"Command: `{command}`", "", *self.body()]
        if self.figures:
            md += ["## Figures", "", *(f"- `{name}`: {caption}" for _, name, caption in self.figures), ""]
        md += [f"CSV: `{csv_path.name}`.", "", f"Wall time of this experiment: {wall_time:.1f} s.", ""]
        with OutputPlan(overwrite=True) as plan:  # a failure leaves no empty folder to be taken for results
            plan.folder(self.dir, self.name)
            with staged(csv_path, md_path, *(self.dir / name for _, name, _ in self.figures)) as temps:
                self._write_csv(temps[0])
                temps[1].write_text("\n".join(md))
                for (fig, _, _), temp in zip(self.figures, temps[2:]):
                    fig.savefig(temp, dpi=110, format="png")
        return csv_path, md_path

    def _write_csv(self, path: Path) -> None:
        keys = list(dict.fromkeys(k for row in self.rows for k in row))
        with path.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            w.writerows({k: _csv_cell(row.get(k)) for k in keys} for row in self.rows)


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return v.item() if isinstance(v, (np.integer, np.bool_)) else v


#: Wheel-acceleration bound [rad/s^2] of the velocity-level barriers (eqn.n5, eqn.nn5, eqn.n7): they command
#: velocities and, in the paper, make velocity jumps; with 60 rad/s^2 their next-step rows are often infeasible.
VELOCITY_LEVEL_ACCEL: float = 1.0e4
ACCEPT_REL: float = 0.10  # relative-difference tolerance of the acceptance check on eqn.n4 and ours (compare-ca)
VIOLATION_TOL: float = 1e-3  # collision tolerance [m] of a safety violation (as the metrics')

#: The paper's deadlock strategies (Table III, Fig. "100") -> our registry names.
DEADLOCK_METHODS: dict[str, str] = {"eqn.12a": "rotate_nominal", "eqn.12b": "rotate_reference_velocity",
                                    "eqn.13": "auxiliary_velocity"}

#: ``(N, radius, duration)`` of the N = 10 comparison (full, ``--quick``).
CA_SIZES: dict[bool, tuple[int, float, float]] = {False: (10, 6.0, 12.0), True: (6, 4.0, 8.0)}


def team_run(s: Settings, key: str, size: tuple[int, float, float], meta: dict[str, Any], *, settle: float = 0.0,
             window: float | None = None, scenario: str = "circle_swap", scene: dict[str, Any] | None = None,
             **filter_kw: Any) -> RunSpec:
    """``size = (N, radius, duration)`` robots on the circle, filtered with the settings' solver, margin, backup."""
    n, radius, duration = size
    kwargs = dict(num_robots=n, radius=radius, duration=duration, settle_time=settle, **(scene or {}))
    fc = FilterConfig.merged({"solver": s.solver, "safety_margin": s.safety_margin, "backup": s.backup}, **filter_kw)
    return RunSpec(key, scenario, kwargs, filter=fc, window=window, meta=meta)


def violated(res: RunResult) -> bool:
    """True when a pair came closer than ``d_s - VIOLATION_TOL`` during the run."""
    d, ds = res.metrics.get("min_center_distance_full"), res.metrics.get("safety_distance")
    return d is not None and ds is not None and d < ds - VIOLATION_TOL


def common_notes(s: Settings) -> list[str]:
    """The settings bullets every multi-robot experiment starts with."""
    return [
        f"QP solver: `{s.solver}`; filter safety margin on d_s: {s.safety_margin:g} m "
        f"({'the paper exact barrier' if s.safety_margin == 0 else 'added to d_s'}); braking backup layer: "
        f"{'on' if s.backup else 'off (the paper method as published)'}",
        "Robots (docs/technical_brief.md section 7, our choice where the paper is silent): wheel radius 0.1 m, "
        "half track 0.2 m, offset l = 0.2 m, |du| <= 60 rad/s^2, radius 0.48 m (d_s = 0.96), dt = 0.005 s",
        "Gains: k1 = k2 = 2, k3 = 1, k4 = 4, zeta = 2, q = -60 deg, D = 3, braking gamma = 1; "
        "trigger: multiplier (eta > 0)",
        "References: straight lines to the antipode, linear in time, starting at rest; the episode "
        "ends with the reference (metrics over exactly the paper's horizon)",
        *(["**QUICK MODE**: smaller scenarios than the paper's; the paper columns are shown for the "
           "format only and the differences are meaningless"] if s.quick else []),
    ]


def axes_labels(ax: Any, xlabel: str, ylabel: str, legend: str | None = "small") -> None:
    """Label ``ax``, add a light grid and (unless ``legend`` is None) a legend of that font size."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if legend:
        ax.legend(fontsize=legend)


def trajectory_panels(res: Results, titles: dict[str, str], panel: tuple[float, float]) -> Any:
    """One figure of the runs ``titles`` (key -> panel title) side by side, each panel of size ``panel``."""
    fig, axes = new_figure(1, len(titles), (panel[0] * len(titles), panel[1]))
    for ax, (key, title) in zip(axes[0], titles.items()):
        tr = res[key].traces
        plot_trajectories(tr["positions"], tr["radii"], tr["references"], ax=ax, title=title)
    return fig
