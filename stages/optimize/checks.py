"""optimize's health checks: :mod:`stages.graph.health` on the solved reduced graph."""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.artifacts import StageInput
from pipeline.errors import StageError
from stages.graph.factors import build_graph
from stages.graph.health import graph_health, strict_error
from stages.graph.problem import GraphProblem
from stages.graph.solve import Solution
from stages.optimize.config import OptimizeConfig


def reduced_health(
    graph_in: StageInput,
    problem: GraphProblem,
    solution: Solution,
    marginals: dict[int, np.ndarray],
    cfg: OptimizeConfig,
) -> dict[str, Any]:
    """The health checks of the solved reduced graph (:mod:`stages.graph.health`); with ``optimize.strict`` a failed
    one stops the stage."""
    graph_summary = graph_in.read_json("summary.json") if graph_in.exists("summary.json") else {}
    size = graph_summary.get("tag_size_m") if isinstance(graph_summary, dict) else None
    health = graph_health(
        problem,
        build_graph(problem.rows),
        solution.values,
        marginals,
        solution.iterations,
        cfg.max_iterations,
        "optimize",
        float(size) if isinstance(size, int | float) else None,
    )
    if cfg.strict and not health["ok"]:
        raise StageError(strict_error("optimize", health))
    return health
