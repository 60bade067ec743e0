"""Batched planar poses (stages/graph/se2.py) and the batched corrected odometry factors against GTSAM's Pose2 and
the one-factor path they replace."""

from __future__ import annotations

import gtsam
import numpy as np

from stages.graph import se2
from stages.graph.calibration import (
    _planar_whitened_residuals,
    _whitened_residual,
    corrected_factor,
    planar_corrected_factors,
)


def _row(p: gtsam.Pose2) -> list[float]:
    return [p.x(), p.y(), p.theta()]


def test_the_batched_operations_are_gtsams_pose2() -> None:
    """between, compose, Logmap, Expmap, retract and local on poses all round the circle (angles near ±π and
    below the small-angle cut included) give GTSAM's values to rounding."""
    rng = np.random.default_rng(7)
    n = 300
    a = np.column_stack([rng.normal(0, 3, n), rng.normal(0, 3, n), rng.uniform(-np.pi, np.pi, n)])
    b = np.column_stack([rng.normal(0, 3, n), rng.normal(0, 3, n), rng.uniform(-np.pi, np.pi, n)])
    v = np.column_stack([rng.normal(0, 1, n), rng.normal(0, 1, n), rng.uniform(-3, 3, n)])
    v[:5, 2] = [0.0, 1e-12, -1e-11, np.pi - 1e-9, -np.pi + 1e-9]
    for i in range(n):
        pa, pb = gtsam.Pose2(*a[i]), gtsam.Pose2(*b[i])
        assert np.allclose(se2.between(a[i : i + 1], b[i : i + 1])[0], _row(pa.between(pb)), atol=1e-12)
        assert np.allclose(se2.compose(a[i : i + 1], b[i : i + 1])[0], _row(pa.compose(pb)), atol=1e-12)
        assert np.allclose(se2.expmap(v[i : i + 1])[0], _row(gtsam.Pose2.Expmap(v[i])), atol=1e-12)
        assert np.allclose(se2.retract(a[i : i + 1], v[i : i + 1])[0], _row(pa.retract(v[i])), atol=1e-12)
        # Logmap and local where the angle is not near π (there the tangent vector's sign is rounding's choice)
        if abs(b[i, 2]) < 3.0:
            assert np.allclose(se2.logmap(b[i : i + 1])[0], gtsam.Pose2.Logmap(pb), atol=1e-9)
        if abs(pa.between(pb).theta()) < 3.0:
            assert np.allclose(se2.local(a[i : i + 1], b[i : i + 1])[0], pa.localCoordinates(pb), atol=1e-9)
    # exp and log invert each other
    assert np.allclose(se2.logmap(se2.expmap(v[np.abs(v[:, 2]) < 3.0])), v[np.abs(v[:, 2]) < 3.0], atol=1e-12)


def test_the_batched_corrected_factors_are_the_one_factor_path() -> None:
    """Corrected increments bit for bit, their covariances and whitened residuals to the finite differences'
    rounding (GTSAM's Logmap loses digits at the differences' tiny angles), for odometry-like increments."""
    rng = np.random.default_rng(8)
    n = 100
    M = np.column_stack([rng.normal(0.3, 0.2, n), rng.normal(0, 0.05, n), rng.normal(0, 0.3, n)])
    A = rng.normal(size=(n, 3, 3)) * 0.01
    covs = A @ A.transpose(0, 2, 1) + 1e-5 * np.eye(3)
    c = np.array([1.02, 0.985, 0.01])
    pred = M + rng.normal(0, 0.01, (n, 3))
    Z, C = planar_corrected_factors(M, covs, c)
    lam = np.array([0.5, 2.0, 1.3])  # the noise level per dimension scales both paths' covariances alike
    R = _planar_whitened_residuals(M, covs, c, pred, lam)
    for i in range(n):
        z, Ci = corrected_factor(M[i], covs[i], c, "planar")
        assert np.array_equal(z, Z[i])
        assert np.allclose(C[i], Ci, rtol=1e-5, atol=1e-5 * np.abs(Ci).max())
        r = _whitened_residual("planar", M[i], covs[i], c, gtsam.Pose2(*pred[i]), lam)
        assert np.allclose(R[i], r, rtol=1e-5, atol=1e-5 * np.abs(r).max())
