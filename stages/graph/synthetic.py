"""Synthetic inputs with ground truth for the graph stage's tests, figures and benchmark (no images).

:func:`synthetic_run` makes ingest- and detect-shaped tables of a robot driving loops in a room with
tags on its walls: odometry with the sample simulator's noise model (white noise on the forward
increment and the yaw increment per sample, first-order propagated pose covariance), and tag
detections drawn from the covariance they report (right perturbation of ``T_camera_tag``), so a
consistent estimator gives a NEES near 1.

:func:`synthetic_planar_problem` makes a planar :class:`GraphProblem` of any size directly
(random-walk odometry, bearing-range landmark measurements), for the benchmark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gtsam
import numpy as np
import pyarrow as pa
from gtsam.symbol_shorthand import L, X

from stages.geometry import pose3_from_matrix, relative_position_to_bearing_range_2d
from stages.graph.factors import SCALE_KEY, FactorRow
from stages.graph.problem import GraphProblem
from stages.ingest.artifacts import Extrinsics, SensorMount

R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Columns: the optical frame's x (right), y (down), z (forward) in a x-forward, z-up body frame."""


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _planar_T(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _rz(yaw)
    T[:3, 3] = [x, y, z]
    return T


@dataclass
class SyntheticRun:
    """Tables shaped like ingest's and detect's artifacts, with the truth."""

    odometry: pa.Table
    detections: pa.Table
    extrinsics: Extrinsics
    true_stamps_ns: np.ndarray
    true_poses: np.ndarray  # N x 3 (x, y, yaw) of base_link in world, at true_stamps_ns
    tags_world: dict[int, np.ndarray] = field(default_factory=dict)  # tag id -> T_world_tag (4x4)

    def true_pose_at(self, stamps_ns: np.ndarray) -> np.ndarray:
        """True (x, y, yaw) interpolated at ``stamps_ns``."""
        t = self.true_stamps_ns.astype(float)
        q = np.asarray(stamps_ns, dtype=float)
        yaw = np.unwrap(self.true_poses[:, 2])
        return np.column_stack(
            [np.interp(q, t, self.true_poses[:, 0]), np.interp(q, t, self.true_poses[:, 1]), np.interp(q, t, yaw)]
        )


def synthetic_run(
    seed: int = 0,
    loops: float = 1.0,
    room_m: tuple[float, float] = (8.0, 6.0),
    tag_spacing_m: float = 1.0,
    tag_height_m: float = 0.4,
    speed_mps: float = 0.4,
    camera_rate_hz: float = 5.0,
    odom_rate_hz: float = 20.0,
    odom_v_sigma_mps: float = 0.04,
    odom_yaw_rate_sigma_radps: float = 0.03,
    max_range_m: float = 4.0,
    camera_yaw_deg: float = 30.0,
    start_ns: int = 1_700_000_000_000_000_000,
) -> SyntheticRun:
    """A robot driving ``loops`` times round an ellipse in a room whose walls carry tags (see the module docstring)."""
    rng = np.random.default_rng(seed)
    W, H = room_m
    a, b = W / 2 - 1.6, H / 2 - 1.4
    cx, cy = W / 2, H / 2
    perim = math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))
    duration = loops * perim / speed_mps
    n_odom = int(duration * odom_rate_hz) + 1
    t_s = np.arange(n_odom) / odom_rate_hz
    phase = 2 * math.pi * speed_mps * t_s / perim
    x = cx + a * np.cos(phase)
    y = cy + b * np.sin(phase)
    yaw = np.unwrap(np.arctan2(b * np.cos(phase), -a * np.sin(phase)))
    stamps = start_ns + np.round(t_s * 1e9).astype(np.int64)

    # odometry: the simulator's model
    sv, sw = odom_v_sigma_mps, odom_yaw_rate_sigma_radps
    ox = oy = oyaw = 0.0
    P = np.zeros((3, 3))
    small = 1e-9
    cols: dict[str, list[object]] = {k: [] for k in ("stamp_ns", "x", "y", "z", "qx", "qy", "qz", "qw", "pose_cov")}
    for k in range(n_odom):
        if k > 0:
            dt = 1.0 / odom_rate_hz
            c, s = math.cos(yaw[k - 1]), math.sin(yaw[k - 1])
            ddx, ddy = x[k] - x[k - 1], y[k] - y[k - 1]
            nv, nw = rng.standard_normal(2)
            dx_b = c * ddx + s * ddy + sv * dt * nv
            dy_b = -s * ddx + c * ddy
            dyaw = yaw[k] - yaw[k - 1] + sw * dt * nw
            co, so = math.cos(oyaw), math.sin(oyaw)
            F = np.array([[1, 0, -so * dx_b - co * dy_b], [0, 1, co * dx_b - so * dy_b], [0, 0, 1]])
            G = np.array([[co, 0], [so, 0], [0, 1]])
            P = F @ P @ F.T + G @ np.diag([(sv * dt) ** 2, (sw * dt) ** 2]) @ G.T
            ox += co * dx_b - so * dy_b
            oy += so * dx_b + co * dy_b
            oyaw += dyaw
        cov = np.diag([0.0, 0.0, small, small, small, 0.0])
        cov[np.ix_([0, 1, 5], [0, 1, 5])] = P
        for name, val in zip(
            ("stamp_ns", "x", "y", "z", "qx", "qy", "qz", "qw"),
            (int(stamps[k]), ox, oy, 0.0, 0.0, 0.0, math.sin(oyaw / 2), math.cos(oyaw / 2)),
            strict=True,
        ):
            cols[name].append(val)
        cols["pose_cov"].append(cov.ravel().tolist())
    odometry = pa.table(cols)

    # tags on the walls, z out of the wall into the room, y up
    tags: dict[int, np.ndarray] = {}
    walls = [
        ((0.0, 0.0), (W, 0.0), (0.0, 1.0)),
        ((W, 0.0), (W, H), (-1.0, 0.0)),
        ((W, H), (0.0, H), (0.0, -1.0)),
        ((0.0, H), (0.0, 0.0), (1.0, 0.0)),
    ]
    tid = 0
    for p0, p1, n in walls:
        length = math.hypot(p1[0] - p0[0], p1[1] - p0[1])
        for s_ in np.arange(tag_spacing_m / 2, length, tag_spacing_m):
            f = s_ / length
            pos = np.array([p0[0] + f * (p1[0] - p0[0]), p0[1] + f * (p1[1] - p0[1]), tag_height_m])
            z_t = np.array([n[0], n[1], 0.0])
            y_t = np.array([0.0, 0.0, 1.0])
            T = np.eye(4)
            T[:3, :3] = np.column_stack([np.cross(y_t, z_t), y_t, z_t])
            T[:3, 3] = pos
            tags[tid] = T
            tid += 1

    # camera
    T_bc = np.eye(4)
    T_bc[:3, :3] = _rz(math.radians(camera_yaw_deg)) @ R_BASE_OPTICAL
    T_bc[:3, 3] = [0.12, 0.0, 0.40]
    hfov, vfov = math.radians(37.0), math.radians(29.0)
    det: dict[str, list[object]] = {
        k: []
        for k in (
            "frame",
            "stamp_ns",
            "camera",
            "tag_id",
            "family",
            "size_m",
            "T_camera_tag",
            "pose_cov",
            "position_cov",
            "reprojection_px",
            "ambiguity_ratio",
            "ambiguous",
            "decision_margin",
            "hamming",
        )
    }
    cam_times = np.arange(0.021, t_s[-1], 1.0 / camera_rate_hz)
    for frame, tc in enumerate(cam_times):
        s_ns = int(start_ns + round(tc * 1e9))
        xi = np.interp(tc, t_s, x)
        yi = np.interp(tc, t_s, y)
        yawi = float(np.interp(tc, t_s, yaw))
        T_wc = _planar_T(xi, yi, yawi) @ T_bc
        T_cw = np.linalg.inv(T_wc)
        for tag, T_wt in tags.items():
            T_ct = T_cw @ T_wt
            p = T_ct[:3, 3]
            d = float(np.linalg.norm(p))
            if p[2] < 0.3 or d > max_range_m:
                continue
            if abs(math.atan2(p[0], p[2])) > hfov or abs(math.atan2(p[1], p[2])) > vfov:
                continue
            if T_ct[2, 2] > -math.cos(math.radians(70.0)):  # tag must face the camera
                continue
            sr = 0.01 + 0.01 * d
            st = 0.002 + 0.003 * d
            cov = np.diag([sr**2, sr**2, (0.5 * sr) ** 2, st**2, st**2, (2.5 * st) ** 2])
            noise = rng.multivariate_normal(np.zeros(6), cov)
            meas = gtsam.Pose3(pose3_from_matrix(T_ct)).compose(gtsam.Pose3.Expmap(noise))
            M = np.asarray(meas.matrix())
            det["frame"].append(frame)
            det["stamp_ns"].append(s_ns)
            det["camera"].append("camera")
            det["tag_id"].append(tag)
            det["family"].append("tag36h11")
            det["size_m"].append(0.16)
            det["T_camera_tag"].append(M.ravel().tolist())
            det["pose_cov"].append(cov.ravel().tolist())
            R = M[:3, :3]
            det["position_cov"].append((R @ cov[3:, 3:] @ R.T).ravel().tolist())
            det["reprojection_px"].append(0.5)
            det["ambiguity_ratio"].append(0.05)
            det["ambiguous"].append(False)
            det["decision_margin"].append(80.0)
            det["hamming"].append(0)
    detections = pa.table(det)
    extrinsics = Extrinsics(
        base_frame="base_link",
        odom_frame="odom",
        sensors={"camera": SensorMount(frame_id="camera", T_base_sensor=T_bc.tolist())},
    )
    return SyntheticRun(odometry, detections, extrinsics, stamps, np.column_stack([x, y, yaw]), tags)


def synthetic_planar_problem(
    n_poses: int = 7000,
    n_landmarks: int = 150,
    n_measurements: int = 10000,
    seed: int = 0,
    tag_scale_sigma: float = 0.0,
) -> GraphProblem:
    """A planar graph of the given size (Victoria Park's by default): a random-walk path in a square park,
    odometry between consecutive poses, and bearing-range measurements from poses to nearby landmarks.

    ``tag_scale_sigma > 0`` adds the shared tag scale as the stage builds it (``graph.tag_scale_sigma``): its
    prior and a third key on every landmark measurement (the measurements themselves are at scale 1)."""
    rng = np.random.default_rng(seed)
    side = 150.0
    lms = rng.uniform(0, side, size=(n_landmarks, 2))
    poses = [gtsam.Pose2(side / 2, side / 2, 0.0)]
    sig_odo = np.array([0.05, 0.05, 0.01])
    for _ in range(n_poses - 1):
        p = poses[-1]
        turn = rng.normal(0, 0.2)
        nxt = p.compose(gtsam.Pose2(1.0, 0.0, turn))
        if not (5 < nxt.x() < side - 5 and 5 < nxt.y() < side - 5):
            nxt = p.compose(gtsam.Pose2(1.0, 0.0, math.pi / 2))
        poses.append(nxt)
    rows: list[FactorRow] = [
        FactorRow(
            "prior",
            "PriorFactorPose2",
            (int(X(0)),),
            np.array([poses[0].x(), poses[0].y(), poses[0].theta()]),
            np.diag([1e-6, 1e-6, 1e-6]),
        )
    ]
    initial = gtsam.Values()
    dr = poses[0]
    initial.insert(int(X(0)), dr)
    for i in range(n_poses - 1):
        rel = poses[i].between(poses[i + 1])
        m = np.array([rel.x(), rel.y(), rel.theta()]) + rng.normal(0, sig_odo)
        rows.append(FactorRow("odometry", "BetweenFactorPose2", (int(X(i)), int(X(i + 1))), m, np.diag(sig_odo**2)))
        dr = dr.compose(gtsam.Pose2(*m))
        initial.insert(int(X(i + 1)), dr)
    scale_keys: tuple[int, ...] = ()
    if tag_scale_sigma > 0:
        rows.append(
            FactorRow("scale_prior", "PriorFactorDouble", (SCALE_KEY,), np.ones(1), np.diag([tag_scale_sigma**2]))
        )
        scale_keys = (SCALE_KEY,)
        initial.insert(SCALE_KEY, 1.0)
    P = np.array([[p.x(), p.y()] for p in poses])
    seen: set[int] = set()
    count = 0
    pose_order = rng.permutation(n_poses)
    i = 0
    while count < n_measurements:
        pi = int(pose_order[i % n_poses])
        i += 1
        d = np.linalg.norm(lms - P[pi], axis=1)
        near = np.flatnonzero(d < 30.0)
        if len(near) == 0:
            continue
        lj = int(near[rng.integers(len(near))])
        rel = np.asarray(poses[pi].transformTo(lms[lj])) + rng.normal(0, 0.1, 2)
        b, r, cov = relative_position_to_bearing_range_2d(rel, np.eye(2) * 0.01)
        rows.append(
            FactorRow(
                "tag",
                "BearingRangeFactor2D",
                (int(X(pi)), int(L(lj)), *scale_keys),
                np.array([b, r]),
                cov,
                tag_id=lj,
                frame=pi,
                stamp_ns=pi * 1_000_000_000,
            )
        )
        if lj not in seen:
            seen.add(lj)
            initial.insert(int(L(lj)), np.asarray(initial.atPose2(int(X(pi))).transformFrom(rel)))
        count += 1
    var_types = {int(X(i)): "Pose2" for i in range(n_poses)}
    var_types.update({int(L(j)): "Point2" for j in sorted(seen)})
    if scale_keys:
        var_types[SCALE_KEY] = "Scale"
    return GraphProblem(
        model="planar",
        rows=rows,
        initial=initial,
        var_types=var_types,
        pose_keys=[int(X(i)) for i in range(n_poses)],
        pose_stamps_ns=[i * 1_000_000_000 for i in range(n_poses)],
        landmark_keys={j: int(L(j)) for j in sorted(seen)},
        info={"synthetic": "victoria-park-sized"},
    )
