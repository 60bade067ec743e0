"""Write the graph stage's artifacts and its Rerun recording (for the full graph and for optimize's reduced one).

Artifacts in ``graph/`` (declared in :mod:`stages.graph.artifacts`): ``factors.parquet``, ``values.npz``,
``marginals.npz``, ``poses.parquet``, ``landmarks.parquet``, ``trajectory.tum``, ``dead_reckoning.tum``,
``graph.g2o``, ``graph.g2o.json`` (and ``summary.json``, written by the runner).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from typing import Any

import gtsam
import numpy as np
import pyarrow as pa
import rerun as rr

from pipeline.artifacts import StageOutput
from pipeline.recording import ellipses_2d, ellipsoids, set_stamp
from stages.columns import POSITION, QUATERNION, YAW
from stages.geometry import pose3_to_vector
from stages.graph.artifacts import (
    CAMERA_POSES,
    DEAD_RECKONING,
    FACTORS,
    G2O,
    G2O_META,
    INDEX,
    LANDMARKS,
    POSE_KEY,
    POSE_STAMP_NS,
    POSES,
    POSITION_COV,
    TANGENT_COVARIANCE,
    TRAJECTORY,
    G2oMetadata,
    MarginalArrays,
    ValueArrays,
)
from stages.graph.factors import rows_to_table
from stages.graph.g2o import g2o_metadata, write_g2o
from stages.graph.problem import GraphProblem, values_to_arrays
from stages.graph.rig import camera_poses_yaml
from stages.graph.solve import Solution

ENTITY = "/graph"


def landmark_position(
    problem: GraphProblem, values: gtsam.Values, tag: int, cov: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """x, y, z of landmark ``tag`` in the map frame and its 3x3 position covariance.

    Planar landmarks take their height and its variance from :attr:`GraphProblem.landmark_heights`.
    """
    key = problem.landmark_keys[tag]
    kind = problem.kind(key)
    value = kind.read(values, key)
    xyz, pc = kind.position(value), kind.position_cov(value, cov)
    if kind.dim == 2:
        z, vz = problem.landmark_heights.get(tag, (0.0, 0.0))
        xyz[2], pc[2, 2] = z, vz
    return xyz, pc


def tum_text(stamps_ns: list[int], poses: list[gtsam.Pose3]) -> str:
    """TUM trajectory: ``t x y z qx qy qz qw`` per line (t in seconds)."""
    lines = []
    for s, p in zip(stamps_ns, poses, strict=True):
        t = np.asarray(p.translation())
        q: gtsam.Quaternion = p.rotation().toQuaternion()  # gtsam's stub misnames the return type
        lines.append(f"{s / 1e9:.9f} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {q.x():.9f} {q.y():.9f} {q.z():.9f} {q.w():.9f}")
    return "\n".join(lines) + "\n"


def write_artifacts(
    out: StageOutput, problem: GraphProblem, solution: Solution, marginals: dict[int, np.ndarray]
) -> dict[str, Any]:
    """Write every artifact; return the headline numbers for the summary."""
    FACTORS.write(out, rows_to_table(problem.rows))
    _write_values(out, problem, solution, marginals)
    _write_poses(out, problem, solution, marginals)
    LANDMARKS.write(out, landmarks_table(problem, solution.values, marginals))
    out.write_text(G2O.file, write_g2o(problem, solution.values))
    G2O_META.write(out, G2oMetadata(**g2o_metadata(problem, solution.values)))
    _write_camera_poses(out, problem)
    kinds = Counter(r.kind for r in problem.rows)
    return {
        "tag_scale": _tag_scale(problem, solution, marginals),
        "model": problem.model,
        "poses": len(problem.pose_keys),
        "landmarks": len(problem.landmark_keys),
        "factors": len(problem.rows),
        "factors_by_kind": dict(sorted(kinds.items())),
        "tag_measurements": int(kinds.get("tag", 0)),
        "optimizer": solution.optimizer,
        "initial_error": solution.initial_error,
        "final_error": solution.final_error,
        "iterations": solution.iterations,
        "optimise_seconds": round(solution.seconds, 4),
    }


def _write_camera_poses(out: StageOutput, problem: GraphProblem) -> None:
    """``camera_poses.yaml`` when the rig calibration estimated a mount (given mounts held fixed)."""
    rig = problem.info.get("rig_calibration")
    if not isinstance(rig, dict) or not rig.get("cameras"):
        out.file(CAMERA_POSES.file).unlink(missing_ok=True)
        return
    mounts: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    for entry in rig.get("given", {}).values():
        mounts[str(entry["frame_id"])] = (np.asarray(entry["T_base_camera"]), None)
    base = "base"
    for entry in rig["cameras"].values():
        cov = entry.get("covariance")
        mounts[str(entry["frame_id"])] = (np.asarray(entry["T_base_camera"]), None if cov is None else np.asarray(cov))
        base = str(entry.get("base_frame", base))
    out.write_text(CAMERA_POSES.file, camera_poses_yaml(dict(sorted(mounts.items())), base))


def _write_values(
    out: StageOutput, problem: GraphProblem, solution: Solution, marginals: dict[int, np.ndarray]
) -> None:
    """``values.npz`` (initial and optimised vectors) and ``marginals.npz`` (covariances padded to 6x6)."""
    keys = list(problem.var_types)
    types = np.array([problem.var_types[k] for k in keys])
    ValueArrays(
        keys=np.array(keys, dtype=np.uint64),
        types=types,
        initial=values_to_arrays(problem.initial, problem.var_types, keys),
        optimised=values_to_arrays(solution.values, problem.var_types, keys),
    ).write(out)
    cov_pad = np.zeros((len(keys), 6, 6))
    dims = np.array([problem.kind(k).dim for k in keys], dtype=np.int32)
    for i, k in enumerate(keys):
        cov_pad[i, : dims[i], : dims[i]] = marginals[k]
    MarginalArrays(keys=np.array(keys, dtype=np.uint64), types=types, dims=dims, covariance=cov_pad).write(out)


def _write_poses(out: StageOutput, problem: GraphProblem, solution: Solution, marginals: dict[int, np.ndarray]) -> None:
    """``poses.parquet`` and the optimised and dead-reckoning trajectories (TUM)."""
    kind = problem.graph_model.pose
    poses3 = problem.pose3s(solution.values)
    vec = np.array([pose3_to_vector(p) for p in poses3]).reshape(-1, 7)
    pos_cov = [kind.position_cov(kind.read(solution.values, k), marginals[k]) for k in problem.pose_keys]
    POSES.write(
        out,
        {
            INDEX: np.arange(len(problem.pose_keys), dtype=np.int64),
            POSE_KEY: np.array(problem.pose_keys, dtype=np.uint64),
            POSE_STAMP_NS: np.array(problem.pose_stamps_ns, dtype=np.int64),
            **{c: vec[:, i] for i, c in enumerate((*POSITION, *QUATERNION))},
            YAW: np.array([p.rotation().yaw() for p in poses3]),
            TANGENT_COVARIANCE: [marginals[k].ravel().tolist() for k in problem.pose_keys],
            POSITION_COV: [c.ravel().tolist() for c in pos_cov],
        },
    )
    out.write_text(TRAJECTORY.file, tum_text(problem.pose_stamps_ns, poses3))
    out.write_text(DEAD_RECKONING.file, tum_text(problem.pose_stamps_ns, problem.pose3s(problem.initial)))


def landmarks_table(problem: GraphProblem, values: gtsam.Values, marginals: dict[int, np.ndarray]) -> pa.Table:
    """``landmarks.parquet`` at ``values`` (see :data:`stages.graph.artifacts.LANDMARKS`)."""
    n_obs = Counter(r.tag_id for r in problem.rows if r.kind == "tag")
    cols: dict[str, list[Any]] = {name: [] for name in LANDMARKS.names}
    for tag, key in problem.landmark_keys.items():
        kind = problem.kind(key)
        xyz, pc = landmark_position(problem, values, tag, marginals[key])
        q = kind.vector(values, key)[3:7].tolist() if kind.is_pose else [None] * 4
        row = (tag, key, *xyz.tolist(), *q, pc.ravel().tolist(), marginals[key].ravel().tolist(), kind.name)
        for name, val in zip(LANDMARKS.names, (*row, int(n_obs.get(tag, 0))), strict=True):
            cols[name].append(val)
    return LANDMARKS.table(cols)


def _tag_scale(problem: GraphProblem, solution: Solution, marginals: dict[int, np.ndarray]) -> dict[str, float] | None:
    """The estimated tag scale, its sigma and its prior's, or None when the graph has no scale."""
    sk = problem.scale_key
    if sk is None:
        return None
    prior = next((r for r in problem.rows if r.kind == "scale_prior"), None)
    return {
        "value": float(solution.values.atDouble(sk)),
        "sigma": float(np.sqrt(marginals[sk][0, 0])),
        "prior_sigma": float(np.sqrt(np.asarray(prior.covariance, dtype=float).ravel()[0]))
        if prior is not None
        else float("nan"),
    }


def log_recording(
    rec: rr.RecordingStream,
    problem: GraphProblem,
    solution: Solution,
    marginals: dict[int, np.ndarray],
    n_sigma: float,
    pose_stride: int = 10,
    calibration_moves: Mapping[int, np.ndarray] | None = None,
) -> None:
    """``graph.rrd``: dead reckoning and optimised path, landmarks with ellipsoids, pose ellipses, tag edges, and
    (``calibration_moves``, when ``odometry_calibration: auto`` tested and left the calibration off) where its
    step would move each landmark, as arrows: what the ``wheel_scale`` check measures, beside the ellipsoids it
    measures it against."""
    poses3 = problem.pose3s(solution.values)
    path = np.array([np.asarray(p.translation()) for p in poses3]).reshape(-1, 3)
    dr = np.array([np.asarray(p.translation()) for p in problem.pose3s(problem.initial)]).reshape(-1, 3)
    rec.log(f"{ENTITY}", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(f"{ENTITY}/dead_reckoning", rr.LineStrips3D([dr], colors=[[150, 150, 150]]), static=True)
    rec.log(f"{ENTITY}/path", rr.LineStrips3D([path], colors=[[40, 120, 255]]), static=True)
    landmarks = _log_landmarks(rec, problem, solution.values, marginals, n_sigma)
    moves = {k: np.asarray(v, dtype=float)[:3] for k, v in (calibration_moves or {}).items() if k in landmarks}
    if moves:
        tags = {k: t for t, k in problem.landmark_keys.items()}
        rec.log(
            f"{ENTITY}/calibration_step",
            rr.Arrows3D(
                origins=np.array([landmarks[k] for k in moves]),
                vectors=np.array(list(moves.values())),
                labels=[str(tags[k]) for k in moves],
                colors=[[220, 40, 160]],
            ),
            static=True,
        )
    _log_mounts(rec, problem, n_sigma)
    idx = list(range(0, len(problem.pose_keys), max(1, pose_stride)))
    if idx:
        kind = problem.graph_model.pose
        keys = [problem.pose_keys[i] for i in idx]
        covs = [kind.position_cov(kind.read(solution.values, k), marginals[k]) for k in keys]
        ellipses = ellipses_2d(path[idx], covs, n_sigma, colors=[[40, 120, 255]])
        rec.log(f"{ENTITY}/pose_covariance", ellipses, static=True)
    # tag-measurement edges, static, and the current pose on the time line
    pose_pos = {k: path[i] for i, k in enumerate(problem.pose_keys)}
    edges = [
        [pose_pos[r.keys[0]], landmarks[r.keys[1]]]
        for r in problem.rows
        if r.kind == "tag" and r.keys[0] in pose_pos and r.keys[1] in landmarks
    ]
    if edges:
        rec.log(f"{ENTITY}/tag_edges", rr.LineStrips3D(edges, colors=[[200, 200, 60, 90]], radii=0.003), static=True)
    for i in idx:
        set_stamp(rec, problem.pose_stamps_ns[i])
        q: gtsam.Quaternion = poses3[i].rotation().toQuaternion()
        xyzw = rr.Quaternion(xyzw=[q.x(), q.y(), q.z(), q.w()])
        rec.log(f"{ENTITY}/pose", rr.Transform3D(translation=path[i], quaternion=xyzw))


def _log_mounts(rec: rr.RecordingStream, problem: GraphProblem, n_sigma: float) -> None:
    """The rig's cameras under the moving ``pose``: estimated mounts with their ellipsoids, given ones as points."""
    rig = problem.info.get("rig_calibration")
    if not isinstance(rig, dict) or not rig.get("cameras"):
        return
    xyz, covs, labels = [], [], []
    for entry in rig["cameras"].values():
        T = np.asarray(entry["T_base_camera"], dtype=float)
        cov = np.asarray(entry.get("covariance", np.zeros((6, 6))), dtype=float)[3:, 3:]
        xyz.append(T[:3, 3])
        covs.append(T[:3, :3] @ cov @ T[:3, :3].T)
        labels.append(str(entry["frame_id"]))
    rec.log(
        f"{ENTITY}/pose/cameras",
        ellipsoids(np.array(xyz), covs, n_sigma, colors=[[220, 40, 160]], labels=labels),
        static=True,
    )
    given = [np.asarray(e["T_base_camera"], dtype=float)[:3, 3] for e in rig.get("given", {}).values()]
    if given:
        names = [str(e["frame_id"]) for e in rig["given"].values()]
        rec.log(f"{ENTITY}/pose/cameras_given", rr.Points3D(np.array(given), labels=names, radii=0.01), static=True)


def _log_landmarks(
    rec: rr.RecordingStream,
    problem: GraphProblem,
    values: gtsam.Values,
    marginals: dict[int, np.ndarray],
    n_sigma: float,
) -> dict[int, np.ndarray]:
    """The landmarks with their ellipsoids and labels; returns their positions by key."""
    positions = {t: landmark_position(problem, values, t, marginals[k]) for t, k in problem.landmark_keys.items()}
    if positions:
        labels = [str(t) for t in positions]
        xyz = np.array([p for p, _ in positions.values()])
        covs = [c for _, c in positions.values()]
        orange = [[255, 140, 0]]
        rec.log(f"{ENTITY}/landmarks", ellipsoids(xyz, covs, n_sigma, colors=orange, labels=labels), static=True)
        rec.log(f"{ENTITY}/landmarks/centers", rr.Points3D(xyz, labels=labels, radii=0.03, colors=orange), static=True)
    return {problem.landmark_keys[t]: p for t, (p, _) in positions.items()}
