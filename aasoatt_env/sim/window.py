"""The window of ``render_mode="human"``: shows rendered pygame surfaces, and says once where there is no display."""

from __future__ import annotations

import os
import sys
import warnings
from types import ModuleType
from typing import Any

__all__ = ["Window"]


def _display_available() -> bool:
    """Best guess whether a window can be opened (no display server -> False)."""
    if os.environ.get("SDL_VIDEODRIVER", "").lower() in ("dummy", "offscreen"):
        return False
    if sys.platform.startswith("linux") or "bsd" in sys.platform:
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


class Window:
    """A pygame window opened at the first :meth:`show`; without a display: one ``RuntimeWarning``, nothing else."""

    def __init__(self, pg: ModuleType, width: int, height: int) -> None:
        self._pg, self.width, self.height = pg, width, height
        self._window: Any = None
        self._clock: Any = None
        self._headless = self._closed_by_user = False

    def _warn_headless(self, reason: str) -> None:
        """Warn once: after this, :meth:`show` returns at once (``_headless``) and never warns again."""
        self._headless = True
        warnings.warn(f"Renderer.show: no display available ({reason}); render_mode='human' does nothing. "
                      "Use render_mode='rgb_array' to get images.", RuntimeWarning, stacklevel=4)

    def _open(self) -> bool:
        """Open the window; False (and a warning, once) where there is no display."""
        pg = self._pg
        if not _display_available():
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

    def show(self, surface: Any, fps: float | None = None) -> None:
        """Show ``surface``, at most ``fps`` times a second."""
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
            if fps and self._clock is not None:
                self._clock.tick(fps)
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
