"""The tag size against the wheel odometry, before any solve: how far the camera moved between two sightings of
one tag, measured by the tag and by the odometry.

A detection gives the tag's position in the camera frame, ``m = f t`` where ``f`` is the assumed tag size over
the true one (the tag looks nearer when it is larger than assumed). For two sightings ``i``, ``j`` of one tag, the
odometry and the extrinsics give the camera's motion ``(R, t) = C_i⁻¹ C_j``, and a still tag satisfies
``t_i = R t_j + t``. So ``m_i − R m_j = f t``: its projection on ``t`` over ``|t|²`` estimates ``f`` from every such
pair, with the odometry's rotation (reliable over a few metres) and only the tags' positions (a tag's orientation
is the least certain part of its pose). The median over the pairs is the run's figure.

The graph's shared tag scale carries the same information, but under a prior that holds it within a percent or
two of 1: a tag size wrong by tens of percent (the default 0.162 m used for 0.30 m tags) then bends the odometry
instead, or moves the odometry calibration's distance scale, and the scale check stays quiet. This figure does not
depend on the solve. It cannot tell a wrong tag size from wheels whose distances are that far off; wheels off by
more than :data:`RATIO_MAX` are rare, so the warning names the tag size first and the wheels second.
"""

from __future__ import annotations

from typing import Any

import numpy as np

MIN_BASELINE_M = 0.3
"""A pair's camera positions at least this far apart (a shorter motion is dominated by the tags' noise)."""
MAX_SPAN_M = 3.0
"""... and at most this much odometry path between them (the odometry's drift stays small)."""
MIN_PAIRS = 20
"""Fewer pairs are not judged."""
RATIO_MAX = 0.10
"""The tags' motion more than this fraction away from the odometry's (and beyond 3 of its standard errors) fails
the ``tag_size`` health check."""


def tag_odometry_ratio(
    keyframe: np.ndarray,
    tag: np.ndarray,
    T_base_camera: np.ndarray,
    t_camera_tag: np.ndarray,
    T_odom_base: np.ndarray,
) -> dict[str, Any]:
    """The median ratio of the camera motion the tags measure to the odometry's (see the module docstring).

    Args:
        keyframe: per detection, the index of its keyframe in ``T_odom_base``.
        tag: per detection, the tag id.
        T_base_camera: per detection, the camera's 4x4 pose in the base frame.
        t_camera_tag: per detection, the tag's position in the camera frame (n x 3).
        T_odom_base: per keyframe, the odometry's 4x4 pose of the base.

    Returns:
        ``{"pairs": n}``, with ``ratio`` (median), ``ratio_se`` (its standard error from the median absolute
        deviation) and ``ratio_iqr`` when there is at least one pair.
    """
    C = T_odom_base[keyframe] @ T_base_camera  # camera poses in the odometry frame
    base = T_odom_base[:, :3, 3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(base, axis=0), axis=1))])
    ratios: list[float] = []
    for t_id in np.unique(tag):
        rows = np.flatnonzero(tag == t_id)
        rows = rows[np.argsort(keyframe[rows], kind="stable")]
        pos = C[rows, :3, 3]
        along = path[keyframe[rows]]
        ends = np.searchsorted(along, along + MAX_SPAN_M, side="right")  # sightings within the span
        for a in range(len(rows) - 1):
            far = np.linalg.norm(pos[a + 1 : ends[a]] - pos[a], axis=1) >= MIN_BASELINE_M
            hit = np.flatnonzero(far)
            if hit.size == 0:
                continue
            i, j = rows[a], rows[a + 1 + hit[0]]
            T = np.linalg.solve(C[i], C[j])  # C_i⁻¹ C_j
            R, t = T[:3, :3], T[:3, 3]
            d = t_camera_tag[i] - R @ t_camera_tag[j]
            ratios.append(float(d @ t) / float(t @ t))
    out: dict[str, Any] = {"pairs": len(ratios)}
    if ratios:
        r = np.asarray(ratios)
        med = float(np.median(r))
        mad = 1.4826 * float(np.median(np.abs(r - med)))
        q1, q3 = np.percentile(r, [25, 75])
        out |= {
            "ratio": round(med, 4),
            "ratio_se": round(float(1.2533 * mad / np.sqrt(r.size)), 4),
            "ratio_iqr": [round(float(q1), 4), round(float(q3), 4)],
        }
    return out


def size_warning(figures: dict[str, Any], tag_size_m: float | None) -> str | None:
    """The ``tag_size`` check's line when the tags and the odometry disagree on distances (None when they agree
    or there are too few pairs to tell)."""
    if figures.get("pairs", 0) < MIN_PAIRS or "ratio" not in figures:
        return None
    ratio, se = figures["ratio"], figures["ratio_se"]
    if abs(ratio - 1.0) <= max(RATIO_MAX, 3.0 * se):
        return None
    size = (
        f"if the wheels' distances are right, the tags are {tag_size_m / ratio:.3f} m, not "
        f"detect.tag_size_m={tag_size_m:g} m"
        if tag_size_m
        else "if the wheels' distances are right, the tag size the detections assumed is wrong by that factor"
    )
    return (
        f"the tags and the wheel odometry disagree on distances: the camera's motion between two sightings of a tag "
        f"is {ratio:.3f} ± {se:.3f} times the odometry's (median of {figures['pairs']} pairs): {size}; measure the "
        "printed tags' black square and set detect.tag_size_m (if the tags are right, the wheel odometry's "
        "distances are off by that factor: graph.odometry_calibration=true estimates it)"
    )
