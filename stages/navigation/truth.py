"""Ground truth of a run, when the run has one, and the map frame it is compared in.

Rule: the ground truth of a recording ``DIR/<name>.bag`` (or ``.mcap``, ``.db3``) is
``DIR/<name>.ground_truth.json``; of a ROS 2 bag folder ``DIR/<name>/`` it is
``DIR/<name>.ground_truth.json`` (the rule of ``sample_data.simulate.ground_truth_path``). The
recording is the run's source (``run.json``). Runs without such a file are evaluated against the
full graph (Table I case 1) and navigate in walls rebuilt from the laser scans.

The graph's map frame is the robot's base at the first keyframe (the graph's prior), so the
truth is brought into it with ``T_world_map`` = the true pose at the first keyframe's stamp.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from pipeline.errors import InputError

if TYPE_CHECKING:
    from pipeline.context import StageContext
    from stages.graph.load import LoadedGraph

FloatArray = npt.NDArray[np.float64]


def ground_truth_path(source: Path) -> Path:
    """Where the ground-truth file of a recording would be (whether or not it exists)."""
    source = Path(source)
    name = source.stem if source.suffix in (".bag", ".mcap", ".db3") else source.name
    return source.parent / f"{name}.ground_truth.json"


def ground_truth_file(source: Path | None) -> Path | None:
    """The ground-truth file beside a run's source recording, or None when there is none."""
    if source is None:
        return None
    path = ground_truth_path(source)
    return path if path.is_file() else None


def se2(x: float, y: float, yaw: float) -> FloatArray:
    """3x3 homogeneous planar transform."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def transform_points(T: npt.NDArray[np.floating], points: npt.ArrayLike) -> FloatArray:
    """Apply a 3x3 planar transform to (N, 2) points."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    return p @ T[:2, :2].T + T[:2, 2]


@dataclass(frozen=True)
class GroundTruth:
    """The simulator's truth: walls, tag positions and the robot's true path, in the world frame."""

    path: Path
    walls_world: FloatArray
    """(W, 4) wall segments x0 y0 x1 y1, m."""
    tags_world: dict[int, FloatArray]
    """Tag id to its centre (x, y, z), m."""
    pose_stamps_ns: npt.NDArray[np.int64]
    poses_world: FloatArray
    """(N, 3) true x, y, yaw of the base at ``pose_stamps_ns``."""

    @classmethod
    def load(cls, path: Path) -> GroundTruth:
        """Read ``<name>.ground_truth.json`` (as written by ``sample_data.simulate``)."""
        try:
            data = json.loads(Path(path).read_text())
            walls = np.asarray(data["world"]["walls"], dtype=float).reshape(-1, 4)
            tags = {int(t["id"]): np.asarray(t["position"], dtype=float) for t in data["tags"]}
            stamps = np.array([int(p["stamp_ns"]) for p in data["poses"]], dtype=np.int64)
            poses = np.array([[p["x"], p["y"], p["yaw"]] for p in data["poses"]], dtype=float).reshape(-1, 3)
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise InputError(
                f"ground truth {str(path)!r} is unreadable ({err}); fix or remove it to evaluate against the full graph"
            ) from err
        return cls(Path(path), walls, tags, stamps, poses)

    def pose_at(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """True (x, y, yaw) interpolated at ``stamps_ns`` (yaw unwrapped, then interpolated)."""
        t = self.pose_stamps_ns.astype(float)
        q = np.asarray(stamps_ns, dtype=float).reshape(-1)
        yaw = np.unwrap(self.poses_world[:, 2])
        return np.column_stack(
            [np.interp(q, t, self.poses_world[:, 0]), np.interp(q, t, self.poses_world[:, 1]), np.interp(q, t, yaw)]
        )

    def T_world_map(self, first_keyframe_ns: int) -> FloatArray:
        """The map frame (the base at the first keyframe) in the world."""
        x, y, yaw = self.pose_at([first_keyframe_ns])[0]
        return se2(x, y, yaw)

    def in_map(self, first_keyframe_ns: int) -> MapTruth:
        """Walls, tags and the true path in the graph's map frame."""
        T = np.linalg.inv(self.T_world_map(first_keyframe_ns))
        walls = np.column_stack(
            [transform_points(T, self.walls_world[:, :2]), transform_points(T, self.walls_world[:, 2:])]
        )
        tags = {i: transform_points(T, p[:2])[0] for i, p in self.tags_world.items()}
        xy = transform_points(T, self.poses_world[:, :2])
        yaw = np.unwrap(self.poses_world[:, 2]) + np.arctan2(T[1, 0], T[0, 0])
        return MapTruth(walls, tags, self.pose_stamps_ns, np.column_stack([xy, yaw]))


@dataclass(frozen=True)
class MapTruth:
    """The truth expressed in the graph's map frame."""

    walls: FloatArray
    """(W, 4) wall segments in the map frame."""
    tags: dict[int, FloatArray]
    """Tag id to its (x, y) in the map frame."""
    pose_stamps_ns: npt.NDArray[np.int64]
    poses: FloatArray
    """(N, 3) true path in the map frame."""

    def pose_at(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """True (x, y, yaw) in the map frame at ``stamps_ns``."""
        t = self.pose_stamps_ns.astype(float)
        q = np.asarray(stamps_ns, dtype=float).reshape(-1)
        return np.column_stack([np.interp(q, t, self.poses[:, i]) for i in range(3)])


def load_truth(ctx: StageContext, loaded: LoadedGraph) -> MapTruth | None:
    """The run's ground truth in the map frame, if a ``<name>.ground_truth.json`` sits beside its source.

    The file is declared to the runner (present or not), so the stage re-runs when it appears, changes or goes.
    """
    if ctx.run.source is None:
        return None
    path = ctx.outside_file(ground_truth_path(ctx.run.source))
    return GroundTruth.load(path).in_map(loaded.pose_stamps_ns[0]) if path is not None else None
