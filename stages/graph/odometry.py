"""Odometry for the graph: the messages as poses with covariances, keyframe choice, and the noise of a motion.

- :class:`Odometry`: ingest's ``odometry.parquet`` as Pose3 poses and gtsam-ordered covariances, interpolated
  to any stamp;
- :func:`keyframes`: the tag frames plus odometry stamps wherever the robot went too long, too far or turned too
  much without one;
- :func:`settings_cov` and :func:`message_cov`: the covariance of the motion between two keyframes, from the
  settings or from the growth of the messages' pose covariances.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
import pyarrow as pa

from stages.columns import POSITION, QUATERNION, STAMP_NS
from stages.geometry import interpolate_pose3, pose3_from_xyz_quat, ros_pose_cov_to_gtsam, rotate_covariance
from stages.graph.config import GraphConfig
from stages.graph.models import GraphModel
from stages.ingest.artifacts import POSE_COV

ODOMETRY_MIN_EIG_RATIO = 1e-3
"""Smallest eigenvalue of an odometry covariance taken from the messages, as a fraction of its largest."""
MESSAGE_VARIANCE_TINY = 1e-12
"""Odometry message variances (m², rad²) that differ by no more than this are taken as not growing."""


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
        order = np.argsort(np.asarray(cols[STAMP_NS], dtype=np.int64), kind="stable")
        stamps = np.asarray(cols[STAMP_NS], dtype=np.int64)[order]
        keep = np.concatenate([[True], np.diff(stamps) > 0])
        order, stamps = order[keep], stamps[keep]
        poses = [pose3_from_xyz_quat([cols[c][i] for c in POSITION], [cols[c][i] for c in QUATERNION]) for i in order]
        if POSE_COV in cols:
            cov = np.array([ros_pose_cov_to_gtsam(cols[POSE_COV][i] or np.zeros(36)) for i in order])
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


def keyframes(det_stamps: np.ndarray, odom: Odometry | None, cfg: GraphConfig) -> tuple[np.ndarray, np.ndarray]:
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


def settings_cov(cfg: GraphConfig, model: GraphModel, dist: float, angle: float) -> np.ndarray:
    """Covariance of a motion of ``dist`` metres and ``angle`` radians from the odometry settings."""
    st = float(np.hypot(cfg.odometry_sigma_m, cfg.odometry_sigma_per_m * dist))
    sr = float(
        np.sqrt(
            cfg.odometry_sigma_rad**2
            + (cfg.odometry_sigma_rad_per_rad * angle) ** 2
            + (cfg.odometry_sigma_rad_per_m * dist) ** 2
        )
    )
    return model.pose_covariance(st, sr)


def unobserved_dims(cov: np.ndarray, model: GraphModel) -> np.ndarray:
    """Dimensions (in the factor's tangent order) whose message variance never changes over the run.

    Planar wheel odometry publishes fixed placeholders for z, roll and pitch: they carry no information
    about the motion and take the settings' value. A dimension that grows anywhere in the run is observed,
    even where it does not grow between two keyframes (the lateral position of a robot driving straight).
    """
    idx = list(model.motion_index)
    d = np.diagonal(cov, axis1=1, axis2=2)[:, idx] if len(cov) else np.zeros((0, len(idx)))
    if len(d) == 0:
        return np.ones(len(idx), dtype=bool)
    return np.ptp(d, axis=0) <= MESSAGE_VARIANCE_TINY


def message_cov(
    model: GraphModel,
    pose_i: gtsam.Pose3,
    pose_j: gtsam.Pose3,
    cov_i: np.ndarray,
    cov_j: np.ndarray,
    fallback: np.ndarray,
    unobserved: np.ndarray | None = None,
    propagated: bool = True,
) -> tuple[np.ndarray, bool]:
    """Covariance of the motion between two keyframes from the messages' pose covariances.

    ``propagated=False`` (:func:`growth_model` decides per run): the messages' covariance grows by plain addition,
    ``Σ_j = Σ_i + Q``, without the lever-arm terms (drivers that accumulate a diagonal), so ``Q = Σ_j − Σ_i``.

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
    Ci, Cj, F, M = model.motion_frames(pose_i, pose_j, cov_i, cov_j)
    Q = Cj - (F @ Ci @ F.T if propagated else Ci)
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


INDEFINITE_MAX = 0.01
"""Propagated growth ``Σ_j − F Σ_i Fᵀ`` whose most negative eigenvalue is, in the median over the run's keyframe
pairs, beyond this fraction of its largest is not a propagation (rounding leaves about 1e-9)."""


def _indefiniteness(
    model: GraphModel,
    pose_i: gtsam.Pose3,
    pose_j: gtsam.Pose3,
    cov_i: np.ndarray,
    cov_j: np.ndarray,
    good: np.ndarray,
    propagated: bool,
) -> float:
    """``−λ_min / λ_max`` of the growth between two messages (0 when positive semidefinite; nan when nothing grew)."""
    Ci, Cj, F, _ = model.motion_frames(pose_i, pose_j, cov_i, cov_j)
    Q = (Cj - (F @ Ci @ F.T if propagated else Ci))[np.ix_(good, good)]
    w = np.linalg.eigvalsh(0.5 * (Q + Q.T))
    if float(w.max()) <= MESSAGE_VARIANCE_TINY:
        return float("nan")
    return max(0.0, -float(w.min())) / float(w.max())


def growth_model(
    model: GraphModel, poses: list[gtsam.Pose3], covs: np.ndarray, unobserved: np.ndarray
) -> tuple[bool, dict[str, Any]]:
    """Whether the run's odometry covariances are propagated through the motion (``Σ_j = F Σ_i Fᵀ + Q``, what
    :func:`message_cov` assumes) or accumulated by plain addition (``Σ_j = Σ_i + Q``, e.g. a driver that adds a
    diagonal each step and has no position-heading cross terms), and the figures that decided it.

    Under the wrong model the growth comes out indefinite: the lever-arm term ``F Σ_i Fᵀ`` subtracted from an
    accumulated diagonal leaves a near rank-one position-heading block (correlation 0.998 on an independent
    simulator's run), which made the heading 30 times too certain and bent the map. The model whose growth is
    positive semidefinite in the median over the keyframe pairs is taken; propagation unless it is indefinite
    beyond :data:`INDEFINITE_MAX` and addition is less so.
    """
    good = ~np.asarray(unobserved, dtype=bool)
    figures: dict[str, Any] = {}
    if len(poses) < 2 or not good.any():
        return True, figures
    medians = {}
    for name, propagated in (("propagated", True), ("added", False)):
        r = [
            _indefiniteness(model, poses[i], poses[i + 1], covs[i], covs[i + 1], good, propagated)
            for i in range(len(poses) - 1)
        ]
        finite = [x for x in r if np.isfinite(x)]
        medians[name] = float(np.median(finite)) if finite else 0.0
        figures[f"indefinite_median_{name}"] = round(medians[name], 6)
    propagated = not (medians["propagated"] > INDEFINITE_MAX and medians["added"] < medians["propagated"])
    figures["model"] = "propagated" if propagated else "added"
    return propagated, figures
