"""Tag pose from its four corners: both planar (IPPE) solutions refined by least squares, with a 6x6 covariance.

Conventions:
    * Corners in the OpenCV aruco order: top-left, top-right, bottom-right, bottom-left of the tag as
      printed (clockwise in the image when the tag faces the camera upright).
    * Tag frame: origin at the tag centre, x right, y up, z out of the printed face (OpenCV's marker
      frame); ``T_camera_tag`` maps tag-frame points into the camera frame (x right, y down, z ahead).
    * Covariance in GTSAM's Pose3 tangent order (rx, ry, rz, tx, ty, tz) with the right perturbation
      ``T = T_hat * Exp(xi)``: the rotation and translation errors are expressed in the tag frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from stages.detect.projection import Projection

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


def _skew(w: Array) -> Array:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _skew_batch(w: Array) -> Array:
    """``[w]x`` of every 3-vector in ``w`` (..., 3) -> (..., 3, 3)."""
    K = np.zeros((*w.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return K


def _so3_exp_batch(w: Array) -> Array:
    """Rotation matrices (M, 3, 3) of the rotation vectors ``w`` (M, 3) (Taylor terms for tiny angles)."""
    t2 = np.einsum("mi,mi->m", w, w)
    small = t2 < 1e-8
    theta = np.sqrt(np.where(small, 1.0, t2))
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(theta) / theta)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(theta)) / (theta * theta))
    K = _skew_batch(w)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def so3_exp(w: Array) -> Array:
    """Rotation matrix of the rotation vector ``w``."""
    return _so3_exp_batch(np.asarray(w, float).reshape(1, 3))[0]


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


def _se3_log_batch(T: Array) -> Array:
    """:func:`se3_log` of every pose in ``T`` (M, 4, 4) -> (M, 6). Rotations within 1e-3 rad of a half turn, where
    the axis from ``R - R^T`` loses digits, go through :func:`se3_log` (OpenCV's Rodrigues)."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    v = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.linalg.norm(v, axis=1)
    theta = np.arctan2(s, 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0))
    t2 = theta * theta
    small = theta < 1e-4
    w = np.where(small, 1.0 + t2 / 6.0, theta / np.where(small, 1.0, s))[:, None] * v
    K = _skew_batch(w)
    a = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(theta)) / np.where(small, 1.0, t2))
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0, (theta - np.sin(theta)) / np.where(small, 1.0, t2 * theta))
    V = np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)
    out = np.concatenate([w, np.linalg.solve(V, t[..., None])[..., 0]], axis=1)
    for k in np.flatnonzero(theta > np.pi - 1e-3):
        out[k] = se3_log(T[k])
    return out


def scale_mode(corners: Array) -> Array:
    """8-vector: every corner moved 1 px outwards along the line from the quad's centre (a scale change)."""
    return _scale_modes(np.asarray(corners, float).reshape(1, 4, 2))[0]


def _scale_modes(corners: Array) -> Array:
    """:func:`scale_mode` of every quad in ``corners`` (M, 4, 2) -> (M, 8)."""
    d = corners - corners.mean(axis=1, keepdims=True)
    return (d / np.linalg.norm(d, axis=2, keepdims=True)).reshape(len(corners), 8)


def _projection(camera: pycolmap.Camera) -> Projection:
    key = (str(camera.model_name), tuple(float(v) for v in camera.params))
    proj = _PROJECTIONS.get(key)
    if proj is None:
        proj = _PROJECTIONS[key] = Projection.of(camera)
    return proj


_PROJECTIONS: dict[tuple[str, tuple[float, ...]], Projection] = {}


@dataclass
class _Evaluation:
    """Residuals (M, 8), Jacobians (M, 8, 6) by the right perturbation, costs (M,) and pixels (M, 4, 2)."""

    res: Array
    J: Array
    cost: Array
    uv: Array
    S: Array | None = None


def _evaluate(
    proj: Projection, R: Array, t: Array, obj: Array, corners: Array, second_order: bool = False
) -> _Evaluation:
    """Reprojection residuals of poses ``R, t`` ((..., M, 3, 3), (..., M, 3)) of the tags ``obj`` (M, 4, 3) seen at
    ``corners`` (M, 4, 2), and their Jacobian by ``xi`` of ``T Exp(xi)``.

    ``d P / d omega = -R [p]x`` and ``d P / d v = R`` for the camera-frame corner ``P = R p + t``. A pose that puts
    a corner at or behind the camera costs infinity. With ``second_order`` (poses (M, 3, 3)), also Newton's
    second-order term ``S = sum_i r_i d2 r_i / d xi2`` (M, 6, 6), so that ``J^T J + S`` is the Hessian of half the
    cost in the coordinates ``(w, v) -> (R Exp(w), t + R v)`` that :func:`_refine_batch` steps in: with
    ``g = R^T Jp^T r`` and ``Hr = sum_c r_c d2 pixel_c / dP2`` per corner, ``S = sum_corners L^T R^T Hr R L`` plus
    ``sym(g p^T) - (g . p) I`` in the rotation block (from ``d2 Exp(w) p / dw2``), with ``L = [-[p]x | I]``.
    """
    # The tag is planar (z = 0 in its frame): P = x R e_x + y R e_y + t, and B [p]x = [-y B_z, x B_z, y B_x - x B_y].
    x, y = obj[..., 0, None], obj[..., 1, None]  # (M, 4, 1)
    P = x * R[..., None, :, 0] + y * R[..., None, :, 1] + t[..., None, :]
    uv, Jp = proj.project(P, jacobian=True)
    assert Jp is not None
    B = Jp @ R[..., None, :, :]  # (..., M, 4, 2, 3): d pixel / d v
    Bx, By, Bz = B[..., 0], B[..., 1], B[..., 2]
    J = np.empty((*B.shape[:-1], 6))
    J[..., 0], J[..., 1], J[..., 2] = y * Bz, -x * Bz, x * By - y * Bx  # x, y (M, 4, 1) against (..., M, 4, 2)
    J[..., 3:] = B
    J = J.reshape(*R.shape[:-2], 8, 6)
    res = (uv - corners).reshape(*R.shape[:-2], 8)
    cost = np.einsum("...i,...i->...", res, res)
    cost[~(P[..., 2] > 0).all(axis=-1) | ~np.isfinite(cost)] = np.inf
    if not second_order:
        return _Evaluation(res, J, cost, uv)
    r = res.reshape(*uv.shape)  # (M, 4, 2)
    Rt = R.transpose(0, 2, 1)
    Hr = Rt[:, None] @ proj.weighted_hessian(P, r) @ R[:, None]  # tag frame, (M, 4, 3, 3)
    g = (B.swapaxes(-1, -2) @ r[..., None])[..., 0]  # R^T Jp^T r, (M, 4, 3)
    L = np.zeros((*obj.shape[:2], 3, 6))
    L[..., :3] = -_skew_batch(obj)
    L[..., 0, 3], L[..., 1, 4], L[..., 2, 5] = 1.0, 1.0, 1.0
    S = (L.swapaxes(-1, -2) @ Hr @ L).sum(axis=1)
    gp = np.einsum("mki,mki->m", g, obj)
    outer = np.einsum("mki,mkj->mij", obj, g)
    S[:, :3, :3] += 0.5 * (outer + outer.transpose(0, 2, 1)) - gp[:, None, None] * np.eye(3)
    return _Evaluation(res, J, cost, uv, S)


def corner_jacobian(camera: pycolmap.Camera, T: Array, obj: Array) -> Array:
    """8 x 6 derivative of the distorted corners (x0 y0 .. x3 y3) by the right perturbation ``T Exp(xi)``."""
    R, t = np.asarray(T, float)[None, :3, :3], np.asarray(T, float)[None, :3, 3]
    o = np.asarray(obj, float)[None]
    return _evaluate(_projection(camera), R, t, o, np.zeros((1, 4, 2))).J[0]


@dataclass
class _Refined:
    """Refined poses of a batch: 4x4 poses, 1 px covariances, squared errors, scale directions, usable flags."""

    T: Array
    cov: Array
    sse: Array
    scale_dir: Array
    ok: Array


def _positive_definite(H: Array) -> Array:
    """Which of the symmetric matrices ``H`` (M, n, n) are positive definite: Gaussian elimination without pivoting,
    every pivot positive (Sylvester's criterion). A few vector operations per column, against LAPACK's eigenvalues
    per matrix (``eigvalsh`` cost a fifth of the solver on the sample)."""
    A = H.copy()
    n = A.shape[-1]
    ok = np.ones(len(A), dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for j in range(n):
            d = A[:, j, j]
            ok &= d > 0
            if j + 1 < n:
                A[:, j + 1 :, j + 1 :] -= A[:, j + 1 :, j, None] * (A[:, None, j, j + 1 :] / d[:, None, None])
    return ok


def _refine_batch(proj: Projection, corners: Array, obj: Array, R: Array, t: Array) -> _Refined:
    """Least-squares poses of the corners (M, 4, 2) of tags ``obj`` (M, 4, 3) from the starts ``R, t``.

    Damped Newton on the right perturbation, all problems at once; every problem takes its own steps and
    damping. The Hessian is the exact one (``J^T J`` and the analytic second-order term of :func:`_evaluate`) where
    it is positive definite, else Gauss-Newton's ``J^T J``: Gauss-Newton alone converges only linearly on these
    problems (the tags' flat, curved valleys of the planar ambiguity), often taking 20-100 steps. A problem stops
    once its step is below 1e-10 (rad, and relative to the distance): at the optimum to near machine precision
    (pycolmap's Ceres stopped at a relative cost change of 1e-6, short of it). The covariance is ``(J^T J)^-1`` at
    the optimum (what ``pycolmap.refine_absolute_pose`` reports, in GTSAM's tangent). Starts: :func:`_ippe_starts`.
    """
    m = len(R)
    R, t = R.copy(), t.copy()
    ev = _evaluate(proj, R, t, obj, corners, second_order=True)
    assert ev.S is not None
    S = ev.S  # the second-order term sum_i r_i d2 r_i
    lam = np.full(m, _LAMBDA0)
    active = np.flatnonzero(np.isfinite(ev.cost))
    eye = np.eye(6)
    for _ in range(_MAX_ITERATIONS):
        if len(active) == 0:
            break
        a = active
        Ra, ta, Ja, la = R[a], t[a], ev.J[a], lam[a]
        Jt = Ja.transpose(0, 2, 1)
        g = np.einsum("mij,mj->mi", Jt, ev.res[a])
        JtJ = Jt @ Ja
        H = JtJ + S[a]
        newton = _positive_definite(H)
        H = np.where(newton[:, None, None], H, JtJ)
        damped = H + la[:, None, None] * (H * eye)
        try:
            step = -np.linalg.solve(damped, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = -np.stack([np.linalg.lstsq(k, v, rcond=None)[0] for k, v in zip(damped, g, strict=True)])
        R_new = Ra @ _so3_exp_batch(step[:, :3])
        t_new = ta + np.einsum("mij,mj->mi", Ra, step[:, 3:])
        trial = _evaluate(proj, R_new, t_new, obj[a], corners[a], second_order=True)
        accept = trial.cost < ev.cost[a]
        acc = a[accept]
        R[acc], t[acc] = R_new[accept], t_new[accept]
        assert trial.S is not None
        S[acc] = trial.S[accept]
        ev.res[acc], ev.J[acc], ev.cost[acc], ev.uv[acc] = (
            trial.res[accept],
            trial.J[accept],
            trial.cost[accept],
            trial.uv[accept],
        )
        # A rejected step raises the damping to at least _LAMBDA_REJECTED at once: after a run of accepted steps it is
        # near 1e-12, and ten rejections in a row (x10 each) were the slowest problems' most common iterations.
        lam[a] = np.where(accept, np.maximum(la * _LAMBDA_ACCEPTED, 1e-12), np.maximum(la * 10.0, _LAMBDA_REJECTED))
        size = np.maximum(np.abs(step[:, :3]).max(axis=1), np.abs(step[:, 3:]).max(axis=1) / np.linalg.norm(ta, axis=1))
        # Done: a step below 1e-10, or one below 1e-7 that rounding made no better (the cost is flat to double
        # precision there; Newton's next step would be ~1e-14), or no step that lowers the cost at all.
        done = (size < 1e-10) | (~accept & (size < 1e-7) & (la < 1.0)) | (lam[a] > 1e12)
        active = a[~done]
    T = np.zeros((m, 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, t, 1.0
    Jt = ev.J.transpose(0, 2, 1)
    H = Jt @ ev.J
    ok = np.isfinite(ev.cost) & (t[:, 2] > 0) & (np.linalg.cond(H) < 1e14)
    H[~ok] = np.eye(6)
    cov = np.linalg.inv(H)
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    scale_dir = np.einsum("mij,mj->mi", cov @ Jt, _scale_modes(ev.uv))
    return _Refined(T, cov, ev.cost, scale_dir, ok)


_LAMBDA0 = 1e-6
_LAMBDA_REJECTED = 1e-2
_LAMBDA_ACCEPTED = 0.1
_MAX_ITERATIONS = 100


def _ippe_starts(normalized: Array, half: Array) -> tuple[Array, Array, Array]:
    """Both planar (IPPE) solutions of every tag from its undistorted corners (N, 4, 2), tags of half-edge ``half``
    (N,): rotations (N, 2, 3, 3), translations (N, 2, 3) and which tags have them (N,), the solution with the
    smaller reprojection error in the normalised image first (the order of OpenCV's ``SOLVEPNP_IPPE_SQUARE``).

    Infinitesimal plane-based pose (Collins and Bartoli 2014), for all tags at once. With ``H`` the homography from
    the tag's plane (corners at +-1) to the normalised image, ``v = (p, q, 1)`` the image ray of the tag's centre
    and ``J`` the homography's 2x2 Jacobian there (per metre of the plane), a rotation ``Rz`` taking ``v`` to the
    optical axis gives ``J = B R'[:2, :2] / s`` with ``B = [[1, 0, -p], [0, 1, -q]] Rz^T[:, :2]``, ``R = Rz^T R'``
    and ``s`` the centre's depth. ``B^-1 J`` has largest singular value ``1 / s``, because a 2x2 block of a
    rotation has largest singular value 1; its third row ``(b0, b1)`` follows from unit columns up to one common
    sign, the two solutions. The translation is then the linear least-squares one (image-plane cross product).
    """
    n = len(normalized)
    x, y = _TAG_UNIT[:, 0] / 2.0, _TAG_UNIT[:, 1] / 2.0  # +-1

    def dlt(uv: Array) -> Array:
        A = np.zeros((len(uv), 8, 8))
        A[:, 0::2, 0], A[:, 0::2, 1], A[:, 0::2, 2] = x, y, 1.0
        A[:, 1::2, 3], A[:, 1::2, 4], A[:, 1::2, 5] = x, y, 1.0
        A[:, 0::2, 6], A[:, 0::2, 7] = -uv[..., 0] * x, -uv[..., 0] * y
        A[:, 1::2, 6], A[:, 1::2, 7] = -uv[..., 1] * x, -uv[..., 1] * y
        return A

    # Corners that are not finite or give no homography (coincident, collinear) are swapped for a frontal square
    # before any solve and reported without solutions.
    with np.errstate(all="ignore"):
        ok = np.asarray(np.isfinite(normalized).all(axis=(1, 2)), dtype=bool)
        ok[ok] = np.abs(np.linalg.det(dlt(normalized[ok]))) > 1e-300
    normalized = np.where(ok[:, None, None], normalized, _TAG_UNIT[None, :, :2])
    u, v = normalized[..., 0], normalized[..., 1]  # (N, 4)
    with np.errstate(all="ignore"):
        h = np.linalg.solve(dlt(normalized), normalized.reshape(n, 8, 1))[..., 0]
        p, q = h[:, 2], h[:, 5]
        J = np.stack([h[:, 0] - p * h[:, 6], h[:, 1] - p * h[:, 7], h[:, 3] - q * h[:, 6], h[:, 4] - q * h[:, 7]], 1)
        J = J.reshape(n, 2, 2) / half[:, None, None]
        ray = np.stack([p, q, np.ones(n)], axis=1)
        nrm = ray / np.linalg.norm(ray, axis=1, keepdims=True)
        # Rz: the rotation about n x e_z taking n to e_z (n_z > 0 here): I + K + K^2 / (1 + n_z).
        K = _skew_batch(np.stack([nrm[:, 1], -nrm[:, 0], np.zeros(n)], axis=1))
        Rz = np.eye(3) + K + (K @ K) / (1.0 + nrm[:, 2])[:, None, None]
        RzT2 = Rz.transpose(0, 2, 1)[:, :, :2]  # (N, 3, 2)
        B = RzT2[:, :2] - ray[:, :2, None] * RzT2[:, 2:3]
        Ahat = np.linalg.solve(B, J)
        ata = Ahat.transpose(0, 2, 1) @ Ahat
        tr, dd = ata[:, 0, 0] + ata[:, 1, 1], ata[:, 0, 0] - ata[:, 1, 1]
        gamma = np.sqrt(0.5 * (tr + np.sqrt(dd * dd + 4.0 * ata[:, 0, 1] ** 2)))
        Rt = Ahat / gamma[:, None, None]
        b0 = np.sqrt(np.maximum(0.0, 1.0 - Rt[:, 0, 0] ** 2 - Rt[:, 1, 0] ** 2))
        b1 = np.sqrt(np.maximum(0.0, 1.0 - Rt[:, 0, 1] ** 2 - Rt[:, 1, 1] ** 2))
        b1 = np.where(Rt[:, 0, 0] * Rt[:, 0, 1] + Rt[:, 1, 0] * Rt[:, 1, 1] > 0, -b1, b1)
        Rp = np.zeros((n, 2, 3, 3))
        for k, sign in enumerate((1.0, -1.0)):
            c0 = np.stack([Rt[:, 0, 0], Rt[:, 1, 0], sign * b0], axis=1)
            c1 = np.stack([Rt[:, 0, 1], Rt[:, 1, 1], sign * b1], axis=1)
            Rp[:, k] = np.stack([c0, c1, np.cross(c0, c1)], axis=2)
        R = Rz.transpose(0, 2, 1)[:, None] @ Rp
        # t minimising sum_k |[m_k]x (R P_k + t)|^2 over the first two rows, m_k = (u_k, v_k, 1): linear in t.
        obj = _TAG_UNIT[None] * half[:, None, None]  # (N, 4, 3)
        RP = np.einsum("nsij,nkj->nski", R, obj)  # (N, 2, 4, 3)
        M = np.zeros((n, 4, 2, 3))
        M[:, :, 0, 0], M[:, :, 0, 2] = 1.0, -u
        M[:, :, 1, 1], M[:, :, 1, 2] = 1.0, -v
        r = -np.einsum("nkij,nskj->nski", M, RP)  # (N, 2, 4, 2)
        MtM = np.einsum("nkij,nkil->njl", M, M)
        Mtr = np.einsum("nkij,nski->nsj", M, r)
        t = np.linalg.solve(MtM[:, None], Mtr[..., None])[..., 0]
        P = RP + t[:, :, None, :]
        err = np.sum((P[..., :2] / P[..., 2:] - normalized[:, None]) ** 2, axis=(2, 3))
    swap = err[:, 1] < err[:, 0]
    R[swap], t[swap] = R[swap][:, ::-1], t[swap][:, ::-1]
    ok &= np.isfinite(R).all(axis=(1, 2, 3)) & np.isfinite(t).all(axis=(1, 2)) & (gamma > 1e-300)
    return R, t, ok


def estimate_tag_poses(
    corners_px: Array | Sequence[Array], sizes_m: Sequence[float], camera: pycolmap.Camera
) -> list[TagPose | None]:
    """:func:`estimate_tag_pose` of many tags seen by one camera, solved together (one batch of numpy operations).

    Args:
        corners_px: the distorted pixel corners of each tag (N x 4 x 2, OpenCV aruco order).
        sizes_m: each tag's edge length.
        camera: the pycolmap camera (PINHOLE, OPENCV, FULL_OPENCV or OPENCV_FISHEYE).
    """
    corners = np.asarray(corners_px, float).reshape(-1, 4, 2)
    n = len(corners)
    if n == 0:
        return []
    half = np.asarray(sizes_m, float).reshape(n) / 2.0
    obj = _TAG_UNIT[None] * half[:, None, None]
    normalized = np.asarray(camera.cam_from_img(corners.reshape(-1, 2))).reshape(n, 4, 2)
    R_ippe, t_ippe, has = _ippe_starts(normalized, half)
    owner = [i for i in np.flatnonzero(has).tolist() for _ in range(2)]
    if not owner:
        return [None] * n
    R0, t0 = R_ippe[has].reshape(-1, 3, 3), t_ippe[has].reshape(-1, 3)
    ref = _refine_batch(_projection(camera), corners[owner], obj[owner], R0, t0)
    usable = np.logical_and(ref.ok, np.isfinite(ref.cov).all(axis=(1, 2)))
    by_tag: list[list[int]] = [[] for _ in range(n)]
    for k, i in enumerate(owner):
        if usable[k]:
            by_tag[i].append(k)
    chosen: list[tuple[int, int | None] | None] = []
    for ks in by_tag:
        if not ks:
            chosen.append(None)
            continue
        ks = sorted(ks, key=lambda k: ref.sse[k])  # stable: the first IPPE solution wins a tie, as before
        best, alt = ks[0], (ks[1] if len(ks) > 1 else None)
        # Two refinements may converge to the same minimum; then the view is not ambiguous.
        if alt is not None and np.linalg.norm(ref.T[alt, :3, :3] - ref.T[best, :3, :3]) < 1e-6:
            alt = None
        chosen.append((best, alt))
    pairs = [(b, a) for c in chosen if c is not None for b, a in [c] if a is not None]
    logs = _se3_log_batch(_relative([b for b, _ in pairs], [a for _, a in pairs], ref.T)) if pairs else np.zeros((0, 6))
    offsets = iter(logs)
    out: list[TagPose | None] = []
    for c in chosen:
        if c is None:
            out.append(None)
            continue
        best, alt = c
        T, cov, sse, a = ref.T[best], ref.cov[best], float(ref.sse[best]), ref.scale_dir[best]
        if alt is None:
            out.append(TagPose(T, cov, sse, None, float("inf"), a))
        else:
            offset = next(offsets)
            out.append(
                TagPose(T, cov, sse, ref.T[alt], float(ref.sse[alt]), a, ref.cov[alt], ref.scale_dir[alt], offset)
            )
    return out


def _relative(i: list[int], j: list[int], T: Array) -> Array:
    """``T[i]^-1 T[j]`` for the index lists ``i``, ``j`` (rigid inverse)."""
    Ri, ti = T[i, :3, :3], T[i, :3, 3]
    RiT = Ri.transpose(0, 2, 1)
    out = np.zeros((len(i), 4, 4))
    out[:, :3, :3] = RiT @ T[j, :3, :3]
    out[:, :3, 3] = np.einsum("mij,mj->mi", RiT, T[j, :3, 3] - ti)
    out[:, 3, 3] = 1.0
    return out


_TAG_UNIT = tag_object_points(2.0)


def estimate_tag_pose(corners_px: Array, size_m: float, camera: pycolmap.Camera) -> TagPose | None:
    """Pose of a tag from its distorted pixel corners (4 x 2, OpenCV aruco order), or None if degenerate.

    Both IPPE solutions of the planar ambiguity are computed on the undistorted corners and refined by least
    squares on the distorted ones through the camera model (:func:`estimate_tag_poses`, analytic Jacobian);
    the one with the smaller reprojection error is returned with the other kept for the ambiguity ratio.
    """
    return estimate_tag_poses(np.asarray(corners_px, float).reshape(1, 4, 2), [size_m], camera)[0]


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
