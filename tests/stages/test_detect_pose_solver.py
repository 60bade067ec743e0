"""detect: the batched tag pose solver against the camera models and the former pycolmap refinement.

The numpy projection must equal pycolmap's for every lens model the project makes, its Jacobian must equal
finite differences, and the solver must reach the least-squares optimum pycolmap's objective has (checked
against an independent solver on pycolmap's projection) with pycolmap's covariance there.
"""

from __future__ import annotations

import numpy as np
import pytest

from stages.camera import colmap_camera
from stages.detect.pose import corner_jacobian, estimate_tag_pose, estimate_tag_poses, tag_object_points
from stages.detect.projection import Projection
from stages.ingest.artifacts import CameraModel
from tests.fixtures.tag_render import TagPlacement, corners_of, look_at_tag
from tests.oracles.tag_pose_colmap import corner_jacobian_fd, estimate_tag_pose_colmap

LENSES = {
    "none": [],
    "plumb_bob": [-0.12, 0.02, 0.0008, -0.0005, 0.0],
    "rational_polynomial": [-0.3, 0.09, 0.0008, -0.0005, -0.01, 0.05, -0.02, 0.004],
    "equidistant": [-0.02, 0.015, -0.009, 0.0017],
}


def _camera(model: str) -> CameraModel:
    f = 300.0 if model == "equidistant" else 420.0
    return CameraModel(
        width=640, height=480, K=[f, 0, 318.3, 0, f * 1.002, 241.7, 0, 0, 1], distortion_model=model, D=LENSES[model]
    )


def _views(cam: object, n: int, seed: int) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Noisy corners of ``n`` random tag views (0.5-3 m, oblique, off-centre), with each tag's size and pose."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        size = float(rng.choice([0.08, 0.16]))
        T = look_at_tag(
            rng.uniform(0.5, 3.0),
            rng.uniform(-50, 50),
            rng.uniform(-30, 30),
            rng.uniform(-20, 20),
            rng.uniform(-0.4, 0.4, 2),
        )
        c = corners_of(cam, TagPlacement(0, "tag36h11", size, T))
        out.append((c + rng.normal(0, 0.3, c.shape), size, T))
    return out


@pytest.mark.parametrize("model", list(LENSES))
def test_projection_equals_pycolmap_and_its_jacobian_finite_differences(model: str) -> None:
    cam = colmap_camera(_camera(model))
    proj = Projection.of(cam)
    rng = np.random.default_rng(0)
    P = np.c_[rng.uniform(-1.2, 1.2, (300, 2)), rng.uniform(0.4, 4.0, 300)]
    P[0] = [0.0, 0.0, 1.0]  # on the optical axis (the fisheye's r = 0 case)
    uv, J = proj.project(P, jacobian=True)
    assert J is not None
    assert np.allclose(uv, np.asarray(cam.img_from_cam(P, check_cheirality=False)), rtol=0, atol=1e-9)
    h = 1e-6
    fd = np.stack([(proj.project(P + h * e)[0] - proj.project(P - h * e)[0]) / (2 * h) for e in np.eye(3)], axis=-1)
    assert np.allclose(J, fd, rtol=1e-6, atol=1e-5 * np.abs(J).max())


def test_projection_refuses_a_model_it_does_not_evaluate() -> None:
    import pycolmap

    with pytest.raises(ValueError, match="SIMPLE_RADIAL"):
        Projection.of(pycolmap.Camera(model="SIMPLE_RADIAL", width=10, height=10, params=[5.0, 5.0, 5.0, 0.1]))


@pytest.mark.parametrize("model", list(LENSES))
def test_corner_jacobian_equals_finite_differences_through_pycolmap(model: str) -> None:
    cam = colmap_camera(_camera(model))
    T = look_at_tag(1.2, 35, -15, 10, (0.2, 0.1))
    obj = tag_object_points(0.16)
    J = corner_jacobian(cam, T, obj)
    assert np.allclose(J, corner_jacobian_fd(cam, T, obj), rtol=1e-6, atol=1e-6 * np.abs(J).max())


@pytest.mark.parametrize("model", list(LENSES))
def test_solver_reaches_the_optimum_of_pycolmaps_objective_with_its_covariance(model: str) -> None:
    """Against pycolmap's refinement carried to the optimum by scipy on pycolmap's projection, with pycolmap's
    covariance there: poses, squared errors, covariances and the ambiguity fields agree to tight tolerances."""
    cam = colmap_camera(_camera(model))
    views = _views(cam, 8, seed=3)
    new = estimate_tag_poses([c for c, _, _ in views], [s for _, s, _ in views], cam)
    for (c, size, _), pose in zip(views, new, strict=True):
        ref = estimate_tag_pose_colmap(c, size, cam, polish=True)
        assert pose is not None and ref is not None
        assert np.allclose(pose.T_camera_tag, ref.T_camera_tag, rtol=0, atol=1e-7)
        assert abs(pose.sse_px2 - ref.sse_px2) < 1e-9
        assert np.allclose(pose.cov_unit, ref.cov_unit, rtol=1e-5, atol=1e-6 * np.abs(ref.cov_unit).max())
        assert np.allclose(pose.scale_dir, ref.scale_dir, rtol=1e-5, atol=1e-6 * np.abs(ref.scale_dir).max())
        assert (pose.alt_T_camera_tag is None) == (ref.alt_T_camera_tag is None)
        if ref.alt_T_camera_tag is not None:
            assert pose.alt_cov_unit is not None and pose.alt_offset is not None and ref.alt_offset is not None
            assert np.allclose(pose.alt_T_camera_tag, ref.alt_T_camera_tag, rtol=0, atol=1e-6)
            assert abs(pose.alt_sse_px2 - ref.alt_sse_px2) < 1e-9
            assert np.allclose(pose.alt_offset, ref.alt_offset, rtol=1e-5, atol=1e-7)


def test_solver_is_at_least_as_good_as_the_former_refinement() -> None:
    """pycolmap's Ceres run stopped at a relative cost change of 1e-6; the solver goes to the optimum, so its
    squared error is never above the former one, and lower where that one had stopped short."""
    cam = colmap_camera(_camera("plumb_bob"))
    views = _views(cam, 30, seed=8)
    new = estimate_tag_poses([c for c, _, _ in views], [s for _, s, _ in views], cam)
    gaps = []
    for (c, size, _), pose in zip(views, new, strict=True):
        old = estimate_tag_pose_colmap(c, size, cam)
        assert pose is not None and old is not None
        assert pose.sse_px2 <= old.sse_px2 + 1e-12
        gaps.append(old.sse_px2 - pose.sse_px2)
    assert max(gaps) > 1e-9


def test_batch_equals_one_tag_at_a_time_and_keeps_the_order() -> None:
    cam = colmap_camera(_camera("plumb_bob"))
    views = _views(cam, 12, seed=5)
    corners = [c for c, _, _ in views]
    corners[4] = np.full((4, 2), np.nan)  # fails alone, and must not disturb the others
    batch = estimate_tag_poses(corners, [s for _, s, _ in views], cam)
    assert batch[4] is None and estimate_tag_poses([], [], cam) == []
    for c, (_, size, T), pose in zip(corners, views, batch, strict=True):
        one = estimate_tag_pose(c, size, cam)
        if pose is None:
            assert one is None
            continue
        assert one is not None
        assert np.allclose(pose.T_camera_tag, one.T_camera_tag, rtol=0, atol=1e-12)
        assert np.allclose(pose.cov_unit, one.cov_unit, rtol=1e-10, atol=0)
        assert np.linalg.norm(pose.T_camera_tag[:3, 3] - T[:3, 3]) < 0.05 * np.linalg.norm(T[:3, 3])


@pytest.mark.parametrize("model", list(LENSES))
def test_weighted_projection_hessian_equals_finite_differences_of_the_jacobian(model: str) -> None:
    proj = Projection.of(colmap_camera(_camera(model)))
    rng = np.random.default_rng(1)
    P = np.c_[rng.uniform(-1.0, 1.0, (200, 2)), rng.uniform(0.5, 4.0, 200)]
    w = rng.normal(size=(200, 2))
    H = proj.weighted_hessian(P, w)
    h = 1e-6
    fd = np.stack(
        [
            np.einsum("mc,mci->mi", w, (proj.project(P + h * e, True)[1] - proj.project(P - h * e, True)[1]) / (2 * h))  # type: ignore[operator]
            for e in np.eye(3)
        ],
        axis=-1,
    )
    assert np.allclose(H, H.transpose(0, 2, 1))
    assert np.allclose(H, fd, rtol=0, atol=1e-6 * np.abs(H).max())


@pytest.mark.parametrize("model", list(LENSES))
def test_newton_hessian_equals_finite_differences_of_the_cost(model: str) -> None:
    """``J^T J + S`` of the solver is the Hessian of half the squared corner error in the coordinates it steps in,
    ``(w, v) -> (R Exp(w), t + R v)``, away from the optimum (noisy corners), where ``S`` matters."""
    from stages.detect.pose import _evaluate, _projection, _so3_exp_batch

    cam = colmap_camera(_camera(model))
    proj = _projection(cam)
    views = _views(cam, 12, seed=5)
    R = np.stack([T[:3, :3] for _, _, T in views])
    t = np.stack([T[:3, 3] for _, _, T in views])
    obj = np.stack([tag_object_points(s) for _, s, _ in views])
    rng = np.random.default_rng(2)
    corners = np.stack([c for c, _, _ in views]) + rng.normal(0, 3.0, (12, 4, 2))
    ev = _evaluate(proj, R, t, obj, corners, second_order=True)
    assert ev.S is not None
    H = ev.J.transpose(0, 2, 1) @ ev.J + ev.S

    def half_cost(xi: np.ndarray) -> np.ndarray:
        Rn = R @ _so3_exp_batch(xi[:, :3])
        return 0.5 * _evaluate(proj, Rn, t + np.einsum("mij,mj->mi", R, xi[:, 3:]), obj, corners).cost

    h = 1e-4
    fd = np.zeros_like(H)
    for i in range(6):
        for j in range(6):
            d = [np.zeros((12, 6)) for _ in range(4)]
            for k, (si, sj) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
                d[k][:, i] += si * h
                d[k][:, j] += sj * h
            f = [half_cost(x) for x in d]
            fd[:, i, j] = (f[0] - f[1] - f[2] + f[3]) / (4 * h * h)
    scale = np.abs(fd).max(axis=(1, 2), keepdims=True)
    assert np.abs(ev.S).max() > 1e-3 * np.abs(H).max()  # the second-order term is not negligible here
    assert np.all(np.abs(H - fd) <= 1e-6 * scale)


def test_batched_ippe_equals_opencv_ippe_square() -> None:
    """The numpy IPPE starts are OpenCV's ``SOLVEPNP_IPPE_SQUARE`` solutions, in its order; corners that give no
    homography (non-finite, coincident, collinear) give none, without raising."""
    import cv2

    from stages.detect.pose import _ippe_starts, so3_exp

    rng = np.random.default_rng(3)
    xy, halves, ref = [], [], []
    while len(xy) < 300:
        R = so3_exp(rng.normal(size=3) * rng.uniform(0, 1.4))
        t = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.4, 8.0)])
        half = rng.uniform(0.02, 0.2)
        P = tag_object_points(2 * half) @ R.T + t
        if np.any(P[:, 2] < 0.1):
            continue
        c = P[:, :2] / P[:, 2:] + rng.normal(0, 1e-3, (4, 2)) * rng.uniform(0, 2)
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            tag_object_points(2 * half), c.reshape(4, 1, 2), np.eye(3), None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        assert n == 2
        xy.append(c)
        halves.append(half)
        ref.append([(cv2.Rodrigues(r)[0], tv.ravel()) for r, tv in zip(rvecs, tvecs, strict=True)])
    bad = [np.full((4, 2), np.nan), np.zeros((4, 2)), np.c_[np.arange(4) * 0.01, np.zeros(4)]]
    R_all, t_all, ok = _ippe_starts(np.array(xy + bad), np.array(halves + [0.1] * 3))
    assert ok[:300].all() and not ok[300:].any()
    for k, sols in enumerate(ref):
        for s, (Rr, tr) in enumerate(sols):
            assert np.allclose(R_all[k, s], Rr, rtol=0, atol=1e-6)
            assert np.allclose(t_all[k, s], tr, rtol=1e-6, atol=0)
