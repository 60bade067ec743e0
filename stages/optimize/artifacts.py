"""Read optimize's results back as a :class:`~stages.optimize.core.ReducedMap`, for evaluate's matching case.

optimize writes the reduced graph with the graph stage's artifacts (``factors.parquet``, ``values.npz``,
``marginals.npz``, ``poses.parquet``, ``landmarks.parquet``), ``kept.parquet`` (reduced factor index to full
index) and its summary (focused entropy, timings, the ``solve`` settings). :func:`read_reduced` rebuilds from
them the same ``ReducedMap`` that :func:`~stages.optimize.core.solve_reduced` returned in the stage.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from pipeline.artifacts import StageInput
from stages.graph.artifacts import LANDMARKS
from stages.graph.load import LoadedGraph, load_graph
from stages.graph.problem import GraphProblem
from stages.graph.solve import Solution
from stages.optimize.core import ReducedMap, landmark_heights
from stages.risk import LandmarkMap


def read_reduced(inp: StageInput, full: LoadedGraph, focused_tag_ids: Iterable[int]) -> ReducedMap:
    """The reduced map optimize solved, from its artifacts.

    Args:
        inp: the finished optimize stage.
        full: the full graph (the landmark map is read as :func:`solve_reduced` makes it, in the full graph's keys).
        focused_tag_ids: the focused landmarks optimize used (select_landmarks' ``tag_ids``).
    """
    red = load_graph(inp)
    summary = inp.summary
    kept = inp.read_table("kept.parquet", columns=["full_index"]).column("full_index").to_numpy()
    problem = GraphProblem(
        model="planar" if red.model == "planar" else "3d",
        rows=red.rows,
        initial=red.initial,
        var_types=red.var_types,
        pose_keys=red.pose_keys,
        pose_stamps_ns=red.pose_stamps_ns,
        landmark_keys=red.landmark_keys,
        landmark_heights=landmark_heights(LANDMARKS.read(inp)),
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
    )
