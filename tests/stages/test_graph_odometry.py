"""Odometry noise from the messages' covariances: dimensions that do not grow between two keyframes."""

from __future__ import annotations

import gtsam
import numpy as np

from stages.graph.config import GraphConfig
from stages.graph.models import PLANAR, SPATIAL
from stages.graph.odometry import growth_model, message_cov, settings_cov, unobserved_dims


def _planar_run(n: int = 20, dt: float = 0.05, v: float = 0.4, sv: float = 0.002, sw: float = 0.0015):
    """Straight drive along x with the simulator's two noise sources (forward step, yaw step)."""
    poses, covs = [], []
    P = np.zeros((3, 3))
    x = yaw = 0.0
    for k in range(n):
        if k:
            F = np.array([[1, 0, -np.sin(yaw) * v * dt], [0, 1, np.cos(yaw) * v * dt], [0, 0, 1]])
            G = np.array([[np.cos(yaw), 0], [np.sin(yaw), 0], [0, 1]])
            P = F @ P @ F.T + G @ np.diag([sv**2, sw**2]) @ G.T
            x += v * dt
        C = np.diag([1e-9] * 6)
        idx = [3, 4, 2]  # x, y, yaw in gtsam's (r, t) order
        C[np.ix_(idx, idx)] = P
        poses.append(gtsam.Pose3(gtsam.Rot3.Yaw(yaw), np.array([x, 0.0, 0.0])))
        covs.append(C)
    return poses, np.array(covs)


def test_lateral_that_does_not_grow_keeps_the_messages_value_not_the_settings_centimetre() -> None:
    poses, covs = _planar_run()
    cfg = GraphConfig()
    unobserved = unobserved_dims(covs, PLANAR)
    assert not unobserved.any()  # x, y and yaw all grow somewhere in the run
    fallback = settings_cov(cfg, PLANAR, 0.02, 0.0)
    # the first step: the lateral variance has not grown yet (straight drive from rest)
    Q, fell_back = message_cov(PLANAR, poses[0], poses[1], covs[0], covs[1], fallback, unobserved)
    assert not fell_back
    assert np.isclose(Q[0, 0], covs[1][3, 3])
    assert np.sqrt(Q[1, 1]) < 0.05 * np.sqrt(Q[0, 0])  # bounded by the condition-number floor, not 1 cm
    assert np.sqrt(Q[1, 1]) < 1e-3
    assert np.linalg.cond(Q) <= 1.01e3


def test_unobserved_dimensions_take_the_settings_in_3d() -> None:
    poses, covs = _planar_run()
    cfg = GraphConfig(model="3d")
    unobserved = unobserved_dims(covs, SPATIAL)
    assert unobserved.tolist() == [True, True, False, False, False, True]  # roll, pitch, z
    fallback = settings_cov(cfg, SPATIAL, 0.02, 0.0)
    Q, fell_back = message_cov(SPATIAL, poses[3], poses[4], covs[3], covs[4], fallback, unobserved)
    assert fell_back
    for d in (0, 1, 5):
        assert np.isclose(Q[d, d], fallback[d, d])
        assert np.allclose(np.delete(Q[d], d), 0.0)
    assert np.isclose(Q[3, 3], 0.002**2)  # forward growth of one step, from the messages


def test_nothing_grew_falls_back_to_the_settings() -> None:
    poses, covs = _planar_run()
    cfg = GraphConfig()
    fallback = settings_cov(cfg, PLANAR, 0.0, 0.0)
    Q, fell_back = message_cov(PLANAR, poses[5], poses[5], covs[5], covs[5], fallback, np.zeros(3, dtype=bool))
    assert fell_back
    assert np.allclose(Q, fallback)


def _turning_run(diagonal: bool, n: int = 120, dt: float = 0.05, v: float = 0.4, w: float = 0.3):
    """A curved drive whose pose covariance is propagated through the motion, or (``diagonal``) summed on a diagonal
    without the position-heading terms, as some drivers and an independent simulator report it; and the variance
    the yaw of each step really adds."""
    sv, sw = 0.002, 0.0015
    poses, covs = [], []
    P = np.zeros((3, 3))
    x = y = yaw = 0.0
    for k in range(n):
        if k:
            F = np.array([[1, 0, -np.sin(yaw) * v * dt], [0, 1, np.cos(yaw) * v * dt], [0, 0, 1]])
            G = np.array([[np.cos(yaw), 0], [np.sin(yaw), 0], [0, 1]])
            step = G @ np.diag([sv**2, sw**2]) @ G.T
            P = P + np.diag(np.diag(step)) if diagonal else F @ P @ F.T + step
            x, y, yaw = x + np.cos(yaw) * v * dt, y + np.sin(yaw) * v * dt, yaw + w * dt
        C = np.diag([1e-9] * 6)
        idx = [3, 4, 2]
        C[np.ix_(idx, idx)] = P
        poses.append(gtsam.Pose3(gtsam.Rot3.Yaw(yaw), np.array([x, y, 0.0])))
        covs.append(C)
    return poses, np.array(covs), sw**2


def test_growth_model_reads_diagonal_covariances_as_summed_not_propagated() -> None:
    """Covariances summed on a diagonal (no lever arm) read as propagated gave every odometry factor a heading
    variance about 30 times too small on an independent simulator's run (the subtracted lever-arm term leaves a
    near rank-one position-heading block), which bent its map by 4 degrees. Each model is recognised, and the
    chosen one gives each step's heading variance as it grew."""
    cfg = GraphConfig()
    for diagonal in (False, True):
        poses, covs, yaw_var = _turning_run(diagonal)
        unobserved = unobserved_dims(covs, PLANAR)
        propagated, figures = growth_model(PLANAR, poses, covs, unobserved)
        assert propagated is (not diagonal), figures
        fallback = settings_cov(cfg, PLANAR, 0.02, 0.0)
        for i in (30, 60, 100):
            Q, _ = message_cov(PLANAR, poses[i], poses[i + 1], covs[i], covs[i + 1], fallback, unobserved, propagated)
            assert np.isclose(Q[2, 2], yaw_var, rtol=1e-6)
            corr = Q[1, 2] / np.sqrt(Q[1, 1] * Q[2, 2])
            assert abs(corr) < 0.9
    # the old reading of the diagonal run: a near rank-one lateral-heading block, so given the lateral step the
    # heading is known far better than it grew
    poses, covs, yaw_var = _turning_run(True)
    Q, _ = message_cov(PLANAR, poses[100], poses[101], covs[100], covs[101], fallback, unobserved_dims(covs, PLANAR))
    corr = Q[1, 2] / np.sqrt(Q[1, 1] * Q[2, 2])
    assert abs(corr) > 0.99
    assert Q[2, 2] * (1 - corr**2) < 0.1 * yaw_var
