"""Planar poses ``(x, y, θ)`` in batches: GTSAM's ``Pose2`` operations on ``(N, 3)`` arrays, one row per pose.

The odometry calibration evaluates a corrected factor and its finite-difference Jacobians for every odometry
factor, several times per outer iteration; one ``gtsam.Pose2`` call per value made that the graph stage's largest
cost on long recordings. These give the same values as ``gtsam.Pose2`` (``between``, ``Logmap``, ``Expmap``,
``compose``, ``retract``: its Expmap chart) to rounding, with angles wrapped to (−π, π] as ``Rot2`` keeps them.
"""

from __future__ import annotations

import numpy as np

SMALL_ANGLE = 1e-10
"""Below this rotation ``Logmap`` and ``Expmap`` take the translation as it is (GTSAM's own cut)."""


def wrap(theta: np.ndarray) -> np.ndarray:
    """Angles in (−π, π]."""
    return np.arctan2(np.sin(theta), np.cos(theta))


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ b`` row by row."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, wrap(b[:, 2] - a[:, 2])])


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a b`` row by row."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack(
        [a[:, 0] + c * b[:, 0] - s * b[:, 1], a[:, 1] + s * b[:, 0] + c * b[:, 1], wrap(a[:, 2] + b[:, 2])]
    )


def logmap(p: np.ndarray) -> np.ndarray:
    """The tangent vector ``(v_x, v_y, ω)`` of each pose: ``V(ω)⁻¹ t`` with ``V⁻¹ = (ω/2) [[cot(ω/2), 1], [−1,
    cot(ω/2)]]``. GTSAM divides by ``(cos ω − 1)² + sin² ω``, which loses digits at the tiny angles of finite
    differences (a relative 1e-6 in the calibration's covariances); this form does not."""
    x, y, w = p[:, 0], p[:, 1], wrap(p[:, 2])
    small = np.abs(w) < SMALL_ANGLE
    half = 0.5 * np.where(small, 1.0, w)
    hcot = half * np.cos(half) / np.sin(half)
    vx = np.where(small, x, hcot * x + half * y)
    vy = np.where(small, y, -half * x + hcot * y)
    return np.column_stack([vx, vy, w])


def expmap(v: np.ndarray) -> np.ndarray:
    """The pose of each tangent vector ``(v_x, v_y, ω)``: ``t = V(ω) v``."""
    vx, vy, w = v[:, 0], v[:, 1], v[:, 2]
    small = np.abs(w) < SMALL_ANGLE
    ws = np.where(small, 1.0, w)
    a, b = np.sin(ws) / ws, (1.0 - np.cos(ws)) / ws
    x = np.where(small, vx, a * vx - b * vy)
    y = np.where(small, vy, b * vx + a * vy)
    return np.column_stack([x, y, wrap(w)])


def retract(p: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``p ⊕ d`` (right perturbation, GTSAM's ``Pose2.retract``)."""
    return compose(p, expmap(d))


def local(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``Log(a⁻¹ b)`` (GTSAM's ``a.localCoordinates(b)``)."""
    return logmap(between(a, b))
