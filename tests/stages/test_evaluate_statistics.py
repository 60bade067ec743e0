"""Statistics over map realisations: the bootstrap interval's coverage, the sign test against a hand computation,
the Wilcoxon test against its exact null distribution, and the paired summary."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from stages.evaluate.statistics import bootstrap_interval, paired, sign_test, wilcoxon_test


def test_bootstrap_interval_covers_the_true_mean_at_about_the_stated_rate() -> None:
    # 400 synthetic studies of 30 realisations each, rates from Beta(2, 5) (true mean 2/7); the percentile
    # bootstrap is a little narrow at n = 30, so its coverage of a 95 % interval sits near 0.93-0.95
    rng = np.random.default_rng(3)
    true_mean = 2 / 7
    hits = 0
    studies = 400
    for k in range(studies):
        lo, hi = bootstrap_interval(rng.beta(2, 5, size=30), resamples=2000, seed=k)
        hits += lo <= true_mean <= hi
    coverage = hits / studies
    print("bootstrap coverage", coverage)
    assert 0.90 <= coverage <= 0.98
    # and a 50 % interval covers about half as often: the level is what sets the width
    hits50 = sum(
        (lambda iv: iv[0] <= true_mean <= iv[1])(bootstrap_interval(rng.beta(2, 5, 30), 0.5, 2000, seed=k))
        for k in range(studies)
    )
    assert 0.40 <= hits50 / studies <= 0.60


def test_bootstrap_interval_edge_cases() -> None:
    assert bootstrap_interval([0.25, 0.25, 0.25]) == (0.25, 0.25)
    assert all(math.isnan(x) for x in bootstrap_interval([float("nan")]))
    lo, hi = bootstrap_interval([0.0, 1.0, float("nan"), 0.0, 1.0], seed=1)
    assert 0.0 <= lo < 0.5 < hi <= 1.0
    assert bootstrap_interval([0.1, 0.4, 0.9], seed=5) == bootstrap_interval([0.1, 0.4, 0.9], seed=5)


def test_sign_test_matches_the_binomial_by_hand() -> None:
    # 9 positive, 2 negative, 3 ties: n = 11, P(X <= 2) = (1 + 11 + 55) / 2048, two-sided doubles it
    diffs = [0.1] * 9 + [-0.2] * 2 + [0.0] * 3
    assert sign_test(diffs) == pytest.approx(2 * 67 / 2048, rel=1e-12)
    assert sign_test([-x for x in diffs]) == pytest.approx(2 * 67 / 2048, rel=1e-12)
    # an even split is p = 1; all ties is no evidence
    assert sign_test([1.0, -1.0, 2.0, -2.0]) == pytest.approx(1.0)
    assert sign_test([0.0, 0.0]) == 1.0
    # 6 of 6 one way: 2 / 64
    assert sign_test([0.5] * 6) == pytest.approx(2 / 64)


def test_wilcoxon_matches_its_exact_null_distribution() -> None:
    # no ties, n = 6: enumerate the 64 sign patterns of ranks 1..6; p = P(min(W+, W-) <= observed) both tails
    diffs = np.array([0.5, -0.1, 0.9, 1.3, 0.7, 2.0])
    ranks = np.argsort(np.argsort(np.abs(diffs))) + 1
    w_plus = ranks[diffs > 0].sum()
    total = ranks.sum()
    stat = min(w_plus, total - w_plus)
    sums = [
        sum(r for r, s in zip(range(1, 7), signs, strict=True) if s) for signs in itertools.product([0, 1], repeat=6)
    ]
    p_exact = sum(1 for w in sums if min(w, total - w) <= stat) / 64
    assert wilcoxon_test(diffs) == pytest.approx(p_exact, rel=1e-12)
    assert wilcoxon_test(np.zeros(4)) == 1.0


def test_paired_counts_and_differences() -> None:
    a = np.array([0.1, 0.2, 0.0, 0.5, np.nan])
    b = np.array([0.3, 0.2, 0.4, 0.6, 0.1])
    p = paired(a, b, seed=0)
    assert (p.n, p.lower, p.higher, p.ties) == (4, 3, 0, 1)
    assert p.mean_diff == pytest.approx((-0.2 + 0.0 - 0.4 - 0.1) / 4)
    assert p.ci_low <= p.mean_diff <= p.ci_high <= 0.0
    assert p.sign_p == pytest.approx(2 / 8)
