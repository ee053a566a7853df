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

Each rollout adds a row to ``metrics.csv`` in the run folder (the whole file rewritten atomically,
so an interrupted run leaves a complete table); :func:`plot_learning_curve` draws it with the
held-out evaluations of :mod:`train.heldout` (``learning_curve.png`` at the end of a run).
"""

from __future__ import annotations

import csv
import io
import math
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from aasoatt_env.errors import DataFileError
from train.runs import atomic_write, write_text

__all__ = ["METRICS", "TelemetryCallback", "plot_learning_curve", "read_metrics", "write_csv"]

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
    history : list of dict, optional
        Rows of the run this one resumes (kept first in ``metrics.csv``; wall times continue theirs).
    """

    def __init__(self, csv_path: str | Path | None = None, total_timesteps: int = 0, print_every: int = 1,
                 stream: TextIO | None = None, success_radius: float = 0.1,
                 history: list[dict[str, float]] | None = None) -> None:
        super().__init__()
        self.csv_path = Path(csv_path) if csv_path is not None else None
        self.total = int(total_timesteps)
        self.print_every = int(print_every)
        self.stream = stream
        self.success_radius = float(success_radius)
        self.history: list[dict[str, float]] = list(history or [])
        self._wall0 = self.history[-1]["wall_time_s"] if self.history else 0.0
        self._rollouts = 0

    # ------------------------------------------------------------------ SB3 hooks
    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter() - self._wall0
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
            "agent_steps_per_s": (self.num_timesteps - self._steps0) / max(elapsed - self._wall0, 1e-9),
        }
        for key in METRICS:
            if not math.isnan(row[key]):
                self.logger.record(f"metrics/{key}", row[key])
        self.history.append(row)
        self._rollouts += 1
        if self.csv_path is not None:
            write_csv(self.csv_path, self.history)
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


def write_csv(path: Path, rows: Sequence[dict[str, float]]) -> None:
    """Write ``rows`` (dicts of the same keys) as a CSV table, atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else [], lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, buf.getvalue())


def read_metrics(path: str | Path, max_bytes: int = 1 << 24) -> list[dict[str, float]]:
    """The rows of a ``metrics.csv`` (or ``eval.csv``): numbers only, at most ``max_bytes``."""
    p = Path(path)
    try:
        if p.stat().st_size > max_bytes:
            raise DataFileError(f"{p}: larger than {max_bytes:,} bytes, expected a metrics table")
        with p.open(newline="") as fh:
            return [{str(k): float(v) for k, v in row.items()} for row in csv.DictReader(fh)]
    except (OSError, ValueError, TypeError, csv.Error, UnicodeDecodeError) as exc:
        raise DataFileError(f"{p}: not a readable metrics table ({type(exc).__name__}: {str(exc)[:200]})") from None


Runs = dict[str, Sequence[Sequence[dict[str, float]]]]
"""Label -> list of runs (seeds), each a list of rows (``metrics.csv`` or ``eval.csv``)."""

_TRAIN_PANELS = [("success_rate", "training rollouts: success", 100.0, "%"),
                 ("tracking_error", "training rollouts: tracking error", 1.0, "m"),
                 ("collision_rate", "training rollouts: decisions in collision", 100.0, "%"),
                 ("mean_correction", "training rollouts: filter correction", 1.0, "rad/s^2")]
_HELDOUT_PANELS = [("success_rate", "held-out: success", 100.0, "%"),
                   ("collision_episode_rate", "held-out: episodes with a collision", 100.0, "%"),
                   ("rmse", "held-out: tracking RMSE", 1.0, "m")]


def _draw(ax: Any, runs: Runs, key: str, scale: float) -> bool:
    """One curve per label: the mean over seeds, with a band (lowest to highest seed, or a one-seed row's 95% CI)."""
    drawn = False
    for color, (name, seeds) in enumerate(runs.items()):
        curves = [(np.array([r["agent_steps"] for r in rows]), np.array([r.get(key, math.nan) for r in rows]),
                   np.array([[r.get(f"{key}_lo", math.nan), r.get(f"{key}_hi", math.nan)] for r in rows]))
                  for rows in seeds if rows]
        if not curves:
            continue
        n = min(len(c[0]) for c in curves)
        x, ys = curves[0][0][:n], np.stack([c[1][:n] for c in curves]) * scale
        if np.isnan(ys).all():
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # rollouts in which no episode ended
            mean, lo, hi = np.nanmean(ys, axis=0), np.nanmin(ys, axis=0), np.nanmax(ys, axis=0)
        if len(curves) == 1:
            lo, hi = curves[0][2][:n, 0] * scale, curves[0][2][:n, 1] * scale
        ok = ~np.isnan(mean)  # join the points across rollouts without a value
        label = name if len(seeds) == 1 else f"{name} ({len(seeds)} seeds)"
        line = ax.plot(x[ok] / 1e6, mean[ok], label=label, color=f"C{color}", marker="." if n < 30 else None)[0]
        band = ok & ~np.isnan(lo) & ~np.isnan(hi)
        if band.any():
            ax.fill_between(x[band] / 1e6, lo[band], hi[band], color=line.get_color(), alpha=0.2)
        drawn = True
    return drawn


def plot_learning_curve(runs: Runs, path: str | Path, title: str | None = None, heldout: Runs | None = None) -> Path:
    """Draw learning curves against agent-steps; write the PNG atomically.

    Parameters
    ----------
    runs : dict
        Label -> list of runs (seeds) of ``metrics.csv`` rows: success, tracking error, collisions
        and (behind a filter) the filter's correction in the training rollouts.
    path : path
        PNG to write.
    title : str, optional
        Figure title.
    heldout : dict, optional
        Label -> list of runs of ``eval.csv`` rows (:mod:`train.heldout`): a top row of panels with
        the held-out success, episodes with a collision and RMSE.  Several seeds are drawn as
        their mean with a band from the lowest to the highest; one seed with its 95% intervals.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [p for p in _TRAIN_PANELS if p[0] != "mean_correction" or any(
        not math.isnan(r.get("mean_correction", math.nan)) for seeds in runs.values() for rows in seeds for r in rows)]
    top = _HELDOUT_PANELS if heldout and any(rows for seeds in heldout.values() for rows in seeds) else []
    rows, cols = (2 if top else 1), max(len(panels), len(top))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax_row, (source, row_panels) in zip(axes, ([(heldout, top)] if top else []) + [(runs, panels)]):
        for ax, (key, label, scale, unit) in zip(ax_row, row_panels):
            _draw(ax, source or {}, key, scale)
            ax.set_title(label, fontsize=10)
            ax.set_xlabel("agent-steps [M]")
            ax.set_ylabel(unit)
            ax.grid(alpha=0.3)
        for ax in ax_row[len(row_panels):]:
            ax.axis("off")
    if axes[0][0].get_legend_handles_labels()[0]:
        axes[0][0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    out = Path(path)
    atomic_write(out, lambda fh: fig.savefig(fh, dpi=110, format="png"))
    plt.close(fig)
    return out
