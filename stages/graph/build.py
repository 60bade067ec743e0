"""Build the full SLAM problem of a recorded run from ingest's odometry and extrinsics and detect's tags.

Keyframes are the stamps of camera frames that saw tags, plus odometry stamps wherever the robot
went too long, too far or turned too much without one (so the path stays connected). Odometry is
interpolated on SE(2)/SE(3) to the keyframe stamps. Factors:

- ``prior`` on the first keyframe (it defines the map frame);
- ``odometry`` between consecutive keyframes (noise from the messages' covariances or the settings),
  or ``motion_prior`` (zero motion, weak) when the run has no odometry;
- ``tag``: one per detection. ``3d``: ``BetweenFactorPose3(X(k), L(tag))`` with ``T_base_tag =
  T_base_camera T_camera_tag`` and the detection's 6x6 covariance (right perturbation, so the
  extrinsic does not change it). ``planar``: the tag centre in the base frame, its 3x3 covariance
  ``R_base_tag Σ_tt R_base_tag^T`` projected onto (x, y), expressed as a ``BearingRangeFactor2D``
  to a ``Point2`` landmark (the bearing-range form of the same 2D relative position, to first order).
- ``scale_prior`` (``graph.tag_scale_sigma > 0``): the shared tag scale ``s`` ~ N(1, sigma²); every tag
  factor then carries ``s`` as a third key and measures ``s`` times its range (planar) or translation (3d).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
import pyarrow as pa
from gtsam.symbol_shorthand import L, X

from pipeline.errors import InputError, StageError
from stages.geometry import (
    interpolate_pose3,
    pose2_from_pose3,
    pose2_to_vector,
    pose3_from_matrix,
    pose3_from_xyz_quat,
    pose3_to_vector,
    relative_position_to_bearing_range_2d,
    ros_pose_cov_to_gtsam,
    rotate_covariance,
)
from stages.graph.config import GraphConfig
from stages.graph.factors import SCALE_KEY, FactorRow
from stages.graph.problem import GraphProblem

ODOMETRY_MIN_EIG_RATIO = 1e-3
"""Smallest eigenvalue of an odometry covariance taken from the messages, as a fraction of its largest."""
MESSAGE_VARIANCE_TINY = 1e-12
"""Odometry message variances (m², rad²) that differ by no more than this are taken as not growing."""
MIN_PLANAR_RANGE_M = 0.05
"""Planar tag measurements closer than this to the base's vertical axis have no usable bearing."""


@dataclass
class Odometry:
    """Odometry poses in the odometry frame, with their covariances in gtsam tangent order (world frame)."""

    stamps_ns: np.ndarray
    poses: list[gtsam.Pose3]
    cov: np.ndarray  # N x 6 x 6, (r, t), ROS covariance reordered (parent frame)

    @classmethod
    def from_table(cls, table: pa.Table | None) -> Odometry | None:
        """Odometry from ingest's ``odometry.parquet``; None when the run has none."""
        if table is None or table.num_rows == 0:
            return None
        cols = table.to_pydict()
        order = np.argsort(np.asarray(cols["stamp_ns"], dtype=np.int64), kind="stable")
        stamps = np.asarray(cols["stamp_ns"], dtype=np.int64)[order]
        keep = np.concatenate([[True], np.diff(stamps) > 0])
        order, stamps = order[keep], stamps[keep]
        poses = [
            pose3_from_xyz_quat(
                [cols["x"][i], cols["y"][i], cols["z"][i]], [cols["qx"][i], cols["qy"][i], cols["qz"][i], cols["qw"][i]]
            )
            for i in order
        ]
        if "pose_cov" in cols:
            cov = np.array([ros_pose_cov_to_gtsam(cols["pose_cov"][i] or np.zeros(36)) for i in order])
        else:
            cov = np.zeros((len(order), 6, 6))
        return cls(stamps, poses, cov)

    def at(self, stamps_ns: np.ndarray) -> tuple[list[gtsam.Pose3], np.ndarray]:
        """Poses (SE(3) interpolation) and covariances (linear interpolation) at ``stamps_ns``, clamped to the ends."""
        t = self.stamps_ns
        idx = np.searchsorted(t, stamps_ns, side="right")
        poses, covs = [], []
        for s, i in zip(np.asarray(stamps_ns, dtype=np.int64), idx, strict=True):
            if i <= 0:
                poses.append(self.poses[0])
                covs.append(self.cov[0])
            elif i >= len(t):
                poses.append(self.poses[-1])
                covs.append(self.cov[-1])
            else:
                a = float(s - t[i - 1]) / float(t[i] - t[i - 1])
                poses.append(interpolate_pose3(self.poses[i - 1], self.poses[i], a))
                covs.append((1 - a) * self.cov[i - 1] + a * self.cov[i])
        return poses, np.array(covs).reshape(len(poses), 6, 6)


def camera_extrinsic(extrinsics: dict[str, Any] | None, camera: str) -> tuple[gtsam.Pose3, str]:
    """``T_base_camera`` for a detection's ``camera`` value, and where it came from."""
    sensors = (extrinsics or {}).get("sensors") or {}
    entry = sensors.get(camera)
    if entry is None:
        entry = next((s for s in sensors.values() if s and s.get("frame_id") == camera), None)
    if entry is None and "camera" in sensors:
        entry = sensors["camera"]
    if entry is None or entry.get("T_base_sensor") is None:
        return gtsam.Pose3(), "identity (no base-to-camera transform in extrinsics.json)"
    return pose3_from_matrix(entry["T_base_sensor"]), "extrinsics.json"


def _keyframes(det_stamps: np.ndarray, odom: Odometry | None, cfg: GraphConfig) -> tuple[np.ndarray, np.ndarray]:
    """Keyframe stamps (sorted) and whether each is a tag frame."""
    if odom is None:
        return det_stamps, np.ones(len(det_stamps), dtype=bool)
    det_set = set(det_stamps.tolist())
    stamps: list[int] = []
    det_i = 0
    last_pose: gtsam.Pose3 | None = None
    last_t = 0
    det_poses, _ = odom.at(det_stamps) if len(det_stamps) else ([], None)
    for t, pose in zip(odom.stamps_ns, odom.poses, strict=True):
        while det_i < len(det_stamps) and det_stamps[det_i] <= t:
            stamps.append(int(det_stamps[det_i]))
            last_pose, last_t = det_poses[det_i], int(det_stamps[det_i])
            det_i += 1
        if last_pose is None:
            stamps.append(int(t))
            last_pose, last_t = pose, int(t)
            continue
        rel = last_pose.between(pose)
        moved = float(np.linalg.norm(np.asarray(rel.translation())[:2]))
        turned = float(np.linalg.norm(gtsam.Rot3.Logmap(rel.rotation())))
        due = (
            (t - last_t) / 1e9 > cfg.keyframe_max_gap_s
            or moved > cfg.keyframe_max_distance_m
            or turned > cfg.keyframe_max_angle_rad
        )
        if due and int(t) not in det_set and int(t) != last_t:
            stamps.append(int(t))
            last_pose, last_t = pose, int(t)
    while det_i < len(det_stamps):
        stamps.append(int(det_stamps[det_i]))
        det_i += 1
    out = np.unique(np.asarray(stamps, dtype=np.int64))
    return out, np.isin(out, det_stamps)


def _settings_cov(cfg: GraphConfig, planar: bool, dist: float, angle: float) -> np.ndarray:
    st = float(np.hypot(cfg.odometry_sigma_m, cfg.odometry_sigma_per_m * dist))
    sr = float(
        np.sqrt(
            cfg.odometry_sigma_rad**2
            + (cfg.odometry_sigma_rad_per_rad * angle) ** 2
            + (cfg.odometry_sigma_rad_per_m * dist) ** 2
        )
    )
    if planar:
        return np.diag([st**2, st**2, sr**2])
    return np.diag([sr**2] * 3 + [st**2] * 3)


def _unobserved_dims(cov: np.ndarray, planar: bool) -> np.ndarray:
    """Dimensions (in the factor's tangent order) whose message variance never changes over the run.

    Planar wheel odometry publishes fixed placeholders for z, roll and pitch: they carry no information
    about the motion and take the settings' value. A dimension that grows anywhere in the run is observed,
    even where it does not grow between two keyframes (the lateral position of a robot driving straight).
    """
    idx = [3, 4, 2] if planar else list(range(6))
    d = np.diagonal(cov, axis1=1, axis2=2)[:, idx] if len(cov) else np.zeros((0, len(idx)))
    if len(d) == 0:
        return np.ones(len(idx), dtype=bool)
    return np.ptp(d, axis=0) <= MESSAGE_VARIANCE_TINY


def _message_cov(
    planar: bool,
    pose_i: gtsam.Pose3,
    pose_j: gtsam.Pose3,
    cov_i: np.ndarray,
    cov_j: np.ndarray,
    fallback: np.ndarray,
    unobserved: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """Covariance of the motion between two keyframes from the messages' pose covariances.

    ROS gives the pose covariance in the odometry (parent) frame. Dead reckoning propagates it as
    ``Σ_j = F Σ_i F^T + Q`` with ``F`` the Jacobian of ``T_j = T_i T_ij`` in world coordinates (the
    lever arm of the displacement), so ``Q = Σ_j - F Σ_i F^T`` is the covariance the motion added;
    it is rotated into the body frame of ``j`` (the tangent of a between factor's error). Dimensions
    the messages never inform (``unobserved``: e.g. z, roll and pitch of planar odometry) take the
    settings' value from ``fallback``, and so does the whole factor when nothing grew at all between
    the two keyframes. A dimension that merely did not grow here (the lateral position of a robot that
    drove straight) keeps the messages' near-zero growth, bounded below by the condition-number floor:
    replacing it with the settings' 1 cm would give the whole map a translation freedom that the
    odometry does not have (measured: every landmark marginal at least 1 cm, NEES/2 0.03 on detections
    drawn from their own covariance). Returns the covariance and whether any dimension fell back.
    """
    dt = np.asarray(pose_j.translation()) - np.asarray(pose_i.translation())
    Rj = np.asarray(pose_j.rotation().matrix())
    if planar:
        idx = [3, 4, 2]  # x, y, yaw in gtsam's (r, t) order
        Ci, Cj = cov_i[np.ix_(idx, idx)], cov_j[np.ix_(idx, idx)]
        F = np.array([[1.0, 0.0, -dt[1]], [0.0, 1.0, dt[0]], [0.0, 0.0, 1.0]])
        yaw = float(np.arctan2(Rj[1, 0], Rj[0, 0]))
        c, s = np.cos(yaw), np.sin(yaw)
        M = np.eye(3)
        M[:2, :2] = np.array([[c, s], [-s, c]])
    else:
        Ci, Cj = cov_i, cov_j
        F = np.eye(6)
        F[3:, :3] = -np.array([[0.0, -dt[2], dt[1]], [dt[2], 0.0, -dt[0]], [-dt[1], dt[0], 0.0]])
        M = np.zeros((6, 6))
        M[:3, :3] = Rj.T
        M[3:, 3:] = Rj.T
    Q = Cj - F @ Ci @ F.T
    tiny = MESSAGE_VARIANCE_TINY
    bad = np.zeros(len(Q), dtype=bool) if unobserved is None else np.asarray(unobserved, dtype=bool).copy()
    # The unobserved dimensions are world z / roll / pitch (planar: none of x, y, yaw); the rotation to
    # the body frame of a planar motion keeps them among themselves, so the mask holds in both frames.
    Q[bad, :] = 0.0
    Q[:, bad] = 0.0
    Q = rotate_covariance(Q, M)
    good = ~bad
    if good.any():
        Qg = Q[np.ix_(good, good)]
        w, V = np.linalg.eigh(Qg)
        if float(w.max()) <= tiny:
            # nothing grew between the two keyframes (odometry at rest without noise): the settings' value
            bad[:] = True
        else:
            # Two noise sources (speed, yaw rate) make Q nearly rank 2; bound its condition number so the
            # graph's information matrix stays well conditioned (this only inflates the tightest direction).
            floor = max(tiny, ODOMETRY_MIN_EIG_RATIO * float(w.max()))
            Q[np.ix_(good, good)] = (V * np.maximum(w, floor)) @ V.T
    if bad.any():
        Q[bad, :] = 0.0
        Q[:, bad] = 0.0
        Q[bad, bad] = np.diag(fallback)[bad]
    return 0.5 * (Q + Q.T), bool(bad.any())


def build_problem(
    detections: pa.Table,
    odometry: pa.Table | None,
    extrinsics: dict[str, Any] | None,
    cfg: GraphConfig,
) -> GraphProblem:
    """The full graph of a run: keyframes, factors and initial values (see the module docstring).

    Raises:
        StageError: when nothing is left to build a graph from.
        InputError: when the detection table lacks a needed column.
    """
    planar = cfg.model == "planar"
    needed = {"frame", "stamp_ns", "camera", "tag_id", "T_camera_tag", "pose_cov"}
    if missing := needed - set(detections.column_names):
        raise InputError(f"detections.parquet lacks columns {sorted(missing)}; re-run 'focusmap detect'")
    det = detections.to_pydict()
    n_det = detections.num_rows
    keep = np.ones(n_det, dtype=bool)
    info: dict[str, Any] = {"detections": n_det}
    if cfg.drop_ambiguous and "ambiguous" in det:
        amb = np.array([bool(a) for a in det["ambiguous"]], dtype=bool)
        info["dropped_ambiguous"] = int((amb & keep).sum())
        keep &= ~amb
    if "reprojection_px" in det:
        rep = np.asarray(det["reprojection_px"], dtype=float)
        bad = ~(rep <= cfg.max_reprojection_px)
        info["dropped_reprojection"] = int((bad & keep).sum())
        keep &= ~bad
    counts = Counter(int(t) for t, k in zip(det["tag_id"], keep, strict=True) if k)
    rare = sorted(t for t, c in counts.items() if c < cfg.min_tag_observations)
    seen_once = sorted(t for t, c in counts.items() if c == 1)
    info["tags_dropped_few_observations"] = rare
    info["tags_seen_once"] = seen_once
    keep &= ~np.isin(np.asarray(det["tag_id"], dtype=np.int64), rare)
    if not keep.any():
        raise StageError(
            f"no usable tag detections among {n_det} (ambiguous, reprojection above {cfg.max_reprojection_px} px, "
            f"or tags seen fewer than {cfg.min_tag_observations} times); relax the graph settings or check detect"
        )
    rows_idx = np.flatnonzero(keep)
    stamps_all = np.asarray(det["stamp_ns"], dtype=np.int64)
    det_stamps = np.unique(stamps_all[rows_idx])

    odom = Odometry.from_table(odometry)
    kf_stamps, _is_tag = _keyframes(det_stamps, odom, cfg)
    n = len(kf_stamps)
    pose_keys = [int(X(i)) for i in range(n)]
    kf_index = {int(s): i for i, s in enumerate(kf_stamps)}
    rows: list[FactorRow] = []
    initial = gtsam.Values()
    var_types: dict[int, str] = {}

    # poses: dead reckoning in the frame of the first keyframe
    if odom is not None:
        odo_poses, odo_covs = odom.at(kf_stamps)
        outside = int(((kf_stamps < odom.stamps_ns[0]) | (kf_stamps > odom.stamps_ns[-1])).sum())
        info["keyframes_outside_odometry"] = outside
        origin = odo_poses[0].inverse()
        rel3 = [origin.compose(p) for p in odo_poses]
    else:
        rel3 = [gtsam.Pose3()] * n
        odo_poses, odo_covs = [], np.zeros((0, 6, 6))

    # prior
    if planar:
        rows.append(
            FactorRow(
                "prior",
                "PriorFactorPose2",
                (pose_keys[0],),
                np.zeros(3),
                np.diag([cfg.prior_sigma_m**2] * 2 + [cfg.prior_sigma_rad**2]),
            )
        )
    else:
        rows.append(
            FactorRow(
                "prior",
                "PriorFactorPose3",
                (pose_keys[0],),
                pose3_to_vector(gtsam.Pose3()),
                np.diag([cfg.prior_sigma_rad**2] * 3 + [cfg.prior_sigma_m**2] * 3),
            )
        )

    # the shared tag scale (the tolerance of the printed tag size)
    use_scale = cfg.tag_scale_sigma > 0
    if use_scale:
        rows.append(
            FactorRow(
                "scale_prior", "PriorFactorDouble", (SCALE_KEY,), np.ones(1), np.array([[cfg.tag_scale_sigma**2]])
            )
        )
    scale_keys = (SCALE_KEY,) if use_scale else ()

    # odometry or motion prior
    noise_source = "none"
    fallbacks = 0
    if odom is not None:
        has_cov = bool(np.any(odom.cov != 0))
        use_msgs = cfg.odometry_noise == "messages" or (cfg.odometry_noise == "auto" and has_cov)
        noise_source = "messages" if use_msgs else "settings"
        unobserved = _unobserved_dims(odom.cov, planar)
        if use_msgs:
            names = ["x", "y", "yaw"] if planar else ["roll", "pitch", "yaw", "x", "y", "z"]
            info["odometry_unobserved_dims"] = [nm for nm, u in zip(names, unobserved, strict=True) if u]
        for i in range(n - 1):
            a, b = odo_poses[i], odo_poses[i + 1]
            rel = a.between(b)
            dist = float(np.linalg.norm(np.asarray(rel.translation())))
            angle = float(np.linalg.norm(gtsam.Rot3.Logmap(rel.rotation())))
            cov = _settings_cov(cfg, planar, dist, angle)
            if use_msgs:
                cov, fell_back = _message_cov(planar, a, b, odo_covs[i], odo_covs[i + 1], cov, unobserved)
                fallbacks += int(fell_back)
            if planar:
                meas = pose2_to_vector(pose2_from_pose3(a).between(pose2_from_pose3(b)))
                rows.append(
                    FactorRow(
                        "odometry",
                        "BetweenFactorPose2",
                        (pose_keys[i], pose_keys[i + 1]),
                        meas,
                        cov,
                        stamp_ns=int(kf_stamps[i + 1]),
                    )
                )
            else:
                rows.append(
                    FactorRow(
                        "odometry",
                        "BetweenFactorPose3",
                        (pose_keys[i], pose_keys[i + 1]),
                        pose3_to_vector(rel),
                        cov,
                        stamp_ns=int(kf_stamps[i + 1]),
                    )
                )
        info["odometry_messages"] = len(odom.stamps_ns)
    elif cfg.motion_prior:
        noise_source = "motion_prior"
        sm, sr = cfg.motion_prior_sigma_m, cfg.motion_prior_sigma_rad
        for i in range(n - 1):
            if planar:
                rows.append(
                    FactorRow(
                        "motion_prior",
                        "BetweenFactorPose2",
                        (pose_keys[i], pose_keys[i + 1]),
                        np.zeros(3),
                        np.diag([sm**2, sm**2, sr**2]),
                        stamp_ns=int(kf_stamps[i + 1]),
                    )
                )
            else:
                rows.append(
                    FactorRow(
                        "motion_prior",
                        "BetweenFactorPose3",
                        (pose_keys[i], pose_keys[i + 1]),
                        pose3_to_vector(gtsam.Pose3()),
                        np.diag([sr**2] * 3 + [sm**2] * 3),
                        stamp_ns=int(kf_stamps[i + 1]),
                    )
                )
    info["odometry_noise"] = noise_source
    info["odometry_noise_fallbacks"] = fallbacks
    if odom is None:
        info["note"] = (
            "the run has no odometry: consecutive keyframes are joined by a weak zero-motion prior"
            if cfg.motion_prior
            else "the run has no odometry and graph.motion_prior is off: poses are tied only by shared tags"
        )

    # tag factors, in time order
    order = rows_idx[np.argsort(stamps_all[rows_idx], kind="stable")]
    extrinsic_cache: dict[str, tuple[gtsam.Pose3, str]] = {}
    landmark_keys: dict[int, int] = {}
    first_sight: dict[int, tuple[int, gtsam.Pose3 | np.ndarray]] = {}
    heights: dict[int, list[tuple[float, float]]] = {}
    scale = cfg.tag_covariance_scale
    floor = np.diag([cfg.tag_sigma_floor_rad**2] * 3 + [cfg.tag_sigma_floor_m**2] * 3)
    dropped_close = 0
    tag_meas: list[tuple[int, int, Any]] = []
    for r in order:
        cam = str(det["camera"][r])
        if cam not in extrinsic_cache:
            extrinsic_cache[cam] = camera_extrinsic(extrinsics, cam)
        T_base_cam, _src = extrinsic_cache[cam]
        T_cam_tag = pose3_from_matrix(det["T_camera_tag"][r])
        T_base_tag = T_base_cam.compose(T_cam_tag)
        cov6 = scale * np.asarray(det["pose_cov"][r], dtype=float).reshape(6, 6) + floor
        tag = int(det["tag_id"][r])
        k = kf_index[int(stamps_all[r])]
        stamp = int(stamps_all[r])
        frame = int(det["frame"][r])
        if planar:
            p = np.asarray(T_base_tag.translation(), dtype=float)
            Rbt = np.asarray(T_base_tag.rotation().matrix())
            cov_p = rotate_covariance(cov6[3:, 3:], Rbt)
            if float(np.hypot(p[0], p[1])) < MIN_PLANAR_RANGE_M:
                dropped_close += 1
                continue
            bearing, rng, cov_br = relative_position_to_bearing_range_2d(p[:2], cov_p[:2, :2])
            row = FactorRow(
                "tag",
                "BearingRangeFactor2D",
                (pose_keys[k], int(L(tag)), *scale_keys),
                np.array([bearing, rng]),
                cov_br,
                cfg.robust_kernel,
                cfg.robust_threshold if cfg.robust_kernel != "none" else 0.0,
                tag_id=tag,
                frame=frame,
                stamp_ns=stamp,
            )
            heights.setdefault(tag, []).append((float(p[2]), float(cov_p[2, 2])))
            tag_meas.append((k, tag, p[:2]))
        else:
            row = FactorRow(
                "tag",
                "BetweenFactorPose3",
                (pose_keys[k], int(L(tag)), *scale_keys),
                pose3_to_vector(T_base_tag),
                cov6,
                cfg.robust_kernel,
                cfg.robust_threshold if cfg.robust_kernel != "none" else 0.0,
                tag_id=tag,
                frame=frame,
                stamp_ns=stamp,
            )
            tag_meas.append((k, tag, T_base_tag))
        rows.append(row)
        landmark_keys.setdefault(tag, int(L(tag)))
        first_sight.setdefault(tag, (k, tag_meas[-1][2]))
    info["dropped_too_close"] = dropped_close
    info["extrinsics"] = {cam: src for cam, (_, src) in extrinsic_cache.items()}

    # initial values
    if odom is None:
        rel3 = _chain_from_tags(n, tag_meas, planar)
    for i, key in enumerate(pose_keys):
        if planar:
            initial.insert(key, pose2_from_pose3(rel3[i]))
            var_types[key] = "Pose2"
        else:
            initial.insert(key, rel3[i])
            var_types[key] = "Pose3"
    for tag, (k, meas) in first_sight.items():
        key = landmark_keys[tag]
        if planar:
            initial.insert(key, np.asarray(pose2_from_pose3(rel3[k]).transformFrom(np.asarray(meas))))
            var_types[key] = "Point2"
        else:
            initial.insert(key, rel3[k].compose(meas))
            var_types[key] = "Pose3"
    if use_scale:
        initial.insert(SCALE_KEY, 1.0)
        var_types[SCALE_KEY] = "Scale"
        info["tag_scale_sigma"] = cfg.tag_scale_sigma
    landmark_heights = {}
    for tag, hs in heights.items():
        z = np.array([h[0] for h in hs])
        v = np.array([max(h[1], 1e-12) for h in hs])
        w = 1.0 / v
        landmark_heights[tag] = (float((w * z).sum() / w.sum()), float(1.0 / w.sum()))
    info["keyframes"] = n
    info["tag_keyframes"] = int(_is_tag.sum())
    info["odometry_keyframes"] = int(n - _is_tag.sum())
    return GraphProblem(
        model=cfg.model,
        rows=rows,
        initial=initial,
        var_types=var_types,
        pose_keys=pose_keys,
        pose_stamps_ns=[int(s) for s in kf_stamps],
        landmark_keys=dict(sorted(landmark_keys.items())),
        landmark_heights=landmark_heights,
        info=info,
    )


def _chain_from_tags(n: int, tag_meas: list[tuple[int, int, Any]], planar: bool) -> list[gtsam.Pose3]:
    """Initial keyframe poses without odometry: from tags already placed, else the previous pose."""
    by_kf: dict[int, list[tuple[int, Any]]] = {}
    for k, tag, meas in tag_meas:
        by_kf.setdefault(k, []).append((tag, meas))
    placed: dict[int, Any] = {}
    poses: list[gtsam.Pose3] = []
    prev = gtsam.Pose3()
    for k in range(n):
        pose = prev if k > 0 else gtsam.Pose3()
        obs = by_kf.get(k, [])
        if k > 0:
            for tag, meas in obs:
                if tag in placed and not planar:
                    pose = placed[tag].compose(meas.inverse())
                    break
        for tag, meas in obs:
            if tag not in placed:
                placed[tag] = pose.compose(meas) if not planar else None
        poses.append(pose)
        prev = pose
    return poses
