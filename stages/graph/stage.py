"""The graph stage: the full factor graph of the run, optimised, with the marginals of every variable."""

from __future__ import annotations

import time
from typing import Any

from pipeline.context import StageContext
from stages.detect.artifacts import DETECTIONS
from stages.graph.build import DETECTION_COLUMNS, DETECTION_FILTER_COLUMNS, ODOMETRY_COLUMNS, build_problem
from stages.graph.config import GRAPH_SOURCE, GraphConfig
from stages.graph.problem import GraphProblem
from stages.graph.solve_all import solve_and_write
from stages.ingest.artifacts import EXTRINSICS, ODOMETRY, TAGS


def run(ctx: StageContext, cfg: GraphConfig) -> dict[str, Any]:
    """Build the graph (from ingest and detect, or from the run's graph file); optimise; write; log."""
    t0 = time.perf_counter()
    if ctx.run.source_kind == GRAPH_SOURCE:
        problem, cfg = _from_file(ctx, cfg)
    else:
        ingest = ctx.input("ingest")
        odometry = ODOMETRY.read(ingest, columns=ODOMETRY_COLUMNS) if ingest.exists(ODOMETRY.file) else None
        extrinsics = EXTRINSICS.read(ingest) if ingest.exists(EXTRINSICS.file) else None
        tags = TAGS.read(ingest) if ingest.exists(TAGS.file) else None
        detections = DETECTIONS.read(ctx.input("detect"), columns=(*DETECTION_COLUMNS, *DETECTION_FILTER_COLUMNS))
        problem = build_problem(detections, odometry, extrinsics, cfg, tags)
    build_s = time.perf_counter() - t0
    summary = solve_and_write(problem, cfg, ctx.output, ctx.rec, ctx.n_sigma)
    summary["timing_s"]["read_and_build"] = round(build_s, 4)
    if ctx.run.source_kind == GRAPH_SOURCE:
        summary["imported_from"] = str(ctx.source)
    return summary


def _from_file(ctx: StageContext, cfg: GraphConfig) -> tuple[GraphProblem, GraphConfig]:
    """The problem of the run's g2o / GTSAM file; the model is the file's."""
    from stages.graph.g2o import read_graph_file, side_file

    ctx.outside_file(side_file(ctx.source))  # the landmark id offset of a g2o file focusmap wrote
    problem = read_graph_file(ctx.source, cfg.prior_sigma_m, cfg.prior_sigma_rad)
    return problem, cfg.model_copy(update={"model": problem.model})
