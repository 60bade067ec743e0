"""Tag pose from its four corners: both planar (IPPE) solutions refined by pycolmap, with a 6x6 covariance.

Conventions:
    * Corners in the OpenCV aruco order: top-left, top-right, bottom-right, bottom-left of the tag as
      printed (clockwise in the image when the tag faces the camera upright).
    * Tag frame: origin at the tag centre, x right, y up, z out of the printed face (OpenCV's marker
      frame); ``T_camera_tag`` maps tag-frame points into the camera frame (x right, y down, z ahead).
    * Covariance in GTSAM's Pose3 tangent order (rx, ry, rz, tx, ty, tz) with the right perturbation
      ``T = T_hat * Exp(xi)``: the rotation and translation errors are expressed in the tag frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    import pycolmap

Array = npt.NDArray[np.float64]


def tag_object_points(size_m: float) -> Array:
    """Corners (4 x 3) of a tag of edge ``size_m`` in its own frame, in the OpenCV aruco order."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class TagPose:
    """The pose of one tag in the camera frame.

    Attributes:
        T_camera_tag: 4x4 pose of the better planar solution.
        cov_unit: 6x6 covariance (GTSAM tangent order, right perturbation) for a corner noise of 1 px;
            multiply by sigma^2.
        sse_px2: sum of squared corner reprojection errors of the chosen solution, px^2.
        alt_T_camera_tag: the other planar solution (None when IPPE gave only one).
        alt_sse_px2: its sum of squared reprojection errors, px^2 (inf without it).
        scale_dir: 6-vector ``(J^T J)^-1 J^T s``: the pose change caused by moving every corner 1 px outwards
            along its diagonal (``s``, a correlated edge bias); its covariance term is ``beta^2 a a^T``.
        alt_cov_unit: 6x6 covariance of the other solution for 1 px corner noise (None without it).
        alt_scale_dir: ``scale_dir`` of the other solution (None without it).
        alt_offset: ``Log(T^-1 T_alt)`` in the GTSAM tangent (None without it): where the other mode lies.
    """

    T_camera_tag: Array
    cov_unit: Array
    sse_px2: float
    alt_T_camera_tag: Array | None  # noqa: N815 (frames in names, as everywhere)
    alt_sse_px2: float
    scale_dir: Array = field(default_factory=lambda: np.zeros(6))
    alt_cov_unit: Array | None = None
    alt_scale_dir: Array | None = None
    alt_offset: Array | None = None

    @property
    def reprojection_px(self) -> float:
        """RMS corner reprojection error, px."""
        return float(np.sqrt(self.sse_px2 / 4.0))

    @property
    def ambiguity_ratio(self) -> float:
        """Squared error of the chosen solution over the other's (0 = unambiguous, 1 = both fit alike)."""
        if not np.isfinite(self.alt_sse_px2):
            return 0.0
        return float(self.sse_px2 / max(self.alt_sse_px2, 1e-300))

    @property
    def position_cov_unit(self) -> Array:
        """3x3 covariance of the tag centre in the camera frame for 1 px corner noise, m^2."""
        R = self.T_camera_tag[:3, :3]
        return R @ self.cov_unit[3:, 3:] @ R.T


def _refinement_options() -> pycolmap.AbsolutePoseRefinementOptions:
    import pycolmap

    opts = pycolmap.AbsolutePoseRefinementOptions()
    opts.loss_function_scale = 1e6  # squared loss: four corners leave no room for robust down-weighting
    opts.gradient_tolerance = 1e-12
    opts.max_num_iterations = 50
    return opts


def colmap_to_gtsam_cov(cov_colmap: Array, R_camera_tag: Array) -> Array:
    """Convert pycolmap's cam_from_world covariance into GTSAM's Pose3 tangent.

    COLMAP perturbs ``R`` on the left through Ceres' quaternion manifold, whose tangent is half the
    rotation angle, and ``t`` additively: ``R = Exp(2 d_r) R_hat``, ``t = t_hat + d_t``. GTSAM perturbs on
    the right, ``T = T_hat Exp(xi)``, so ``omega = R^T 2 d_r`` and ``v = R^T d_t``.
    """
    M = np.zeros((6, 6))
    M[:3, :3] = 2.0 * R_camera_tag.T
    M[3:, 3:] = R_camera_tag.T
    out = M @ np.asarray(cov_colmap, float) @ M.T
    return 0.5 * (out + out.T)


def _refine(
    camera: pycolmap.Camera, corners: Array, obj: Array, R: Array, t: Array
) -> tuple[Array, Array, float, Array] | None:
    """The pose refined from ``R, t`` on the corners: 4x4 pose, GTSAM covariance, squared error, scale mode."""
    import pycolmap

    start = pycolmap.Rigid3d(rotation=pycolmap.Rotation3d(R), translation=t)
    res = pycolmap.refine_absolute_pose(
        start, corners, obj, np.ones(4, bool), camera, _refinement_options(), return_covariance=True
    )
    if res is None:
        return None
    pose = res["cam_from_world"]
    T = np.eye(4)
    T[:3, :4] = np.asarray(pose.matrix())
    if T[2, 3] <= 0:
        return None
    proj = np.asarray(camera.img_from_cam(obj @ T[:3, :3].T + T[:3, 3], check_cheirality=False))
    sse = float(np.sum((proj - corners) ** 2))
    cov = colmap_to_gtsam_cov(np.asarray(res["covariance"]), T[:3, :3])
    J = corner_jacobian(camera, T, obj)
    return T, cov, sse, cov @ J.T @ scale_mode(proj)


def _skew(w: Array) -> Array:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_exp(w: Array) -> Array:
    """Rotation matrix of the rotation vector ``w``."""
    theta = float(np.linalg.norm(w))
    K = _skew(w)
    if theta < 1e-8:
        return np.eye(3) + K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * K @ K


def se3_log(T: Array) -> Array:
    """GTSAM's ``Pose3.Logmap`` (rx, ry, rz, tx, ty, tz) of a 4x4 pose."""
    import cv2

    w = np.asarray(cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0], dtype=float).ravel()
    theta = float(np.linalg.norm(w))
    K = _skew(w)
    if theta < 1e-8:
        V = np.eye(3) + 0.5 * K
    else:
        V = np.eye(3) + (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * K @ K
    return np.concatenate([w, np.linalg.solve(V, T[:3, 3])])


_SKEW_BASIS = np.array(
    [[[0, 0, 0], [0, 0, -1], [0, 1, 0]], [[0, 0, 1], [0, 0, 0], [-1, 0, 0]], [[0, -1, 0], [1, 0, 0], [0, 0, 0]]], float
)


def corner_jacobian(camera: pycolmap.Camera, T: Array, obj: Array, h: float = 1e-6) -> Array:
    """8 x 6 derivative of the distorted corners (x0 y0 .. x3 y3) by the right perturbation ``T Exp(xi)``.

    Central differences; ``R Exp(+-h w)`` is taken as ``R (I +- h [w]x)``, whose central difference is the
    same to O(h^2).
    """
    R, t = T[:3, :3], T[:3, 3]
    base = obj @ R.T + t
    delta = np.empty((6, 4, 3))
    delta[:3] = np.einsum("nj,kij->kni", obj, R @ _SKEW_BASIS)  # d/dw_k of R (I + [w]x) p = R [e_k]x p
    delta[3:] = R.T[:, None, :]  # d/dv_k of t + R v = R e_k
    pts = np.concatenate([base + h * delta, base - h * delta], axis=0).reshape(-1, 3)
    proj = np.asarray(camera.img_from_cam(pts, check_cheirality=False)).reshape(2, 6, 8)
    return ((proj[0] - proj[1]) / (2 * h)).T


def scale_mode(corners: Array) -> Array:
    """8-vector: every corner moved 1 px outwards along the line from the quad's centre (a scale change)."""
    c = np.asarray(corners, float).reshape(4, 2)
    d = c - c.mean(axis=0)
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).ravel()


def estimate_tag_pose(corners_px: Array, size_m: float, camera: pycolmap.Camera) -> TagPose | None:
    """Pose of a tag from its distorted pixel corners (4 x 2, OpenCV aruco order), or None if degenerate.

    Both IPPE solutions of the planar ambiguity are computed on the undistorted corners and refined
    on the distorted ones through the pycolmap camera model; the one with the smaller reprojection
    error is returned with the other kept for the ambiguity ratio.
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
        refined = _refine(camera, corners, obj, np.asarray(R, float), np.asarray(tvec, float).ravel())
        if refined is not None and np.all(np.isfinite(refined[1])):
            candidates.append(refined)
    if not candidates:
        return None
    candidates.sort(key=lambda c: c[2])
    T, cov, sse, scale_dir = candidates[0]
    alt = candidates[1] if len(candidates) > 1 else None
    # Two refinements may converge to the same minimum; then the view is not ambiguous.
    if alt is not None and np.linalg.norm(alt[0][:3, :3] - T[:3, :3]) < 1e-6:
        alt = None
    if alt is None:
        return TagPose(T, cov, sse, None, float("inf"), scale_dir)
    offset = se3_log(np.asarray(np.linalg.solve(T, alt[0]), dtype=float))
    return TagPose(T, cov, sse, alt[0], alt[2], scale_dir, alt[1], alt[3], offset)


def pose_covariance(
    cov_unit: Array,
    scale_dir: Array,
    sigma_px: float,
    beta_px: float,
    sse_px2: float = 0.0,
    alt: tuple[Array, Array, Array, float] | None = None,
    mixture: bool = True,
) -> tuple[Array, float]:
    """The reported 6x6 pose covariance and the probability that the other planar solution is the true one.

    Corner noise ``Sigma_c = sigma^2 I + beta^2 s s^T`` (white noise plus a correlated outward/inward edge
    bias along the scale mode ``s``) propagated through the least-squares solution:
    ``(J^T J)^-1 J^T Sigma_c J (J^T J)^-1 = sigma^2 (J^T J)^-1 + beta^2 a a^T``.

    With the other planar (IPPE) solution ``alt = (cov_unit, scale_dir, offset, sse_px2)`` and ``mixture``,
    the two solutions are weighted by their Laplace evidence ``exp(-SSE / 2 sigma^2) sqrt(det C)`` and the
    covariance is the second moment of that two-mode mixture about the chosen solution:
    ``(1 - p) C + p (C_alt + d d^T)`` with ``d = Log(T^-1 T_alt)``. Views where both solutions fit alike
    (small, far, near-frontal tags) thus report the flip they may be; clear views are unchanged.
    """
    sigma2 = sigma_px**2
    a = np.asarray(scale_dir, float)
    cov = sigma2 * np.asarray(cov_unit, float) + beta_px**2 * np.outer(a, a)
    if alt is None or not mixture:
        return cov, 0.0
    alt_unit, alt_dir, offset, alt_sse = alt
    b = np.asarray(alt_dir, float)
    cov_alt = sigma2 * np.asarray(alt_unit, float) + beta_px**2 * np.outer(b, b)
    sign, logdet = np.linalg.slogdet(cov)
    sign_a, logdet_a = np.linalg.slogdet(cov_alt)
    if sign <= 0 or sign_a <= 0 or not np.isfinite(alt_sse):
        return cov, 0.0
    log_odds = (alt_sse - sse_px2) / (2.0 * sigma2) - 0.5 * (logdet_a - logdet)
    p = float(1.0 / (1.0 + np.exp(min(log_odds, 700.0))))
    d = np.asarray(offset, float)
    out = (1.0 - p) * cov + p * (cov_alt + np.outer(d, d))
    return 0.5 * (out + out.T), p
