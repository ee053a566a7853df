"""The set-up the experiments share (SPEC section 7; our choices where the paper is silent) and their helpers."""

from __future__ import annotations

from typing import Any

from aasoatt_env.analysis.plotting import new_figure, plot_trajectories
from aasoatt_env.apps.reproduce.report import Results, Settings
from aasoatt_env.apps.reproduce.runner import RunResult, RunSpec
from aasoatt_env.safety.config import FilterConfig

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


def filter_config(s: Settings, **kw: Any) -> FilterConfig:
    """The filter of a paper run: the experiment's solver, margin and backup, then ``kw``."""
    return FilterConfig.merged({"solver": s.solver, "safety_margin": s.safety_margin, "backup": s.backup}, **kw)


def team_run(s: Settings, key: str, size: tuple[int, float, float], meta: dict[str, Any], *, settle: float = 0.0,
             window: float | None = None, scenario: str = "circle_swap", scene: dict[str, Any] | None = None,
             **filter_kw: Any) -> RunSpec:
    """A run of ``size = (N, radius, duration)`` robots on the circle behind the paper's filter (``filter_kw``)."""
    n, radius, duration = size
    kwargs = dict(num_robots=n, radius=radius, duration=duration, settle_time=settle, **(scene or {}))
    return RunSpec(key, scenario, kwargs, filter=filter_config(s, **filter_kw), window=window, meta=meta)


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
        "Robots (SPEC 7, our choice where the paper is silent): wheel radius 0.1 m, half track 0.2 m, "
        "offset l = 0.2 m, |du| <= 60 rad/s^2, radius 0.48 m (d_s = 0.96), dt = 0.005 s",
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
