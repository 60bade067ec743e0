"""Differential entropy of a Gaussian, the one formula every stage reports its focused entropy with.

``H = ½ log det(2πe Σ) = ½ (log det Σ + d log(2πe))`` nats, ``d`` the dimension of ``Σ``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

LOG_2PI_E = float(np.log(2.0 * np.pi * np.e))
"""``log(2πe)``: the entropy of a unit-variance Gaussian is ``½ log(2πe)`` nats per dimension."""


def entropy_from_logdet(logdet_cov: float, dim: int) -> float:
    """Entropy (nats) of a ``dim``-dimensional Gaussian whose covariance has log-determinant ``logdet_cov``."""
    return 0.5 * (logdet_cov + dim * LOG_2PI_E)


def gaussian_entropy(cov: FloatArray) -> float:
    """``½ log det(2πe Σ)`` nats of a dense covariance (0 for an empty matrix, -inf if not positive definite)."""
    d = cov.shape[0]
    if d == 0:
        return 0.0
    sign, logdet = np.linalg.slogdet(0.5 * (cov + cov.T))
    if sign <= 0:
        return float("-inf")
    return entropy_from_logdet(float(logdet), d)
