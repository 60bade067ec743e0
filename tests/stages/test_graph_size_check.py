"""The tag size against the odometry (stages.graph.size_check): the ratio of the camera motion two sightings of a
tag measure to the odometry's, exact on noiseless sightings from a camera mounted off the base's axis."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.graph.size_check import MIN_PAIRS, size_warning, tag_odometry_ratio


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
    out = tag_odometry_ratio(
        np.array(kf), np.array(ids), np.repeat(T_base_camera[None], n, axis=0), np.array(t_ct), np.array(base)
    )
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
