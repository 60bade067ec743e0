"""What optimize writes into ``RUN/optimize/``, and :func:`read_reduced`, which reads it back for evaluate.

optimize writes the reduced graph with the graph stage's writer (``factors.parquet``, ``values.npz``,
``marginals.npz``, ``poses.parquet``, ``landmarks.parquet``, ``trajectory.tum``, ``dead_reckoning.tum``,
``graph.g2o``: the graph stage's layout, declared there), and its own tables: :data:`KEPT` (reduced factor index
to full index), :data:`LANDMARK_ERRORS` and :data:`RISK`. Its summary holds the focused entropy, the timings and
the ``solve`` settings. :func:`read_reduced` rebuilds from them the same ``ReducedMap`` that
:func:`~stages.optimize.core.solve_reduced` returned in the stage.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Final

import numpy as np
import pyarrow as pa

from pipeline.artifacts import StageInput
from pipeline.contracts import ArtifactSet, Column, FileSpec, TableSpec
from stages.columns import STAMP_NS, TAG_ID, YAW, X, Y
from stages.graph.artifacts import ARTIFACTS as GRAPH_ARTIFACTS
from stages.graph.artifacts import CALIBRATION, CAMERA_POSES
from stages.select_landmarks.artifacts import CLEARANCE_M, LOCALISED, SIGMA_STAR

if TYPE_CHECKING:
    from stages.graph.load import LoadedGraph
    from stages.optimize.core import ReducedMap

_F64 = pa.float64()

# kept.parquet ------------------------------------------------------------------------------------------
INDEX = Column("index", pa.int64(), "factor of the reduced graph (its row of `optimize/factors.parquet`)")
FULL_INDEX = Column(
    "full_index",
    pa.int64(),
    "the same factor's row of `graph/factors.parquet`; -1: a prior on the first pose that the reduced graph adds "
    "when no selected measurement reaches a surveyed tag, its only anchor (at the full graph's solution and marginal)",
)
KEPT: Final = TableSpec("kept.parquet", "one row per factor of the reduced graph", [INDEX, FULL_INDEX])

# landmark_errors.parquet -------------------------------------------------------------------------------
IS_FOCUSED = Column("focused", pa.bool_(), "one of the focused landmarks")
N_MEASUREMENTS = Column("n_measurements", pa.int64(), "kept tag measurements of the landmark")
SIGMA_M = Column("sigma_m", _F64, "√trace of the (x, y) marginal covariance, m")
ERROR_VS_FULL_M = Column("error_vs_full_m", _F64, "planar distance to the full graph's estimate, m")
ERROR_VS_TRUTH_M = Column("error_vs_truth_m", _F64, "planar distance to the ground truth, m (NaN without one)")
LANDMARK_ERRORS: Final = TableSpec(
    "landmark_errors.parquet",
    "one row per landmark of the reduced map (those with a kept measurement): its position and errors",
    [
        TAG_ID,
        IS_FOCUSED,
        N_MEASUREMENTS,
        Column(X, _F64, "position x in the map frame, m"),
        Column(Y, _F64, "position y in the map frame, m"),
        SIGMA_M,
        ERROR_VS_FULL_M,
        ERROR_VS_TRUTH_M,
    ],
)

# risk.parquet ------------------------------------------------------------------------------------------
P_COLLISION = Column("p_collision", _F64, "half-plane collision probability with the reduced map (NaN without laser)")
MAHALANOBIS = Column("mahalanobis", _F64, "eq. 20 with the reduced map (inf: no obstacle)")
P_COLLISION_FULL = Column("p_collision_full", _F64, "collision probability with the full graph's map")
RISK: Final = TableSpec(
    "risk.parquet",
    "one row per keyframe of the full graph, in time order: Σ and the collision risk with the reduced map "
    "(the risk model of `select_landmarks/focused.json`)",
    [
        STAMP_NS,
        X,
        Y,
        YAW,
        CLEARANCE_M,
        Column(LOCALISED, pa.bool_(), "the keyframe sees a focused landmark of the reduced map"),
        Column(SIGMA_STAR, SIGMA_STAR.type, "Σ of (x, y), 2×2 row-major, m², with the reduced map"),
        P_COLLISION,
        MAHALANOBIS,
        P_COLLISION_FULL,
    ],
)

# the reduced graph, in the graph stage's layout ----------------------------------------------------------
GRAPH_FILES: Final = tuple(
    FileSpec(spec.file, f"the reduced graph, as `graph/{spec.file}` (see graph's declarations)")
    for spec in GRAPH_ARTIFACTS.specs
    if spec is not CALIBRATION  # the full graph's, read through kept.parquet's `full_index`
    and spec is not CAMERA_POSES  # the rig's mounts are the full graph's: the reduced graph holds them fixed
)

ARTIFACTS: Final = ArtifactSet(
    "optimize",
    "The reduced graph (every non-tag factor and the kept measurements of the focused landmarks) re-optimised, "
    "with its errors and the collision risk of the path with its map.",
    [*GRAPH_FILES, KEPT, LANDMARK_ERRORS, RISK],
)


def read_reduced(inp: StageInput, full: LoadedGraph, focused_tag_ids: Iterable[int]) -> ReducedMap:
    """The reduced map optimize solved, from its artifacts.

    Args:
        inp: the finished optimize stage.
        full: the full graph (the landmark map is read as :func:`solve_reduced` makes it, in the full graph's keys).
        focused_tag_ids: the focused landmarks optimize used (select_landmarks' ``tag_ids``).
    """
    from stages.graph.consider import consider_term
    from stages.graph.load import load_graph
    from stages.graph.marginals import key_dims
    from stages.graph.problem import GraphProblem
    from stages.graph.solve import Solution
    from stages.optimize.core import ReducedMap
    from stages.risk import LandmarkMap

    red = load_graph(inp)
    summary = inp.summary
    kept = KEPT.read(inp, columns=[FULL_INDEX]).column(FULL_INDEX).to_numpy()
    problem = GraphProblem(
        model="planar" if red.model == "planar" else "3d",
        rows=red.rows,
        initial=red.initial,
        var_types=red.var_types,
        pose_keys=red.pose_keys,
        pose_stamps_ns=red.pose_stamps_ns,
        landmark_keys=red.landmark_keys,
        landmark_heights=red.landmark_heights,
    )
    solution = Solution(
        values=red.values,
        initial_error=float(summary.get("initial_error", float("nan"))),
        final_error=float(summary.get("final_error", float("nan"))),
        iterations=int(summary.get("iterations", 0)),
        optimizer="lm",
        seconds=float(summary.get("timing_s", {}).get("optimise", 0.0)),
    )
    timing = {k: float(v) for k, v in summary.get("timing_s", {}).items() if k != "total"}
    return ReducedMap(
        problem=problem,
        solution=solution,
        marginals=red.marginals,
        full_index=np.asarray(kept, dtype=np.int64),
        focused_tag_ids=sorted({int(t) for t in focused_tag_ids}),
        observed_tag_ids=sorted(red.landmark_keys),
        landmark_map=LandmarkMap.from_graph(full, red.values, red.marginals),
        focused_entropy=float(summary["focused_entropy"]),
        focused_entropy_observed=float(summary["focused_entropy_observed"]),
        focused_dim=int(summary["focused_dim"]),
        n_measurements=sum(1 for r in red.rows if r.kind == "tag"),
        dropped_unfocused=int(summary.get("dropped_unfocused_measurements", 0)),
        timing_s=timing,
        consider=consider_term(red.rows, red.graph.linearize(red.values), key_dims(red.values), full.calibration, kept)
        if full.calibration is not None
        else None,
    )
