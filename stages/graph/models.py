"""The planar and the 3D graph model behind one interface, chosen once from ``graph.model``.

A model says which variable kinds a graph uses, which factor types join them, and how a motion, a
prior or a tag measurement becomes a factor row::

    model = graph_model(cfg.model)                       # PLANAR or SPATIAL
    model.pose, model.tag_landmark                       # Pose2 / Point2, or Pose3 / Pose3
    model.prior_row(key, model.identity, sigma_m, sigma_rad)
    model.between_row("odometry", keys, a, b, cov)       # a, b: Pose3 (the model projects them)
    model.tag_measurement(T_base_tag, cov6)              # bearing-range (planar) or relative pose (3d)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import gtsam
import numpy as np
import numpy.typing as npt

from stages.geometry import (
    pose2_from_pose3,
    pose2_to_vector,
    pose3_to_vector,
    relative_position_to_bearing_range_2d,
    rotate_covariance,
)
from stages.graph.factors import FactorRow
from stages.graph.variables import POINT2, POINT3, POSE2, POSE3, VarKind

FloatArray = npt.NDArray[np.float64]
Model = Literal["planar", "3d"]

MIN_PLANAR_RANGE_M = 0.05
"""Planar tag measurements closer than this to the base's vertical axis have no usable bearing."""


@dataclass(frozen=True)
class TagMeasurement:
    """A tag detection in the base frame, as the model measures it.

    Attributes:
        type: the factor type of its row.
        measurement: the row's measurement vector.
        covariance: the row's covariance.
        relative: the landmark in the base frame (planar: x, y; 3d: ``T_base_tag``), to place it initially.
        height: planar: (z, var z) of the tag in the base frame (kept aside for the written map); 3d: None.
    """

    type: str
    measurement: FloatArray
    covariance: FloatArray
    relative: Any
    height: tuple[float, float] | None = None


class GraphModel:
    """What differs between a planar and a 3D graph.

    Attributes:
        name: ``planar`` or ``3d`` (the ``graph.model`` setting).
        pose: kind of the robot poses.
        point: kind of point landmarks (imported graphs).
        tag_landmark: kind of the landmarks built from tag detections.
        motion_dims: names of the odometry factor's tangent dimensions, in its order.
        motion_index: their positions in gtsam's 6-dimensional (r, t) tangent order.
        between_type, prior_type: the factor types of pose-to-pose motions and pose priors.
    """

    name: Model
    pose: VarKind
    point: VarKind
    tag_landmark: VarKind
    motion_dims: tuple[str, ...]
    motion_index: tuple[int, ...]
    between_type: str
    prior_type: str

    @property
    def identity(self) -> FloatArray:
        """The measurement vector of the identity pose."""
        raise NotImplementedError

    def pose_covariance(self, sigma_m: float, sigma_rad: float) -> FloatArray:
        """Diagonal pose covariance with the given translation and rotation sigmas, in tangent order."""
        raise NotImplementedError

    def prior_row(self, key: int, measurement: FloatArray, sigma_m: float, sigma_rad: float) -> FactorRow:
        """A prior on pose ``key`` at ``measurement`` (a stored pose vector) with the given sigmas."""
        return FactorRow("prior", self.prior_type, (key,), measurement, self.pose_covariance(sigma_m, sigma_rad))

    def motion(self, a: gtsam.Pose3, b: gtsam.Pose3) -> FloatArray:
        """The measurement vector of the motion from ``a`` to ``b``."""
        raise NotImplementedError

    def between_row(
        self, kind: str, keys: tuple[int, int], measurement: FloatArray, cov: FloatArray, stamp_ns: int
    ) -> FactorRow:
        """A pose-to-pose row (``odometry`` or ``motion_prior``)."""
        return FactorRow(kind, self.between_type, keys, measurement, cov, stamp_ns=stamp_ns)

    def motion_frames(
        self, pose_i: gtsam.Pose3, pose_j: gtsam.Pose3, cov_i: FloatArray, cov_j: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The two world-frame pose covariances in tangent order, the Jacobian ``F`` of ``T_j = T_i T_ij`` in
        world coordinates (the lever arm of the displacement), and the rotation ``M`` to the body frame of ``j``."""
        raise NotImplementedError

    def tag_measurement(self, T_base_tag: gtsam.Pose3, cov6: FloatArray) -> TagMeasurement | None:
        """The measurement of a tag at ``T_base_tag`` with 6x6 covariance ``cov6`` (None: unusable)."""
        raise NotImplementedError

    def initial_pose(self, pose: gtsam.Pose3) -> Any:
        """The initial value of a robot pose at ``pose``."""
        raise NotImplementedError

    def initial_landmark(self, pose: gtsam.Pose3, relative: Any) -> Any:
        """The initial value of a tag landmark seen at ``relative`` (:attr:`TagMeasurement.relative`) from ``pose``."""
        raise NotImplementedError

    def chain_from_tags(
        self, n: int, tag_meas: list[tuple[int, int, Any]], placed: dict[int, gtsam.Pose3] | None = None
    ) -> list[gtsam.Pose3]:
        """Initial keyframe poses of a run without odometry, from its tag measurements ``(keyframe, tag, relative)``
        and the tags already ``placed`` (surveyed ones)."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"GraphModel({self.name})"


class _Planar(GraphModel):
    """Pose2 robot poses and Point2 tag landmarks, measured by bearing and range."""

    name = "planar"
    pose, point, tag_landmark = POSE2, POINT2, POINT2
    motion_dims = ("x", "y", "yaw")
    motion_index = (3, 4, 2)  # x, y, yaw in gtsam's (r, t) order
    between_type, prior_type = "BetweenFactorPose2", "PriorFactorPose2"

    @property
    def identity(self) -> FloatArray:
        return np.zeros(3)

    def pose_covariance(self, sigma_m: float, sigma_rad: float) -> FloatArray:
        return np.diag([sigma_m**2, sigma_m**2, sigma_rad**2])

    def motion(self, a: gtsam.Pose3, b: gtsam.Pose3) -> FloatArray:
        return pose2_to_vector(pose2_from_pose3(a).between(pose2_from_pose3(b)))

    def motion_frames(
        self, pose_i: gtsam.Pose3, pose_j: gtsam.Pose3, cov_i: FloatArray, cov_j: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        dt = np.asarray(pose_j.translation()) - np.asarray(pose_i.translation())
        Rj = np.asarray(pose_j.rotation().matrix())
        idx = list(self.motion_index)
        F = np.array([[1.0, 0.0, -dt[1]], [0.0, 1.0, dt[0]], [0.0, 0.0, 1.0]])
        yaw = float(np.arctan2(Rj[1, 0], Rj[0, 0]))
        c, s = np.cos(yaw), np.sin(yaw)
        M = np.eye(3)
        M[:2, :2] = np.array([[c, s], [-s, c]])
        return cov_i[np.ix_(idx, idx)], cov_j[np.ix_(idx, idx)], F, M

    def tag_measurement(self, T_base_tag: gtsam.Pose3, cov6: FloatArray) -> TagMeasurement | None:
        """The tag centre in the base frame, its covariance ``R_base_tag Σ_tt R_base_tag^T`` projected onto
        (x, y), as bearing and range; None when it is closer than :data:`MIN_PLANAR_RANGE_M` to the base's axis."""
        p = np.asarray(T_base_tag.translation(), dtype=float)
        Rbt = np.asarray(T_base_tag.rotation().matrix())
        cov_p = rotate_covariance(cov6[3:, 3:], Rbt)
        if float(np.hypot(p[0], p[1])) < MIN_PLANAR_RANGE_M:
            return None
        bearing, rng, cov_br = relative_position_to_bearing_range_2d(p[:2], cov_p[:2, :2])
        return TagMeasurement(
            "BearingRangeFactor2D", np.array([bearing, rng]), cov_br, p[:2], (float(p[2]), float(cov_p[2, 2]))
        )

    def initial_pose(self, pose: gtsam.Pose3) -> gtsam.Pose2:
        return pose2_from_pose3(pose)

    def initial_landmark(self, pose: gtsam.Pose3, relative: Any) -> FloatArray:
        return np.asarray(pose2_from_pose3(pose).transformFrom(np.asarray(relative)))

    def chain_from_tags(
        self, n: int, tag_meas: list[tuple[int, int, Any]], placed: dict[int, gtsam.Pose3] | None = None
    ) -> list[gtsam.Pose3]:
        """Every keyframe at the origin: a bearing-range sighting does not locate the robot from one tag."""
        return [gtsam.Pose3()] * n


class _Spatial(GraphModel):
    """Pose3 robot poses and Pose3 tag landmarks, measured by their relative pose."""

    name = "3d"
    pose, point, tag_landmark = POSE3, POINT3, POSE3
    motion_dims = ("roll", "pitch", "yaw", "x", "y", "z")
    motion_index = (0, 1, 2, 3, 4, 5)
    between_type, prior_type = "BetweenFactorPose3", "PriorFactorPose3"

    @property
    def identity(self) -> FloatArray:
        return pose3_to_vector(gtsam.Pose3())

    def pose_covariance(self, sigma_m: float, sigma_rad: float) -> FloatArray:
        return np.diag([sigma_rad**2] * 3 + [sigma_m**2] * 3)

    def motion(self, a: gtsam.Pose3, b: gtsam.Pose3) -> FloatArray:
        return pose3_to_vector(a.between(b))

    def motion_frames(
        self, pose_i: gtsam.Pose3, pose_j: gtsam.Pose3, cov_i: FloatArray, cov_j: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        dt = np.asarray(pose_j.translation()) - np.asarray(pose_i.translation())
        Rj = np.asarray(pose_j.rotation().matrix())
        F = np.eye(6)
        F[3:, :3] = -np.array([[0.0, -dt[2], dt[1]], [dt[2], 0.0, -dt[0]], [-dt[1], dt[0], 0.0]])
        M = np.zeros((6, 6))
        M[:3, :3] = Rj.T
        M[3:, 3:] = Rj.T
        return cov_i, cov_j, F, M

    def tag_measurement(self, T_base_tag: gtsam.Pose3, cov6: FloatArray) -> TagMeasurement:
        """``T_base_tag`` with the detection's 6x6 covariance (right perturbation: the extrinsic leaves it alone)."""
        return TagMeasurement("BetweenFactorPose3", pose3_to_vector(T_base_tag), cov6, T_base_tag)

    def initial_pose(self, pose: gtsam.Pose3) -> gtsam.Pose3:
        return pose

    def initial_landmark(self, pose: gtsam.Pose3, relative: Any) -> gtsam.Pose3:
        return pose.compose(relative)

    def chain_from_tags(
        self, n: int, tag_meas: list[tuple[int, int, Any]], placed: dict[int, gtsam.Pose3] | None = None
    ) -> list[gtsam.Pose3]:
        """Each keyframe from the first tag it sees that is already placed (a surveyed tag first), else at the
        previous keyframe. Without surveyed tags the first keyframe is the origin; with them it starts where the
        chain's first sighting of a surveyed tag puts it, so the tags seen before are placed in the same frame."""
        by_kf: dict[int, list[tuple[int, Any]]] = {}
        for k, tag, meas in tag_meas:
            by_kf.setdefault(k, []).append((tag, meas))
        surveyed = dict(placed or {})
        start = gtsam.Pose3()
        first = next(((k, tag, m) for k, tag, m in tag_meas if tag in surveyed), None)
        if first is not None:
            free = self._chain(n, by_kf, {}, start)
            k, tag, m = first
            start = surveyed[tag].compose(m.inverse()).compose(free[k].inverse())
        return self._chain(n, by_kf, surveyed, start)

    @staticmethod
    def _chain(
        n: int, by_kf: dict[int, list[tuple[int, Any]]], surveyed: dict[int, gtsam.Pose3], start: gtsam.Pose3
    ) -> list[gtsam.Pose3]:
        placed = dict(surveyed)
        poses: list[gtsam.Pose3] = []
        pose = start
        for k in range(n):
            obs = sorted(by_kf.get(k, []), key=lambda o: o[0] not in surveyed)  # stable: surveyed tags first
            pose = next((placed[tag].compose(m.inverse()) for tag, m in obs if tag in placed), pose)
            for tag, meas in obs:
                placed.setdefault(tag, pose.compose(meas))
            poses.append(pose)
        return poses


PLANAR: GraphModel = _Planar()
SPATIAL: GraphModel = _Spatial()
MODELS: dict[str, GraphModel] = {m.name: m for m in (PLANAR, SPATIAL)}


def graph_model(name: str) -> GraphModel:
    """The model named by ``graph.model`` (``planar`` or ``3d``)."""
    try:
        return MODELS[name]
    except KeyError:
        raise ValueError(f"unknown graph model {name!r}; use planar or 3d") from None


def model_of_poses(pose_type: str) -> GraphModel:
    """The model whose robot poses are of kind ``pose_type`` (planar for ``Pose2``, else 3D)."""
    return next((m for m in MODELS.values() if m.pose.name == pose_type), SPATIAL)
