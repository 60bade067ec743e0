"""The tag pose as the detect stage computed it before the batched solver: each IPPE solution refined by
``pycolmap.refine_absolute_pose(return_covariance=True)`` one at a time, the scale direction from a
finite-difference Jacobian. The reference :func:`stages.detect.pose.estimate_tag_poses` is checked against
(tests) and timed against (``tests/benchmarks/bench_detect.py``). Tests and benchmarks only.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from stages.detect.pose import TagPose, scale_mode, se3_log, tag_object_points

Array = npt.NDArray[np.float64]

_SKEW_BASIS = np.array(
    [[[0, 0, 0], [0, 0, -1], [0, 1, 0]], [[0, 0, 1], [0, 0, 0], [-1, 0, 0]], [[0, -1, 0], [1, 0, 0], [0, 0, 0]]], float
)


def _refinement_options(iterations: int = 50) -> Any:
    import pycolmap

    opts = pycolmap.AbsolutePoseRefinementOptions()
    opts.loss_function_scale = 1e6  # squared loss: four corners leave no room for robust down-weighting
    opts.gradient_tolerance = 1e-12
    opts.max_num_iterations = iterations
    return opts


def colmap_to_gtsam_cov(cov_colmap: Array, R_camera_tag: Array) -> Array:
    """pycolmap's cam_from_world covariance (left quaternion-manifold rotation, half-angle tangent; additive
    translation) in GTSAM's Pose3 tangent (right perturbation): ``omega = R^T 2 d_r``, ``v = R^T d_t``."""
    M = np.zeros((6, 6))
    M[:3, :3] = 2.0 * R_camera_tag.T
    M[3:, 3:] = R_camera_tag.T
    out = M @ np.asarray(cov_colmap, float) @ M.T
    return 0.5 * (out + out.T)


def corner_jacobian_fd(camera: Any, T: Array, obj: Array, h: float = 1e-6) -> Array:
    """8 x 6 derivative of the distorted corners by the right perturbation ``T Exp(xi)``, by central differences
    through ``camera.img_from_cam`` (``R Exp(+-h w)`` taken as ``R (I +- h [w]x)``, equal to O(h^2))."""
    R, t = T[:3, :3], T[:3, 3]
    base = obj @ R.T + t
    delta = np.empty((6, 4, 3))
    delta[:3] = np.einsum("nj,kij->kni", obj, R @ _SKEW_BASIS)
    delta[3:] = R.T[:, None, :]
    pts = np.concatenate([base + h * delta, base - h * delta], axis=0).reshape(-1, 3)
    proj = np.asarray(camera.img_from_cam(pts, check_cheirality=False)).reshape(2, 6, 8)
    return ((proj[0] - proj[1]) / (2 * h)).T


def _polish(camera: Any, corners: Array, obj: Array, start: Any) -> Any:
    """The least-squares optimum near ``start`` by scipy's Levenberg-Marquardt through ``camera.img_from_cam``
    (central differences, tolerances at machine precision): independent of the stage's solver and projection."""
    import pycolmap
    from scipy.optimize import least_squares

    from stages.detect.pose import so3_exp

    T0 = np.asarray(start.matrix())

    def pose(xi: Array) -> tuple[Array, Array]:
        return T0[:3, :3] @ so3_exp(xi[:3]), T0[:3, 3] + T0[:3, :3] @ xi[3:]

    def residual(xi: Array) -> Array:
        R, t = pose(xi)
        return (np.asarray(camera.img_from_cam(obj @ R.T + t, check_cheirality=False)) - corners).ravel()

    fit = least_squares(
        residual, np.zeros(6), jac="3-point", method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000
    )
    R, t = pose(fit.x)
    return pycolmap.Rigid3d(rotation=pycolmap.Rotation3d(R), translation=t)


def _refine(
    camera: Any, corners: Array, obj: Array, R: Array, t: Array, polish: bool = False
) -> tuple[Array, Array, float, Array] | None:
    import pycolmap

    start = pycolmap.Rigid3d(rotation=pycolmap.Rotation3d(R), translation=t)
    res = pycolmap.refine_absolute_pose(
        start, corners, obj, np.ones(4, bool), camera, _refinement_options(), return_covariance=True
    )
    if res is not None and polish:  # pycolmap's covariance at the optimum, without a step
        start = _polish(camera, corners, obj, res["cam_from_world"])
        res = pycolmap.refine_absolute_pose(
            start, corners, obj, np.ones(4, bool), camera, _refinement_options(0), return_covariance=True
        )
    if res is None:
        return None
    T = np.eye(4)
    T[:3, :4] = np.asarray(res["cam_from_world"].matrix())
    if T[2, 3] <= 0:
        return None
    proj = np.asarray(camera.img_from_cam(obj @ T[:3, :3].T + T[:3, 3], check_cheirality=False))
    sse = float(np.sum((proj - corners) ** 2))
    cov = colmap_to_gtsam_cov(np.asarray(res["covariance"]), T[:3, :3])
    J = corner_jacobian_fd(camera, T, obj)
    return T, cov, sse, cov @ J.T @ scale_mode(proj)


def estimate_tag_pose_colmap(corners_px: Array, size_m: float, camera: Any, polish: bool = False) -> TagPose | None:
    """The tag pose of :func:`stages.detect.pose.estimate_tag_pose`, computed the former way (pycolmap).

    One ``refine_absolute_pose`` per IPPE solution (``polish=False``) is what the stage did: Ceres stops there
    at its default function tolerance (a relative cost change of 1e-6), short of the optimum. With ``polish``
    scipy carries that result to the optimum and pycolmap refines once more from there, for its covariance at
    the optimum.
    """
    import cv2

    corners = np.asarray(corners_px, float).reshape(4, 2)
    obj = tag_object_points(size_m)
    normalized = np.asarray(camera.cam_from_img(corners))
    if not np.all(np.isfinite(normalized)):
        return None
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj, normalized.reshape(4, 1, 2), np.eye(3), None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
    except cv2.error:
        return None
    candidates = []
    for rvec, tvec in zip(rvecs[:n], tvecs[:n], strict=True):
        R, _ = cv2.Rodrigues(rvec)
        refined = _refine(camera, corners, obj, np.asarray(R, float), np.asarray(tvec, float).ravel(), polish)
        if refined is not None and np.all(np.isfinite(refined[1])):
            candidates.append(refined)
    if not candidates:
        return None
    candidates.sort(key=lambda c: c[2])
    T, cov, sse, scale_dir = candidates[0]
    alt = candidates[1] if len(candidates) > 1 else None
    if alt is not None and np.linalg.norm(alt[0][:3, :3] - T[:3, :3]) < 1e-6:
        alt = None
    if alt is None:
        return TagPose(T, cov, sse, None, float("inf"), scale_dir)
    offset = se3_log(np.asarray(np.linalg.solve(T, alt[0]), dtype=float))
    return TagPose(T, cov, sse, alt[0], alt[2], scale_dir, alt[1], alt[3], offset)
