"""Odometry noise from the messages' covariances: dimensions that do not grow between two keyframes."""

from __future__ import annotations

import gtsam
import numpy as np

from stages.graph.config import GraphConfig
from stages.graph.models import PLANAR, SPATIAL
from stages.graph.odometry import message_cov, settings_cov, unobserved_dims


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
