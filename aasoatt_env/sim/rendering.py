"""Headless-safe rendering of team snapshots to RGB arrays, windows and animations.

A :class:`Frame` holds everything one picture shows (robots, references, goals,
obstacles, trails, which robots are avoiding).  :class:`Renderer` rasterises it
with pygame surfaces (no display needed) into an ``(H, W, 3)`` ``uint8`` array,
or shows it in a window for ``render_mode="human"``; :func:`save_animation`
writes a list of such arrays as a GIF or MP4.

The optional dependencies (pygame, imageio) are imported lazily, so the core
library imports this module without them; using a feature whose dependency is
missing raises an :class:`ImportError` that says to
``pip install "aasoatt[render]"``.

Conventions
-----------
World coordinates are metres with ``y`` pointing up; the picture keeps the
aspect ratio (one scale for both axes) and centres ``world_bounds`` in it.
Robot discs are drawn at their true radius around the control point.
"""

from __future__ import annotations

import colorsys
import importlib
import importlib.util
import math
import os
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from aasoatt_env.errors import ConfigError

__all__ = [
    "ANIMATION_SUFFIXES",
    "BACKGROUND",
    "Frame",
    "Renderer",
    "animation_writer_missing",
    "robot_colors",
    "save_animation",
]

RENDER_EXTRA_HINT = 'pip install "aasoatt[render]"'

BACKGROUND: tuple[int, int, int] = (255, 255, 255)
"""Background colour of rendered frames (RGB)."""

GRID_COLOR = (232, 232, 232)
BOUNDS_COLOR = (190, 190, 190)
OBSTACLE_FILL = (140, 140, 140)
OBSTACLE_EDGE = (90, 90, 90)
AVOID_COLOR = (220, 20, 20)
TEXT_COLOR = (30, 30, 30)

# Tableau-like palette without pure red (red marks robots in collision avoidance).
_PALETTE: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
    (0, 0, 128),
    (0, 128, 128),
    (128, 128, 0),
    (255, 187, 120),
    (152, 223, 138),
    (174, 199, 232),
    (197, 176, 213),
    (196, 156, 148),
    (247, 182, 210),
    (219, 219, 141),
    (158, 218, 229),
)


def robot_colors(n: int) -> np.ndarray:
    """Distinct, deterministic RGB colours for ``n`` robots.

    The first 20 come from a fixed palette (no pure red, which marks robots in
    collision avoidance); more are spread over the hue circle by the golden angle.

    Parameters
    ----------
    n : int
        Number of robots.

    Returns
    -------
    numpy.ndarray
        ``(n, 3)`` array of ``uint8`` RGB colours.
    """
    out = np.empty((max(n, 0), 3), dtype=np.uint8)
    for i in range(max(n, 0)):
        if i < len(_PALETTE):
            out[i] = _PALETTE[i]
        else:
            hue = (0.1 + 0.618033988749895 * i) % 1.0
            # Keep away from red hues (roughly +-0.04 around 0).
            hue = 0.04 + 0.92 * hue
            value = 0.85 if i % 2 else 0.65
            r, g, b = colorsys.hsv_to_rgb(hue, 0.75, value)
            out[i] = (int(r * 255), int(g * 255), int(b * 255))
    return out


def _require(module: str, feature: str) -> ModuleType:
    """Import ``module`` or raise an ImportError telling how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        package = module.split(".")[0]
        raise ImportError(
            f"{feature} needs the optional dependency {package!r}, which is not installed; "
            f"install the rendering extras with: {RENDER_EXTRA_HINT}"
        ) from exc


def _import_pygame(feature: str) -> ModuleType:
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    return _require("pygame", feature)


def _as_array(name: str, value: Any, shape_tail: tuple[int, ...], n: int | None) -> np.ndarray:
    """Convert ``value`` to a float array of shape ``(n, *shape_tail)`` or raise ConfigError."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0 and n in (None, 0):
        return arr.reshape((0, *shape_tail))
    ok = arr.ndim == 1 + len(shape_tail) and arr.shape[1:] == shape_tail and (n is None or arr.shape[0] == n)
    if not ok:
        lead = "N" if n is None else str(n)
        exp = "(" + ", ".join([lead, *map(str, shape_tail)]) + (",)" if not shape_tail else ")")
        raise ConfigError(f"Frame.{name}: got shape {arr.shape}, expected {exp}")
    return arr


@dataclass
class Frame:
    """Everything one rendered picture shows.

    Parameters
    ----------
    positions : array_like, shape (N, 2)
        Control-point positions [m]; robot discs are centred here.
    headings : array_like, shape (N,)
        Headings [rad], drawn as a line from the disc centre to its rim.
    radii : array_like, shape (N,)
        Disc radii [m].
    references : array_like, shape (N, 2), optional
        Current reference points, drawn as small dots in each robot's colour.
    goals : array_like, shape (N, 2), optional
        Goals, drawn as small hollow squares in each robot's colour.
    obstacle_centers : array_like, shape (M, 2)
        Static obstacle centres (``M`` may be 0).
    obstacle_radii : array_like, shape (M,)
        Static obstacle radii.
    trails : array_like, shape (T, N, 2), optional
        Past positions, oldest first, drawn as thin polylines; non-finite points
        break a polyline.
    avoiding : array_like of bool, shape (N,), optional
        Robots currently in collision avoidance; they get a red outline.
    sensing_range : float, optional
        If given, a faint circle of this radius is drawn around each robot.
    time : float
        Simulation time [s], printed in the top-left corner.
    title : str, optional
        Printed at the top centre.
    world_bounds : tuple of float, optional
        ``(xmin, xmax, ymin, ymax)`` of the visible region.  ``None`` fits
        everything in the frame with a margin.
    """

    positions: np.ndarray
    headings: np.ndarray
    radii: np.ndarray
    references: np.ndarray | None = None
    goals: np.ndarray | None = None
    obstacle_centers: np.ndarray | None = None
    obstacle_radii: np.ndarray | None = None
    trails: np.ndarray | Sequence[np.ndarray] | None = None
    avoiding: np.ndarray | None = None
    sensing_range: float | None = None
    time: float = 0.0
    title: str | None = None
    world_bounds: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        self.positions = _as_array("positions", self.positions, (2,), None)
        n = self.positions.shape[0]
        self.headings = _as_array("headings", np.broadcast_to(self.headings, (n,)), (), n)
        self.radii = _as_array("radii", np.broadcast_to(self.radii, (n,)), (), n)
        if self.references is not None:
            self.references = _as_array("references", self.references, (2,), n)
        if self.goals is not None:
            self.goals = _as_array("goals", self.goals, (2,), n)
        centers = np.zeros((0, 2)) if self.obstacle_centers is None else self.obstacle_centers
        self.obstacle_centers = _as_array("obstacle_centers", centers, (2,), None)
        m = self.obstacle_centers.shape[0]
        radii = np.zeros(0) if self.obstacle_radii is None else np.broadcast_to(self.obstacle_radii, (m,))
        self.obstacle_radii = _as_array("obstacle_radii", radii, (), m)
        if self.trails is not None:
            trails = np.asarray(self.trails, dtype=np.float64)
            if trails.size == 0:
                trails = trails.reshape(0, n, 2)
            if trails.ndim != 3 or trails.shape[1:] != (n, 2):
                raise ConfigError(f"Frame.trails: got shape {trails.shape}, expected (T, {n}, 2)")
            self.trails = trails
        if self.avoiding is not None:
            avoiding = np.asarray(self.avoiding, dtype=bool)
            if avoiding.shape != (n,):
                raise ConfigError(f"Frame.avoiding: got shape {avoiding.shape}, expected ({n},)")
            self.avoiding = avoiding
        if self.sensing_range is not None:
            self.sensing_range = float(self.sensing_range)
        self.time = float(self.time)
        if self.world_bounds is not None:
            b = tuple(float(v) for v in self.world_bounds)
            if len(b) != 4 or not all(math.isfinite(v) for v in b) or b[1] <= b[0] or b[3] <= b[2]:
                raise ConfigError(
                    f"Frame.world_bounds: got {self.world_bounds!r}, expected finite "
                    "(xmin, xmax, ymin, ymax) with xmin < xmax and ymin < ymax"
                )
            self.world_bounds = b  # type: ignore[assignment]

    @property
    def n(self) -> int:
        """Number of robots."""
        return int(self.positions.shape[0])

    def bounds(self, margin: float = 0.1) -> tuple[float, float, float, float]:
        """``world_bounds`` if set, else a box around all content, padded by ``margin`` of its size."""
        if self.world_bounds is not None:
            return self.world_bounds  # type: ignore[return-value]
        pts = [self.positions - self.radii[:, None], self.positions + self.radii[:, None]]
        for extra in (self.references, self.goals):
            if extra is not None:
                pts.append(extra)
        if self.obstacle_centers.shape[0]:
            r = self.obstacle_radii[:, None]
            pts += [self.obstacle_centers - r, self.obstacle_centers + r]
        if self.trails is not None:
            pts.append(np.asarray(self.trails).reshape(-1, 2))
        allp = np.concatenate(pts, axis=0) if pts else np.zeros((0, 2))
        allp = allp[np.all(np.isfinite(allp), axis=1)]
        if allp.shape[0] == 0:
            return (-1.0, 1.0, -1.0, 1.0)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        size = max(float(np.max(hi - lo)), 1.0)
        pad = margin * size
        return (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad)


class _Transform:
    """World [m] -> pixel mapping with one scale for both axes (y flipped)."""

    def __init__(self, bounds: tuple[float, float, float, float], width: int, height: int) -> None:
        xmin, xmax, ymin, ymax = bounds
        self.scale = min(width / (xmax - xmin), height / (ymax - ymin))
        self.ox = 0.5 * (width - (xmax - xmin) * self.scale) - xmin * self.scale
        self.oy = 0.5 * (height - (ymax - ymin) * self.scale) + ymax * self.scale
        self.limit = 8.0 * max(width, height) + 1.0

    def points(self, p: np.ndarray) -> np.ndarray:
        """Pixel coordinates (float) of world points ``(..., 2)``."""
        p = np.asarray(p, dtype=np.float64)
        out = np.empty_like(p)
        out[..., 0] = self.ox + p[..., 0] * self.scale
        out[..., 1] = self.oy - p[..., 1] * self.scale
        return out

    def ipoints(self, p: np.ndarray) -> np.ndarray:
        """Return rounded, clipped integer pixel coordinates of world points ``(..., 2)``."""
        return np.clip(np.rint(self.points(p)), -self.limit, self.limit).astype(np.int64)


def _mix(color: Sequence[int], other: Sequence[int], t: float) -> tuple[int, int, int]:
    """Blend ``t`` of ``other`` into ``color``."""
    return tuple(int(round((1.0 - t) * c + t * o)) for c, o in zip(color, other))  # type: ignore[return-value]


def _nice_step(span: float, target_lines: int = 10) -> float:
    raw = span / max(target_lines, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if raw <= m * mag:
            return m * mag
    return 10.0 * mag


def _display_available() -> bool:
    """Best guess whether a window can be opened (no display server -> False)."""
    driver = os.environ.get("SDL_VIDEODRIVER", "").lower()
    if driver in ("dummy", "offscreen"):
        return False
    if sys.platform.startswith("linux") or "bsd" in sys.platform:
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


class Renderer:
    """Rasterise :class:`Frame` objects with pygame surfaces (no display needed).

    Parameters
    ----------
    width, height : int
        Picture size in pixels.
    grid : bool
        Draw a faint metric grid and the outline of ``world_bounds``.
    show_text : bool
        Print the time and title (needs ``pygame.font``; silently skipped if absent).
    fps : float, optional
        In :meth:`show`, wait so that windows update at most ``fps`` times a second.

    Raises
    ------
    ImportError
        If pygame is not installed (``pip install "aasoatt[render]"``).

    Examples
    --------
    >>> r = Renderer(200, 200)
    >>> img = r.rgb_array(Frame(positions=[[0.0, 0.0]], headings=[0.0], radii=[0.5]))
    >>> img.shape, img.dtype
    ((200, 200, 3), dtype('uint8'))
    """

    def __init__(
        self,
        width: int = 600,
        height: int = 600,
        *,
        grid: bool = True,
        show_text: bool = True,
        fps: float | None = None,
    ) -> None:
        if int(width) <= 0 or int(height) <= 0:
            raise ConfigError(f"Renderer: got size {width}x{height}, expected positive width and height")
        self.width = int(width)
        self.height = int(height)
        self.grid = bool(grid)
        self.show_text = bool(show_text)
        self.fps = fps
        self._pg = _import_pygame("Renderer")
        try:
            self._gfx: ModuleType | None = importlib.import_module("pygame.gfxdraw")
        except ImportError:  # pragma: no cover - gfxdraw ships with pygame
            self._gfx = None
        self._surface = self._pg.Surface((self.width, self.height))
        self._font: Any = None
        self._font_failed = False
        self._window: Any = None
        self._clock: Any = None
        self._headless = False
        self._warned = False
        self._closed_by_user = False

    # ------------------------------------------------------------------ drawing
    def _get_font(self) -> Any:
        if self._font is None and not self._font_failed:
            try:
                if not self._pg.font.get_init():
                    self._pg.font.init()
                self._font = self._pg.font.Font(None, max(12, min(self.width, self.height) // 28))
            except Exception:  # noqa: BLE001 - fonts are optional decoration
                self._font_failed = True
        return self._font

    def _disc(self, center: np.ndarray, r: int, color: Sequence[int], edge: Sequence[int] | None) -> None:
        x, y = int(center[0]), int(center[1])
        gfx = self._gfx
        if gfx is not None and r >= 1 and abs(x) + r < 32000 and abs(y) + r < 32000:
            gfx.filled_circle(self._surface, x, y, r, color)
            gfx.aacircle(self._surface, x, y, r, edge if edge is not None else color)
        else:
            self._pg.draw.circle(self._surface, color, (x, y), max(r, 1))
            if edge is not None:
                self._pg.draw.circle(self._surface, edge, (x, y), max(r, 1), 1)

    def _visible(self, c: np.ndarray, r: float) -> bool:
        return -r <= c[0] <= self.width + r and -r <= c[1] <= self.height + r

    def _draw_grid(self, tf: _Transform, bounds: tuple[float, float, float, float]) -> None:
        pg = self._pg
        xmin, xmax, ymin, ymax = bounds
        step = _nice_step(max(xmax - xmin, ymax - ymin))
        for gx in np.arange(math.ceil(xmin / step) * step, xmax + 1e-9, step):
            px = int(round(tf.ox + gx * tf.scale))
            pg.draw.line(self._surface, GRID_COLOR, (px, 0), (px, self.height - 1))
        for gy in np.arange(math.ceil(ymin / step) * step, ymax + 1e-9, step):
            py = int(round(tf.oy - gy * tf.scale))
            pg.draw.line(self._surface, GRID_COLOR, (0, py), (self.width - 1, py))
        corners = tf.ipoints(np.array([[xmin, ymax], [xmax, ymin]]))
        rect = pg.Rect(
            int(corners[0, 0]),
            int(corners[0, 1]),
            int(corners[1, 0] - corners[0, 0]),
            int(corners[1, 1] - corners[0, 1]),
        )
        pg.draw.rect(self._surface, BOUNDS_COLOR, rect, 1)

    def _draw_trails(self, tf: _Transform, trails: np.ndarray, colors: np.ndarray) -> None:
        pg = self._pg
        if trails.shape[0] < 2:
            return
        pix = tf.points(trails)  # (T, N, 2)
        finite = np.all(np.isfinite(pix), axis=2)
        pix = np.clip(np.nan_to_num(pix), -tf.limit, tf.limit)
        for i in range(trails.shape[1]):
            color = _mix(colors[i], BACKGROUND, 0.35)
            ok = finite[:, i]
            if ok.all():
                runs = [pix[:, i]]
            else:
                idx = np.flatnonzero(ok)
                if idx.size < 2:
                    continue
                breaks = np.flatnonzero(np.diff(idx) > 1) + 1
                runs = [pix[seg, i] for seg in np.split(idx, breaks)]
            for run in runs:
                if run.shape[0] >= 2:
                    pg.draw.aalines(self._surface, color, False, run.tolist())

    def draw(self, frame: Frame) -> Any:
        """Draw ``frame`` on the internal surface and return it (a ``pygame.Surface``)."""
        if not isinstance(frame, Frame):
            raise ConfigError(f"Renderer: got {type(frame).__name__}, expected a Frame")
        pg = self._pg
        surf = self._surface
        surf.fill(BACKGROUND)
        bounds = frame.bounds()
        tf = _Transform(bounds, self.width, self.height)
        n = frame.n
        colors = robot_colors(n)
        if self.grid:
            self._draw_grid(tf, bounds)

        # Obstacles.
        oc = tf.points(frame.obstacle_centers)
        for c, r in zip(oc, frame.obstacle_radii):
            rp = max(1, int(round(r * tf.scale)))
            if np.all(np.isfinite(c)) and self._visible(c, rp):
                self._disc(np.rint(c), rp, OBSTACLE_FILL, OBSTACLE_EDGE)

        # Trails.
        if frame.trails is not None and n:
            self._draw_trails(tf, np.asarray(frame.trails), colors)

        pos = tf.points(frame.positions)
        finite = np.all(np.isfinite(pos), axis=1)
        rpix = np.maximum(2, np.rint(frame.radii * tf.scale)).astype(int)

        # Sensing ranges.
        if frame.sensing_range is not None and frame.sensing_range > 0:
            rs = max(1, int(round(frame.sensing_range * tf.scale)))
            for i in range(n):
                if finite[i] and self._visible(pos[i], rs) and rs < 32000:
                    c = np.rint(pos[i]).astype(int)
                    color = _mix(colors[i], BACKGROUND, 0.7)
                    if self._gfx is not None and abs(c[0]) + rs < 32000 and abs(c[1]) + rs < 32000:
                        self._gfx.aacircle(surf, int(c[0]), int(c[1]), rs, color)
                    else:
                        pg.draw.circle(surf, color, (int(c[0]), int(c[1])), rs, 1)

        # Goals: hollow squares.
        if frame.goals is not None:
            gp = tf.points(frame.goals)
            for i in range(n):
                if np.all(np.isfinite(gp[i])):
                    h = max(4, int(round(0.35 * rpix[i])))
                    rect = pg.Rect(int(round(gp[i, 0])) - h, int(round(gp[i, 1])) - h, 2 * h + 1, 2 * h + 1)
                    pg.draw.rect(surf, tuple(int(v) for v in colors[i]), rect, 2)

        # Robots.
        avoiding = frame.avoiding if frame.avoiding is not None else np.zeros(n, dtype=bool)
        for i in range(n):
            if not finite[i] or not self._visible(pos[i], rpix[i]):
                continue
            color = tuple(int(v) for v in colors[i])
            dark = _mix(color, (0, 0, 0), 0.55)
            c = np.rint(pos[i])
            self._disc(c, int(rpix[i]), color, dark)
            th = frame.headings[i]
            if math.isfinite(th):
                tip = (pos[i, 0] + rpix[i] * math.cos(th), pos[i, 1] - rpix[i] * math.sin(th))
                pg.draw.line(
                    surf,
                    dark,
                    (int(c[0]), int(c[1])),
                    (round(tip[0]), round(tip[1])),
                    max(1, int(rpix[i]) // 8),
                )
            if avoiding[i]:
                pg.draw.circle(
                    surf,
                    AVOID_COLOR,
                    (int(c[0]), int(c[1])),
                    int(rpix[i]) + 1,
                    max(2, min(4, int(rpix[i]) // 5)),
                )

        # References: small dots with a dark outline, on top of everything.
        if frame.references is not None:
            rp = tf.points(frame.references)
            for i in range(n):
                if np.all(np.isfinite(rp[i])):
                    c = (int(round(rp[i, 0])), int(round(rp[i, 1])))
                    color = tuple(int(v) for v in colors[i])
                    s = max(3, int(round(0.15 * rpix[i])))
                    pg.draw.circle(surf, _mix(color, (0, 0, 0), 0.6), c, s + 1)
                    pg.draw.circle(surf, color, c, s)

        # Text.
        if self.show_text:
            font = self._get_font()
            if font is not None:
                label = font.render(f"t = {frame.time:.2f} s", True, TEXT_COLOR)
                surf.blit(label, (6, 4))
                if frame.title:
                    label = font.render(str(frame.title), True, TEXT_COLOR)
                    surf.blit(label, ((self.width - label.get_width()) // 2, 4))
        return surf

    def rgb_array(self, frame: Frame) -> np.ndarray:
        """Render ``frame`` to an RGB image.

        Parameters
        ----------
        frame : Frame
            What to draw.

        Returns
        -------
        numpy.ndarray
            ``(height, width, 3)`` array of ``uint8``.
        """
        surf = self.draw(frame)
        raw = self._pg.image.tobytes(surf, "RGB")
        return np.frombuffer(raw, dtype=np.uint8).reshape(self.height, self.width, 3).copy()

    # ------------------------------------------------------------------ window
    def _warn_headless(self, reason: str) -> None:
        self._headless = True
        if not self._warned:
            self._warned = True
            warnings.warn(
                f"Renderer.show: no display available ({reason}); render_mode='human' does nothing. "
                "Use render_mode='rgb_array' to get images.",
                RuntimeWarning,
                stacklevel=3,
            )

    def show(self, frame: Frame) -> None:
        """Show ``frame`` in a pygame window (``render_mode="human"``).

        Without a display (headless machine, ``SDL_VIDEODRIVER=dummy``) this
        warns once and otherwise does nothing; it never raises for lack of a
        display.  Closing the window stops further updates.
        """
        surf = self.draw(frame)
        if self._headless or self._closed_by_user:
            return
        pg = self._pg
        if self._window is None:
            if not _display_available():
                self._warn_headless("no DISPLAY/WAYLAND_DISPLAY, or a dummy SDL video driver")
                return
            try:
                pg.display.init()
                driver = pg.display.get_driver()
                if driver in ("offscreen", "dummy"):
                    # SDL fell back to an invisible driver: there is no real display.
                    pg.display.quit()
                    self._warn_headless(f"SDL video driver {driver!r}")
                    return
                self._window = pg.display.set_mode((self.width, self.height))
                pg.display.set_caption("aasoatt")
                self._clock = pg.time.Clock()
            except Exception as exc:  # noqa: BLE001 - any failure means: no window
                self._window = None
                self._warn_headless(str(exc) or type(exc).__name__)
                return
        try:
            for event in pg.event.get():
                if event.type == pg.QUIT:
                    self._closed_by_user = True
                    self.close()
                    return
            self._window.blit(surf, (0, 0))
            pg.display.flip()
            if self.fps and self._clock is not None:
                self._clock.tick(self.fps)
        except Exception as exc:  # noqa: BLE001
            self.close()
            self._warn_headless(str(exc) or type(exc).__name__)

    def close(self) -> None:
        """Close the window, if one is open.  Safe to call more than once."""
        if self._window is not None:
            self._window = None
            try:
                self._pg.display.quit()
            except Exception:  # noqa: BLE001  # pragma: no cover
                pass

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


ANIMATION_SUFFIXES: tuple[str, ...] = (".gif", ".mp4", ".mov", ".mkv", ".avi")
"""File suffixes :func:`save_animation` writes: ``.gif`` with imageio and Pillow, the videos (H.264)
with imageio-ffmpeg.  ``.webm`` (no H.264 in WebM) and ``.m4v`` (no imageio backend) are not offered."""


def animation_writer_missing(suffix: str) -> list[str]:
    """The packages (pip names) that writing an animation with ``suffix`` needs and that are not installed."""
    needs = ("imageio", "PIL") if suffix.lower() == ".gif" else ("imageio", "imageio_ffmpeg")
    pip = {"PIL": "Pillow", "imageio_ffmpeg": "imageio-ffmpeg"}
    return [pip.get(name, name) for name in needs if importlib.util.find_spec(name) is None]


def save_animation(frames: Sequence[np.ndarray], path: str | os.PathLike[str], fps: float = 20) -> Path:
    """Write RGB frames as an animation, GIF or video chosen by the file suffix.

    Parameters
    ----------
    frames : sequence of numpy.ndarray
        Images of shape ``(H, W, 3)`` (or ``(H, W, 4)``), all the same size;
        ``uint8``, or floats in ``[0, 1]``.
    path : str or os.PathLike
        Output file, one of :data:`ANIMATION_SUFFIXES`; ``.gif`` uses imageio with
        Pillow, the videos need imageio-ffmpeg.  The file is written under a temporary
        name beside it and moved into place when complete: a writer that fails leaves
        no partial file (and an earlier file at ``path`` is kept).
    fps : float
        Frames per second.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    ImportError
        If imageio (or, for videos, imageio-ffmpeg) is missing.
    ConfigError
        For an unsupported suffix, no frames, mismatched sizes or ``fps <= 0``.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in ANIMATION_SUFFIXES:
        raise ConfigError(f"save_animation: got suffix {path.suffix!r}, expected one of {list(ANIMATION_SUFFIXES)}")
    fps = float(fps)
    if not math.isfinite(fps) or fps <= 0:
        raise ConfigError(f"save_animation: got fps={fps}, expected a positive number")
    images = [_to_uint8(f, k) for k, f in enumerate(frames)]
    if not images:
        raise ConfigError("save_animation: got no frames, expected at least one")
    shape = images[0].shape
    for k, img in enumerate(images):
        if img.shape != shape:
            raise ConfigError(f"save_animation: frame {k} has shape {img.shape}, expected {shape} (frame 0)")
    iio = _require("imageio.v3", "save_animation")
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")  # same suffix: same writer
    try:
        _write_animation(iio, images, partial, suffix, fps)
        os.replace(partial, path)
    finally:
        if partial.exists():
            partial.unlink()
    return path


def _write_animation(iio: ModuleType, images: list[np.ndarray], path: Path, suffix: str, fps: float) -> None:
    """Write the frames to ``path`` (GIF or video by ``suffix``)."""
    shape = images[0].shape
    if suffix == ".gif":
        _require("PIL", "save_animation (GIF)")
        duration_ms = 1000.0 / fps
        iio.imwrite(path, np.stack(images), extension=".gif", duration=duration_ms, loop=0)
        return
    try:
        importlib.import_module("imageio_ffmpeg")
    except ImportError as exc:
        raise ImportError(
            f"save_animation: writing {suffix!r} video needs 'imageio-ffmpeg' "
            "(pip install imageio-ffmpeg); or save as '.gif' instead, which only needs imageio and Pillow"
        ) from exc
    # H.264/yuv420p needs even sizes: pad with background by at most one pixel.
    h, w = shape[:2]
    ph, pw = h % 2, w % 2
    if ph or pw:
        images = [np.pad(img, ((0, ph), (0, pw), (0, 0)), mode="edge") for img in images]
    iio_v2 = _require("imageio.v2", "save_animation")
    with iio_v2.get_writer(path, fps=fps, macro_block_size=1) as writer:
        for img in images:
            writer.append_data(img)


def _to_uint8(frame: np.ndarray, k: int) -> np.ndarray:
    arr = np.asarray(frame)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ConfigError(f"save_animation: frame {k} has shape {arr.shape}, expected (H, W, 3) or (H, W, 4)")
    if arr.dtype != np.uint8:
        if np.issubdtype(arr.dtype, np.floating):
            arr = np.rint(np.clip(np.nan_to_num(arr), 0.0, 1.0) * 255.0)
        arr = np.clip(arr, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(arr[..., :3])
