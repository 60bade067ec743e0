"""Statistics over map realisations: per case a bootstrap interval of the mean, and paired tests between cases.

```python
lo, hi = bootstrap_interval(rates, seed=0)            # percentile bootstrap of the mean over realisations
p = sign_test(diffs)                                  # exact two-sided binomial test on the signs (ties dropped)
pair = paired(focus_info_rates, other_rates, seed=0)  # mean difference, its interval, wins, sign and Wilcoxon p
```

The realisations are the unit: each one redraws the map (and re-runs the navigation), so two cases' values in the
same realisation are paired (same measurements, same navigation seed) and different realisations are independent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
RESAMPLES = 10_000
"""Bootstrap resamples."""


def _finite(values: npt.ArrayLike) -> FloatArray:
    v = np.asarray(values, dtype=float).ravel()
    return v[np.isfinite(v)]


def bootstrap_interval(
    values: npt.ArrayLike, confidence: float = 0.95, resamples: int = RESAMPLES, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of ``values`` (NaNs dropped): the ``(1 ± confidence) / 2``
    quantiles of the means of ``resamples`` resamples with replacement. (NaN, NaN) without values."""
    v = _finite(values)
    if len(v) == 0:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    means = v[rng.integers(0, len(v), size=(resamples, len(v)))].mean(axis=1)
    a = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(means, [a, 1.0 - a])
    return float(lo), float(hi)


def sign_test(diffs: npt.ArrayLike) -> float:
    """Two-sided exact sign test of median 0: ties (zeros) dropped, ``P`` of a split at least as uneven as the
    observed one under Binomial(n, ½). 1.0 when every difference is 0 (or there are none)."""
    d = _finite(diffs)
    d = d[d != 0]
    if len(d) == 0:
        return 1.0
    from scipy import stats  # imported here: 0.6 s, for evaluate's realisations only

    return float(stats.binomtest(int((d > 0).sum()), len(d), 0.5).pvalue)


def wilcoxon_test(diffs: npt.ArrayLike) -> float:
    """Two-sided Wilcoxon signed-rank p-value of median 0 (zeros dropped, scipy's ``wilcox`` rule; exact for small
    samples without ties, else the normal approximation). 1.0 when every difference is 0 (or there are none)."""
    d = _finite(diffs)
    d = d[d != 0]
    if len(d) == 0:
        return 1.0
    from scipy import stats

    return float(stats.wilcoxon(d, zero_method="wilcox", alternative="two-sided").pvalue)


@dataclass(frozen=True)
class Paired:
    """``a − b`` over the realisations where both are finite."""

    n: int
    mean_diff: float
    ci_low: float
    ci_high: float
    lower: int
    """Realisations where ``a < b``."""
    higher: int
    ties: int
    sign_p: float
    wilcoxon_p: float


def paired(a: npt.ArrayLike, b: npt.ArrayLike, confidence: float = 0.95, seed: int = 0) -> Paired:
    """The paired comparison of ``a`` against ``b`` (same realisation, same index)."""
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    d = x[ok] - y[ok]
    lo, hi = bootstrap_interval(d, confidence, seed=seed)
    return Paired(
        n=len(d),
        mean_diff=float(d.mean()) if len(d) else float("nan"),
        ci_low=lo,
        ci_high=hi,
        lower=int((d < 0).sum()),
        higher=int((d > 0).sum()),
        ties=int((d == 0).sum()),
        sign_p=sign_test(d),
        wilcoxon_p=wilcoxon_test(d),
    )
