"""Uncertainty of evaluation results: Wilson score intervals for rates, mean and spread over seeds."""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["Z95", "spread", "wilson"]

Z95 = 1.959963984540054
"""The standard normal quantile of a two-sided 95% interval."""


def wilson(successes: float, trials: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a binomial rate ``successes / trials`` (95% by default).

    Unlike the normal approximation it stays inside ``[0, 1]`` and is informative at 0 and at
    ``trials`` successes (100 of 100 gives ``[0.963, 1]``), the cases that matter for success
    and collision rates.  Trials are assumed independent; ``(nan, nan)`` without trials.
    """
    if trials <= 0:
        return math.nan, math.nan
    p = min(max(successes / trials, 0.0), 1.0)
    z2 = z * z
    centre = (p + z2 / (2 * trials)) / (1 + z2 / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z2 / (4 * trials * trials)) / (1 + z2 / trials)
    lo = 0.0 if p == 0.0 else max(0.0, centre - half)  # (exact at the ends, not rounded off them)
    hi = 1.0 if p == 1.0 else min(1.0, centre + half)
    return lo, hi


def spread(values: Sequence[float]) -> dict[str, float]:
    """Mean, sample standard deviation, lowest and highest of ``values`` (e.g. one per training seed)."""
    vals = [float(v) for v in values if v is not None and math.isfinite(v)]
    if not vals:
        return {"mean": math.nan, "std": math.nan, "min": math.nan, "max": math.nan, "n": 0}
    mean = sum(vals) / len(vals)
    std = math.sqrt(sum((v - mean) ** 2 for v in vals) / (len(vals) - 1)) if len(vals) > 1 else 0.0
    return {"mean": mean, "std": std, "min": min(vals), "max": max(vals), "n": len(vals)}
