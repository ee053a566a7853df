"""Training telemetry: what the policy does in each rollout, in TensorBoard, a progress line, a CSV and a figure.

:class:`TelemetryCallback` reads the env's own infos during rollout collection
(:attr:`train.vec_env.BatchedVecEnv.last_infos`, no extra episodes) and, per
rollout, over the robot-decisions of slots whose robot acted:

=============================  ===================================================
key (TensorBoard ``metrics/``)  meaning
=============================  ===================================================
``success_rate``               robot-episodes that ended in the rollout within the
                               success radius (0.1 m) of their goal, not terminated
``tracking_error``             mean ``|p - p_d|`` [m]
``collision_rate``             robot-decisions in collision (clearance below
                               ``-collision_tolerance`` at some physics step)
``collided_episodes``          robot-episodes that ended in the rollout with a
                               collision at some step
``intervention_rate``          robot-decisions the filter changed (behind a filter)
``mean_correction``            mean of the filter's largest ``|du_safe - du_nom|``
                               per robot-decision [rad/s^2] (behind a filter)
``episodes``                   robot-episodes that ended in the rollout
``agent_steps_per_s``          throughput since the start of training
=============================  ===================================================

Each rollout appends a row to ``metrics.csv`` in the run folder;
:func:`plot_learning_curve` draws it (``learning_curve.png`` at the end of a run).
"""

from __future__ import annotations

import csv
import math
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["METRICS", "TelemetryCallback", "plot_learning_curve", "read_metrics"]

METRICS: tuple[str, ...] = ("success_rate", "tracking_error", "collision_rate", "collided_episodes",
                            "intervention_rate", "mean_correction", "episodes", "agent_steps_per_s")
"""Keys logged per rollout (``metrics/<key>`` in TensorBoard, columns of ``metrics.csv``)."""


class TelemetryCallback(BaseCallback):
    """Per-rollout telemetry (module docstring).

    Parameters
    ----------
    csv_path : path, optional
        ``metrics.csv`` to append rows to (None: none).
    total_timesteps : int
        For the progress line's percentage and ETA.
    print_every : int
        Print a progress line every this many rollouts (0: never); the last rollout is always printed.
    stream : file, optional
        Where progress lines go (default ``sys.stdout``).
    success_radius : float
        Goal distance [m] that counts as success.
    """

    def __init__(self, csv_path: str | Path | None = None, total_timesteps: int = 0, print_every: int = 1,
                 stream: TextIO | None = None, success_radius: float = 0.1) -> None:
        super().__init__()
        self.csv_path = Path(csv_path) if csv_path is not None else None
        self.total = int(total_timesteps)
        self.print_every = int(print_every)
        self.stream = stream
        self.success_radius = float(success_radius)
        self.history: list[dict[str, float]] = []
        self._rollouts = 0

    # ------------------------------------------------------------------ SB3 hooks
    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter()
        self._steps0 = self.num_timesteps
        base = self.training_env.unwrapped
        self._base = base if hasattr(base, "last_infos") else None
        n = self.training_env.num_envs
        self._ep_collided = np.zeros(n, dtype=bool)

    def _on_rollout_start(self) -> None:
        self._sum = dict.fromkeys(("err", "col", "int", "corr", "dec", "fdec", "eps", "succ", "colep"), 0.0)

    def _on_step(self) -> bool:
        base = self._base
        if base is None or not base.last_infos:
            return True
        info = base.last_infos
        acted = base.acted_slots
        s = self._sum
        col = info["collision"].ravel() & acted
        s["dec"] += acted.sum()
        s["err"] += info["tracking_error"].ravel()[acted].sum()
        s["col"] += col.sum()
        if "filter_correction" in info:
            s["fdec"] += acted.sum()
            s["int"] += (info["filter_intervened"].ravel() & acted).sum()
            s["corr"] += info["filter_correction"].ravel()[acted].sum()
        self._ep_collided |= col
        dones = base.last_dones
        if dones.any():
            idx = np.flatnonzero(dones)
            infos = self.locals.get("infos")
            if infos is not None:
                s["succ"] += sum(bool(infos[i].get("is_success", False)) for i in idx)
            s["eps"] += idx.size
            s["colep"] += self._ep_collided[idx].sum()
            self._ep_collided[idx] = False
        return True

    def _on_rollout_end(self) -> None:
        s = self._sum
        if not s["dec"]:
            return
        elapsed = time.perf_counter() - self._t0
        row = {
            "agent_steps": float(self.num_timesteps),
            "wall_time_s": elapsed,
            "success_rate": s["succ"] / s["eps"] if s["eps"] else math.nan,
            "tracking_error": s["err"] / s["dec"],
            "collision_rate": s["col"] / s["dec"],
            "collided_episodes": s["colep"] / s["eps"] if s["eps"] else math.nan,
            "intervention_rate": s["int"] / s["fdec"] if s["fdec"] else math.nan,
            "mean_correction": s["corr"] / s["fdec"] if s["fdec"] else math.nan,
            "episodes": s["eps"],
            "agent_steps_per_s": (self.num_timesteps - self._steps0) / max(elapsed, 1e-9),
        }
        for key in METRICS:
            if not math.isnan(row[key]):
                self.logger.record(f"metrics/{key}", row[key])
        self.history.append(row)
        self._rollouts += 1
        if self.csv_path is not None:
            new = not self.csv_path.exists()
            with self.csv_path.open("a", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(row))
                if new:
                    w.writeheader()
                w.writerow(row)
        last = self.total and self.num_timesteps >= self.total
        if self.print_every and (self._rollouts % self.print_every == 0 or last):
            print(progress_line(row, self.total), file=self.stream or sys.stdout, flush=True)


def _duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    return f"{seconds // 60}m{seconds % 60:02d}s"


def progress_line(row: dict[str, float], total: int = 0) -> str:
    """One line of a rollout's telemetry: steps, rate, ETA, success, tracking error, collisions, filter."""
    steps, rate = int(row["agent_steps"]), row["agent_steps_per_s"]
    head = f"{steps:>10,} agent-steps"
    if total:
        head = f"[{100 * min(steps / total, 1):5.1f}%] {head} eta {_duration((total - steps) / max(rate, 1e-9))}"
    parts = [head, f"{rate:,.0f}/s", f"elapsed {_duration(row['wall_time_s'])}"]
    if not math.isnan(row["success_rate"]):
        parts.append(f"success {100 * row['success_rate']:.1f}%")
    parts += [f"err {row['tracking_error']:.3f} m", f"collisions {100 * row['collision_rate']:.2f}%"]
    if not math.isnan(row["intervention_rate"]):
        parts += [f"intervention {100 * row['intervention_rate']:.1f}%", f"correction {row['mean_correction']:.2f}"]
    return " | ".join(parts)


def read_metrics(path: str | Path) -> list[dict[str, float]]:
    """The rows of a ``metrics.csv``."""
    with Path(path).open(newline="") as fh:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def plot_learning_curve(
    runs: dict[str, Sequence[Sequence[dict[str, float]]]], path: str | Path, title: str | None = None,
) -> Path:
    """Draw learning curves: success, tracking error, collisions and (if any) filter correction vs agent-steps.

    Parameters
    ----------
    runs : dict
        Label -> list of runs (seeds), each a list of ``metrics.csv`` rows; several
        seeds are drawn as their mean with a band from the lowest to the highest.
    path : path
        PNG to write.
    title : str, optional
        Figure title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("success_rate", "success (episodes ending in the rollout)", 100.0, "%"),
              ("tracking_error", "tracking error |p - p_d|", 1.0, "m"),
              ("collision_rate", "robot-decisions in collision", 100.0, "%")]
    if any(not math.isnan(r.get("mean_correction", math.nan)) for seeds in runs.values() for rows in seeds
           for r in rows):
        panels.append(("mean_correction", "filter correction (mean)", 1.0, "rad/s^2"))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4), squeeze=False)
    for ax, (key, label, scale, unit) in zip(axes[0], panels):
        for color, (name, seeds) in enumerate(runs.items()):
            curves = [(np.array([r["agent_steps"] for r in rows]), np.array([r.get(key, math.nan) for r in rows]))
                      for rows in seeds if rows]
            if not curves:
                continue
            n = min(len(x) for x, _ in curves)
            x = curves[0][0][:n]
            ys = np.stack([y[:n] for _, y in curves]) * scale
            if np.isnan(ys).all():
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # rollouts in which no episode ended
                mean, lo, hi = np.nanmean(ys, axis=0), np.nanmin(ys, axis=0), np.nanmax(ys, axis=0)
            ok = ~np.isnan(mean)  # join the points across rollouts without a value
            label_ = name if len(seeds) == 1 else f"{name} ({len(seeds)} seeds)"
            line = ax.plot(x[ok] / 1e6, mean[ok], label=label_, color=f"C{color}")[0]
            if len(curves) > 1:
                ax.fill_between(x[ok] / 1e6, lo[ok], hi[ok], color=line.get_color(), alpha=0.2)
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("agent-steps [M]")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
    if axes[0][0].get_legend_handles_labels()[0]:
        axes[0][0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
