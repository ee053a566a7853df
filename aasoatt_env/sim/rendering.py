"""Headless-safe rendering of :class:`Frame` s to RGB arrays, a window or an animation (``aasoatt[render]``)."""

from __future__ import annotations

import colorsys
import contextlib
import importlib
import importlib.util
import math
import os
import sys
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.cli_support import staged
from aasoatt_env.errors import ConfigError

__all__ = ["ANIMATION_SUFFIXES", "BACKGROUND", "Frame", "Renderer", "animation_writer_missing", "robot_colors",
           "save_animation"]

Color = tuple[int, int, int]
BACKGROUND: Color = (255, 255, 255)
"""Background colour of rendered frames (RGB)."""
GRID_COLOR, BOUNDS_COLOR, TEXT_COLOR, AVOID_COLOR = (232, 232, 232), (190, 190, 190), (30, 30, 30), (220, 20, 20)
OBSTACLE_FILL, OBSTACLE_EDGE = (140, 140, 140), (90, 90, 90)
_PALETTE: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (148, 103, 189), (140, 86, 75), (227, 119, 194),
    (127, 127, 127), (188, 189, 34), (23, 190, 207), (0, 0, 128), (0, 128, 128), (128, 128, 0),
    (255, 187, 120), (152, 223, 138), (174, 199, 232), (197, 176, 213), (196, 156, 148), (247, 182, 210),
    (219, 219, 141), (158, 218, 229),
)  # Tableau-like, without the red that marks robots in collision avoidance


def robot_colors(n: int) -> np.ndarray:
    """Distinct, deterministic RGB colours ``(n, 3)`` ``uint8``: a fixed palette, then golden-angle hues (no red)."""
    hues = 0.04 + 0.92 * ((0.1 + 0.618033988749895 * np.arange(max(n, 0))) % 1.0)  # away from red (+-0.04 around 0)
    out = [_PALETTE[i] if i < len(_PALETTE) else [int(c * 255) for c in
                                                  colorsys.hsv_to_rgb(h, 0.75, 0.85 if i % 2 else 0.65)]
           for i, h in enumerate(hues.tolist())]
    return np.array(out, dtype=np.uint8).reshape(-1, 3)


def _require(module: str, feature: str) -> ModuleType:
    if module == "pygame":
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImportError(f"{feature} needs the optional dependency {module.split('.')[0]!r}, which is not installed; "
                          'install the rendering extras with: pip install "aasoatt[render]"') from exc


def _as_array(name: str, value: Any, shape: tuple[int | str, ...], dtype: type = np.float64) -> np.ndarray:
    """``Frame.<name>`` as an array of ``shape`` (a letter: any size; no data at all: zero rows)."""
    arr = np.asarray(value, dtype=dtype)
    if arr.size == 0 and shape[0] in ("N", "T", 0):
        return arr.reshape((0, *shape[1:]))
    if arr.ndim != len(shape) or any(isinstance(want, int) and got != want for got, want in zip(arr.shape, shape)):
        exp = "(" + ", ".join(map(str, shape)) + (",)" if len(shape) == 1 else ")")
        raise ConfigError(f"Frame.{name}: got shape {arr.shape}, expected {exp}")
    return arr


@dataclass
class Frame:
    """Everything one picture shows: discs at ``positions (N, 2)`` [m] with ``headings (N,)`` and ``radii (N,)``.

    Optional: ``references`` (dots) and ``goals`` (squares) ``(N, 2)``; obstacles ``(M, 2)``, ``(M,)``;
    ``trails (T, N, 2)``, oldest first; ``avoiding (N,)`` bool (a red outline); ``sensing_range`` [m] (a faint
    circle); ``time`` [s] and ``title`` (printed); ``world_bounds`` ``(xmin, xmax, ymin, ymax)`` (None: fit all).
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
        self.positions = _as_array("positions", self.positions, ("N", 2))
        n = self.positions.shape[0]
        self.headings = _as_array("headings", np.broadcast_to(self.headings, (n,)), (n,))
        self.radii = _as_array("radii", np.broadcast_to(self.radii, (n,)), (n,))
        centers = np.zeros((0, 2)) if self.obstacle_centers is None else self.obstacle_centers
        self.obstacle_centers = _as_array("obstacle_centers", centers, ("N", 2))
        m = self.obstacle_centers.shape[0]
        radii = np.zeros(0) if self.obstacle_radii is None else np.broadcast_to(self.obstacle_radii, (m,))
        self.obstacle_radii = _as_array("obstacle_radii", radii, (m,))
        for name, shape, dtype in (("references", (n, 2), float), ("goals", (n, 2), float),
                                   ("trails", ("T", n, 2), float), ("avoiding", (n,), bool)):
            if getattr(self, name) is not None:
                setattr(self, name, _as_array(name, getattr(self, name), shape, dtype))
        self.sensing_range = None if self.sensing_range is None else float(self.sensing_range)
        self.time = float(self.time)
        if self.world_bounds is not None:
            b = tuple(float(v) for v in self.world_bounds)
            if len(b) != 4 or not all(math.isfinite(v) for v in b) or b[1] <= b[0] or b[3] <= b[2]:
                raise ConfigError(f"Frame.world_bounds: got {self.world_bounds!r}, expected finite "
                                  "(xmin, xmax, ymin, ymax) with xmin < xmax and ymin < ymax")
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
        pts += [extra for extra in (self.references, self.goals) if extra is not None]
        if self.obstacle_centers.shape[0]:
            r = self.obstacle_radii[:, None]
            pts += [self.obstacle_centers - r, self.obstacle_centers + r]
        if self.trails is not None:
            pts.append(np.asarray(self.trails).reshape(-1, 2))
        allp = np.concatenate(pts, axis=0)
        allp = allp[np.all(np.isfinite(allp), axis=1)]
        if allp.shape[0] == 0:
            return (-1.0, 1.0, -1.0, 1.0)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        pad = margin * max(float(np.max(hi - lo)), 1.0)
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
        return np.stack((self.ox + p[..., 0] * self.scale, self.oy - p[..., 1] * self.scale), axis=-1)


def _mix(color: Sequence[int], other: Sequence[int], t: float) -> tuple[int, int, int]:
    """Blend ``t`` of ``other`` into ``color``."""
    return tuple(int(round((1.0 - t) * c + t * o)) for c, o in zip(color, other))  # type: ignore[return-value]


def _pixels(tf: _Transform, points: np.ndarray | None) -> Iterator[tuple[int, tuple[int, int]]]:
    """``(i, rounded pixel)`` of each finite world point ``i`` of ``points`` (None: none)."""
    for i, c in enumerate(() if points is None else tf.points(points)):
        if np.all(np.isfinite(c)):
            yield i, (int(round(c[0])), int(round(c[1])))


def _nice_step(span: float) -> float:
    raw = span / 10  # about ten grid lines, at a step of 1, 2 or 5 times a power of ten
    mag = 10.0 ** math.floor(math.log10(raw))
    return next((m * mag for m in (1.0, 2.0, 5.0, 10.0) if raw <= m * mag), 10.0 * mag)


class Renderer:
    """Rasterise :class:`Frame` s to ``width x height`` pixels with pygame surfaces (no display needed).

    ``grid``: a metric grid and the outline of ``world_bounds``; ``show_text``: the time and title;
    ``fps``: the most window updates a second in :meth:`show`.
    """

    def __init__(self, width: int = 600, height: int = 600, *, grid: bool = True, show_text: bool = True,
                 fps: float | None = None) -> None:
        if int(width) <= 0 or int(height) <= 0:
            raise ConfigError(f"Renderer: got size {width}x{height}, expected positive width and height")
        self.width, self.height = int(width), int(height)
        self.grid, self.show_text, self.fps = bool(grid), bool(show_text), fps
        self._pg = _require("pygame", "Renderer")
        self._gfx = importlib.import_module("pygame.gfxdraw")  # (part of every pygame)
        self._surface = self._pg.Surface((self.width, self.height))
        self._font: Any = None  # False: no font available
        self._window: Any = None  # render_mode="human": opened at the first show
        self._clock: Any = None
        self._headless = self._closed_by_user = False

    def _get_font(self) -> Any:
        if self._font is None:
            try:
                self._pg.font.init()  # (a no-op when initialised)
                self._font = self._pg.font.Font(None, max(12, min(self.width, self.height) // 28))
            except Exception:  # noqa: BLE001 - fonts are optional decoration
                self._font = False
        return self._font or None

    def _circle(self, c: np.ndarray, r: int, color: Sequence[int], edge: Sequence[int] | None = None, *,
                fill: bool = True) -> None:
        """A disc (anti-aliased rim ``edge``) or, with ``fill=False``, a thin anti-aliased circle."""
        x, y = int(c[0]), int(c[1])
        gfx = self._gfx
        if r >= 1 and abs(x) + r < 32000 and abs(y) + r < 32000:
            if fill:
                gfx.filled_circle(self._surface, x, y, r, color)
            gfx.aacircle(self._surface, x, y, r, edge if edge is not None else color)
        elif fill:
            self._pg.draw.circle(self._surface, color, (x, y), max(r, 1))
            if edge is not None:
                self._pg.draw.circle(self._surface, edge, (x, y), max(r, 1), 1)
        else:
            self._pg.draw.circle(self._surface, color, (x, y), r, 1)

    def _visible(self, c: np.ndarray, r: float) -> bool:
        return -r <= c[0] <= self.width + r and -r <= c[1] <= self.height + r

    def _draw_grid(self, tf: _Transform, bounds: tuple[float, float, float, float]) -> None:
        pg, surf = self._pg, self._surface
        xmin, xmax, ymin, ymax = bounds
        step = _nice_step(max(xmax - xmin, ymax - ymin))
        for gx in np.arange(math.ceil(xmin / step) * step, xmax + 1e-9, step):
            px = int(round(tf.ox + gx * tf.scale))
            pg.draw.line(surf, GRID_COLOR, (px, 0), (px, self.height - 1))
        for gy in np.arange(math.ceil(ymin / step) * step, ymax + 1e-9, step):
            py = int(round(tf.oy - gy * tf.scale))
            pg.draw.line(surf, GRID_COLOR, (0, py), (self.width - 1, py))
        (x0, y0), (x1, y1) = np.rint(tf.points(np.array([[xmin, ymax], [xmax, ymin]]))).astype(int).tolist()
        pg.draw.rect(surf, BOUNDS_COLOR, pg.Rect(x0, y0, x1 - x0, y1 - y0), 1)  # (inside the image)

    def _draw_trails(self, tf: _Transform, trails: np.ndarray, colors: list[Color]) -> None:
        if trails.shape[0] < 2:
            return
        pix = tf.points(trails)  # (T, N, 2)
        finite = np.all(np.isfinite(pix), axis=2)
        pix = np.clip(np.nan_to_num(pix), -tf.limit, tf.limit)
        for i in range(trails.shape[1]):
            idx = np.flatnonzero(finite[:, i])  # the finite samples, drawn as runs of consecutive ones
            for seg in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
                run = pix[seg, i]
                if run.shape[0] >= 2:
                    self._pg.draw.aalines(self._surface, _mix(colors[i], BACKGROUND, 0.35), False, run.tolist())

    def _draw_marks(self, frame: Frame, tf: _Transform, pos: np.ndarray, finite: np.ndarray, rpix: np.ndarray,
                    colors: list[Color]) -> None:
        """Sensing ranges (faint circles) and goals (hollow squares), under the robots."""
        pg = self._pg
        if frame.sensing_range is not None and frame.sensing_range > 0:
            rs = max(1, int(round(frame.sensing_range * tf.scale)))
            for i in range(frame.n):
                if finite[i] and self._visible(pos[i], rs) and rs < 32000:
                    self._circle(np.rint(pos[i]).astype(int), rs, _mix(colors[i], BACKGROUND, 0.7), fill=False)
        for i, (x, y) in _pixels(tf, frame.goals):
            h = max(4, int(round(0.35 * rpix[i])))
            pg.draw.rect(self._surface, colors[i], pg.Rect(x - h, y - h, 2 * h + 1, 2 * h + 1), 2)

    def _draw_robots(self, frame: Frame, pos: np.ndarray, finite: np.ndarray, rpix: np.ndarray,
                     colors: list[Color]) -> None:
        pg, surf = self._pg, self._surface
        avoiding = frame.avoiding if frame.avoiding is not None else np.zeros(frame.n, dtype=bool)
        for i in range(frame.n):
            if not finite[i] or not self._visible(pos[i], rpix[i]):
                continue
            color = colors[i]
            dark = _mix(color, (0, 0, 0), 0.55)
            c = np.rint(pos[i])
            r = int(rpix[i])
            self._circle(c, r, color, dark)
            th = frame.headings[i]
            if math.isfinite(th):
                tip = (round(pos[i, 0] + rpix[i] * math.cos(th)), round(pos[i, 1] - rpix[i] * math.sin(th)))
                pg.draw.line(surf, dark, (int(c[0]), int(c[1])), tip, max(1, r // 8))
            if avoiding[i]:
                pg.draw.circle(surf, AVOID_COLOR, (int(c[0]), int(c[1])), r + 1, max(2, min(4, r // 5)))

    def _draw_references(self, frame: Frame, tf: _Transform, rpix: np.ndarray, colors: list[Color]) -> None:
        for i, c in _pixels(tf, frame.references):
            s = max(3, int(round(0.15 * rpix[i])))
            self._pg.draw.circle(self._surface, _mix(colors[i], (0, 0, 0), 0.6), c, s + 1)
            self._pg.draw.circle(self._surface, colors[i], c, s)

    def draw(self, frame: Frame) -> Any:
        """Draw ``frame`` on the internal surface and return it (a ``pygame.Surface``)."""
        if not isinstance(frame, Frame):
            raise ConfigError(f"Renderer: got {type(frame).__name__}, expected a Frame")
        self._surface.fill(BACKGROUND)
        bounds = frame.bounds()
        tf = _Transform(bounds, self.width, self.height)
        colors = [tuple(int(v) for v in c) for c in robot_colors(frame.n)]
        if self.grid:
            self._draw_grid(tf, bounds)
        for c, r in zip(tf.points(frame.obstacle_centers), frame.obstacle_radii):
            rp = max(1, int(round(r * tf.scale)))
            if np.all(np.isfinite(c)) and self._visible(c, rp):
                self._circle(np.rint(c), rp, OBSTACLE_FILL, OBSTACLE_EDGE)
        if frame.trails is not None and frame.n:
            self._draw_trails(tf, np.asarray(frame.trails), colors)
        pos = tf.points(frame.positions)
        finite = np.all(np.isfinite(pos), axis=1)
        rpix = np.maximum(2, np.rint(frame.radii * tf.scale)).astype(int)
        self._draw_marks(frame, tf, pos, finite, rpix, colors)
        self._draw_robots(frame, pos, finite, rpix, colors)
        self._draw_references(frame, tf, rpix, colors)
        font = self._get_font() if self.show_text else None
        if font is not None:
            self._surface.blit(font.render(f"t = {frame.time:.2f} s", True, TEXT_COLOR), (6, 4))
            if frame.title:
                label = font.render(str(frame.title), True, TEXT_COLOR)
                self._surface.blit(label, ((self.width - label.get_width()) // 2, 4))
        return self._surface

    def rgb_array(self, frame: Frame) -> np.ndarray:
        """Render ``frame`` to an ``(height, width, 3)`` ``uint8`` RGB image."""
        raw = self._pg.image.tobytes(self.draw(frame), "RGB")
        return np.frombuffer(raw, dtype=np.uint8).reshape(self.height, self.width, 3).copy()

    def _warn_headless(self, reason: str) -> None:
        """Warn once: after this, :meth:`show` returns at once (``_headless``) and never warns again."""
        self._headless = True
        warnings.warn(f"Renderer.show: no display available ({reason}); render_mode='human' does nothing. "
                      "Use render_mode='rgb_array' to get images.", RuntimeWarning, stacklevel=4)

    def _open(self) -> bool:
        """Open the window; False (and a warning, once) where there is no display."""
        pg = self._pg
        if os.environ.get("SDL_VIDEODRIVER", "").lower() in ("dummy", "offscreen") or (
                (sys.platform.startswith("linux") or "bsd" in sys.platform)
                and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))):
            self._warn_headless("no DISPLAY/WAYLAND_DISPLAY, or a dummy SDL video driver")
            return False
        try:
            pg.display.init()
            driver = pg.display.get_driver()
            if driver in ("offscreen", "dummy"):  # SDL fell back to an invisible driver: no real display
                pg.display.quit()
                self._warn_headless(f"SDL video driver {driver!r}")
                return False
            self._window = pg.display.set_mode((self.width, self.height))
            pg.display.set_caption("aasoatt")
            self._clock = pg.time.Clock()
        except Exception as exc:  # noqa: BLE001 - any failure means: no window
            self._window = None
            self._warn_headless(str(exc) or type(exc).__name__)
            return False
        return True

    def show(self, frame: Frame) -> None:
        """Show ``frame`` in a window (``render_mode="human"``, at most ``fps`` a second); headless: a warning, once."""
        surface = self.draw(frame)
        if self._headless or self._closed_by_user or (self._window is None and not self._open()):
            return
        pg = self._pg
        try:
            for event in pg.event.get():
                if event.type == pg.QUIT:
                    self._closed_by_user = True
                    self.close()
                    return
            self._window.blit(surface, (0, 0))
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
            with contextlib.suppress(Exception):
                self._pg.display.quit()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


ANIMATION_SUFFIXES: tuple[str, ...] = (".gif", ".mp4", ".mov", ".mkv", ".avi")
"""Suffixes :func:`save_animation` writes: ``.gif`` (imageio and Pillow), H.264 videos (imageio-ffmpeg)."""


def animation_writer_missing(suffix: str) -> list[str]:
    """The packages (pip names) that writing an animation with ``suffix`` needs and that are not installed."""
    needs = ("imageio", "PIL") if suffix.lower() == ".gif" else ("imageio", "imageio_ffmpeg")
    pip = {"PIL": "Pillow", "imageio_ffmpeg": "imageio-ffmpeg"}
    return [pip.get(name, name) for name in needs if importlib.util.find_spec(name) is None]


def save_animation(frames: Sequence[np.ndarray], path: str | os.PathLike[str], fps: float = 20) -> Path:
    """Write RGB frames ``(H, W, 3 or 4)`` (``uint8``, or floats in ``[0, 1]``) as a GIF or video; returns the path.

    The suffix (:data:`ANIMATION_SUFFIXES`) picks the format (a missing writer: ``ImportError``); the file is
    written beside ``path`` and moved into place when complete (a failure leaves no partial file).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in ANIMATION_SUFFIXES:
        raise ConfigError(f"save_animation: got suffix {path.suffix!r}, expected one of {list(ANIMATION_SUFFIXES)}")
    fps = check.positive("save_animation: fps", fps)
    images = [_to_uint8(f, k) for k, f in enumerate(frames)]
    if not images:
        raise ConfigError("save_animation: got no frames, expected at least one")
    for k, img in enumerate(images):
        if img.shape != images[0].shape:
            raise ConfigError(f"save_animation: frame {k} has shape {img.shape}, expected {images[0].shape} (frame 0)")
    iio = _require("imageio.v3", "save_animation")
    path.parent.mkdir(parents=True, exist_ok=True)
    with staged(path) as (partial,):  # the same suffix: the same writer
        _write_animation(iio, images, partial, suffix, fps)
    return path


def _write_animation(iio: ModuleType, images: list[np.ndarray], path: Path, suffix: str, fps: float) -> None:
    if suffix == ".gif":
        _require("PIL", "save_animation (GIF)")
        iio.imwrite(path, np.stack(images), extension=".gif", duration=1000.0 / fps, loop=0)
        return
    try:
        importlib.import_module("imageio_ffmpeg")
    except ImportError as exc:
        raise ImportError(f"save_animation: writing {suffix!r} video needs 'imageio-ffmpeg' (pip install "
                          "imageio-ffmpeg); or save as '.gif' instead, which only needs imageio and Pillow") from exc
    h, w = images[0].shape[:2]  # H.264/yuv420p needs even sizes: pad by at most one pixel
    if h % 2 or w % 2:
        images = [np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") for img in images]
    with _require("imageio.v2", "save_animation").get_writer(path, fps=fps, macro_block_size=1) as writer:
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
