"""Table I: single-robot tracking, SBC's PD law (k3 = 10, 80) vs the paper's law (k3 = 1), k4 = 4."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from aasoatt_env.apps.reproduce import paper
from aasoatt_env.apps.reproduce.experiments.common import (
    Settings,
    metric_cells,
    metric_headers,
    result_row,
    run_specs,
)
from aasoatt_env.apps.reproduce.report import Report, md_table, new_figure
from aasoatt_env.apps.reproduce.runner import RunSpec

__all__ = ["table1"]

TABLE1_TRAJECTORIES: dict[str, dict[str, Any]] = {
    # |v_d| = 0.5 m/s: SBC's steady error k4 |v_d| / k3 = 0.2 (k3 = 10) and 0.025 (k3 = 80) match Table I
    "straight": dict(trajectory="straight", speed=0.5 / math.sqrt(1.25)),
    # p_d = (t, sin t): SBC k3 = 10 mean error ~ mean|k4 v_d + a_d| / k3 = 0.486 (paper 0.4857)
    "sine": dict(trajectory="sine", speed=1.0, amplitude=1.0, frequency=1.0),
    # radius 2 at 1 m/s: |k4 v_d + a_d| / |k3 - w^2 + i k4 w| = 0.405 (paper 0.4056)
    "circle": dict(trajectory="circle", speed=1.0, circle_radius=2.0),
}
TABLE1_CONTROLLERS: dict[str, tuple[str, float, float]] = {
    "SBC k3=10": ("pd", 10.0, 4.0),
    "SBC k3=80": ("pd", 80.0, 4.0),
    "ours k3=1": ("tracking", 1.0, 4.0),
}


def table1(s: Settings) -> Report:
    """Table I: single-robot tracking, SBC's PD nominal vs the paper's law."""
    rep = Report("table1", "Table I - single-robot trajectory tracking", s.out)
    duration = 6.0 if s.quick else 12.0
    specs = []
    for traj, kw in TABLE1_TRAJECTORIES.items():
        for ctrl, (kind, k3, k4) in TABLE1_CONTROLLERS.items():
            specs.append(
                RunSpec(
                    f"{traj}/{ctrl}",
                    "tracking",
                    dict(kw, duration=duration),
                    kind,
                    k3,
                    k4,
                    meta={"trajectory": traj, "controller": ctrl},
                )
            )
    res = run_specs(s, specs, "table1")
    metrics = ("rmse", "mae", "std")
    rows = []
    for spec in specs:
        r = res[spec.key]
        ref = paper.TABLE1[spec.meta["trajectory"]][spec.meta["controller"]]
        rep.add_row(result_row("table1", r, ref, metrics))
        rows.append([spec.meta["trajectory"], spec.meta["controller"], *metric_cells(r.metrics, ref, metrics)])
    rep.setting(
        "Bare environment (one robot: no barrier rows, so the filter would only keep the input "
        "bounds), actions saturated to |du| <= 60 rad/s^2 (never active here)"
    )
    rep.setting(
        f"Robot: wheel radius 0.1 m, half track 0.2 m, l = 0.2 m; start on the reference at rest with "
        f"theta(0) = theta_d; dt = 0.005 s; {duration:g} s"
    )
    rep.setting(
        "References (the paper gives none; chosen so SBC's steady-state error matches Table I): "
        "straight at 0.5 m/s; sine p_d = (t, sin t); circle of radius 2 m at 1 m/s"
    )
    rep.setting("SBC nominal a = -k3 (p - p_d) - k4 v (k4 = 4); ours a = a_d - (k3 + k4)(v - v_d) - k3 k4 (p - p_d)")
    if s.quick:
        rep.setting("**QUICK MODE**: 6 s instead of 12 s")
    rep.section(
        "## Results (paper | ours | relative difference)\n\n"
        + md_table(["trajectory", "controller", *metric_headers(metrics)], rows)
    )
    better = [
        t for t in TABLE1_TRAJECTORIES if res[f"{t}/ours k3=1"].metrics["rmse"] < res[f"{t}/SBC k3=10"].metrics["rmse"]
    ]
    rep.section(
        "## Findings\n\n"
        f"- Ours (k3 = 1) has a lower RMSE than SBC with k3 = 10 on {len(better)}/3 references "
        f"({', '.join(better) or 'none'}), as in the paper; SBC needs k3 = 80 to be level.\n"
        "- SBC's numbers depend only on the reference speed and are matched by construction of the "
        "references; ours depend on the initial transient (start at rest), which the paper does not "
        "specify, hence larger relative differences on MAE/std."
    )
    fig, axes = new_figure(1, 3, (12, 3.4))
    for ax, traj in zip(axes[0], TABLE1_TRAJECTORIES):
        for ctrl in TABLE1_CONTROLLERS:
            tr = res[f"{traj}/{ctrl}"].traces
            err = np.linalg.norm(tr["positions"][:, 0] - tr["references"][:, 0], axis=-1)
            ax.plot(tr["times"], err, label=ctrl)
        ax.set_title(traj)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("|p - p_d| [m]")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize="small")
    rep.figure(fig, "table1_errors.png", "tracking error over time per reference and controller")
    return rep
