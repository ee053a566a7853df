"""Static plots of recorded runs (trajectories, distances, speeds, snapshots).

Every function builds a :class:`matplotlib.figure.Figure` attached to the Agg
canvas directly, never through :mod:`matplotlib.pyplot`: nothing needs a
display, no global figure registry fills up, and the caller's pyplot backend is
left alone.  Pass ``path`` to also save a PNG (or any format matplotlib knows by
suffix).  matplotlib is imported lazily; without it these functions raise an
:class:`ImportError` that says to ``pip install "aasoatt[render]"``.

Robot colours match :func:`aasoatt_env.sim.rendering.robot_colors`.

Obstacles are given either as a pair ``(centers (M, 2), radii (M,))`` or as one
``(M, 3)`` array of rows ``(x, y, r)``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.errors import ConfigError
from aasoatt_env.sim.rendering import _require, robot_colors

__all__ = [
    "plot_distance_profile",
    "plot_snapshots",
    "plot_trajectories",
    "plot_velocity_profile",
]

PathLike = str | os.PathLike[str]
Obstacles = tuple[Any, Any] | np.ndarray | None


def _new_figure(figsize: tuple[float, float]) -> Any:
    """Create a Figure on an Agg canvas, without pyplot."""
    figure_mod = _require("matplotlib.figure", "aasoatt_env.analysis.plotting")
    agg = _require("matplotlib.backends.backend_agg", "aasoatt_env.analysis.plotting")
    fig = figure_mod.Figure(figsize=figsize, layout="constrained")
    agg.FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: PathLike | None, dpi: int) -> None:
    if path is not None:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(p, dpi=dpi)


def _colors(n: int) -> np.ndarray:
    return robot_colors(n).astype(np.float64) / 255.0


def _positions(name: str, positions: Any) -> np.ndarray:
    arr = np.asarray(positions, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[2] != 2 or arr.shape[0] == 0:
        raise ConfigError(f"{name}: got shape {arr.shape}, expected (T, N, 2) with T >= 1")
    return arr


def _radii(radii: Any, n: int, default: float = 0.0) -> np.ndarray:
    if radii is None:
        return np.full(n, default)
    r = np.asarray(radii, dtype=np.float64)
    try:
        return np.broadcast_to(r, (n,)).copy()
    except ValueError:
        raise ConfigError(f"radii: got shape {r.shape}, expected () or ({n},)") from None


def _obstacles(obstacles: Obstacles) -> tuple[np.ndarray, np.ndarray]:
    """Normalise obstacles to ``(centers (M, 2), radii (M,))``."""
    if obstacles is None:
        return np.zeros((0, 2)), np.zeros(0)
    if isinstance(obstacles, tuple) and len(obstacles) == 2:
        centers = np.asarray(obstacles[0], dtype=np.float64).reshape(-1, 2)
        radii = np.broadcast_to(np.asarray(obstacles[1], dtype=np.float64), (centers.shape[0],))
        return centers, np.asarray(radii)
    arr = np.asarray(obstacles, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2)), np.zeros(0)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ConfigError(
            f"obstacles: got shape {arr.shape}, expected (centers (M, 2), radii (M,)) or an (M, 3) array"
        )
    return arr[:, :2], arr[:, 2]


def _draw_obstacles(ax: Any, obstacles: Obstacles) -> None:
    patches = _require("matplotlib.patches", "aasoatt_env.analysis.plotting")
    centers, radii = _obstacles(obstacles)
    for c, r in zip(centers, radii):
        ax.add_patch(patches.Circle(tuple(c), r, facecolor="0.55", edgecolor="0.35", lw=0.8, zorder=1))


def _fit_axes(ax: Any, points: np.ndarray, pad: float) -> None:
    """Equal-aspect limits covering ``points`` (finite ones) plus ``pad``."""
    pts = points[np.all(np.isfinite(points), axis=1)]
    if pts.shape[0]:
        lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")


def plot_trajectories(
    positions: Any,
    radii: Any = None,
    references: Any = None,
    goals: Any = None,
    obstacles: Obstacles = None,
    path: PathLike | None = None,
    title: str | None = None,
    *,
    figsize: tuple[float, float] = (6.0, 6.0),
    dpi: int = 150,
) -> Any:
    """Plot the paths of a team in the plane.

    Parameters
    ----------
    positions : array_like, shape (T, N, 2)
        Control-point positions over time [m].
    radii : float or array_like, shape (N,), optional
        Disc radii [m]; the final positions are drawn as discs at true scale
        (as small dots if not given).
    references : array_like, shape (T, N, 2), optional
        Reference trajectories, drawn dashed.
    goals : array_like, shape (N, 2), optional
        Goals, drawn as hollow squares.
    obstacles : (centers, radii) or array_like (M, 3), optional
        Static obstacles, drawn as grey discs.
    path : str or os.PathLike, optional
        If given, the figure is also saved there (PNG by default).
    title : str, optional
        Axes title.
    figsize : tuple of float
        Figure size in inches.
    dpi : int
        Resolution of the saved file.

    Returns
    -------
    matplotlib.figure.Figure
        The figure (not registered with pyplot).
    """
    pos = _positions("positions", positions)
    _, n, _ = pos.shape
    r = _radii(radii, n)
    colors = _colors(n)
    patches = _require("matplotlib.patches", "aasoatt_env.analysis.plotting")
    fig = _new_figure(figsize)
    ax = fig.add_subplot()
    _draw_obstacles(ax, obstacles)
    pts = [pos.reshape(-1, 2)]
    ref = None
    if references is not None:
        ref = _positions("references", references)
        if ref.shape[1:] != (n, 2):
            raise ConfigError(f"references: got shape {ref.shape}, expected (T, {n}, 2)")
        pts.append(ref.reshape(-1, 2))
    for i in range(n):
        c = colors[i]
        if ref is not None:
            ax.plot(ref[:, i, 0], ref[:, i, 1], ls="--", lw=0.9, color=c, alpha=0.7, zorder=2)
        ax.plot(pos[:, i, 0], pos[:, i, 1], lw=1.4, color=c, zorder=3)
        ax.plot(pos[0, i, 0], pos[0, i, 1], marker="o", ms=5, mfc="white", mec=c, mew=1.4, zorder=4)
        if r[i] > 0:
            ax.add_patch(
                patches.Circle(
                    tuple(pos[-1, i]), r[i], facecolor=c, edgecolor="black", lw=0.6, alpha=0.85, zorder=5
                )
            )
        else:
            ax.plot(pos[-1, i, 0], pos[-1, i, 1], marker="o", ms=6, color=c, zorder=5)
    if goals is not None:
        g = np.asarray(goals, dtype=np.float64)
        if g.shape != (n, 2):
            raise ConfigError(f"goals: got shape {g.shape}, expected ({n}, 2)")
        ax.scatter(g[:, 0], g[:, 1], marker="s", s=40, facecolors="none", edgecolors=colors, lw=1.4, zorder=6)
        pts.append(g)
    centers, oradii = _obstacles(obstacles)
    if centers.shape[0]:
        pts += [centers - oradii[:, None], centers + oradii[:, None]]
    allp = np.concatenate(pts)
    finite = allp[np.all(np.isfinite(allp), axis=1)]
    span = float(np.max(finite.max(axis=0) - finite.min(axis=0))) if finite.shape[0] else 1.0
    pad = (float(r.max()) if n else 0.0) + 0.05 * span
    _fit_axes(ax, allp, max(pad, 0.1))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.4, alpha=0.5)
    if title:
        ax.set_title(title)
    _save(fig, path, dpi)
    return fig


def plot_distance_profile(
    times: Any,
    min_distance: Any,
    safety_distance: float | Sequence[float] | None,
    path: PathLike | None = None,
    *,
    labels: Sequence[str] | None = None,
    title: str | None = None,
    figsize: tuple[float, float] = (6.5, 3.5),
    dpi: int = 150,
) -> Any:
    """Plot inter-robot distances over time against the safety distance.

    Parameters
    ----------
    times : array_like, shape (T,)
        Time stamps [s].
    min_distance : array_like, shape (T,) or (T, P)
        The minimum distance over all pairs, or one column per pair [m].  With
        several columns each is drawn thin and their minimum bold.
    safety_distance : float or sequence of float, optional
        Safety distance ``d_s`` (sum of radii), drawn as a horizontal red line;
        several values (heterogeneous teams) draw several lines.
    path : str or os.PathLike, optional
        If given, the figure is also saved there.
    labels : sequence of str, optional
        Legend labels of the columns of a ``(T, P)`` input.
    title : str, optional
        Axes title.
    figsize : tuple of float
        Figure size in inches.
    dpi : int
        Resolution of the saved file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    d = np.asarray(min_distance, dtype=np.float64)
    if d.ndim == 1:
        d = d[:, None]
    if d.ndim != 2 or d.shape[0] != t.shape[0]:
        raise ConfigError(f"min_distance: got shape {d.shape}, expected ({t.shape[0]},) or ({t.shape[0]}, P)")
    fig = _new_figure(figsize)
    ax = fig.add_subplot()
    if d.shape[1] == 1:
        ax.plot(t, d[:, 0], lw=1.5, color="C0", label=labels[0] if labels else "min distance")
    else:
        for k in range(d.shape[1]):
            ax.plot(t, d[:, k], lw=0.8, alpha=0.6, label=labels[k] if labels and k < len(labels) else None)
        ax.plot(t, np.nanmin(d, axis=1), lw=1.8, color="black", label="min over pairs")
    if safety_distance is not None:
        for k, ds in enumerate(np.atleast_1d(np.asarray(safety_distance, dtype=np.float64))):
            ax.axhline(ds, color="red", ls="--", lw=1.2, label=f"$d_s$ = {ds:g} m" if k < 3 else None)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("distance [m]")
    ax.set_ylim(bottom=0.0)
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(title)
    _save(fig, path, dpi)
    return fig


def plot_velocity_profile(
    times: Any,
    speeds: Any,
    path: PathLike | None = None,
    *,
    max_speed: float | None = None,
    title: str | None = None,
    ylabel: str = "speed [m/s]",
    figsize: tuple[float, float] = (6.5, 3.5),
    dpi: int = 150,
) -> Any:
    """Plot each robot's speed over time.

    Parameters
    ----------
    times : array_like, shape (T,)
        Time stamps [s].
    speeds : array_like, shape (T, N)
        Speed of each robot's control point [m/s] (or any per-robot signal,
        with ``ylabel`` changed accordingly).
    path : str or os.PathLike, optional
        If given, the figure is also saved there.
    max_speed : float, optional
        Drawn as a dashed horizontal line.
    title : str, optional
        Axes title.
    ylabel : str
        Label of the y axis.
    figsize : tuple of float
        Figure size in inches.
    dpi : int
        Resolution of the saved file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    v = np.asarray(speeds, dtype=np.float64)
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] != t.shape[0]:
        raise ConfigError(f"speeds: got shape {v.shape}, expected ({t.shape[0]}, N)")
    colors = _colors(v.shape[1])
    fig = _new_figure(figsize)
    ax = fig.add_subplot()
    for i in range(v.shape[1]):
        ax.plot(t, v[:, i], lw=1.1, color=colors[i], label=f"robot {i}" if v.shape[1] <= 10 else None)
    if max_speed is not None and np.isfinite(max_speed):
        ax.axhline(float(max_speed), color="0.3", ls="--", lw=1.0, label="limit")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.grid(True, lw=0.4, alpha=0.5)
    if v.shape[1] <= 10:
        ax.legend(loc="best", fontsize="x-small", ncols=2)
    if title:
        ax.set_title(title)
    _save(fig, path, dpi)
    return fig


def plot_snapshots(
    positions: Any,
    times: Any,
    indices: Sequence[int],
    radii: Any,
    obstacles: Obstacles = None,
    path: PathLike | None = None,
    *,
    references: Any = None,
    goals: Any = None,
    trails: bool = True,
    panel_size: float = 3.0,
    dpi: int = 150,
) -> Any:
    """Plot a row of panels showing the team at chosen time steps (paper Fig. 5 style).

    Parameters
    ----------
    positions : array_like, shape (T, N, 2)
        Control-point positions over time [m].
    times : array_like, shape (T,)
        Time stamps [s], used for the panel titles.
    indices : sequence of int
        Time-step indices to show, one panel each (negative indices allowed).
    radii : float or array_like, shape (N,)
        Disc radii [m]; robots are drawn at true scale.
    obstacles : (centers, radii) or array_like (M, 3), optional
        Static obstacles.
    path : str or os.PathLike, optional
        If given, the figure is also saved there.
    references : array_like, shape (T, N, 2), optional
        Reference trajectories; the current reference points are marked.
    goals : array_like, shape (N, 2), optional
        Goals, drawn as hollow squares.
    trails : bool
        Draw each robot's path up to the snapshot.
    panel_size : float
        Size of each (square) panel in inches.
    dpi : int
        Resolution of the saved file.

    Returns
    -------
    matplotlib.figure.Figure
    """
    pos = _positions("positions", positions)
    t_len, n, _ = pos.shape
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.shape[0] != t_len:
        raise ConfigError(f"times: got {t.shape[0]} time stamps, expected {t_len} (one per row of positions)")
    idx = [int(k) for k in indices]
    if not idx:
        raise ConfigError("indices: got none, expected at least one time-step index")
    for k in idx:
        if not -t_len <= k < t_len:
            raise ConfigError(f"indices: got {k}, expected an index in [-{t_len}, {t_len})")
    idx = [k % t_len for k in idx]
    r = _radii(radii, n)
    ref = None if references is None else _positions("references", references)
    colors = _colors(n)
    patches = _require("matplotlib.patches", "aasoatt_env.analysis.plotting")
    fig = _new_figure((panel_size * len(idx), panel_size + 0.3))
    axes = fig.subplots(1, len(idx), squeeze=False, sharex=True, sharey=True)[0]
    pts = [pos.reshape(-1, 2)]
    if goals is not None:
        g = np.asarray(goals, dtype=np.float64).reshape(n, 2)
        pts.append(g)
    centers, oradii = _obstacles(obstacles)
    if centers.shape[0]:
        pts += [centers - oradii[:, None], centers + oradii[:, None]]
    allp = np.concatenate(pts)
    pad = (float(r.max()) if n else 0.0) + 0.3
    for ax, k in zip(axes, idx):
        _draw_obstacles(ax, obstacles)
        for i in range(n):
            c = colors[i]
            if trails and k > 0:
                ax.plot(pos[: k + 1, i, 0], pos[: k + 1, i, 1], lw=0.9, color=c, alpha=0.7, zorder=2)
            ax.add_patch(
                patches.Circle(
                    tuple(pos[k, i]),
                    r[i] if r[i] > 0 else 0.05,
                    facecolor=c,
                    edgecolor="black",
                    lw=0.5,
                    alpha=0.9,
                    zorder=4,
                )
            )
            if ref is not None:
                ax.plot(ref[k, i, 0], ref[k, i, 1], marker="+", ms=6, color=c, mew=1.3, zorder=5)
        if goals is not None:
            ax.scatter(
                g[:, 0], g[:, 1], marker="s", s=20, facecolors="none", edgecolors=colors, lw=1.0, zorder=3
            )
        ax.set_title(f"t = {t[k]:.2f} s", fontsize="medium")
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.set_xlabel("x [m]")
        _fit_axes(ax, allp, pad)
    axes[0].set_ylabel("y [m]")
    _save(fig, path, dpi)
    return fig
