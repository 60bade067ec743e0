"""Two checks of each case's numbers against each other: the entropy split, and the risk model against the simulation.

* :func:`entropy_split`: the focused entropy is the entropy of the observed focused landmarks plus an independent
  prior part, one fixed term per focused landmark the case does not observe (``optimize.unobserved_sigma_m``,
  100 m by default: about +19 nats each). The split shows how much of a case's figure is the prior's.
* :func:`predicted_path_probability`: the risk model gives a collision probability ``P_t`` per keyframe; the
  probability that the robot collides *somewhere* on the path lies in ``[max_t P_t, min(1, Σ_t P_t)]``: at least
  the riskiest keyframe's, at most the union bound.
* :func:`disagrees`: the simulated collision rate (a Wilson 95 % interval over the trials) disagrees with the
  risk model by orders of magnitude when the interval lies more than :data:`FACTOR` times outside that bracket:
  its low end above ``FACTOR × Σ_t P_t``, or its high end below ``max_t P_t / FACTOR``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from stages.evaluate import artifacts as art

FACTOR: Final = 10.0
"""How far outside the risk model's bracket the simulated rate's interval must lie to be flagged."""


def entropy_split(
    focused_entropy: float, focused_entropy_observed: float, n_focus: int, n_observed_focus: int
) -> tuple[int, float]:
    """``(unobserved focused landmarks, the prior's part of the focused entropy in nats)``."""
    return n_focus - n_observed_focus, float(focused_entropy - focused_entropy_observed)


def predicted_path_probability(p_collision: npt.ArrayLike) -> tuple[float, float]:
    """``(max_t P_t, min(1, Σ_t P_t))`` over the finite per-keyframe probabilities; NaN, NaN when there are none."""
    p = np.asarray(p_collision, dtype=float).reshape(-1)
    p = p[np.isfinite(p)]
    if len(p) == 0:
        return float("nan"), float("nan")
    return float(p.max()), float(min(1.0, p.sum()))


def disagrees(low: float, high: float, ci_low: float, ci_high: float, factor: float = FACTOR) -> bool | None:
    """Whether the simulated rate's interval ``[ci_low, ci_high]`` lies more than ``factor`` times outside the
    predicted bracket ``[low, high]``; None when either is not available (NaN)."""
    if not all(math.isfinite(v) for v in (low, high, ci_low, ci_high)):
        return None
    return bool(ci_low > factor * high or ci_high < low / factor)


def direction(low: float, high: float, ci_low: float, ci_high: float, factor: float = FACTOR) -> str:
    """Which side the simulation falls on when it disagrees: ``above``, ``below``, else empty."""
    if disagrees(low, high, ci_low, ci_high, factor) is not True:
        return ""
    return "above" if ci_low > factor * high else "below"


def check_columns(
    row: Mapping[str, Any], p_collision: npt.ArrayLike, n_focus: int
) -> dict[str, float | int | bool | None]:
    """The :data:`~stages.evaluate.artifacts.CHECK_COLUMNS` of one case, from its row of ``cases.parquet`` (its
    entropies, focused landmarks and collision interval), its per-keyframe ``p_collision`` and the size of the
    focused set."""
    n_unobserved, prior = entropy_split(
        float(row[art.FOCUSED_ENTROPY]),
        float(row[art.FOCUSED_ENTROPY_OBSERVED]),
        n_focus,
        int(row[art.FOCUSED_LANDMARKS]),
    )
    low, high = predicted_path_probability(p_collision)
    rate_known = bool(row.get(art.TRIALS))
    ci_low = float(row[art.COLLISION_CI_LOW]) if rate_known else float("nan")
    ci_high = float(row[art.COLLISION_CI_HIGH]) if rate_known else float("nan")
    return {
        art.UNOBSERVED_FOCUSED: n_unobserved,
        art.FOCUSED_ENTROPY_PRIOR: prior,
        art.PREDICTED_COLLISION_LOW: low,
        art.PREDICTED_COLLISION_HIGH: high,
        art.RISK_DISAGREES: disagrees(low, high, ci_low, ci_high),
    }
