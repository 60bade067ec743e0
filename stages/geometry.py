"""SE(2)/SE(3) helpers shared by the stages: conversions, interpolation on the group, covariance maps.

Conventions:
- 4x4 homogeneous matrices ``T_a_b`` map points in frame ``b`` into frame ``a``.
- Quaternions cross library boundaries as ``quat_xyzw`` (ROS, Rerun, TUM) or ``quat_wxyz`` (gtsam).
- gtsam's ``Pose3`` tangent order is ``(rx, ry, rz, tx, ty, tz)`` with right perturbation
  ``T * Exp(xi)``; ``Pose2``'s is ``(x, y, theta)``.
"""

from __future__ import annotations

import gtsam
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def wrap_angle(a: float | FloatArray) -> float | FloatArray:
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def pose3_from_matrix(T: npt.ArrayLike) -> gtsam.Pose3:
    """A gtsam ``Pose3`` from a 4x4 matrix (or 16 row-major numbers); the rotation is re-orthonormalised."""
    M = np.asarray(T, dtype=float).reshape(4, 4)
    U, _, Vt = np.linalg.svd(M[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] = -U[:, -1]
        R = U @ Vt
    return gtsam.Pose3(gtsam.Rot3(R), M[:3, 3].copy())


def pose3_from_xyz_quat(xyz: npt.ArrayLike, quat_xyzw: npt.ArrayLike) -> gtsam.Pose3:
    """A gtsam ``Pose3`` from a translation and a quaternion (x, y, z, w); the quaternion is normalised."""
    q = np.asarray(quat_xyzw, dtype=float)
    q = q / np.linalg.norm(q)
    return gtsam.Pose3(gtsam.Rot3.Quaternion(q[3], q[0], q[1], q[2]), np.asarray(xyz, dtype=float))


def quat_xyzw(pose_or_rot: gtsam.Pose3 | gtsam.Rot3) -> FloatArray:
    """The quaternion (x, y, z, w) of a ``Pose3`` or ``Rot3``, with w >= 0."""
    R = pose_or_rot.rotation() if isinstance(pose_or_rot, gtsam.Pose3) else pose_or_rot
    # annotated: gtsam's stub names the return type ``Quaternion`` inside ``Rot3``, where that name is a method
    q: gtsam.Quaternion = R.toQuaternion()
    out = np.array([q.x(), q.y(), q.z(), q.w()])
    return out if out[3] >= 0 else -out


def pose3_to_vector(p: gtsam.Pose3) -> FloatArray:
    """``[x, y, z, qx, qy, qz, qw]`` of a ``Pose3``."""
    return np.concatenate([np.asarray(p.translation(), dtype=float), quat_xyzw(p)])


def pose3_from_vector(v: npt.ArrayLike) -> gtsam.Pose3:
    """Inverse of :func:`pose3_to_vector`."""
    v = np.asarray(v, dtype=float)
    return pose3_from_xyz_quat(v[:3], v[3:7])


def pose2_to_vector(p: gtsam.Pose2) -> FloatArray:
    """``[x, y, theta]`` of a ``Pose2``."""
    return np.array([p.x(), p.y(), p.theta()])


def pose2_from_pose3(p: gtsam.Pose3) -> gtsam.Pose2:
    """Project a ``Pose3`` onto the plane: (x, y) and the yaw of its rotation."""
    t = np.asarray(p.translation())
    return gtsam.Pose2(float(t[0]), float(t[1]), float(p.rotation().yaw()))


def pose3_from_pose2(p: gtsam.Pose2, z: float = 0.0) -> gtsam.Pose3:
    """Lift a ``Pose2`` into 3D at height ``z`` (rotation about z only)."""
    return gtsam.Pose3(gtsam.Rot3.Yaw(p.theta()), np.array([p.x(), p.y(), z]))


def yaw_from_quat_xyzw(q: npt.ArrayLike) -> FloatArray:
    """Yaw (rotation about z, ZYX convention) of quaternion(s) (x, y, z, w), shape (..., 4)."""
    q = np.asarray(q, dtype=float)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def interpolate_pose3(a: gtsam.Pose3, b: gtsam.Pose3, alpha: float) -> gtsam.Pose3:
    """Geodesic interpolation on SE(3): ``a * Exp(alpha * Log(a^-1 b))`` (alpha in [0, 1], or beyond to extrapolate)."""
    return a.compose(gtsam.Pose3.Expmap(alpha * gtsam.Pose3.Logmap(a.between(b))))


def interpolate_pose2(a: gtsam.Pose2, b: gtsam.Pose2, alpha: float) -> gtsam.Pose2:
    """Geodesic interpolation on SE(2): ``a * Exp(alpha * Log(a^-1 b))``."""
    return a.compose(gtsam.Pose2.Expmap(alpha * gtsam.Pose2.Logmap(a.between(b))))


def interpolate_poses3(stamps: npt.ArrayLike, poses: list[gtsam.Pose3], query: npt.ArrayLike) -> list[gtsam.Pose3]:
    """SE(3) interpolation of a time series of poses at ``query`` stamps (same units as ``stamps``).

    Stamps outside the series are clamped to its ends (no extrapolation).
    """
    t = np.asarray(stamps, dtype=np.int64 if np.asarray(stamps).dtype.kind in "iu" else float)
    q = np.asarray(query)
    if len(t) == 0:
        raise ValueError("cannot interpolate an empty pose series")
    idx = np.searchsorted(t, q, side="right")
    out: list[gtsam.Pose3] = []
    for s, i in zip(q, idx, strict=True):
        if i <= 0:
            out.append(poses[0])
        elif i >= len(t):
            out.append(poses[-1])
        else:
            t0, t1 = t[i - 1], t[i]
            alpha = 0.0 if t1 == t0 else float(s - t0) / float(t1 - t0)
            out.append(interpolate_pose3(poses[i - 1], poses[i], alpha))
    return out


def _se2_v(theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(sin θ / θ, (1 − cos θ) / θ)``: the entries of SE(2)'s left Jacobian ``V``, with their limits at θ = 0."""
    small = np.abs(theta) < 1e-9
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(th) / th)
    b = np.where(small, theta / 2.0, (1.0 - np.cos(th)) / th)
    return a, b


def interpolate_planar(stamps: npt.ArrayLike, poses: npt.ArrayLike, query: npt.ArrayLike) -> FloatArray:
    """Geodesic SE(2) interpolation of an (N, 3) series of (x, y, yaw) at ``query`` stamps, vectorised.

    The same curve as :func:`interpolate_pose2` between neighbouring poses (``a * Exp(alpha * Log(a^-1 b))``):
    a constant-twist arc, not a straight chord, while the robot turns. Stamps outside the series are clamped to
    its ends (no extrapolation). Returns (M, 3) with yaw continuous from the pose before each query.
    """
    t = np.asarray(stamps)
    P = np.asarray(poses, dtype=float).reshape(-1, 3)
    q = np.asarray(query).reshape(-1)
    if len(t) == 0:
        raise ValueError("cannot interpolate an empty pose series")
    if len(t) == 1:
        return np.repeat(P, len(q), axis=0)
    i = np.clip(np.searchsorted(t, q, side="right"), 1, len(t) - 1)
    t0, t1 = t[i - 1], t[i]
    span = (t1 - t0).astype(float)
    alpha = np.clip(np.where(span > 0, (q - t0).astype(float) / np.where(span > 0, span, 1.0), 0.0), 0.0, 1.0)
    a, b = P[i - 1], P[i]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    lx, ly = c * dx + s * dy, -s * dx + c * dy  # b's position in a's frame
    th = np.asarray(wrap_angle(b[:, 2] - a[:, 2]))
    va, vb = _se2_v(th)
    det = va**2 + vb**2
    ux, uy = (va * lx + vb * ly) / det, (-vb * lx + va * ly) / det  # V(θ)^-1 t: the twist's translation
    wa, wb = _se2_v(alpha * th)
    px, py = alpha * (wa * ux - wb * uy), alpha * (wb * ux + wa * uy)  # V(αθ) α u
    return np.column_stack([a[:, 0] + c * px - s * py, a[:, 1] + s * px + c * py, a[:, 2] + alpha * th])


def pose3_adjoint(p: gtsam.Pose3) -> FloatArray:
    """The 6x6 adjoint of ``p`` in gtsam's (rotation, translation) tangent order."""
    return np.asarray(p.AdjointMap(), dtype=float)


def rotate_covariance(cov: npt.ArrayLike, R: npt.ArrayLike) -> FloatArray:
    """``R cov R^T`` for a square covariance and a rotation of the same size."""
    C = np.asarray(cov, dtype=float)
    M = np.asarray(R, dtype=float)
    out = M @ C @ M.T
    return 0.5 * (out + out.T)


def ros_pose_cov_to_gtsam(cov36: npt.ArrayLike) -> FloatArray:
    """ROS pose covariance (x y z roll pitch yaw, row-major 36) reordered to gtsam's (r, t) tangent order.

    The frames are not changed: ROS gives the covariance in the parent frame, whereas gtsam's is
    in the body frame; use :func:`world_to_body_pose_cov` afterwards where that matters.
    """
    C = np.asarray(cov36, dtype=float).reshape(6, 6)
    perm = [3, 4, 5, 0, 1, 2]
    return C[np.ix_(perm, perm)]


def relative_position_to_bearing_range_2d(p: npt.ArrayLike, cov: npt.ArrayLike) -> tuple[float, float, FloatArray]:
    """A 2D relative position with its 2x2 covariance as (bearing, range) and their 2x2 covariance.

    The covariance is mapped through the Jacobian of (atan2(y, x), |p|) at ``p`` (first order).
    """
    x, y = (float(v) for v in np.asarray(p, dtype=float)[:2])
    r = float(np.hypot(x, y))
    if r <= 0:
        raise ValueError("relative position at the origin has no bearing")
    J = np.array([[-y / r**2, x / r**2], [x / r, y / r]])
    return float(np.arctan2(y, x)), r, rotate_covariance(np.asarray(cov, dtype=float)[:2, :2], J)


def bearing_range_to_relative_position_2d(
    bearing: float, rng: float, cov: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`relative_position_to_bearing_range_2d`: (x, y) and its 2x2 covariance."""
    c, s = np.cos(bearing), np.sin(bearing)
    J = np.array([[-rng * s, c], [rng * c, s]])
    return np.array([rng * c, rng * s]), rotate_covariance(cov, J)


def relative_position_to_bearing_range_3d(
    p: npt.ArrayLike, cov: npt.ArrayLike
) -> tuple[gtsam.Unit3, float, FloatArray]:
    """A 3D relative position with its 3x3 covariance as (Unit3 bearing, range) and their 3x3 covariance.

    The bearing's two tangent coordinates are those of ``Unit3.basis()`` at the measurement.
    """
    p = np.asarray(p, dtype=float)
    r = float(np.linalg.norm(p))
    if r <= 0:
        raise ValueError("relative position at the origin has no bearing")
    u = gtsam.Unit3(p)
    B = np.asarray(u.basis())
    J = np.vstack([B.T / r, (p / r)[None, :]])
    return u, r, rotate_covariance(cov, J)


def bearing_range_to_relative_position_3d(
    bearing: gtsam.Unit3, rng: float, cov: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`relative_position_to_bearing_range_3d`: (x, y, z) and its 3x3 covariance."""
    d = np.asarray(bearing.point3(), dtype=float)
    B = np.asarray(bearing.basis())
    J = np.hstack([rng * B, d[:, None]])
    return rng * d, rotate_covariance(cov, J)


def umeyama_alignment(
    source: npt.ArrayLike, target: npt.ArrayLike, with_scale: bool = False
) -> tuple[FloatArray, FloatArray, float]:
    """Least-squares rigid (or similarity) alignment ``target ≈ s R source + t`` (Umeyama 1991).

    Args:
        source: N x d points (d = 2 or 3).
        target: N x d points.
        with_scale: also estimate a scale factor.

    Returns:
        ``(R, t, s)``.
    """
    X = np.asarray(source, dtype=float)
    Y = np.asarray(target, dtype=float)
    mx, my = X.mean(axis=0), Y.mean(axis=0)
    Xc, Yc = X - mx, Y - my
    S = Yc.T @ Xc / len(X)
    U, D, Vt = np.linalg.svd(S)
    E = np.eye(X.shape[1])
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        E[-1, -1] = -1
    R = U @ E @ Vt
    s = float(np.trace(np.diag(D) @ E) / (Xc**2).sum() * len(X)) if with_scale else 1.0
    t = my - s * R @ mx
    return R, t, s
