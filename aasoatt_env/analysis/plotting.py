"""Static plots of recorded runs: trajectories, distance and speed profiles, snapshots.

Figures use the Agg canvas, never pyplot (no display; the caller's pyplot state untouched); ``path`` also
saves one atomically.  Obstacles are ``(centers (M, 2), radii (M,))`` or an ``(M, 3)`` array.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.analysis.rollout import checked_array
from aasoatt_env.cli_support import atomic_write
from aasoatt_env.errors import ConfigError
from aasoatt_env.sim.rendering import _require, robot_colors

__all__ = ["new_figure", "plot_distance_profile", "plot_snapshots", "plot_trajectories", "plot_velocity_profile",
           "team_colors"]

PathLike = str | os.PathLike[str]
Obstacles = tuple[Any, Any] | np.ndarray | None


def new_figure(nrows: int = 1, ncols: int = 1, figsize: tuple[float, float] = (6.0, 4.0), **kw: Any) -> tuple[Any, Any]:
    """A figure on an Agg canvas (no pyplot) and its ``(nrows, ncols)`` array of axes (``kw``: to ``subplots``)."""
    figure_mod = _require("matplotlib.figure", "aasoatt_env.analysis.plotting")
    agg = _require("matplotlib.backends.backend_agg", "aasoatt_env.analysis.plotting")
    fig = figure_mod.Figure(figsize=figsize, layout="constrained")
    agg.FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=False, **kw)


def team_colors(n: int) -> np.ndarray:
    """One RGB colour in ``[0, 1]`` per robot, as the renderer draws them."""
    return robot_colors(n).astype(np.float64) / 255.0


def _label(ax: Any, title: str | None, xlabel: str, ylabel: str) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, lw=0.4, alpha=0.5)
    if title:
        ax.set_title(title)


def _save(fig: Any, path: PathLike | None, dpi: int) -> Any:
    if path is not None:
        p = Path(path) if Path(path).suffix else Path(path).with_suffix(".png")
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(p, lambda tmp: fig.savefig(tmp, dpi=dpi, format=p.suffix[1:]))
    return fig


_SHAPES: dict[str, tuple[str | int, ...]] = {"positions": ("T", "N", 2), "references": ("T", "N", 2), "goals": ("N", 2),
                                              "radii": ("N",), "times": ("T",), "speeds": ("T", "N"),
                                              "min_distance": ("T", "P")}


def _checked(**arrays: Any) -> list[Any]:
    """The input checks of every plot: ``arrays`` as float arrays of the shapes of ``_SHAPES``, sizes consistent.

    None stays None; a series ``(T,)`` is one column; one radius is every robot's; ``times`` may hold its T stamps
    in any shape; NaN in a path or series is a gap.
    """
    sizes: dict[str, int] = {}
    out = []
    for name, value in arrays.items():
        value = 0.0 if value is None and name == "radii" else value
        if value is not None:
            if name == "times":
                value = np.reshape(value, -1)
            elif np.ndim(value) == 1 and name in ("speeds", "min_distance"):
                value = np.reshape(value, (-1, 1))
            elif np.ndim(value) == 0 and name == "radii":
                value = np.full(sizes["N"], value)
            value = checked_array(name, value, _SHAPES[name], sizes, finite=name in ("goals", "radii"))
            if sizes.get("T") == 0:
                raise ConfigError(f"{name}: got shape {value.shape}, expected at least one time step")
        out.append(value)
    return out


def _obstacles(obstacles: Obstacles) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(obstacles, tuple) and len(obstacles) == 2:
        centers = np.asarray(obstacles[0], dtype=np.float64).reshape(-1, 2)
        return centers, np.broadcast_to(np.asarray(obstacles[1], dtype=np.float64), (centers.shape[0],)).copy()
    arr = np.zeros((0, 3)) if obstacles is None else np.asarray(obstacles, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2)), np.zeros(0)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ConfigError(f"obstacles: got shape {arr.shape}, expected (centers (M, 2), radii (M,)) or an (M, 3) array")
    return arr[:, :2], arr[:, 2]


def _scene(ax: Any, obstacles: Obstacles, points: list[np.ndarray], pad: float) -> None:
    """Draw the obstacles, then fit equal-aspect limits around ``points`` and the obstacles plus ``pad``."""
    patches = _require("matplotlib.patches", "aasoatt_env.analysis.plotting")
    centers, radii = _obstacles(obstacles)
    for c, r in zip(centers, radii):
        ax.add_patch(patches.Circle(tuple(c), r, facecolor="0.55", edgecolor="0.35", lw=0.8, zorder=1))
    pts = np.concatenate([*points, centers - radii[:, None], centers + radii[:, None]])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0]:
        lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")


def _disc(ax: Any, center: np.ndarray, radius: float, color: Any, **kw: Any) -> None:
    patches = _require("matplotlib.patches", "aasoatt_env.analysis.plotting")
    ax.add_patch(patches.Circle(tuple(center), radius, facecolor=color, edgecolor="black", **kw))


def _goals(ax: Any, goals: np.ndarray | None, colors: np.ndarray, size: float, lw: float, zorder: int) -> None:
    if goals is not None:
        ax.scatter(goals[:, 0], goals[:, 1], marker="s", s=size, facecolors="none", edgecolors=colors, lw=lw,
                   zorder=zorder)


def plot_trajectories(positions: Any, radii: Any = None, references: Any = None, goals: Any = None,
                      obstacles: Obstacles = None, path: PathLike | None = None, title: str | None = None, *,
                      figsize: tuple[float, float] = (6.0, 6.0), dpi: int = 150, ax: Any = None) -> Any:
    """Plot a team's paths ``(T, N, 2)``, final discs of ``radii``, references dashed, goals (``ax``: a panel)."""
    pos, ref, g, r = _checked(positions=positions, references=references, goals=goals, radii=radii)
    n, colors = pos.shape[1], team_colors(pos.shape[1])
    if ax is None:
        _, ((ax,),) = new_figure(1, 1, figsize)
    for i in range(n):
        if ref is not None:
            ax.plot(ref[:, i, 0], ref[:, i, 1], ls="--", lw=0.9, color=colors[i], alpha=0.7, zorder=2)
        ax.plot(pos[:, i, 0], pos[:, i, 1], lw=1.4, color=colors[i], zorder=3)
        ax.plot(pos[0, i, 0], pos[0, i, 1], marker="o", ms=5, mfc="white", mec=colors[i], mew=1.4, zorder=4)
        if r[i] > 0:
            _disc(ax, pos[-1, i], r[i], colors[i], lw=0.6, alpha=0.85, zorder=5)
        else:
            ax.plot(pos[-1, i, 0], pos[-1, i, 1], marker="o", ms=6, color=colors[i], zorder=5)
    _goals(ax, g, colors, 40, 1.4, 6)
    points = [pos.reshape(-1, 2)] + [a.reshape(-1, 2) for a in (ref, g) if a is not None]
    finite = np.concatenate(points)
    finite = finite[np.all(np.isfinite(finite), axis=1)]
    span = float(np.max(finite.max(axis=0) - finite.min(axis=0))) if finite.shape[0] else 1.0
    _scene(ax, obstacles, points, max((float(r.max()) if n else 0.0) + 0.05 * span, 0.1))
    _label(ax, title, "x [m]", "y [m]")
    return _save(ax.figure, path, dpi)


def plot_distance_profile(times: Any, min_distance: Any, safety_distance: float | Sequence[float] | None,
                          path: PathLike | None = None, *, labels: Sequence[str] | None = None,
                          title: str | None = None, figsize: tuple[float, float] = (6.5, 3.5), dpi: int = 150) -> Any:
    """Plot the minimum distance ``(T,)`` or one per pair ``(T, P)`` (and their minimum) against ``d_s``."""
    t, d = _checked(times=times, min_distance=min_distance)
    fig, ((ax,),) = new_figure(1, 1, figsize)
    if d.shape[1] == 1:
        ax.plot(t, d[:, 0], lw=1.5, color="C0", label=labels[0] if labels else "min distance")
    else:
        for k in range(d.shape[1]):
            ax.plot(t, d[:, k], lw=0.8, alpha=0.6, label=labels[k] if labels and k < len(labels) else None)
        ax.plot(t, np.nanmin(d, axis=1), lw=1.8, color="black", label="min over pairs")
    if safety_distance is not None:
        for k, ds in enumerate(np.atleast_1d(np.asarray(safety_distance, dtype=np.float64))):
            ax.axhline(ds, color="red", ls="--", lw=1.2, label=f"$d_s$ = {ds:g} m" if k < 3 else None)
    ax.set_ylim(bottom=0.0)
    ax.legend(loc="best", fontsize="small")
    _label(ax, title, "time [s]", "distance [m]")
    return _save(fig, path, dpi)


def plot_velocity_profile(times: Any, speeds: Any, path: PathLike | None = None, *, max_speed: float | None = None,
                          title: str | None = None, ylabel: str = "speed [m/s]",
                          figsize: tuple[float, float] = (6.5, 3.5), dpi: int = 150) -> Any:
    """Plot each robot's speed ``(T, N)`` (or any per-robot signal, with ``ylabel``) and ``max_speed`` dashed."""
    t, v = _checked(times=times, speeds=speeds)
    colors = team_colors(v.shape[1])
    fig, ((ax,),) = new_figure(1, 1, figsize)
    for i in range(v.shape[1]):
        ax.plot(t, v[:, i], lw=1.1, color=colors[i], label=f"robot {i}" if v.shape[1] <= 10 else None)
    if max_speed is not None and np.isfinite(max_speed):
        ax.axhline(float(max_speed), color="0.3", ls="--", lw=1.0, label="limit")
    if v.shape[1] <= 10:
        ax.legend(loc="best", fontsize="x-small", ncols=2)
    _label(ax, title, "time [s]", ylabel)
    return _save(fig, path, dpi)


def plot_snapshots(positions: Any, times: Any, indices: Sequence[int], radii: Any, obstacles: Obstacles = None,
                   path: PathLike | None = None, *, references: Any = None, goals: Any = None, trails: bool = True,
                   panel_size: float = 3.0, dpi: int = 150) -> Any:
    """Plot a row of panels of the team (discs to scale, trails) at the steps ``indices`` (paper Fig. 5 style)."""
    pos, t, ref, g, r = _checked(positions=positions, times=times, references=references, goals=goals, radii=radii)
    (t_len, n), idx = pos.shape[:2], [int(k) for k in indices]
    if not idx or not all(-t_len <= k < t_len for k in idx):
        raise ConfigError(f"indices: got {idx}, expected one or more time-step indices in [-{t_len}, {t_len})")
    colors = team_colors(n)
    fig, (axes,) = new_figure(1, len(idx), (panel_size * len(idx), panel_size + 0.3), sharex=True, sharey=True)
    points = [pos.reshape(-1, 2)] + ([] if g is None else [g])
    for ax, k in zip(axes, (k % t_len for k in idx)):
        for i in range(n):
            if trails and k > 0:
                ax.plot(pos[: k + 1, i, 0], pos[: k + 1, i, 1], lw=0.9, color=colors[i], alpha=0.7, zorder=2)
            _disc(ax, pos[k, i], r[i] if r[i] > 0 else 0.05, colors[i], lw=0.5, alpha=0.9, zorder=4)
            if ref is not None:
                ax.plot(ref[k, i, 0], ref[k, i, 1], marker="+", ms=6, color=colors[i], mew=1.3, zorder=5)
        _goals(ax, g, colors, 20, 1.0, 3)
        _scene(ax, obstacles, points, (float(r.max()) if n else 0.0) + 0.3)
        _label(ax, f"t = {t[k]:.2f} s", "x [m]", "y [m]" if ax is axes[0] else "")
    return _save(fig, path, dpi)
