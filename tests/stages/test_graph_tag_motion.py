"""The tag size against the odometry (stages.graph.tag_motion): the ratio of the camera motion two sightings of a
tag measure to the odometry's, exact on noiseless sightings from a camera mounted off the base's axis."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.graph.tag_motion import (
    MIN_PAIRS,
    MOUNT_MAX_DEG,
    motion_pairs,
    mounting_figures,
    mounting_warning,
    ratio_figures,
    size_warning,
)


def _pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = (x, y, z)
    return T


@pytest.mark.parametrize("f", [0.54, 1.0, 1.25])
def test_the_ratio_is_the_tag_size_error_with_a_lever_arm(f: float) -> None:
    rng = np.random.default_rng(4)
    # a base driving a curve; a camera 0.4 m ahead, 0.1 m left, 0.35 m up, looking 30 degrees left, optical axes
    T_base_camera = _pose(0.4, 0.1, math.radians(30), 0.35) @ np.array(
        [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float
    )
    base = [_pose(0.25 * k, 0.02 * k * k, 0.05 * k) for k in range(40)]
    tags = {i: np.array([rng.uniform(0, 12), rng.uniform(-3, 4), 0.35]) for i in range(8)}
    kf, ids, t_ct = [], [], []
    for k, B in enumerate(base):
        C = B @ T_base_camera
        for i, p in tags.items():
            local = np.linalg.solve(C, np.append(p, 1.0))[:3]
            if local[2] > 0.5:  # in front of the camera
                kf.append(k)
                ids.append(i)
                t_ct.append(f * local)  # tags of another size than assumed: every translation f times
    n = len(kf)
    one = np.zeros(n, dtype=int)
    mounts = np.repeat(T_base_camera[None], n, axis=0)
    out = ratio_figures(motion_pairs(np.array(kf), np.array(ids), one, mounts, np.array(t_ct), np.array(base)))
    assert out["pairs"] >= MIN_PAIRS
    assert out["ratio"] == pytest.approx(f, abs=1e-4) and out["ratio_se"] < 1e-4
    warning = size_warning(out, 0.162)
    if f == 1.0:
        assert warning is None
    else:
        assert warning is not None and f"the tags are {0.162 / f:.3f} m, not detect.tag_size_m=0.162 m" in warning


def test_too_few_pairs_or_a_small_disagreement_say_nothing() -> None:
    assert size_warning({"pairs": MIN_PAIRS - 1, "ratio": 0.5, "ratio_se": 0.001}, 0.162) is None
    assert size_warning({"pairs": 500, "ratio": 0.93, "ratio_se": 0.002}, 0.162) is None  # wheels a few % off
    assert size_warning({"pairs": 500, "ratio": 0.85, "ratio_se": 0.06}, 0.162) is None  # within its noise
    assert size_warning({"pairs": 500, "ratio": 0.85, "ratio_se": 0.01}, None) is not None


def _sightings(base: list[np.ndarray], T_base_camera: np.ndarray, tags: dict[int, np.ndarray], f: float = 1.0):
    """Noiseless sightings of the tags in front of the camera from each base pose: keyframe, tag, position."""
    kf, ids, t_ct = [], [], []
    for k, B in enumerate(base):
        C = B @ T_base_camera
        for i, p in tags.items():
            local = np.linalg.solve(C, np.append(p, 1.0))[:3]
            if 0.5 < local[2] < 8.0 and abs(local[0]) < local[2]:  # in front, within a 90 degree field of view
                kf.append(k)
                ids.append(i)
                t_ct.append(f * local)
    return np.array(kf), np.array(ids), np.array(t_ct)


_OPTICAL = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)


def _rotated(T: np.ndarray, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """``T``'s rotation turned in the base frame (degrees), its position kept."""
    from scipy.spatial.transform import Rotation

    out = T.copy()
    out[:3, :3] = Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix() @ T[:3, :3]
    return out


@pytest.mark.parametrize(("path", "error"), [("curve", (0, 0, 5)), ("curve", (0, 4, 0)), ("line", (0, 0, 0)),
                                             ("line", (0, 0, 5)), ("curve", (0, 0, 0))])  # fmt: skip
def test_a_rotated_mounting_is_measured_and_its_correction_named(path: str, error: tuple[float, float, float]) -> None:
    """The extrinsics say the camera is mounted ``error`` (roll, pitch, yaw) off its true rotation: the fit names
    the correction, the opposite turn. Along a straight corridor driven there and back, a turn about the direction
    of travel cannot be seen, and the fit must not invent one (a 180 degree turn maps a line onto itself)."""
    rng = np.random.default_rng(5)
    true_mount = _pose(0.3, 0.05, math.radians(20), 0.4) @ _OPTICAL
    if path == "curve":
        base = [_pose(0.2 * k * math.cos(0.03 * k), 0.2 * k * math.sin(0.03 * k), 0.03 * k) for k in range(60)]
        tags = {i: np.array([rng.uniform(-2, 12), rng.uniform(-2, 8), 0.4]) for i in range(30)}
    else:
        out = [_pose(0.2 * k, 0.0, 0.0) for k in range(40)]
        base = out + [_pose(8.0 - 0.2 * k, 0.0, math.pi) for k in range(40)]
        tags = {i: np.array([rng.uniform(-1, 10), rng.choice([-1.2, 1.2]), 0.4]) for i in range(30)}
    kf, ids, t_ct = _sightings(base, true_mount, tags)
    used = _rotated(true_mount, *error)
    pairs = motion_pairs(kf, ids, np.zeros(len(kf), int), np.repeat(used[None], len(kf), axis=0), t_ct, np.array(base))
    out = mounting_figures(pairs, 0, used[:3, :3])
    assert out["pairs_fitted"] >= MIN_PAIRS and out["collinear"] == (path == "line")
    roll, pitch, yaw = out["correction_roll_pitch_yaw_deg"]
    if path == "line":  # only the yaw of the corridor's axis can be seen
        assert yaw == pytest.approx(-error[2], abs=0.05) and out["angle_deg"] == pytest.approx(error[2], abs=0.05)
    else:
        assert [roll, pitch, yaw] == pytest.approx([-e for e in error], abs=0.05)
    warning = mounting_warning("cam", out, "/tf_static")
    assert (warning is None) == (max(error) < MOUNT_MAX_DEG)
    if warning is not None:
        assert "check the camera's transform (/tf_static or --extrinsics)" in warning
