"""Check, optimise, compute marginals, write and log: the common tail of the stage, from a recording or a file."""

from __future__ import annotations

import time
from typing import Any

import rerun as rr

from pipeline.artifacts import StageOutput
from pipeline.errors import StageError
from stages.graph.calibration import applies as calibration_applies
from stages.graph.calibration import calibrate
from stages.graph.config import GraphConfig
from stages.graph.factors import build_graph
from stages.graph.health import graph_health, strict_error
from stages.graph.outputs import log_recording, write_artifacts
from stages.graph.problem import GraphProblem
from stages.graph.solve import check_problem, marginal_covariances, optimise


def solve_and_write(
    problem: GraphProblem, cfg: GraphConfig, out: StageOutput, rec: rr.RecordingStream | None, n_sigma: float
) -> dict[str, Any]:
    """Check the graph, optimise it, take every marginal from one factorisation, write the artifacts, log.

    Returns:
        The stage summary (counts, errors, iterations, timings, the problem's notes and the health checks).

    Raises:
        StageError: with ``graph.strict``, when a health check fails (nothing is written).
    """
    t0 = time.perf_counter()
    check_problem(problem)
    calibration = None
    if calibration_applies(problem, cfg):
        t1 = time.perf_counter()
        result = calibrate(problem, cfg)
        problem, graph, solution, marginals = result.problem, result.graph, result.solution, result.marginals
        calibration = result.summary
        t2 = time.perf_counter()
    else:
        graph = build_graph(problem.rows)
        t1 = time.perf_counter()
        solution = optimise(problem, graph, cfg.optimizer, cfg.max_iterations, cfg.relative_error_tol)
        t2 = time.perf_counter()
        marginals = marginal_covariances(problem, graph, solution.values, list(problem.var_types))
    health = graph_health(
        problem,
        graph,
        solution.values,
        marginals,
        solution.iterations,
        cfg.max_iterations,
        "graph",
        problem.info.get("tag_size_m"),
    )
    if cfg.strict and not health["ok"]:
        raise StageError(strict_error("graph", health))
    t3 = time.perf_counter()
    summary = write_artifacts(out, problem, solution, marginals)
    if rec is not None:
        log_recording(rec, problem, solution, marginals, n_sigma, cfg.pose_ellipse_stride)
    summary.update(problem.info)
    summary["health"] = health
    if calibration is not None:
        summary["odometry_calibration"] = calibration
    summary["timing_s"] = {
        "check_and_build": round(t1 - t0, 4),
        "optimise": round(t2 - t1, 4),
        "marginals": round(t3 - t2, 4),
        "write": round(time.perf_counter() - t3, 4),
    }
    return summary
