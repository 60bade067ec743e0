"""optimize for a pose-focused selection (``select_measurements.focus: poses``): the pose graph with only the kept
loop closures, re-optimised, and how far its trajectory and its pose entropy are from the full graph's.

The reduced graph is every factor of the full graph but the loop closures that select_measurements did not keep.
The pose entropy is ``½ log det(2πe Σ_P)`` over every pose, from sparse log-determinants of the information at
each graph's solution (:func:`stages.estimation.sparse_cov.marginal_logdet`), so thousands of poses need no dense
covariance.
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
import rerun as rr

from pipeline.context import StageContext
from stages.estimation.gaussian import entropy_from_logdet
from stages.estimation.linear_system import LinearSystem
from stages.estimation.sparse_cov import marginal_logdet
from stages.graph.factors import build_graph
from stages.graph.load import LoadedGraph
from stages.graph.outputs import write_artifacts
from stages.graph.solve import check_problem, optimise
from stages.optimize.artifacts import FULL_INDEX, INDEX, KEPT
from stages.optimize.checks import reduced_health
from stages.optimize.config import OptimizeConfig
from stages.optimize.core import marginals_of
from stages.select_measurements.artifacts import SelectedMeasurements


def pose_entropy(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, pose_keys: list[int]) -> float:
    """Entropy (nats) of every pose jointly, linearised at ``values``."""
    poses = set(pose_keys)
    system = LinearSystem.from_gtsam(graph, values, is_landmark=lambda k: k not in poses)
    cols = system.columns([system.index_of_key(k) for k in pose_keys])
    return entropy_from_logdet(marginal_logdet(system.information(), cols), len(cols))


def trajectory_difference(loaded: LoadedGraph, a: gtsam.Values, b: gtsam.Values) -> dict[str, float]:
    """RMSE and largest distance between the pose positions of two solutions (same frame: the prior is kept), m."""
    d = np.array([np.linalg.norm(loaded.position(a, k) - loaded.position(b, k)) for k in loaded.pose_keys], dtype=float)
    return {"rmse_m": float(np.sqrt(np.mean(d**2))), "max_m": float(d.max(initial=0.0))}


def run_pose_focus(
    ctx: StageContext, cfg: OptimizeConfig, loaded: LoadedGraph, selection: SelectedMeasurements
) -> dict[str, Any]:
    """Solve the pose graph with the kept loop closures; write the graph-stage layout and ``kept.parquet``."""
    keep = np.array(selection.keep_factor_indices(loaded), dtype=np.int64)
    rows = [loaded.rows[int(i)] for i in keep]
    src = loaded.initial if cfg.initialise_from == "dead_reckoning" else loaded.values
    problem = loaded.restricted(rows, src)
    check_problem(problem)
    graph = build_graph(rows)
    solution = optimise(problem, graph, "lm", cfg.max_iterations, cfg.relative_error_tol)
    marginals = marginals_of(problem, graph, solution)
    health = reduced_health(ctx.input("graph"), problem, solution, marginals, cfg)
    summary = write_artifacts(ctx.output, problem, solution, marginals)
    log_pose_graph(ctx.rec, loaded, solution.values, [int(i) for i in selection.factor_indices])
    KEPT.write(ctx.output, {INDEX: np.arange(len(keep)), FULL_INDEX: keep})
    h_reduced = pose_entropy(graph, solution.values, loaded.pose_keys)
    h_full = pose_entropy(loaded.graph, loaded.values, loaded.pose_keys)
    loops = sum(1 for r in loaded.rows if r.kind == "loop")
    summary.update(
        {
            "focus": "poses",
            "measurement_strategy": selection.strategy,
            "K": selection.budget,
            "loop_closures_kept": len(selection.factor_indices),
            "loop_closures_total": loops,
            "pose_entropy": h_reduced,
            "pose_entropy_full": h_full,
            "pose_entropy_increase": h_reduced - h_full,
            "trajectory_vs_full": trajectory_difference(loaded, solution.values, loaded.values),
            "final_error_full_graph_at_reduced_solution": float(loaded.graph.error(solution.values)),
            "final_error_full_graph": float(loaded.graph.error(loaded.values)),
            "health": health,
        }
    )
    return summary


def log_pose_graph(rec: rr.RecordingStream, loaded: LoadedGraph, reduced: gtsam.Values, kept_loops: list[int]) -> None:
    """``optimize.rrd``: the full graph's trajectory (grey), the reduced one (orange) and the kept loop closures."""
    rec.log("/optimize", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    full = np.array([loaded.position(loaded.values, k) for k in loaded.pose_keys]).reshape(-1, 3)
    red = np.array([loaded.position(reduced, k) for k in loaded.pose_keys]).reshape(-1, 3)
    rec.log("/optimize/full/path", rr.LineStrips3D([full], colors=[[150, 150, 150]]), static=True)
    rec.log("/optimize/reduced/path", rr.LineStrips3D([red], colors=[[255, 120, 0]]), static=True)
    edges = [
        [loaded.position(reduced, loaded.rows[i].keys[0]), loaded.position(reduced, loaded.rows[i].keys[1])]
        for i in kept_loops
    ]
    if edges:
        rec.log(
            "/optimize/reduced/loop_closures", rr.LineStrips3D(edges, colors=[[255, 40, 200]], radii=0.01), static=True
        )
