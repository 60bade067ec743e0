"""The camera's motion as the tags measure it against the wheel odometry's, before any solve: how far the camera
moved between two sightings of one tag (the tag size, :func:`ratio_figures`) and in which direction (the camera's
mounting rotation, :func:`mounting_figures`).

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

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

MIN_BASELINE_M = 0.3
"""A pair's camera positions at least this far apart (a shorter motion is dominated by the tags' noise)."""
MAX_SPAN_M = 3.0
"""... and at most this much odometry path between them (the odometry's drift stays small)."""
MIN_PAIRS = 20
"""Fewer pairs are not judged."""
MAX_SIZE_FACTOR = 4.0
"""A ratio beyond this factor either way is not read as a tag size (a motion at right angles gives about 0)."""
OUTLIER_DEG = 20.0
"""Pairs whose directions differ by more than this after the first rotation fit are left out of the second."""
MAX_TURN_DEG = 10.0
"""Pairs along which the camera turned more are not used for the mounting rotation."""
COLLINEAR = 0.02
"""Directions whose second principal value is below this share of their count lie along one line."""
MOUNT_ROUNDS = 5
"""Fits of the mounting rotation, each on the pairs recomputed with the last one's correction."""
BOOTSTRAP = 40
"""Resamples of the pairs for the rotation angle's standard error."""
MOUNT_MAX_DEG = 3.0
"""A camera whose fitted rotation exceeds this (and 3 of its standard errors) fails the ``extrinsics`` check (at
5 m a 3 degree turn moves a tag 26 cm sideways). Wheels whose heading drifts by ``b`` rad per metre bend each pair's
tag-measured motion by about ``b`` times the tag's range, which looks like a mounting error: 0.01 rad/m (a strong
bias) gave up to 1.9 degrees on held-out worlds with exact mountings."""
RATIO_MAX = 0.10
"""The tags' motion more than this fraction away from the odometry's (and beyond 3 of its standard errors) fails
the ``tag_size`` health check."""


@dataclass
class Sightings:
    """The detections, in any order: ``keyframe`` (index into ``T_odom_base``), ``camera`` (a camera index),
    ``T_base_camera`` (n x 4 x 4, each detection's camera mount) and ``t_camera_tag`` (n x 3)."""

    keyframe: np.ndarray
    camera: np.ndarray
    T_base_camera: np.ndarray
    t_camera_tag: np.ndarray
    T_odom_base: np.ndarray
    """Per keyframe, the odometry's 4x4 pose of the base."""


@dataclass
class MotionPairs:
    """Pairs of sightings of one tag: the camera's motion the odometry gives and the one the tags measure."""

    odometry: np.ndarray
    """n x 3: ``t``, the camera's translation between the two sightings, from the odometry and the extrinsics, in
    the first sighting's camera frame."""
    tags: np.ndarray
    """n x 3: ``m_i − R m_j``, the same translation as the tags measure it (``f t`` for tags ``1/f`` times the
    assumed size)."""
    camera: np.ndarray
    """Per pair, the camera of both sightings, or -1 when two cameras saw them."""
    turn_deg: np.ndarray
    """Per pair, the camera's rotation between the sightings from the odometry, degrees."""
    first: np.ndarray
    second: np.ndarray
    """The two sightings of each pair (indices into :class:`Sightings`)."""
    sightings: Sightings

    def with_mount(self, camera: int, T_base_camera: np.ndarray) -> MotionPairs:
        """The same pairs with ``camera`` mounted at ``T_base_camera`` instead."""
        mounts = self.sightings.T_base_camera.copy()
        mounts[self.sightings.camera == camera] = T_base_camera
        return _vectors(replace(self.sightings, T_base_camera=mounts), self.first, self.second)


def _vectors(s: Sightings, i: np.ndarray, j: np.ndarray) -> MotionPairs:
    C = s.T_odom_base[s.keyframe] @ s.T_base_camera  # camera poses in the odometry frame
    T = np.linalg.solve(C[i], C[j]) if i.size else np.zeros((0, 4, 4))  # C_i⁻¹ C_j
    R, t = T[:, :3, :3], T[:, :3, 3]
    d = s.t_camera_tag[i] - np.einsum("nij,nj->ni", R, s.t_camera_tag[j])
    same = np.where(s.camera[i] == s.camera[j], s.camera[i], -1)
    turn = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    return MotionPairs(t.reshape(-1, 3), d.reshape(-1, 3), same, turn, i, j, s)


def motion_pairs(
    keyframe: np.ndarray,
    tag: np.ndarray,
    camera: np.ndarray,
    T_base_camera: np.ndarray,
    t_camera_tag: np.ndarray,
    T_odom_base: np.ndarray,
) -> MotionPairs:
    """For each sighting, the next sighting of its tag at least :data:`MIN_BASELINE_M` away within
    :data:`MAX_SPAN_M` of odometry path (see the module docstring).

    Args:
        keyframe: per detection, the index of its keyframe in ``T_odom_base``.
        tag: per detection, the tag id.
        camera: per detection, a camera index.
        T_base_camera: per detection, its camera's 4x4 pose in the base frame.
        t_camera_tag: per detection, the tag's position in the camera frame (n x 3).
        T_odom_base: per keyframe, the odometry's 4x4 pose of the base.
    """
    sightings = Sightings(keyframe, camera, T_base_camera, t_camera_tag, T_odom_base)
    C = T_odom_base[keyframe] @ T_base_camera
    base = T_odom_base[:, :3, 3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(base, axis=0), axis=1))])
    firsts: list[int] = []
    seconds: list[int] = []
    for t_id in np.unique(tag):
        rows = np.flatnonzero(tag == t_id)
        rows = rows[np.argsort(keyframe[rows], kind="stable")]
        pos = C[rows, :3, 3]
        along = path[keyframe[rows]]
        ends = np.searchsorted(along, along + MAX_SPAN_M, side="right")  # sightings within the span
        for a in range(len(rows) - 1):
            hit = np.flatnonzero(np.linalg.norm(pos[a + 1 : ends[a]] - pos[a], axis=1) >= MIN_BASELINE_M)
            if hit.size:
                firsts.append(int(rows[a]))
                seconds.append(int(rows[a + 1 + hit[0]]))
    return _vectors(sightings, np.asarray(firsts, dtype=np.int64), np.asarray(seconds, dtype=np.int64))


def ratio_figures(pairs: MotionPairs) -> dict[str, Any]:
    """The median of ``(m_i − R m_j)·t / |t|²`` over the pairs: ``{"pairs": n}``, with ``ratio``, ``ratio_se`` (its
    standard error from the median absolute deviation) and ``ratio_iqr`` when there is at least one pair."""
    t, d = pairs.odometry, pairs.tags
    out: dict[str, Any] = {"pairs": len(t)}
    if len(t):
        r = np.einsum("ni,ni->n", d, t) / np.einsum("ni,ni->n", t, t)
        med = float(np.median(r))
        mad = 1.4826 * float(np.median(np.abs(r - med)))
        q1, q3 = np.percentile(r, [25, 75])
        out |= {
            "ratio": round(med, 4),
            "ratio_se": round(float(1.2533 * mad / np.sqrt(r.size)), 4),
            "ratio_iqr": [round(float(q1), 4), round(float(q3), 4)],
        }
    return out


def _kabsch(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The rotation ``R`` that best maps the unit vectors ``u`` onto ``v`` (rows)."""
    U, _, Vt = np.linalg.svd(u.T @ v)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T))) or 1.0])
    return np.asarray(Vt.T @ D @ U.T)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _axis(u: np.ndarray) -> np.ndarray:
    """The principal direction of the unit vectors ``u`` (rows), signed towards most of them."""
    a = np.linalg.eigh(u.T @ u)[1][:, -1]
    return a if float(np.sum(u @ a > 0)) >= len(u) / 2 else -a


def _fit(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The rotation that best turns ``u`` into ``v``: Kabsch's, or, when the ``u`` lie along one line (a corridor:
    a turn about that line changes nothing and cannot be told), the smallest turn of their axis onto ``v``'s."""
    if np.linalg.svd(u, compute_uv=False)[1] ** 2 >= COLLINEAR * len(u):
        return _kabsch(u, v)
    a = _axis(u)
    b = _axis(v)
    b = b if float(np.mean(np.sign(u @ a) * np.sign(v @ b))) >= 0 else -b
    w, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(w) < 1e-12:
        return np.eye(3)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    return np.asarray(np.eye(3) + K + K @ K / (1.0 + c))


def _rotation_fit(pairs: MotionPairs, camera: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The fitted rotation and the unit directions it was fitted on (odometry's, tags'), or None with too few."""
    keep = (pairs.camera == camera) & (pairs.turn_deg < MAX_TURN_DEG)
    t, d = pairs.odometry[keep], pairs.tags[keep]
    ok = (np.linalg.norm(t, axis=1) > 0) & (np.linalg.norm(d, axis=1) > 0)
    u = t[ok] / np.linalg.norm(t[ok], axis=1)[:, None]
    v = d[ok] / np.linalg.norm(d[ok], axis=1)[:, None]
    if len(u) < MIN_PAIRS:
        return None
    R = _fit(u, v)
    near = np.einsum("ni,ni->n", u @ R.T, v) > np.cos(np.radians(OUTLIER_DEG))
    if near.sum() >= MIN_PAIRS:
        u, v = u[near], v[near]
        R = _fit(u, v)
    return R, u, v


def mounting_figures(pairs: MotionPairs, camera: int, R_base_camera: np.ndarray, seed: int = 0) -> dict[str, Any]:
    """How far the camera's mounting rotation looks off: the rotation that best turns the directions of the
    odometry's camera motions into the tags' (:func:`_fit` on unit vectors, again without the pairs more than
    :data:`OUTLIER_DEG` off after the first fit), its angle, a bootstrap standard error of the angle, and the
    correction as roll, pitch and yaw in the base frame (``R_base_camera`` should be that rotation times the one
    used). The odometry's rotation between two sightings, seen from the camera, depends on the mounting too, so the
    fit is repeated with the corrected mounting (:data:`MOUNT_ROUNDS` times). Only pairs along which the camera
    turned less than :data:`MAX_TURN_DEG`: over a turn, the wheels' yaw-rate error bends the odometry's direction
    of travel as a mounting error would. ``{"pairs": n}`` alone below :data:`MIN_PAIRS`."""
    rows = pairs.sightings.camera == camera
    T_used = pairs.sightings.T_base_camera[np.flatnonzero(rows)[0]] if rows.any() else np.eye(4)
    Q = np.eye(3)  # the correction so far, in the base frame
    fitted = None
    for _ in range(MOUNT_ROUNDS):
        T = T_used.copy()
        T[:3, :3] = Q @ R_base_camera
        fitted = _rotation_fit(pairs.with_mount(camera, T) if fitted is not None else pairs, camera)
        if fitted is None:
            return {"pairs": int(np.sum((pairs.camera == camera) & (pairs.turn_deg < MAX_TURN_DEG)))}
        R = fitted[0]
        Q = T[:3, :3] @ R.T @ T[:3, :3].T @ Q  # this round's correction on top of the last
    assert fitted is not None
    R, u, v = fitted
    rng = np.random.default_rng(seed)
    spread = [_angle_deg(R.T @ _fit(u[k], v[k])) for k in (rng.integers(0, len(u), len(u)) for _ in range(BOOTSTRAP))]
    return {
        "pairs": int(np.sum((pairs.camera == camera) & (pairs.turn_deg < MAX_TURN_DEG))),
        "pairs_fitted": len(u),
        "collinear": bool(np.linalg.svd(u, compute_uv=False)[1] ** 2 < COLLINEAR * len(u)),
        "angle_deg": round(_angle_deg(Q), 3),
        "angle_se_deg": round(float(np.sqrt(np.mean(np.square(spread)))), 3),
        "correction_roll_pitch_yaw_deg": [
            round(float(np.degrees(a)), 3)
            for a in (np.arctan2(Q[2, 1], Q[2, 2]), -np.arcsin(np.clip(Q[2, 0], -1, 1)), np.arctan2(Q[1, 0], Q[0, 0]))
        ],
    }


def mounting_warning(name: str, figures: dict[str, Any], source: str) -> str | None:
    """The ``extrinsics`` check's line for one camera whose mounting rotation looks off (None when it does not, or
    when there are too few pairs to tell)."""
    if "angle_deg" not in figures:
        return None
    angle, se = figures["angle_deg"], figures["angle_se_deg"]
    if angle <= max(MOUNT_MAX_DEG, 3.0 * se):
        return None
    roll, pitch, yaw = figures["correction_roll_pitch_yaw_deg"]
    return (
        f"the camera {name!r} moves, as its tags see it, in directions {angle:.1f} ± {se:.1f} degrees from those the "
        f"odometry and its extrinsics ({source}) give (fitted over {figures['pairs_fitted']} pairs of sightings): its "
        f"mounting rotation looks off by roll {roll:+.1f}, pitch {pitch:+.1f}, yaw {yaw:+.1f} degrees in the base "
        "frame; check the camera's transform (/tf_static or --extrinsics) before the tag size or the noise settings"
    )


def size_warning(figures: dict[str, Any], tag_size_m: float | None) -> str | None:
    """The ``tag_size`` check's line when the tags and the odometry disagree on distances (None when they agree
    or there are too few pairs to tell)."""
    if figures.get("pairs", 0) < MIN_PAIRS or "ratio" not in figures:
        return None
    ratio, se = figures["ratio"], figures["ratio_se"]
    if abs(ratio - 1.0) <= max(RATIO_MAX, 3.0 * se):
        return None
    if not 1.0 / MAX_SIZE_FACTOR <= ratio <= MAX_SIZE_FACTOR:  # no tag size explains that: the motions' directions
        return (
            f"the camera's motion between two sightings of a tag follows the odometry's nowhere near (its component "
            f"along the odometry's is {ratio:.3f} times as long, median of {figures['pairs']} pairs): the camera's "
            "extrinsics are likely wrong (see the extrinsics check), or the odometry is not this robot's"
        )
    size = (
        f"if the wheels' distances are right, the tags are {tag_size_m / ratio:.3f} m, not "
        f"detect.tag_size_m={tag_size_m:g} m"
        if tag_size_m
        else "if the wheels' distances are right, the tag size the detections assumed is wrong by that factor"
    )
    return (
        f"the tags and the wheel odometry disagree on distances: the camera's motion between two sightings of a tag "
        f"is {ratio:.3f} ± {se:.3f} times the odometry's (median of {figures['pairs']} pairs): {size}; measure the "
        "printed tags' black square and set detect.tag_size_m (if the tags are right, the camera model's focal "
        "length or the wheel odometry's distances are off by that factor; graph.odometry_calibration=true "
        "estimates the wheels')"
    )
