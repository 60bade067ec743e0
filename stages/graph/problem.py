"""The graph problem as plain data: factor rows, variable types, initial values and what each key means."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import gtsam
import numpy as np

from stages.graph.factors import FactorRow
from stages.graph.models import GraphModel, Model, graph_model
from stages.graph.variables import (
    SCALE,
    VALUE_WIDTH,
    VAR_DIMS,
    VarKind,
    insert_value,
    value_vector,
    var_kind,
)

__all__ = [
    "VALUE_WIDTH",
    "VAR_DIMS",
    "GraphProblem",
    "Model",
    "VarType",
    "arrays_to_values",
    "insert_value",
    "value_vector",
    "values_to_arrays",
]

VarType = Literal["Pose2", "Pose3", "Point2", "Point3", "Scale"]


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
        row_cameras: the camera of each row, for messages (may be empty).
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
    row_cameras: list[str | None] = field(default_factory=list)
    """The camera of each row (None for rows that are not a sighting); empty when unknown (graphs read from a file,
    restricted problems). Only error messages read it."""

    def describe(self, key: int) -> str:
        """A person's name for a variable: ``pose 12 (t=3.210 s)`` or ``tag 17``."""
        if key in self._pose_index:
            i = self._pose_index[key]
            t0 = self.pose_stamps_ns[0] if self.pose_stamps_ns else 0
            return f"pose {i} (t={(self.pose_stamps_ns[i] - t0) / 1e9:.3f} s, stamp_ns {self.pose_stamps_ns[i]})"
        if key in self._landmark_id:
            return f"tag {self._landmark_id[key]}"
        if key == self.scale_key:
            return "the tag scale s"
        return f"variable {key}"

    @property
    def graph_model(self) -> GraphModel:
        """The planar or 3D model of the graph (:mod:`stages.graph.models`)."""
        return graph_model(self.model)

    def kind(self, key: int) -> VarKind:
        """The kind of variable ``key`` (:mod:`stages.graph.variables`)."""
        return var_kind(self.var_types[key])

    def position(self, values: gtsam.Values, key: int) -> np.ndarray:
        """x, y, z of variable ``key`` in the map frame at ``values`` (2D kinds: z = 0)."""
        kind = self.kind(key)
        return kind.position(kind.read(values, key))

    def pose3s(self, values: gtsam.Values) -> list[gtsam.Pose3]:
        """The robot poses at ``values`` as Pose3, in time order."""
        kind = self.graph_model.pose
        return [kind.pose3(kind.read(values, k)) for k in self.pose_keys]

    @property
    def scale_key(self) -> int | None:
        """Key of the shared tag scale ``s``, or None when the graph has none (``graph.tag_scale_sigma: 0``)."""
        return next((k for k, t in self.var_types.items() if t == SCALE.name), None)

    @property
    def tag_factor_indices(self) -> np.ndarray:
        """Indices of the tag-measurement factors (the selection candidates)."""
        return np.array([i for i, r in enumerate(self.rows) if r.kind == "tag"], dtype=np.int64)

    @property
    def fixed_factor_indices(self) -> np.ndarray:
        """Indices of every other factor (priors, the tag-scale prior, odometry, loops, motion priors)."""
        return np.array([i for i, r in enumerate(self.rows) if r.kind != "tag"], dtype=np.int64)

    def restricted(
        self,
        rows: list[FactorRow],
        values: gtsam.Values,
        landmark_heights: dict[int, tuple[float, float]] | None = None,
    ) -> GraphProblem:
        """The problem of ``rows`` only: the variables they touch, initialised from ``values``.

        Every pose stays (a pose no row touches is kept in ``pose_keys``, not in the values); landmarks no row
        touches are left out, and so are their heights.
        """
        used = {k for r in rows for k in r.keys}
        initial = gtsam.Values()
        var_types: dict[int, str] = {}
        for k, t in self.var_types.items():
            if k in used:
                insert_value(initial, k, t, value_vector(values, k, t))
                var_types[k] = t
        observed = sorted(t for t, k in self.landmark_keys.items() if k in used)
        heights = self.landmark_heights if landmark_heights is None else landmark_heights
        return GraphProblem(
            model=self.model,
            rows=rows,
            initial=initial,
            var_types=var_types,
            pose_keys=list(self.pose_keys),
            pose_stamps_ns=list(self.pose_stamps_ns),
            landmark_keys={t: self.landmark_keys[t] for t in observed},
            landmark_heights={t: h for t, h in heights.items() if t in set(observed)},
        )

    @property
    def _pose_index(self) -> dict[int, int]:
        return {k: i for i, k in enumerate(self.pose_keys)}

    @property
    def _landmark_id(self) -> dict[int, int]:
        return {k: t for t, k in self.landmark_keys.items()}


def values_to_arrays(values: gtsam.Values, var_types: dict[int, str], keys: list[int]) -> np.ndarray:
    """N x 7 array of the stored vectors of ``keys``."""
    return np.array([value_vector(values, k, var_types[k]) for k in keys]).reshape(len(keys), VALUE_WIDTH)


def arrays_to_values(keys: np.ndarray, types: np.ndarray, vectors: np.ndarray) -> gtsam.Values:
    """Inverse of :func:`values_to_arrays`."""
    values = gtsam.Values()
    for k, t, v in zip(keys, types, vectors, strict=True):
        insert_value(values, int(k), str(t), v)
    return values
