"""The one Gaussian-entropy formula: against the density's own integral and in its edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from stages.estimation.gaussian import LOG_2PI_E, entropy_from_logdet, gaussian_entropy


def test_entropy_equals_the_expected_negative_log_density() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    cov = A @ A.T + 0.5 * np.eye(3)
    x = rng.multivariate_normal(np.zeros(3), cov, size=400_000)
    inv = np.linalg.inv(cov)
    neg_log_p = 0.5 * (np.einsum("ni,ij,nj->n", x, inv, x) + np.linalg.slogdet(2 * np.pi * cov)[1])
    h = gaussian_entropy(cov)
    assert h == pytest.approx(neg_log_p.mean(), abs=4 * neg_log_p.std() / np.sqrt(len(x)))
    assert h == pytest.approx(entropy_from_logdet(np.linalg.slogdet(cov)[1], 3), rel=1e-14)


def test_entropy_edge_cases() -> None:
    assert gaussian_entropy(np.zeros((0, 0))) == 0.0
    assert gaussian_entropy(np.diag([1.0, 0.0])) == -np.inf
    assert entropy_from_logdet(0.0, 1) == pytest.approx(0.5 * np.log(2 * np.pi * np.e))
    assert np.log(2 * np.pi) + 1.0 == pytest.approx(LOG_2PI_E)
