"""``circle_obstacles``: the circle swap among static disc obstacles (the paper's Fig. 5)."""

from __future__ import annotations

from typing import Any

import numpy as np

from aasoatt_env.sim.scenarios.circle_swap import CircleSwap

__all__ = ["CircleSwapObstacles", "FIG5_OBSTACLES"]

FIG5_OBSTACLES: tuple[tuple[float, float, float], ...] = ((0.0, 0.0, 0.6), (2.8, 1.6, 0.4), (-2.2, -2.6, 0.8))
"""The three obstacles of our Fig. 5 preset: ``(x, y, radius)``."""


class CircleSwapObstacles(CircleSwap):
    """Circle swap among static disc obstacles (default: 20 robots, :data:`FIG5_OBSTACLES`), as :class:`CircleSwap`."""

    name = "circle_obstacles"

    def __init__(self, num_robots: int = 20, obstacles: tuple[Any, Any] | None = None, **kwargs: Any) -> None:
        if obstacles is None:
            arr = np.array(FIG5_OBSTACLES)
            obstacles = (arr[:, :2], arr[:, 2])
        super().__init__(num_robots=num_robots, obstacles=obstacles, **kwargs)
