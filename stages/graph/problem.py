"""The graph problem as plain data: factor rows, variable types, initial values and what each key means."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import gtsam
import numpy as np

from stages.geometry import pose2_to_vector, pose3_from_vector, pose3_to_vector
from stages.graph.factors import FactorRow

Model = Literal["planar", "3d"]
VarType = Literal["Pose2", "Pose3", "Point2", "Point3", "Scale"]
VAR_DIMS: dict[str, int] = {"Pose2": 3, "Pose3": 6, "Point2": 2, "Point3": 3, "Scale": 1}
"""Tangent dimension of each variable type."""
VALUE_WIDTH = 7
"""Width of stored value vectors: Pose2 x y theta, Pose3 x y z qx qy qz qw, Point2 x y, Point3 x y z,
Scale s (a gtsam ``Double``: the shared tag scale) (NaN-padded)."""


@dataclass
class GraphProblem:
    """A factor graph ready to optimise, with the meaning of its keys.

    Attributes:
        model: ``planar`` (Pose2 poses) or ``3d`` (Pose3 poses).
        rows: the factors, in graph order.
        initial: initial values of every variable.
        var_types: gtsam type name of every variable, by key.
        pose_keys: pose keys in time order.
        pose_stamps_ns: the stamp of each pose (ns; imported graphs: vertex id x 1 s).
        landmark_keys: landmark key by tag (or landmark vertex) id.
        landmark_heights: planar model only: tag id to (mean height in m, height variance m²) of its sightings.
        info: counts and notes for the summary.
    """

    model: Model
    rows: list[FactorRow]
    initial: gtsam.Values
    var_types: dict[int, str]
    pose_keys: list[int]
    pose_stamps_ns: list[int]
    landmark_keys: dict[int, int]
    landmark_heights: dict[int, tuple[float, float]] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def describe(self, key: int) -> str:
        """A person's name for a variable: ``pose 12 (t=3.210 s)`` or ``tag 17``."""
        if key in self._pose_index:
            i = self._pose_index[key]
            t0 = self.pose_stamps_ns[0] if self.pose_stamps_ns else 0
            return f"pose {i} (t={(self.pose_stamps_ns[i] - t0) / 1e9:.3f} s, stamp_ns {self.pose_stamps_ns[i]})"
        if key in self._landmark_id:
            return f"tag {self._landmark_id[key]}"
        if self.var_types.get(key) == "Scale":
            return "the tag scale s"
        return f"variable {key}"

    @property
    def scale_key(self) -> int | None:
        """Key of the shared tag scale ``s``, or None when the graph has none (``graph.tag_scale_sigma: 0``)."""
        return next((k for k, t in self.var_types.items() if t == "Scale"), None)

    @property
    def _pose_index(self) -> dict[int, int]:
        return {k: i for i, k in enumerate(self.pose_keys)}

    @property
    def _landmark_id(self) -> dict[int, int]:
        return {k: t for t, k in self.landmark_keys.items()}


def value_vector(values: gtsam.Values, key: int, var_type: str) -> np.ndarray:
    """The stored vector of one variable (NaN-padded to :data:`VALUE_WIDTH`)."""
    out = np.full(VALUE_WIDTH, np.nan)
    if var_type == "Pose2":
        out[:3] = pose2_to_vector(values.atPose2(key))
    elif var_type == "Pose3":
        out[:7] = pose3_to_vector(values.atPose3(key))
    elif var_type == "Point2":
        out[:2] = values.atPoint2(key)
    elif var_type == "Point3":
        out[:3] = values.atPoint3(key)
    elif var_type == "Scale":
        out[0] = values.atDouble(key)
    else:
        raise ValueError(f"unknown variable type {var_type!r}")
    return out


def insert_value(values: gtsam.Values, key: int, var_type: str, vec: np.ndarray) -> None:
    """Insert one variable from its stored vector."""
    v = np.asarray(vec, dtype=float)
    if var_type == "Pose2":
        values.insert(key, gtsam.Pose2(v[0], v[1], v[2]))
    elif var_type == "Pose3":
        values.insert(key, pose3_from_vector(v[:7]))
    elif var_type == "Point2":
        values.insert(key, v[:2].copy())
    elif var_type == "Point3":
        values.insert(key, v[:3].copy())
    elif var_type == "Scale":
        values.insert(key, float(v[0]))
    else:
        raise ValueError(f"unknown variable type {var_type!r}")


def values_to_arrays(values: gtsam.Values, var_types: dict[int, str], keys: list[int]) -> np.ndarray:
    """N x 7 array of the stored vectors of ``keys``."""
    return np.array([value_vector(values, k, var_types[k]) for k in keys]).reshape(len(keys), VALUE_WIDTH)


def arrays_to_values(keys: np.ndarray, types: np.ndarray, vectors: np.ndarray) -> gtsam.Values:
    """Inverse of :func:`values_to_arrays`."""
    values = gtsam.Values()
    for k, t, v in zip(keys, types, vectors, strict=True):
        insert_value(values, int(k), str(t), v)
    return values
