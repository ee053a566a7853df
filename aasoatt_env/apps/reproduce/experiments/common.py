"""What the reproduction experiments share: :class:`Settings`, the set-up text, table rows and figure helpers.

Set-up shared by all multi-robot runs (SPEC section 7; our choices where the
paper is silent): wheel radius 0.1 m, half track 0.2 m, offset l = 0.2 m,
|du| <= 60 rad/s^2, robot radius 0.48 m (d_s = 0.96), dt = 0.005 s,
linear-in-time straight references starting at rest, k1 = k2 = 2, k3 = 1,
k4 = 4, zeta = 2, q = -60 deg, D = 3, braking gamma = 1, velocity-barrier
varsigma = 2, rho_v = 1, sigma = 0.  The episode ends when the reference
does (no settle time), so the metrics cover exactly the paper's 12 s / 20 s.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.apps.reproduce.report import Report, fmt, fmt_rel, rel_diff
from aasoatt_env.apps.reproduce.runner import RunResult, RunSpec, run_many
from aasoatt_env.safety.config import FilterConfig

__all__ = [
    "ACCEPT_REL",
    "VELOCITY_LEVEL_ACCEL",
    "VIOLATION_TOL",
    "Settings",
    "ca_size",
    "circle",
    "DEADLOCK_METHODS",
    "robot_colors",
    "common_settings",
    "draw_paths",
    "filter_config",
    "metric_cells",
    "metric_headers",
    "result_row",
    "run_specs",
    "violated",
]

#: Wheel-acceleration bound [rad/s^2] used for the velocity-level barriers
#: (eqn.n5, eqn.nn5, eqn.n7): those methods command velocities and, in the
#: paper, produce velocity jumps; with the paper robots' 60 rad/s^2 the rows
#: applied to the next-step velocity are often infeasible.
VELOCITY_LEVEL_ACCEL: float = 1.0e4

#: Relative-difference tolerance of the acceptance check on eqn.n4 and ours (compare-ca).
ACCEPT_REL: float = 0.10

#: Collision tolerance [m] when declaring a safety violation (as :mod:`aasoatt_env.analysis.metrics`).
VIOLATION_TOL: float = 1e-3


@dataclass(frozen=True)
class Settings:
    """Options shared by all experiments.

    Parameters
    ----------
    quick : bool
        Small, fast variants (CI); numbers are then *not* comparable to the paper.
    out : Path
        Results root directory.
    jobs : int
        Worker processes for independent runs.
    solver : str
        QP solver of the safety filter (default ``daqp``, an exact active-set
        solver; the paper used its projection neural network, ``neural``).
    backup : bool
        The filter's braking backup layer (off: the paper's method as published).
    safety_margin : float
        Margin added to ``d_s`` by the filter [m] (0: the paper's exact
        barrier; the product's default adds about 1 cm).
    progress : bool
        Show progress bars.
    command : str
        Command line recorded in the Markdown.
    """

    quick: bool = False
    out: Path = Path("results")
    jobs: int = 1
    solver: str = "daqp"
    safety_margin: float = 0.0
    backup: bool = False
    progress: bool = True
    command: str = "aasoatt reproduce"


def filter_config(s: Settings, **kw: Any) -> FilterConfig:
    """The filter of a paper run: the experiment's solver and margin, then ``kw``."""
    return FilterConfig.merged({"solver": s.solver, "safety_margin": s.safety_margin, "backup": s.backup}, **kw)


def circle(n: int, radius: float, duration: float, settle: float = 0.0, **kw: Any) -> dict[str, Any]:
    """Circle-swap scenario keywords."""
    return dict(num_robots=n, radius=radius, duration=duration, settle_time=settle, **kw)


def run_specs(s: Settings, specs: list[RunSpec], desc: str) -> dict[str, RunResult]:
    """Run ``specs`` (in ``s.jobs`` processes) and key the results by run key."""
    return {r.spec.key: r for r in run_many(specs, jobs=s.jobs, desc=desc, progress=s.progress)}


def common_settings(rep: Report, s: Settings) -> None:
    """Write the shared set-up lines into ``rep``."""
    rep.setting(
        f"QP solver: `{s.solver}`; filter safety margin on d_s: {s.safety_margin:g} m "
        f"({'the paper exact barrier' if s.safety_margin == 0 else 'added to d_s'}); braking backup layer: "
        f"{'on' if s.backup else 'off (the paper method as published)'}"
    )
    rep.setting(
        "Robots (SPEC 7, our choice where the paper is silent): wheel radius 0.1 m, half track 0.2 m, "
        "offset l = 0.2 m, |du| <= 60 rad/s^2, radius 0.48 m (d_s = 0.96), dt = 0.005 s"
    )
    rep.setting(
        "Gains: k1 = k2 = 2, k3 = 1, k4 = 4, zeta = 2, q = -60 deg, D = 3, braking gamma = 1; "
        "trigger: multiplier (eta > 0)"
    )
    rep.setting(
        "References: straight lines to the antipode, linear in time, starting at rest; the episode "
        "ends with the reference (metrics over exactly the paper's horizon)"
    )
    if s.quick:
        rep.setting(
            "**QUICK MODE**: smaller scenarios than the paper's; the paper columns are shown for the "
            "format only and the differences are meaningless"
        )


def metric_cells(m: dict[str, Any], ref: dict[str, Any] | None, metrics: tuple[str, ...]) -> list[Any]:
    """Table cells: ours, the paper's and the relative difference of each metric."""
    cells: list[Any] = []
    for k in metrics:
        p = None if ref is None else ref.get(k)
        cells += [fmt(p), fmt(m.get(k)), fmt_rel(rel_diff(m.get(k), p))]
    return cells


def metric_headers(metrics: tuple[str, ...]) -> list[str]:
    """Table headers matching :func:`metric_cells`."""
    names = {"intervention_time": "IT [s]", "rmse": "RMSE", "mae": "MAE", "std": "std"}
    out: list[str] = []
    for k in metrics:
        out += [f"{names[k]} paper", f"{names[k]} ours", "rel."]
    return out


def result_row(exp: str, res: RunResult, ref: dict[str, Any] | None, metrics: tuple[str, ...]) -> dict[str, Any]:
    """One CSV row: the run's labels, metrics, the paper's numbers and the relative differences."""
    row: dict[str, Any] = {"experiment": exp, "key": res.spec.key, **res.spec.meta}
    keys = (
        "intervention_time",
        "rmse",
        "mae",
        "std",
        "max_tracking_error",
        "min_center_distance_full",
        "min_robot_gap_full",
        "min_obstacle_gap",
        "n_collision_pairs",
        "n_obstacle_collisions",
        "final_error_mean",
        "final_error_max",
        "reach_rate",
        "n_deadlocked",
        "triggered_fraction",
        "relaxed_fraction",
        "unsafe_fraction",
        "failed_fraction",
        "slack_max",
        "solve_time_median",
        "wall_time",
    )
    for k in keys:
        if k in res.metrics:
            row[k] = res.metrics[k]
    for k, v in res.metrics.items():
        if k.endswith("_end"):
            row[k] = v
    for k in metrics:
        p = None if ref is None else ref.get(k)
        row[f"paper_{k}"] = p
        row[f"rel_{k}"] = rel_diff(res.metrics.get(k), p)
    return row


def violated(res: RunResult) -> bool:
    """True when a pair came closer than ``d_s - VIOLATION_TOL`` during the run."""
    d = res.metrics.get("min_center_distance_full")
    ds = res.metrics.get("safety_distance")
    return d is not None and ds is not None and d < ds - VIOLATION_TOL



DEADLOCK_METHODS: dict[str, str] = {
    "eqn.12a": "rotate_nominal",
    "eqn.12b": "rotate_reference_velocity",
    "eqn.13": "auxiliary_velocity",
}
"""The paper's deadlock strategies (Table III, Fig. "100") -> our registry names."""


def ca_size(s: Settings) -> tuple[int, float, float]:
    """``(N, radius, duration)`` of the N = 10 comparison (smaller with ``quick``)."""
    return (6, 4.0, 8.0) if s.quick else (10, 6.0, 12.0)



def draw_paths(ax: Any, tr: dict[str, np.ndarray], alpha: float = 0.9) -> None:
    """Draw the paths, references, final discs and obstacles of a run's traces on ``ax``."""
    from matplotlib.patches import Circle

    pos, ref = tr["positions"], tr["references"]
    n = pos.shape[1]
    colors = robot_colors(n)
    for i in range(n):
        ax.plot(ref[:, i, 0], ref[:, i, 1], ls=":", lw=0.6, color=colors[i], alpha=0.5)
        ax.plot(pos[:, i, 0], pos[:, i, 1], lw=0.9, color=colors[i], alpha=alpha)
        ax.add_patch(Circle(pos[-1, i], tr["radii"][i], fill=False, lw=0.6, color=colors[i]))
    for c, r in zip(tr["obstacle_centers"], tr["obstacle_radii"]):
        ax.add_patch(Circle(c, r, color="0.5", alpha=0.6))
    ax.set_aspect("equal")
    lim = float(np.abs(np.concatenate([pos.reshape(-1, 2), ref.reshape(-1, 2)])).max()) + 1.0
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.tick_params(labelsize="small")


def robot_colors(n: int) -> np.ndarray:
    """One hue per robot."""
    from matplotlib import colormaps

    return colormaps["hsv"](np.linspace(0, 1, n, endpoint=False))
