"""Synthetic planar SLAM problems (a robot driving loops among point landmarks), for tests and benchmarks.

Ground truth is used as the linearisation point, as the selection stages linearise once at the
full-graph solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
import numpy.typing as npt
from gtsam.symbol_shorthand import L, X

FloatArray = npt.NDArray[np.float64]


@dataclass
class PlanarProblem:
    """A planar pose + point-landmark factor graph with its ground truth."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    poses: FloatArray
    """(T, 3) x, y, θ."""
    landmarks: FloatArray
    """(n_landmarks, 2); only the measured ones are in ``values`` (all when ``n_measurements ≥ n_landmarks``)."""
    measurement_factors: list[int]
    """Indices (in ``graph``) of the bearing-range factors, in time order."""
    measured: list[tuple[int, int]]
    """(pose index, landmark index) of each measurement factor."""


def planar_problem(
    n_poses: int,
    n_landmarks: int,
    n_measurements: int,
    seed: int = 0,
    extent: float = 60.0,
    sensor_range: float = 15.0,
    odometry_sigmas: tuple[float, float, float] = (0.05, 0.05, 0.01),
    bearing_range_sigmas: tuple[float, float] = (0.02, 0.10),
) -> PlanarProblem:
    """A robot on a smooth random closed-ish path; each measurement joins a pose and a landmark in range.

    Landmarks are scattered around the path (each within ``0.9 · sensor_range`` of a random pose, so
    every one is in range of some pose). Every landmark is measured at least once (from a random
    pose in range) when ``n_measurements ≥ n_landmarks``; the other measurements are drawn at random
    among (pose, landmark) pairs within ``sensor_range`` (nearest landmark as fallback).
    """
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2.0 * np.pi * max(1.0, n_poses / 1500.0), n_poses)
    r = 0.38 * extent * (1.0 + 0.25 * np.sin(3.0 * t + rng.uniform(0, 2 * np.pi)))
    xy = np.stack([r * np.cos(t), r * np.sin(t)], axis=1) + 0.5 * extent
    d = np.gradient(xy, axis=0)
    theta = np.arctan2(d[:, 1], d[:, 0])
    poses = np.column_stack([xy, theta])
    anchor = rng.integers(0, n_poses, size=n_landmarks)
    radius = 0.9 * sensor_range * np.sqrt(rng.uniform(0.0, 1.0, size=n_landmarks))
    angle = rng.uniform(0.0, 2.0 * np.pi, size=n_landmarks)
    landmarks = xy[anchor] + radius[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, (x, y, th) in enumerate(poses):
        values.insert(X(i), gtsam.Pose2(x, y, th))
    graph.add(
        gtsam.PriorFactorPose2(
            X(0), gtsam.Pose2(*poses[0]), gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.001]))
        )
    )
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(odometry_sigmas))
    for i in range(n_poses - 1):
        a, b = gtsam.Pose2(*poses[i]), gtsam.Pose2(*poses[i + 1])
        graph.add(gtsam.BetweenFactorPose2(X(i), X(i + 1), a.between(b), odo))
    # choose measurements: one per landmark from a pose in range, the rest random poses with a
    # random landmark in range; then in time (pose) order
    dist = np.linalg.norm(xy[:, None, :] - landmarks[None, :, :], axis=2)
    pairs: list[tuple[int, int]] = []
    for k in range(min(n_landmarks, n_measurements)):
        in_range = np.flatnonzero(dist[:, k] < sensor_range)
        pairs.append((int(rng.choice(in_range)) if len(in_range) else int(np.argmin(dist[:, k])), k))
    for i in rng.integers(0, n_poses, size=n_measurements - len(pairs)):
        in_range = np.flatnonzero(dist[i] < sensor_range)
        pairs.append((int(i), int(rng.choice(in_range)) if len(in_range) else int(np.argmin(dist[i]))))
    pairs.sort(key=lambda ik: ik[0])
    br = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(bearing_range_sigmas))
    measurement_factors: list[int] = []
    measured: list[tuple[int, int]] = []
    for i, k in pairs:
        p = gtsam.Pose2(*poses[i])
        pt = gtsam.Point2(*landmarks[k])
        measurement_factors.append(graph.size())
        graph.add(gtsam.BearingRangeFactor2D(X(i), L(k), p.bearing(pt), p.range(pt), br))
        measured.append((i, k))
    for k in sorted({k for _, k in measured}):  # unmeasured landmarks are not in the graph
        values.insert(L(k), gtsam.Point2(*landmarks[k]))
    return PlanarProblem(graph, values, poses, landmarks, measurement_factors, measured)


def random_mi_problem(
    rng: np.random.Generator, T: int = 8, L: int = 15
) -> tuple[FloatArray, list[tuple[npt.NDArray[np.int64], FloatArray]]]:
    """A planar pose chain (strong prior on the first pose) and ``L`` random landmark information blocks on 1-3 poses.

    The small landmark-selection problems of the tests and of ``bench_landmarks`` (greedy vs brute force).
    """
    n = 3 * T
    info0 = np.zeros((n, n))
    info0[:3, :3] += 1e4 * np.eye(3)
    for t in range(T - 1):
        J = np.hstack([-np.eye(3), np.eye(3)]) * rng.uniform(3, 10)
        idx = np.arange(3 * t, 3 * t + 6)
        info0[np.ix_(idx, idx)] += J.T @ J
    contrib = []
    for _ in range(L):
        poses = rng.choice(T, size=rng.integers(1, 4), replace=False)
        cols = np.concatenate([np.arange(3 * p, 3 * p + 3) for p in sorted(poses)])
        J = rng.normal(size=(2 * len(poses), len(cols))) * rng.uniform(0.5, 5)
        contrib.append((cols, J.T @ J))
    return info0, contrib
