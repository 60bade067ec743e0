"""detect: the pose covariance model beyond white corner noise, checked by Monte Carlo.

* correlated corner noise ``Sigma_c = sigma^2 I + beta^2 s s^T`` (an edge bias moving all four corners along
  their diagonals together) propagated as ``(J^T J)^-1 J^T Sigma_c J (J^T J)^-1``;
* the two-mode mixture of both planar (IPPE) solutions for views where either may be the true one.
"""

from __future__ import annotations

import numpy as np
import pytest

from stages.camera import colmap_camera
from stages.detect.pose import (
    corner_jacobian,
    estimate_tag_pose,
    pose_covariance,
    scale_mode,
    se3_log,
    so3_exp,
    tag_object_points,
)
from tests.fixtures.tag_render import TagPlacement, corners_of, look_at_tag, plumb_bob_camera
from tests.oracles.tag_pose_colmap import corner_jacobian_fd, estimate_tag_pose_colmap

CAMERA = plumb_bob_camera()


def _errors(cam: object, T_true: np.ndarray, corners: list[np.ndarray], size: float) -> list[tuple[object, np.ndarray]]:
    import gtsam

    out = []
    for c in corners:
        pose = estimate_tag_pose(c, size, cam)
        assert pose is not None
        out.append((pose, gtsam.Pose3(pose.T_camera_tag).localCoordinates(gtsam.Pose3(T_true))))
    return out


def _alt(pose: object) -> tuple | None:
    if pose.alt_cov_unit is None:  # type: ignore[attr-defined]
        return None
    return (pose.alt_cov_unit, pose.alt_scale_dir, pose.alt_offset, pose.alt_sse_px2)  # type: ignore[attr-defined]


def test_jacobian_matches_pycolmap_covariance_and_se3_log_matches_gtsam() -> None:
    import gtsam

    cam = colmap_camera(CAMERA)
    T = look_at_tag(1.5, 30, 10, 5, (0.1, 0.05))
    pose = estimate_tag_pose(corners_of(cam, TagPlacement(0, "tag36h11", 0.15, T)), 0.15, cam)
    assert pose is not None
    J = corner_jacobian(cam, pose.T_camera_tag, tag_object_points(0.15))
    assert np.allclose(J, corner_jacobian_fd(cam, pose.T_camera_tag, tag_object_points(0.15)), rtol=1e-6, atol=1e-4)
    # pycolmap's own covariance at the optimum (its quaternion tangent converted to GTSAM's) is (J^T J)^-1.
    ref = estimate_tag_pose_colmap(corners_of(cam, TagPlacement(0, "tag36h11", 0.15, T)), 0.15, cam, polish=True)
    assert ref is not None
    assert np.allclose(ref.cov_unit, pose.cov_unit, rtol=1e-5, atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(5):
        xi = rng.normal(0, 0.8, 6)
        assert np.allclose(se3_log(gtsam.Pose3.Expmap(xi).matrix()), xi, atol=1e-8)
    assert np.allclose(so3_exp(np.array([0, 0, np.pi / 2])) @ [1, 0, 0], [0, 1, 0])
    # The scale mode: unit outward displacement of each corner from the quad's centre.
    s = scale_mode(np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])).reshape(4, 2)
    assert np.allclose(np.linalg.norm(s, axis=1), 1.0) and np.allclose(s[0], [-(0.5**0.5), -(0.5**0.5)])


def test_correlated_edge_bias_matches_monte_carlo_spread() -> None:
    """White noise plus a random common outward/inward shift of every corner (beta): the reported
    covariance must match the sampled spread; the white-only covariance must not."""
    cam = colmap_camera(CAMERA)
    T_true = look_at_tag(1.2, 35, -15, 10, (0.1, 0.05))
    truth = corners_of(cam, TagPlacement(0, "tag36h11", 0.15, T_true))
    sigma, beta = 0.15, 0.4
    s = scale_mode(truth).reshape(4, 2)
    rng = np.random.default_rng(5)
    noisy = [truth + rng.normal(0, sigma, (4, 2)) + rng.normal(0, beta) * s for _ in range(300)]
    results = _errors(cam, T_true, noisy, 0.15)
    errors = np.array([e for _, e in results])
    pose0 = results[0][0]
    cov, _ = pose_covariance(pose0.cov_unit, pose0.scale_dir, sigma, beta, mixture=False)  # type: ignore[attr-defined]
    white, _ = pose_covariance(pose0.cov_unit, pose0.scale_dir, sigma, 0.0, mixture=False)  # type: ignore[attr-defined]
    sample = np.cov(errors.T)
    ratio = np.sqrt(np.diag(sample) / np.diag(cov))
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio
    nees = np.mean([e @ np.linalg.solve(cov, e) for e in errors]) / 6
    nees_white = np.mean([e @ np.linalg.solve(white, e) for e in errors]) / 6
    assert 0.75 < nees < 1.35, nees
    assert nees_white > 2.0, nees_white  # the correlated part is not visible in the residuals
    # beta adds exactly a rank-one term along the scale direction
    assert np.linalg.matrix_rank(cov - white, tol=1e-12) == 1


def test_ambiguity_mixture_is_honest_where_the_planar_solution_flips() -> None:
    """A small, far, near-frontal tag: the chosen IPPE solution is often the wrong one. The local covariance
    is then far too small (NEES >> 1); the mixture covariance of both solutions is honest."""
    cam = colmap_camera(CAMERA)
    T_true = look_at_tag(4.0, 15, 5, 0, (0.2, 0.0))
    size, sigma = 0.16, 0.15
    truth = corners_of(cam, TagPlacement(0, "tag36h11", size, T_true))
    rng = np.random.default_rng(7)
    results = _errors(cam, T_true, [truth + rng.normal(0, sigma, (4, 2)) for _ in range(300)], size)
    nees_local, nees_mix, flips, p_alt = [], [], 0, []
    for pose, e in results:
        local, _ = pose_covariance(pose.cov_unit, pose.scale_dir, sigma, 0.0, mixture=False)  # type: ignore[attr-defined]
        alt = _alt(pose)
        mix, p = pose_covariance(pose.cov_unit, pose.scale_dir, sigma, 0.0, pose.sse_px2, alt)  # type: ignore[attr-defined]
        nees_local.append(e @ np.linalg.solve(local, e) / 6)
        nees_mix.append(e @ np.linalg.solve(mix, e) / 6)
        p_alt.append(p)
        flips += bool(np.linalg.norm(e[:3]) > 0.1)
    assert flips > 15  # the view is genuinely ambiguous
    assert np.mean(nees_local) > 10, np.mean(nees_local)
    assert 0.5 < np.mean(nees_mix) < 2.0, np.mean(nees_mix)
    # the reported flip probability is of the order of the flip rate
    assert 0.3 * flips / len(results) < np.mean(p_alt) < 3 * flips / len(results)


@pytest.mark.parametrize("distance", [0.6, 1.2])
def test_mixture_leaves_clear_views_alone(distance: float) -> None:
    cam = colmap_camera(CAMERA)
    T = look_at_tag(distance, 40, -20, 10, (0.1, 0.05))
    truth = corners_of(cam, TagPlacement(0, "tag36h11", 0.15, T))
    pose = estimate_tag_pose(truth + np.random.default_rng(1).normal(0, 0.15, (4, 2)), 0.15, cam)
    assert pose is not None
    local, _ = pose_covariance(pose.cov_unit, pose.scale_dir, 0.15, 0.0, mixture=False)
    mix, p = pose_covariance(pose.cov_unit, pose.scale_dir, 0.15, 0.0, pose.sse_px2, _alt(pose))
    assert p < 1e-6
    assert np.allclose(mix, local, rtol=1e-4, atol=1e-15)
