"""Confidence intervals for rates estimated from Monte Carlo trials."""

from __future__ import annotations

import math

from stages.estimation.normal import normal_ppf


def wilson_interval(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``successes / trials``.

    Unlike the normal approximation it stays inside [0, 1] and is not empty at 0 or ``trials``
    successes (0 collisions in 50 trials gives [0, 0.071] at 95 %). ``trials == 0`` gives (0, 1).
    """
    if trials <= 0:
        return 0.0, 1.0
    if not 0 <= successes <= trials:
        raise ValueError(f"successes {successes} outside [0, {trials}]")
    z = float(normal_ppf(0.5 + confidence / 2.0))
    p = successes / trials
    denom = 1.0 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denom
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == trials else min(1.0, centre + half)
    return lo, hi
