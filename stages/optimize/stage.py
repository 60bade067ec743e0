"""The optimize stage: the reduced graph re-optimised, its map, entropy, errors, risk and size."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr

from pipeline.context import StageContext
from pipeline.errors import StageError
from pipeline.recording import colormap, ellipsoids, set_stamp
from stages.columns import STAMP_NS, TAG_ID, YAW, X, Y
from stages.estimation.blas import blas_single
from stages.graph.load import LoadedGraph, load_graph
from stages.graph.outputs import write_artifacts
from stages.navigation.truth import MapTruth, load_truth
from stages.optimize.artifacts import (
    ERROR_VS_FULL_M,
    ERROR_VS_TRUTH_M,
    FULL_INDEX,
    INDEX,
    IS_FOCUSED,
    KEPT,
    LANDMARK_ERRORS,
    MAHALANOBIS,
    N_MEASUREMENTS,
    P_COLLISION,
    P_COLLISION_FULL,
    RISK,
    SIGMA_M,
)
from stages.optimize.checks import reduced_health
from stages.optimize.config import OptimizeConfig
from stages.optimize.core import (
    ReducedMap,
    landmark_errors,
    local_map,
    map_size,
    mean_or_nan,
    solve_reduced,
    solve_settings,
)
from stages.risk import (
    LandmarkMap,
    PathGeometry,
    PathRisk,
    RiskParams,
    full_local_map,
    path_geometry,
    path_risk,
    read_path_inputs,
)
from stages.select_landmarks.artifacts import CLEARANCE_M, FOCUSED, LOCALISED, SIGMA_STAR, xy_blocks
from stages.select_measurements.artifacts import SELECTION

ENTITY = "/optimize"


def load_geometry(ctx: StageContext, loaded: LoadedGraph, params: RiskParams) -> PathGeometry:
    """Clearances and visibility of the recorded path (scans from ingest, detections from detect when present)."""
    read = read_path_inputs(ctx)
    return path_geometry(loaded, read.scans, read.T_base_laser, read.detections, params)


@blas_single
def run(ctx: StageContext, cfg: OptimizeConfig) -> dict[str, Any]:
    """Build and solve the reduced graph; write graph-like artifacts plus entropy, errors, risk and size."""
    t0 = time.perf_counter()
    graph_in = ctx.input("graph")
    loaded = load_graph(graph_in)
    selection = SELECTION.read(ctx.input("select_measurements"))
    if selection.focus == "poses":
        from stages.optimize.pose_graph import run_pose_focus

        return run_pose_focus(ctx, cfg, loaded, selection)
    if not ctx.has_input("select_landmarks"):
        raise StageError(
            f"stage 'optimize' needs 'select_landmarks', which has not run in {str(ctx.run.path)!r}; run "
            f"'focusmap select-landmarks {ctx.run.path}' first"
        )
    focused = FOCUSED.read(ctx.input("select_landmarks"))
    reduced = solve_reduced(
        loaded,
        focused.tag_ids,
        selection.factor_indices,
        loaded.landmark_heights,
        cfg.initialise_from,
        cfg.max_iterations,
        cfg.relative_error_tol,
        cfg.unobserved_sigma_m,
    )
    health = reduced_health(graph_in, reduced.problem, reduced.solution, reduced.marginals, cfg)
    summary = write_artifacts(ctx.output, reduced.problem, reduced.solution, reduced.marginals)
    KEPT.write(ctx.output, {INDEX: np.arange(len(reduced.full_index)), FULL_INDEX: reduced.full_index})
    full_map = LandmarkMap.from_graph(loaded)
    truth = load_truth(ctx, loaded, cfg.truth_file)
    true_tags = truth if truth is not None and truth.has_tags else None  # errors against the truth need its tags
    lm_table, errors = error_table(reduced, full_map, true_tags)
    LANDMARK_ERRORS.write(ctx.output, lm_table)

    params = focused.risk_params  # the risk model of the landmark selection, so the figures compare
    geometry = load_geometry(ctx, loaded, params)
    risk_reduced = path_risk(geometry, local_map(reduced, geometry), reduced.focused_observed, params)
    risk_full = path_risk(geometry, full_local_map(loaded, geometry), full_map.tag_ids.tolist(), params)
    RISK.write(ctx.output, risk_rows(geometry, risk_reduced, risk_full))
    size = map_size(loaded, reduced)
    log_recording(
        ctx.rec, loaded, reduced, full_map, truth, geometry, risk_reduced, ctx.n_sigma, cfg.pose_ellipse_stride
    )

    summary.update(
        {
            "focused_strategy": focused.strategy,
            "alpha": focused.budget,
            "measurement_strategy": selection.strategy,
            "K": selection.budget,
            "focused_landmarks": len(reduced.focused_tag_ids),
            "focused_observed": len(reduced.focused_observed),
            "observed_landmarks": len(reduced.observed_tag_ids),
            "focused_entropy": reduced.focused_entropy,
            "focused_entropy_observed": reduced.focused_entropy_observed,
            "focused_dim": reduced.focused_dim,
            "entropy_convention": "0.5*logdet(Sigma_F) + (d/2)*log(2*pi*e) nats; unobserved focused landmarks "
            f"enter with sigma {cfg.unobserved_sigma_m} m per dimension",
            **errors,
            "reference": "ground_truth" if true_tags is not None else "full_graph",
            "max_collision_probability": risk_reduced.max,
            "mean_collision_probability": risk_reduced.mean,
            "max_collision_probability_full": risk_full.max,
            "mean_collision_probability_full": risk_full.mean,
            "map_size": size,
            "dropped_unfocused_measurements": reduced.dropped_unfocused,
            "initialise_from": cfg.initialise_from,
            "solve": solve_settings(cfg),
            "health": health,
            "timing_s": {**reduced.timing_s, "total": round(time.perf_counter() - t0, 4)},
        }
    )
    if truth is not None and truth.missing:
        summary["notes"] = truth.missing_notes()
    return summary


def error_table(
    reduced: ReducedMap, full_map: LandmarkMap, truth: MapTruth | None
) -> tuple[pa.Table, dict[str, float]]:
    """Per observed landmark: errors against the full graph and the truth; and their means for the summary."""
    lmap = reduced.landmark_map
    vs_full = landmark_errors(lmap, dict(zip(full_map.tag_ids.tolist(), full_map.positions, strict=True)))
    vs_truth = landmark_errors(lmap, truth.tags) if truth is not None else {}
    focused = set(reduced.focused_tag_ids)
    tags = lmap.tag_ids.tolist()
    n_meas: dict[int, int] = {}
    for r in reduced.problem.rows:
        if r.kind == "tag" and r.tag_id is not None:
            n_meas[int(r.tag_id)] = n_meas.get(int(r.tag_id), 0) + 1
    table = LANDMARK_ERRORS.table(
        {
            TAG_ID: tags,
            IS_FOCUSED: [t in focused for t in tags],
            N_MEASUREMENTS: [n_meas.get(t, 0) for t in tags],
            X: lmap.positions[:, 0],
            Y: lmap.positions[:, 1],
            SIGMA_M: np.sqrt(np.trace(lmap.covariances, axis1=1, axis2=2)),
            ERROR_VS_FULL_M: [vs_full.get(t, float("nan")) for t in tags],
            ERROR_VS_TRUTH_M: [vs_truth.get(t, float("nan")) for t in tags],
        }
    )
    ref = vs_truth if truth is not None else vs_full
    errors = {
        "error_all_m": mean_or_nan(ref.values()),
        "focused_error_m": mean_or_nan(v for t, v in ref.items() if t in focused),
        "error_all_vs_full_m": mean_or_nan(vs_full.values()),
        "focused_error_vs_full_m": mean_or_nan(v for t, v in vs_full.items() if t in focused),
    }
    if truth is not None:
        errors["error_all_vs_truth_m"] = mean_or_nan(vs_truth.values())
        errors["focused_error_vs_truth_m"] = mean_or_nan(v for t, v in vs_truth.items() if t in focused)
    return table, errors


def risk_rows(geometry: PathGeometry, reduced: PathRisk, full: PathRisk) -> pa.Table:
    """``risk.parquet``: per keyframe, Σ* (x, y block) and collision probability with the reduced and full maps."""
    return RISK.table(
        {
            STAMP_NS: geometry.stamps_ns,
            X: geometry.poses[:, 0],
            Y: geometry.poses[:, 1],
            YAW: geometry.poses[:, 2],
            CLEARANCE_M: geometry.clearance_m,
            LOCALISED: reduced.localised,
            SIGMA_STAR: xy_blocks(reduced.sigma),
            P_COLLISION: reduced.p_collision,
            MAHALANOBIS: reduced.mahalanobis,
            P_COLLISION_FULL: full.p_collision,
        }
    )


def _lm_xyz(lmap: LandmarkMap) -> np.ndarray:
    return np.column_stack([lmap.positions, lmap.heights])


def _cov3(lmap: LandmarkMap) -> list[np.ndarray]:
    out = []
    for c in lmap.covariances:
        m = np.zeros((3, 3))
        m[:2, :2] = c
        out.append(m)
    return out


def log_recording(
    rec: rr.RecordingStream,
    loaded: LoadedGraph,
    reduced: ReducedMap,
    full_map: LandmarkMap,
    truth: MapTruth | None,
    geometry: PathGeometry,
    risk: PathRisk,
    n_sigma: float,
    stride: int,
) -> None:
    """``optimize.rrd``: the reduced map beside the full one (ellipses), the path coloured by risk, risk over time."""
    rec.log(ENTITY, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    if len(full_map.tag_ids):
        rec.log(
            f"{ENTITY}/full/landmarks",
            ellipsoids(
                _lm_xyz(full_map),
                _cov3(full_map),
                n_sigma,
                colors=[[150, 150, 150]],
                labels=[str(t) for t in full_map.tag_ids],
            ),
            static=True,
        )
    lmap = reduced.landmark_map
    if len(lmap.tag_ids):
        focused = set(reduced.focused_tag_ids)
        colors = [[255, 120, 0] if int(t) in focused else [60, 140, 255] for t in lmap.tag_ids]
        rec.log(
            f"{ENTITY}/reduced/landmarks",
            ellipsoids(_lm_xyz(lmap), _cov3(lmap), n_sigma, colors=colors, labels=[str(t) for t in lmap.tag_ids]),
            static=True,
        )
    if truth is not None:
        walls = [[[w[0], w[1], 0.0], [w[2], w[3], 0.0]] for w in truth.walls]
        rec.log(f"{ENTITY}/truth/walls", rr.LineStrips3D(walls, colors=[[90, 90, 90]]), static=True)
        pts = np.array([[*p[:2], 0.0] for p in truth.tags.values()]).reshape(-1, 3)
        rec.log(f"{ENTITY}/truth/landmarks", rr.Points3D(pts, colors=[[0, 200, 0]], radii=0.02), static=True)
    # path coloured by the reduced map's collision probability
    xy = geometry.poses[:, :2]
    p = np.nan_to_num(risk.p_collision, nan=0.0)
    if len(xy) > 1:
        segs = [[[*xy[i], 0.0], [*xy[i + 1], 0.0]] for i in range(len(xy) - 1)]
        rec.log(
            f"{ENTITY}/path",
            rr.LineStrips3D(segs, colors=colormap(p[:-1], 0.0, max(float(p.max()), 1e-9))),
            static=True,
        )
    # kept measurements as edges
    pose_xy = {k: xy[i] for i, k in enumerate(loaded.pose_keys)}
    lm_xy = {int(loaded.landmark_keys[int(t)]): lmap.positions[i] for i, t in enumerate(lmap.tag_ids)}
    edges = [
        [[*pose_xy[r.keys[0]], 0.0], [*lm_xy[r.keys[1]], 0.0]]
        for r in reduced.problem.rows
        if r.kind == "tag" and r.keys[0] in pose_xy and r.keys[1] in lm_xy
    ]
    if edges:
        rec.log(
            f"{ENTITY}/reduced/measurements",
            rr.LineStrips3D(edges, colors=[[255, 200, 0, 120]], radii=0.004),
            static=True,
        )
    for i in range(0, len(geometry.stamps_ns), max(1, stride)):
        set_stamp(rec, int(geometry.stamps_ns[i]))
        rec.log(f"{ENTITY}/risk/p_collision", rr.Scalars(float(p[i])))
        rec.log(f"{ENTITY}/pose", rr.Points3D([[*xy[i], 0.0]], radii=0.06, colors=colormap(p[i : i + 1], 0.0, 1.0)))
