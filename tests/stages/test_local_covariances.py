"""The map's local covariances held pair by pair (stages.risk.LocalCovariances): lookups and subsets give what the
dense (T, L, 2, 2) array with NaN for unseen pairs gave."""

from __future__ import annotations

import numpy as np

from stages.risk import LandmarkMap, LocalCovariances


def _random_pairs(rng: np.random.Generator, T: int, L: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    codes = rng.choice(T * L, size=n, replace=False)
    return codes // L, codes % L


def test_lookup_and_subset_match_a_dense_array() -> None:
    rng = np.random.default_rng(4)
    T, L = 40, 7
    kf, rows = _random_pairs(rng, T, L, 90)
    A = rng.normal(size=(90, 2, 2))
    covs = A @ np.swapaxes(A, 1, 2)
    dense = np.full((T, L, 2, 2), np.nan)
    dense[kf, rows] = covs
    held = LocalCovariances.from_pairs(kf, rows, covs, L)

    qk, qr = rng.integers(0, T, 500), rng.integers(0, L, 500)
    found, got = held.lookup(qk, qr)
    np.testing.assert_array_equal(found, np.isfinite(dense[qk, qr]).all(axis=(1, 2)))
    np.testing.assert_array_equal(got, dense[qk, qr])  # NaN where not held

    keep = np.zeros(L, dtype=bool)
    keep[[1, 4, 6]] = True
    sub = held.subset(keep)
    dense_sub = dense[:, keep]
    qr = rng.integers(0, 3, 500)
    found, got = sub.lookup(qk, qr)
    np.testing.assert_array_equal(found, np.isfinite(dense_sub[qk, qr]).all(axis=(1, 2)))
    np.testing.assert_array_equal(got, dense_sub[qk, qr])


def test_the_map_uses_local_covariances_where_held_and_marginals_elsewhere() -> None:
    marg = np.stack([np.eye(2) * 4.0, np.eye(2) * 9.0])
    held = LocalCovariances.from_pairs([3, 1], [1, 0], [np.eye(2), np.eye(2) * 2.0], 2)
    lm = LandmarkMap(np.array([10, 11]), np.zeros((2, 2)), marg, np.zeros(2), held)
    got = lm.covariance_at(np.array([1, 1, 3, 3, 0]), np.array([0, 1, 1, 0, 0]))
    np.testing.assert_array_equal(got[:, 0, 0], [2.0, 9.0, 1.0, 4.0, 4.0])
    sub = lm.subset([11])
    np.testing.assert_array_equal(sub.covariance_at(np.array([3, 1]), np.array([0, 0]))[:, 0, 0], [1.0, 9.0])


def test_no_pairs() -> None:
    held = LocalCovariances.from_pairs([], [], np.zeros((0, 2, 2)), 3)
    found, got = held.lookup(np.array([0, 2]), np.array([1, 2]))
    assert not found.any() and np.isnan(got).all()
