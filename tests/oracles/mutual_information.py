"""Mutual information of a landmark subset, from scratch, and its brute-force maximum: the references the MI greedy
(:func:`stages.estimation.landmark_selection.select_mutual_information`) is checked against. Tests and benchmarks only.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def mutual_information(
    info0: FloatArray, contributions: Sequence[tuple[npt.NDArray[np.int64], FloatArray]], subset: Sequence[int]
) -> float:
    """``F(A)`` from scratch (dense), for brute force and checks."""
    lam = info0.copy()
    for l_ in subset:
        cols, B = contributions[l_]
        lam[np.ix_(cols, cols)] += B
    return 0.5 * (np.linalg.slogdet(lam)[1] - np.linalg.slogdet(info0)[1])


def brute_force_mutual_information(
    info0: FloatArray, contributions: Sequence[tuple[npt.NDArray[np.int64], FloatArray]], budget: int
) -> tuple[float, tuple[int, ...]]:
    """Best ``F`` over all subsets of size ``budget`` (small problems only)."""
    best = (-np.inf, ())
    for sub in itertools.combinations(range(len(contributions)), budget):
        v = mutual_information(info0, contributions, sub)
        if v > best[0]:
            best = (v, sub)
    return best
