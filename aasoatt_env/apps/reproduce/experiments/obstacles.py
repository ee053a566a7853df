"""Fig. 5: 20 robots among 3 static obstacles."""

from __future__ import annotations

import numpy as np

from aasoatt_env.analysis.plotting import plot_snapshots
from aasoatt_env.apps.reproduce import paper
from aasoatt_env.apps.reproduce.experiments.common import (
    Settings,
    common_settings,
    filter_config,
    result_row,
    run_specs,
)
from aasoatt_env.apps.reproduce.report import Report, md_table
from aasoatt_env.apps.reproduce.runner import RunSpec

__all__ = ["obstacles"]

def obstacles(s: Settings) -> Report:
    """Fig. 5: 20 robots and 3 static obstacles (circle_obstacles scenario)."""
    rep = Report("obstacles", "Fig. 5 - 20 robots and 3 static obstacles", s.out)
    n, duration, settle = (8, 8.0, 2.0) if s.quick else (20, 12.0, 3.0)
    spec = RunSpec(
        "obstacles",
        "circle_obstacles",
        dict(num_robots=n, radius=6.0, duration=duration, settle_time=settle),
        filter=filter_config(s),
        window=duration,
        meta={"method": "ours + eqn.13", "N": n},
    )
    r = run_specs(s, [spec], "obstacles")["obstacles"]
    rep.add_row(result_row("obstacles", r, None, paper.METRICS))
    m = r.metrics
    common_settings(rep, s)
    rep.setting(
        f"N = {n}, radius 6 m, {duration:g} s + {settle:g} s settle; obstacles (x, y, radius): "
        "(0, 0, 0.6), (2.8, 1.6, 0.4), (-2.2, -2.6, 0.8) - the paper gives no positions"
    )
    rep.section(
        "## Results (the paper gives only the figure)\n\n"
        + md_table(
            [
                "IT [s]",
                "RMSE",
                "MAE",
                "std",
                "min robot gap",
                "min obstacle gap",
                "collisions (pairs / obstacle)",
                f"reached @ {duration + settle:g} s",
            ],
            [
                [
                    m["intervention_time"],
                    m["rmse"],
                    m["mae"],
                    m["std"],
                    m["min_robot_gap_full"],
                    m["min_obstacle_gap"],
                    f"{m['n_collision_pairs']} / {m['n_obstacle_collisions']}",
                    m["reach_rate_end"],
                ]
            ],
        )
    )
    tr = r.traces
    t = tr["times"]
    idx = [0, int(np.searchsorted(t, 0.45 * duration)), int(np.searchsorted(t, 0.75 * duration)), len(t) - 1]
    fig = plot_snapshots(
        tr["positions"],
        t,
        idx,
        tr["radii"],
        obstacles=(tr["obstacle_centers"], tr["obstacle_radii"]),
        references=tr["references"],
        goals=tr["goals"],
    )
    rep.figure(fig, "fig5_snapshots.png", "(a) initial, (b) avoidance, (c) return, (d) final (paper Fig. 5)")
    return rep
