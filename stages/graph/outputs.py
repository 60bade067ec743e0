"""Write the graph stage's artifacts and its Rerun recording (shared by the stage and ``import_graph``).

Artifacts in ``graph/`` (schemas in ``docs/graph.md``): ``factors.parquet``, ``values.npz``,
``marginals.npz``, ``poses.parquet``, ``landmarks.parquet``, ``trajectory.tum``,
``dead_reckoning.tum``, ``graph.g2o`` (and ``summary.json``, written by the runner).
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import gtsam
import numpy as np
import pyarrow as pa
import rerun as rr

from pipeline.artifacts import StageOutput
from pipeline.recording import ellipses_2d, ellipsoids, set_stamp
from stages.geometry import pose3_from_pose2, pose3_to_vector
from stages.graph.factors import rows_to_table
from stages.graph.g2o import write_g2o
from stages.graph.problem import VAR_DIMS, GraphProblem, value_vector, values_to_arrays
from stages.graph.solve import Solution

ENTITY = "/graph"


def _pose3(values: gtsam.Values, key: int, var_type: str) -> gtsam.Pose3:
    return values.atPose3(key) if var_type == "Pose3" else pose3_from_pose2(values.atPose2(key))


def position_cov_in_map(var_type: str, value: Any, cov: np.ndarray) -> np.ndarray:
    """3x3 position covariance in the map frame from a variable's tangent-space marginal."""
    out = np.zeros((3, 3))
    if var_type == "Pose3":
        R = np.asarray(value.rotation().matrix())
        out = R @ cov[3:, 3:] @ R.T
    elif var_type == "Pose2":
        c, s = np.cos(value.theta()), np.sin(value.theta())
        R2 = np.array([[c, -s], [s, c]])
        out[:2, :2] = R2 @ cov[:2, :2] @ R2.T
    elif var_type == "Point2":
        out[:2, :2] = cov
    elif var_type == "Point3":
        out = cov.copy()
    return 0.5 * (out + out.T)


def tum_text(stamps_ns: list[int], poses: list[gtsam.Pose3]) -> str:
    """TUM trajectory: ``t x y z qx qy qz qw`` per line (t in seconds)."""
    lines = []
    for s, p in zip(stamps_ns, poses, strict=True):
        t = np.asarray(p.translation())
        q = p.rotation().toQuaternion()
        lines.append(f"{s / 1e9:.9f} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {q.x():.9f} {q.y():.9f} {q.z():.9f} {q.w():.9f}")
    return "\n".join(lines) + "\n"


def write_artifacts(
    out: StageOutput, problem: GraphProblem, solution: Solution, marginals: dict[int, np.ndarray]
) -> dict[str, Any]:
    """Write every artifact; return the headline numbers for the summary."""
    rows = problem.rows
    out.write_table("factors.parquet", rows_to_table(rows))
    keys = list(problem.var_types)
    types = np.array([problem.var_types[k] for k in keys])
    out.write_npz(
        "values.npz",
        keys=np.array(keys, dtype=np.uint64),
        types=types,
        initial=values_to_arrays(problem.initial, problem.var_types, keys),
        optimised=values_to_arrays(solution.values, problem.var_types, keys),
    )
    cov_pad = np.zeros((len(keys), 6, 6))
    dims = np.array([VAR_DIMS[problem.var_types[k]] for k in keys], dtype=np.int32)
    for i, k in enumerate(keys):
        cov_pad[i, : dims[i], : dims[i]] = marginals[k]
    out.write_npz("marginals.npz", keys=np.array(keys, dtype=np.uint64), types=types, dims=dims, covariance=cov_pad)

    # poses
    pose_type = problem.var_types[problem.pose_keys[0]]
    poses3 = [_pose3(solution.values, k, pose_type) for k in problem.pose_keys]
    init3 = [_pose3(problem.initial, k, pose_type) for k in problem.pose_keys]
    vec = np.array([pose3_to_vector(p) for p in poses3]).reshape(-1, 7)
    pos_cov = [
        position_cov_in_map(
            pose_type, solution.values.atPose3(k) if pose_type == "Pose3" else solution.values.atPose2(k), marginals[k]
        )
        for k in problem.pose_keys
    ]
    out.write_table(
        "poses.parquet",
        {
            "index": np.arange(len(problem.pose_keys), dtype=np.int64),
            "key": np.array(problem.pose_keys, dtype=np.uint64),
            "stamp_ns": np.array(problem.pose_stamps_ns, dtype=np.int64),
            "x": vec[:, 0],
            "y": vec[:, 1],
            "z": vec[:, 2],
            "qx": vec[:, 3],
            "qy": vec[:, 4],
            "qz": vec[:, 5],
            "qw": vec[:, 6],
            "yaw": np.array([p.rotation().yaw() for p in poses3]),
            "covariance": [marginals[k].ravel().tolist() for k in problem.pose_keys],
            "position_cov": [c.ravel().tolist() for c in pos_cov],
        },
    )
    out.write_text("trajectory.tum", tum_text(problem.pose_stamps_ns, poses3))
    out.write_text("dead_reckoning.tum", tum_text(problem.pose_stamps_ns, init3))

    # landmarks
    n_obs = Counter(r.tag_id for r in rows if r.kind == "tag")
    lm_rows: dict[str, list[Any]] = {
        k: []
        for k in (
            "tag_id",
            "key",
            "x",
            "y",
            "z",
            "qx",
            "qy",
            "qz",
            "qw",
            "position_cov",
            "covariance",
            "type",
            "n_observations",
        )
    }
    for tag, key in problem.landmark_keys.items():
        t = problem.var_types[key]
        v = value_vector(solution.values, key, t)
        C = marginals[key]
        q: list[float | None] = [None] * 4
        if t == "Pose3":
            xyz = v[:3]
            q = [float(a) for a in v[3:7]]
            pc = position_cov_in_map(t, solution.values.atPose3(key), C)
        elif t == "Point2":
            z, vz = problem.landmark_heights.get(tag, (0.0, 0.0))
            xyz = np.array([v[0], v[1], z])
            pc = position_cov_in_map(t, None, C)
            pc[2, 2] = vz
        else:
            xyz = v[:3]
            pc = position_cov_in_map(t, None, C)
        for name, val in zip(("tag_id", "key", "x", "y", "z"), (tag, key, *xyz.tolist()), strict=True):
            lm_rows[name].append(val)
        for name, val in zip(("qx", "qy", "qz", "qw"), q, strict=True):
            lm_rows[name].append(val)
        lm_rows["position_cov"].append(pc.ravel().tolist())
        lm_rows["covariance"].append(C.ravel().tolist())
        lm_rows["type"].append(t)
        lm_rows["n_observations"].append(int(n_obs.get(tag, 0)))
    schema = pa.schema(
        [
            ("tag_id", pa.int64()),
            ("key", pa.uint64()),
            ("x", pa.float64()),
            ("y", pa.float64()),
            ("z", pa.float64()),
            ("qx", pa.float64()),
            ("qy", pa.float64()),
            ("qz", pa.float64()),
            ("qw", pa.float64()),
            ("position_cov", pa.list_(pa.float64())),
            ("covariance", pa.list_(pa.float64())),
            ("type", pa.string()),
            ("n_observations", pa.int64()),
        ]
    )
    out.write_table("landmarks.parquet", pa.table(lm_rows, schema=schema))
    out.write_text("graph.g2o", write_g2o(problem, solution.values))

    kinds = Counter(r.kind for r in rows)
    scale: dict[str, float] | None = None
    if problem.scale_key is not None:
        sk = problem.scale_key
        prior = next((r for r in rows if r.kind == "scale_prior"), None)
        scale = {
            "value": float(solution.values.atDouble(sk)),
            "sigma": float(np.sqrt(marginals[sk][0, 0])),
            "prior_sigma": float(np.sqrt(np.asarray(prior.covariance, dtype=float).ravel()[0]))
            if prior is not None
            else float("nan"),
        }
    return {
        "tag_scale": scale,
        "model": problem.model,
        "poses": len(problem.pose_keys),
        "landmarks": len(problem.landmark_keys),
        "factors": len(rows),
        "factors_by_kind": dict(sorted(kinds.items())),
        "tag_measurements": int(kinds.get("tag", 0)),
        "optimizer": solution.optimizer,
        "initial_error": solution.initial_error,
        "final_error": solution.final_error,
        "iterations": solution.iterations,
        "optimise_seconds": round(solution.seconds, 4),
    }


def log_recording(
    rec: rr.RecordingStream,
    problem: GraphProblem,
    solution: Solution,
    marginals: dict[int, np.ndarray],
    n_sigma: float,
    pose_stride: int = 10,
) -> None:
    """``graph.rrd``: dead reckoning and optimised path, landmarks with ellipsoids, pose ellipses, tag edges."""
    pose_type = problem.var_types[problem.pose_keys[0]]
    poses3 = [_pose3(solution.values, k, pose_type) for k in problem.pose_keys]
    init3 = [_pose3(problem.initial, k, pose_type) for k in problem.pose_keys]
    path = np.array([np.asarray(p.translation()) for p in poses3]).reshape(-1, 3)
    dr = np.array([np.asarray(p.translation()) for p in init3]).reshape(-1, 3)
    rec.log(f"{ENTITY}", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(f"{ENTITY}/dead_reckoning", rr.LineStrips3D([dr], colors=[[150, 150, 150]]), static=True)
    rec.log(f"{ENTITY}/path", rr.LineStrips3D([path], colors=[[40, 120, 255]]), static=True)
    # landmarks
    lm_pos, lm_cov, labels = [], [], []
    for tag, key in problem.landmark_keys.items():
        t = problem.var_types[key]
        v = value_vector(solution.values, key, t)
        if t == "Point2":
            z, vz = problem.landmark_heights.get(tag, (0.0, 0.0))
            lm_pos.append([v[0], v[1], z])
            pc = position_cov_in_map(t, None, marginals[key])
            pc[2, 2] = vz
        else:
            lm_pos.append(v[:3].tolist())
            pc = position_cov_in_map(t, solution.values.atPose3(key) if t == "Pose3" else None, marginals[key])
        lm_cov.append(pc)
        labels.append(str(tag))
    if lm_pos:
        rec.log(
            f"{ENTITY}/landmarks",
            ellipsoids(np.array(lm_pos), lm_cov, n_sigma, colors=[[255, 140, 0]], labels=labels),
            static=True,
        )
        rec.log(
            f"{ENTITY}/landmarks/centers",
            rr.Points3D(np.array(lm_pos), labels=labels, radii=0.03, colors=[[255, 140, 0]]),
            static=True,
        )
    # pose ellipses along the path (a stride)
    idx = list(range(0, len(problem.pose_keys), max(1, pose_stride)))
    centers = path[idx]
    covs = [
        position_cov_in_map(
            pose_type,
            solution.values.atPose3(problem.pose_keys[i])
            if pose_type == "Pose3"
            else solution.values.atPose2(problem.pose_keys[i]),
            marginals[problem.pose_keys[i]],
        )
        for i in idx
    ]
    if idx:
        rec.log(f"{ENTITY}/pose_covariance", ellipses_2d(centers, covs, n_sigma, colors=[[40, 120, 255]]), static=True)
    # tag-measurement edges, static, and the current pose on the time line
    pose_pos = {k: path[i] for i, k in enumerate(problem.pose_keys)}
    lm_by_key = {problem.landmark_keys[int(lab)]: np.array(p) for lab, p in zip(labels, lm_pos, strict=True)}
    edges = [
        [pose_pos[r.keys[0]], lm_by_key[r.keys[1]]]
        for r in problem.rows
        if r.kind == "tag" and r.keys[0] in pose_pos and r.keys[1] in lm_by_key
    ]
    if edges:
        rec.log(f"{ENTITY}/tag_edges", rr.LineStrips3D(edges, colors=[[200, 200, 60, 90]], radii=0.003), static=True)
    for i in idx:
        set_stamp(rec, problem.pose_stamps_ns[i])
        q = poses3[i].rotation().toQuaternion()
        rec.log(f"{ENTITY}/pose", rr.Transform3D(translation=path[i], quaternion=[q.x(), q.y(), q.z(), q.w()]))
