"""Read a finished graph stage back for the selection stages: the gtsam graph, its solution, its tables.

```python
loaded = load_graph(ctx.input("graph"))
linear = loaded.graph.linearize(loaded.values)          # the full graph at the solution
reduced = build_reduced(loaded, keep_factor_indices)     # a gtsam graph with only those factors
```
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import gtsam
import numpy as np
import pyarrow as pa

from pipeline.artifacts import StageInput
from pipeline.errors import InputError
from stages.columns import TAG_ID, Z
from stages.graph.artifacts import (
    FACTORS,
    LANDMARK_KEY,
    LANDMARKS,
    POSE_KEY,
    POSE_STAMP_NS,
    POSES,
    POSITION_COV,
    VALUES,
    MarginalArrays,
    ValueArrays,
)
from stages.graph.consider import ConsiderTerm, OdometryCalibration, consider_term
from stages.graph.factors import make_factor, table_to_rows
from stages.graph.marginals import key_dims
from stages.graph.models import model_of_poses
from stages.graph.problem import GraphProblem, arrays_to_values
from stages.graph.variables import var_kind


@dataclass(kw_only=True)
class LoadedGraph(GraphProblem):
    """A finished graph stage in memory: its :class:`GraphProblem` plus what the stage computed.

    ``rows``, ``initial`` (dead reckoning and first sightings), ``var_types``, ``pose_keys``, ``pose_stamps_ns``
    (imported graphs: vertex id x 1 s), ``landmark_keys`` (sorted by tag id) and ``model`` are the problem's; the
    shared tag scale is in no ``pose_keys`` / ``landmark_keys`` (see :attr:`scale_key`).

    Attributes:
        graph: the full ``NonlinearFactorGraph``; factor ``i`` is row ``index == i`` of ``factors``.
        values: the optimised values of every variable.
        factors: ``factors.parquet`` as a pyarrow table (the same factors as ``rows``).
        marginals: marginal covariance of each key (tangent space), from ``marginals.npz``.
        calibration: the odometry calibration the rows were corrected with, from ``calibration.npz`` (None: not
            calibrated, or a reduced graph of optimize, whose rows keep their full-graph indices in ``kept.parquet``).
    """

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    factors: pa.Table
    marginals: dict[int, np.ndarray]
    calibration: OdometryCalibration | None = None

    def consider_term(self) -> ConsiderTerm | None:
        """The calibration's uncertainty that covariances computed from :attr:`graph` lack (its ``marginals``
        already hold it; None when the run was not calibrated): see :mod:`stages.graph.consider`."""
        if self.calibration is None:  # no linearisation of the whole graph for nothing
            return None
        return consider_term(self.rows, self.graph.linearize(self.values), key_dims(self.values), self.calibration)


def load_graph(graph_input: StageInput) -> LoadedGraph:
    """Rebuild the graph stage's factor graph and solution from its artifacts.

    Raises:
        InputError: an artifact is missing, lacks a declared column or is inconsistent (the message names the stage
            to re-run: ``graph``, or ``optimize`` for its reduced graph).
    """
    factors = FACTORS.read(graph_input)
    rows = table_to_rows(factors)
    vals = ValueArrays.read(graph_input)
    margs = MarginalArrays.read(graph_input)
    poses = POSES.read(graph_input, columns=[POSE_KEY, POSE_STAMP_NS]).to_pydict()
    landmarks = LANDMARKS.read(graph_input)
    lms = landmarks.select([TAG_ID, LANDMARK_KEY]).to_pydict()
    keys = [int(k) for k in vals.keys]
    types = [str(t) for t in vals.types]
    var_types = dict(zip(keys, types, strict=True))
    values = arrays_to_values(vals.keys, vals.types, vals.optimised)
    initial = arrays_to_values(vals.keys, vals.types, vals.initial)
    graph = gtsam.NonlinearFactorGraph()
    for i, row in enumerate(rows):
        for k in row.keys:
            if k not in var_types:
                raise InputError(
                    f"{graph_input.stage} factor {i} refers to key {k} missing from {VALUES.file}; "
                    f"re-run 'focusmap {graph_input.stage}'"
                )
        graph.add(make_factor(row))
    marginals = {
        int(k): np.asarray(c[:d, :d]) for k, d, c in zip(margs.keys, margs.dims, margs.covariance, strict=True)
    }
    pose_keys = [int(k) for k in poses[POSE_KEY]]
    model = model_of_poses(var_types.get(pose_keys[0], ""))
    return LoadedGraph(
        graph=graph,
        values=values,
        initial=initial,
        factors=factors,
        rows=rows,
        pose_keys=pose_keys,
        pose_stamps_ns=[int(s) for s in poses[POSE_STAMP_NS]],
        landmark_keys={int(t): int(k) for t, k in zip(lms[TAG_ID], lms[LANDMARK_KEY], strict=True)},
        landmark_heights=landmark_heights(landmarks),
        var_types=var_types,
        model=model.name,
        marginals=marginals,
        calibration=OdometryCalibration.read(graph_input) if graph_input.stage == "graph" else None,
    )


def build_reduced(
    loaded: LoadedGraph, keep_factor_indices: Iterable[int]
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """A graph of only the given factors, with the optimised values of the variables they touch.

    Variables that no kept factor touches are left out of the values (a dropped landmark), so the
    pair can be optimised directly. Factor ``j`` of the result is the ``j``-th smallest kept index; when
    a kept tag factor uses the tag scale and its prior (``scale_prior``) was not kept, the prior is
    appended after them (the scale is never left without its prior).
    """
    keep = sorted({int(i) for i in keep_factor_indices})
    graph = gtsam.NonlinearFactorGraph()
    used: set[int] = set()
    for i in keep:
        if not 0 <= i < len(loaded.rows):
            raise IndexError(f"factor index {i} out of range (graph has {len(loaded.rows)} factors)")
        graph.add(make_factor(loaded.rows[i]))
        used.update(loaded.rows[i].keys)
    scale = loaded.scale_key
    if scale is not None and scale in used:
        kept = set(keep)
        for i, row in enumerate(loaded.rows):
            if row.kind == "scale_prior" and i not in kept:
                graph.add(make_factor(row))
    values = gtsam.Values()
    for k, t in loaded.var_types.items():
        if k in used:
            var_kind(t).copy(values, loaded.values, k)
    return graph, values


def landmark_heights(graph_landmarks: pa.Table) -> dict[int, tuple[float, float]]:
    """Tag id to (z, var z) from a ``landmarks.parquet`` (planar graphs keep the height aside)."""
    cols = graph_landmarks.to_pydict()
    return {
        int(t): (float(z), float(pc[8]) if pc and len(pc) == 9 else 0.0)
        for t, z, pc in zip(cols[TAG_ID], cols[Z], cols[POSITION_COV], strict=True)
    }
