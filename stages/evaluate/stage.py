"""The evaluate stage: every case of Table I (and other pairs) on the run, navigation, report, recording."""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
import rerun as rr

from pipeline.context import StageContext
from pipeline.memory import map_large_blocks, release_freed_memory
from pipeline.recording import colormap, ellipsoids
from pipeline.workers import WorkerPool
from stages.estimation.blas import blas_single
from stages.evaluate import artifacts as art
from stages.evaluate.analysis import OVERCONFIDENCE_FALSE_ALARM
from stages.evaluate.cases import (
    TABLE_I_LABELS,
    EvalInputs,
    Upstream,
    UpstreamReduced,
    cases,
    cases_table,
    greedy_rows,
    map_rows,
    risk_rows,
    run_all,
)
from stages.evaluate.config import EvaluateConfig
from stages.evaluate.figures import warm_up
from stages.evaluate.realisations import Study, report_section, run_realisations, statistics_rows, study_table
from stages.evaluate.report import expectation_checks, figures, html_report, markdown_report, why_findings
from stages.evaluate.risk_check import check_columns, direction
from stages.graph.load import LoadedGraph, load_graph
from stages.navigation.truth import MISSING, load_truth
from stages.optimize import OptimizeConfig, read_reduced, solve_settings
from stages.optimize.artifacts import FULL_INDEX, KEPT
from stages.risk import read_path_inputs
from stages.select_landmarks import LandmarkInputs
from stages.select_landmarks.artifacts import FOCUSED
from stages.select_measurements.artifacts import SELECTION

ENTITY = "/evaluate"
HEADLINE = (
    art.CASE,
    art.FOCUSED_ENTROPY,
    art.FOCUSED_ENTROPY_OBSERVED,
    art.UNOBSERVED_FOCUSED,
    art.FOCUSED_ENTROPY_PRIOR,
    art.FOCUSED_ERROR_M,
    art.MAX_COLLISION_PROBABILITY,
    art.COLLISION_RATE,
    art.COLLISION_CI_LOW,
    art.COLLISION_CI_HIGH,
)
"""The columns of the headline case in the summary (what ``focusmap run`` prints last)."""
PER_CASE = (
    art.FOCUSED_ENTROPY,
    art.FOCUSED_ENTROPY_OBSERVED,
    art.UNOBSERVED_FOCUSED,
    art.FOCUSED_ENTROPY_PRIOR,
    art.FOCUSED_ERROR_M,
    art.ERROR_ALL_M,
    art.MAX_COLLISION_PROBABILITY,
    art.PREDICTED_COLLISION_HIGH,
    art.COLLISION_RATE,
    art.RISK_DISAGREES,
)
"""The columns of every case in the summary's ``table``."""


LARGE_RUN_KEYFRAMES = 4000
"""Above this many keyframes evaluate has glibc map every block of 1 MB or more on its own
(:func:`pipeline.memory.map_large_blocks`): on an hour's recording the peak fell from 1,157 to 1,050-1,064 MiB. Each
such block then costs page faults when it is made: on the sample (573 keyframes) 1.5 s more system time in a 25 s
stage, side by side, for no memory that matters there."""


@blas_single
def run(ctx: StageContext, cfg: EvaluateConfig) -> dict[str, Any]:
    """Run every case, write ``cases.parquet``, the report with its figures, and ``evaluate.rrd``."""
    t0 = time.perf_counter()
    # a worker process (evaluate.workers=2) navigates each case while this one solves the next, then draws two
    # figures; it starts now and imports what it runs while this one loads the inputs
    pool = WorkerPool(1) if cfg.workers > 1 else None
    try:
        if pool is not None:
            pool.submit(warm_up, cfg.plots)
        return _load_and_run(ctx, cfg, pool, t0)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)


def _load_and_run(ctx: StageContext, cfg: EvaluateConfig, pool: WorkerPool | None, t0: float) -> dict[str, Any]:
    # α, K, the strategies and the risk model are what the selection stages used, read from their artifacts
    focused = FOCUSED.read(ctx.input("select_landmarks"))
    selection = SELECTION.read(ctx.input("select_measurements"))
    sl_cfg, sm_cfg = focused.settings, selection.settings
    if cfg.robot_radius_m is not None:  # one robot model: evaluate's radius is the radius of the focus too
        sl_cfg = sl_cfg.model_copy(update={"robot_radius_m": cfg.robot_radius_m})
    loaded = load_graph(ctx.input("graph"))
    if len(loaded.pose_keys) > LARGE_RUN_KEYFRAMES:
        map_large_blocks()
    read = read_path_inputs(ctx)  # once, for the landmark inputs and the navigation's occupancy grid
    landmarks = LandmarkInputs.from_pieces(
        loaded, read.scans, read.T_base_laser, read.detections, sl_cfg, read.laser_note
    )
    scans, T_base_laser = read.scans, read.T_base_laser
    inputs = EvalInputs(
        loaded=loaded,
        landmarks=landmarks,
        truth=load_truth(ctx, loaded, cfg.truth_file),
        heights=loaded.landmark_heights,
        sl_cfg=sl_cfg,
        sm_cfg=sm_cfg,
        cfg=cfg,
        scans=scans,
        T_base_laser=T_base_laser,
        upstream=Upstream(focused, selection, _optimized(ctx, loaded, focused.tag_ids)),
    )
    todo = cases(cfg)
    detections = read.detections
    del read, scans  # the scans' table (54 MB on an hour's recording) goes with inputs.scans (see run_all)
    return _run(ctx, cfg, inputs, todo, detections, pool, t0)


def _run(
    ctx: StageContext,
    cfg: EvaluateConfig,
    inputs: EvalInputs,
    todo: list[Any],
    detections: Any,
    pool: WorkerPool | None,
    t0: float,
) -> dict[str, Any]:
    landmarks = inputs.landmarks
    results = run_all(inputs, todo, ctx.progress, pool)
    release_freed_memory()  # the last case's solves, before the tables, figures and recording are made on top
    for r in results:  # the entropy split and the risk model against the simulation, from what each case measured
        r.row.update(check_columns(r.row, r.risk.p_collision, len(inputs.focus)))
    out = ctx.output
    art.CASES.write(out, cases_table(results))
    art.MAPS.write(out, map_rows(results))
    art.PATH_RISK.write(out, risk_rows(inputs, results))
    art.GREEDY.write(out, greedy_rows(results))
    stage_notes = _notes(inputs)
    notes: list[str] = [f"- {n}" for n in stage_notes]
    if not landmarks.geometry.has_laser:
        notes.append(
            "- the run has no laser scans: collision probabilities are not available and the focused set is picked "
            "by mutual information instead of Alg. 2"
        )
    notes += [f"- {line}" for line in inputs.skipped]
    study = _realisations(inputs, todo, inputs.cfg, detections)  # inputs.cfg: no trials when there are no walls
    art.REALISATIONS.write(out, study_table(study))
    images = figures(inputs, results, out.path, ctx.n_sigma, pool) if cfg.plots else []
    graph_summary = ctx.input("graph").summary
    health = graph_summary.get("health") or {}
    map_warnings = [str(w) for w in health.get("warnings") or []]
    overconfident = overconfidence_warnings(inputs, results, tag_variance_factor(graph_summary))
    md = markdown_report(inputs, results, images, notes, map_warnings, overconfident)
    md += report_section(study, cfg, TABLE_I_LABELS)
    out.write_text(art.REPORT_MD.file, md)
    out.write_text(art.REPORT_HTML.file, html_report(md, out.path))
    log_recording(ctx.rec, inputs, results, ctx.n_sigma)
    by_case = {r.case.name: r.row for r in results}
    head = by_case.get("focus_info", results[0].row)
    return {
        "cases": [r.case.name for r in results],
        "alpha": inputs.alpha,
        "K": inputs.K,
        "focused_tag_ids": inputs.focus,
        "reference": results[0].row[art.ERROR_REFERENCE],
        "walls": inputs.navigation.obstacles.kind if inputs.navigation is not None else None,
        "trials": inputs.cfg.trials,
        "navigation_skipped": skipped.reason if (skipped := inputs.navigation_skipped) is not None else None,
        "headline": {str(k): computed(head[k]) for k in HEADLINE},
        "table": {name: {str(k): computed(row[k]) for k in PER_CASE} for name, row in by_case.items()},
        "expectation": expectation_checks(results),
        "regime": cfg.regime,
        "why": computed(why_findings(inputs, results)),
        "report": str(ctx.run.stage_dir("evaluate") / art.REPORT_HTML.file),
        "map_health_warnings": len(map_warnings),
        "from_upstream": {r.case.name: r.reused for r in results if r.reused},
        "realisations": _realisations_summary(study),
        "timing_s": {"total": round(time.perf_counter() - t0, 3)},
        **({"notes": stage_notes} if stage_notes else {}),
        **({"warnings": warnings} if (warnings := [*inputs.skipped, *overconfident, *risk_warnings(results)]) else {}),
    }


def _notes(inputs: EvalInputs) -> list[str]:
    """The stage's notes: what the ground truth lacks and, when no case was navigated for want of walls, why."""
    note = inputs.navigation_skipped.note if inputs.navigation_skipped is not None else ""
    truth_notes = inputs.truth.missing_notes() if inputs.truth is not None else []
    # the truth's own line on missing walls says the laser grid stands in: not so when there is no laser either
    out = [n for n in truth_notes if not (note and n == f"ground truth: {MISSING['walls']}")]
    return [*out, note] if note else out


def computed(value: Any) -> Any:
    """``value`` with every float that was not computed (NaN) as None, through dicts and lists: the summary's JSON
    says null, not NaN."""
    if isinstance(value, dict):
        return {k: computed(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [computed(v) for v in value]
    return None if isinstance(value, float) and not math.isfinite(value) else value


def tag_variance_factor(graph_summary: Mapping[str, Any]) -> float | None:
    """The full graph's whitened χ² per degree of freedom of its tag measurements (its health check's): how many
    times too small their stated variance is (about 1 when it is right; None when not known)."""
    health = graph_summary.get("health") or {}
    tag = ((health.get("checks") or {}).get("chi2") or {}).get("by_kind", {}).get("tag") or {}
    value = tag.get("chi2_per_dof")
    return float(value) if isinstance(value, int | float) and math.isfinite(value) and value > 0 else None


def overconfidence_warnings(inputs: EvalInputs, results: list[Any], tag_variance: float | None = None) -> list[str]:
    """One line when the headline case's reduced map is further off than its own covariance allows
    (:func:`stages.evaluate.analysis.overconfidence`): its focused error would otherwise read as a fact, with nothing
    to say the map believes itself far better than it is.

    The line names the likely cause. ``tag_variance`` (:func:`tag_variance_factor`) above 1 says the tag measurements'
    stated variance is that many times too small; the reduced map's covariance scales with it, so when the worst NEES
    divided by it passes the test, the stated noise explains the failure (the full map averages thousands of such
    measurements, K of them do not). Otherwise the budget cannot hold the trajectory (a camera-only run leaves the
    keyframes between its kept measurements to the weak zero-motion prior), and the line gives the fewest
    measurements of a case evaluated here whose map is within its covariance (no extra solve)."""
    by_case = {r.case.name: r for r in results}
    head = by_case.get("focus_info")
    check = head.overconfidence if head is not None else None
    if head is None or check is None or not check.fails:
        return []
    reference = head.row[art.ERROR_REFERENCE]
    against = "the ground truth" if reference == "ground_truth" else "the full map (case optimal)"
    line = (
        f"the reduced map ({head.row[art.LABEL]}, the headline's: {head.row[art.MEASUREMENTS]} measurements, focused "
        f"error {100 * float(head.row[art.FOCUSED_ERROR_M]):.1f} cm) is far worse than its own covariance says: "
        f"landmark {check.tag_id} lies {100 * check.error_m:.1f} cm from {against}, {check.sigmas:.1f} sigma of its "
        f"stated {100 * check.sigma_m:.2g} cm along that error (NEES {check.nees:.3g} above {check.limit:.3g}, the "
        f"bound a right covariance passes at {100 * (1 - OVERCONFIDENCE_FALSE_ALARM):g} % over its {check.count} "
        "focused landmarks)"
    )
    optimal = by_case.get("optimal")
    full_check = optimal.overconfidence if optimal is not None else None
    if full_check is not None and full_check.fails:  # against the truth: the full map fails too
        return [
            f"{line}; the full map fails the same test against the ground truth, so the measurements' stated noise "
            "is too small or biased (see the graph stage's health checks), not the budget"
        ]
    if tag_variance is not None and tag_variance > 1 and check.nees / tag_variance <= check.limit:
        return [
            f"{line}; likely cause: the tag measurements' stated noise, {math.sqrt(tag_variance):.3g}x too small in "
            f"sigma (the full graph's tag chi2 per dof {tag_variance:.3g}, expected about 1): the full map averages "
            f"all of them, its K = {inputs.K} do not, and its covariance scaled by that factor holds the worst "
            f"landmark (NEES {check.nees / tag_variance:.3g}); fix the measurement model (camera calibration, "
            "extrinsics, tag size) or state the noise (graph.tag_covariance_scale) rather than raise the budget"
        ]
    odometry = any(r.kind in ("odometry", "loop") for r in inputs.loaded.rows)
    cause = (
        f"the budget K = {inputs.K} cannot hold the trajectory: between the kept measurements the map rests on the "
        "odometry, which drifts more than its stated noise allows"
        if odometry
        else f"a camera-only run (no odometry): between its K = {inputs.K} kept measurements the keyframes are held "
        "only by the weak zero-motion prior, so that budget cannot hold the trajectory"
    )
    n = int(head.row[art.MEASUREMENTS])
    holding = sorted(
        (int(r.row[art.MEASUREMENTS]), str(r.row[art.LABEL]))
        for r in results
        if r.overconfidence is not None and r.overconfidence.fails is False and int(r.row[art.MEASUREMENTS]) > n
    )
    if holding:
        m, label = holding[0]
        fix = (
            f"the map with {m} measurements ({label}) is within its covariance: raise select_measurements.budget "
            f"(evaluate.measurement_budget) from {inputs.K} towards {m}"
        )
    else:
        fix = (
            "no case evaluated here is within its covariance with more measurements either: raise "
            f"select_measurements.budget well above {inputs.K}, and check the tag measurements' stated noise"
        )
    return [f"{line}; likely cause: {cause}; {fix}"]


WARN_COLLISION_RATE = 0.05
"""Lowest end of the simulated collision rate's interval for which a disagreement above the model is a warning."""


def risk_warnings(results: list[Any]) -> list[str]:
    """One line when simulated navigations disagree with the risk model by orders of magnitude (``risk_disagrees``):
    the headline's collision rate is then doubtful, and a user reading only it would not know."""
    sides = [
        (r.row, direction(*(float(r.row[k]) for k in (art.PREDICTED_COLLISION_LOW, art.PREDICTED_COLLISION_HIGH,
                                                        art.COLLISION_CI_LOW, art.COLLISION_CI_HIGH))))
        for r in results
        if r.row.get(art.RISK_DISAGREES)
    ]  # fmt: skip
    # above: only where collisions are a share a user would act on (the sample's extra cases collide once in 100
    # trials against a predicted 1e-19: flagged in the report, not worth a warning on every run)
    above = [row for row, side in sides if side == "above" and row[art.COLLISION_CI_LOW] >= WARN_COLLISION_RATE]
    below = [row for row, side in sides if side == "below"]
    out = []
    if above:
        names = ", ".join(str(r[art.CASE]) for r in above)
        rate = max(float(r[art.COLLISION_RATE]) for r in above)
        predicted = max(float(r[art.PREDICTED_COLLISION_HIGH]) for r in above)
        track = max(float(r[art.RMS_TRACKING_ERROR_M]) for r in above)
        out.append(
            f"the simulated robots collide far more often than the risk model predicts in case(s) {names} (rate up "
            f"to {rate:.2f} against a predicted path probability of at most {predicted:.2g}; RMS tracking error up "
            f"to {track:.2f} m): these collision rates are doubtful (the risk model leaves out how far the robot "
            "strays from its planned path); see the report's 'Risk model against the simulation'"
        )
    if below:
        names = ", ".join(str(r[art.CASE]) for r in below)
        out.append(
            f"the simulated robots collide far less often than the risk model predicts in case(s) {names}: the "
            "model's probabilities are doubtful there; see the report's 'Risk model against the simulation'"
        )
    return out


def _realisations(inputs: EvalInputs, todo: list[Any], cfg: EvaluateConfig, detections: Any) -> Study | None:
    """``evaluate.realisations`` map realisations of every case (None when off)."""
    if cfg.realisations <= 0:
        return None
    trials = cfg.trials if cfg.realisation_trials is None else cfg.realisation_trials
    return run_realisations(inputs, todo, cfg.realisations, trials, cfg.seed, detections)


def _realisations_summary(study: Study | None) -> dict[str, Any] | None:
    """The summary's ``realisations``: what was run and per case the mean collision rate with its interval."""
    if study is None:
        return None
    return {
        "realisations": study.realisations,
        "trials": study.trials,
        "world": study.world,
        "failed": len(study.failed),
        "seconds": round(study.seconds, 3),
        "collision_rate": {
            r["case"]: {
                "mean": r["mean_rate"],
                "ci": [r["ci_low"], r["ci_high"]],
                "vs_focus_info_sign_p": r["paired"].sign_p if r["paired"] is not None else None,
                "vs_focus_info_wilcoxon_p": r["paired"].wilcoxon_p if r["paired"] is not None else None,
            }
            for r in statistics_rows(study)
        },
    }


def _optimized(ctx: StageContext, loaded: LoadedGraph, focused_tag_ids: list[int]) -> UpstreamReduced | None:
    """optimize's reduced map, when it has run and solved as evaluate does (else None: evaluate solves itself); read
    when a case matches it."""
    if not ctx.has_input("optimize"):
        return None
    inp = ctx.input("optimize")
    if inp.summary.get("solve") != solve_settings(OptimizeConfig()):
        return None
    kept = KEPT.read(inp, columns=[FULL_INDEX]).column(FULL_INDEX).to_numpy()
    return UpstreamReduced(
        sorted({int(t) for t in focused_tag_ids}),
        np.asarray(kept, dtype=np.int64),
        functools.partial(read_reduced, inp, loaded, focused_tag_ids),
    )


def log_recording(rec: rr.RecordingStream, inputs: EvalInputs, results: list[Any], n_sigma: float) -> None:
    """``evaluate.rrd``: one entity per case (its map with ellipses, its path coloured by risk, sample trials)."""
    rec.log(ENTITY, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    geo = inputs.landmarks.geometry
    if inputs.truth is not None:
        walls = [[[w[0], w[1], 0.0], [w[2], w[3], 0.0]] for w in inputs.truth.walls]
        rec.log(f"{ENTITY}/walls", rr.LineStrips3D(walls, colors=[[90, 90, 90]]), static=True)
    focus = set(inputs.focus)
    for r in results:
        base = f"{ENTITY}/cases/{r.case.name}"
        lm = r.landmark_map
        if len(lm.tag_ids):
            covs = []
            for c in lm.covariances:
                m = np.zeros((3, 3))
                m[:2, :2] = c
                covs.append(m)
            centers = np.column_stack([lm.positions, lm.heights])
            colors = [[230, 60, 40] if int(t) in focus else [40, 170, 80] for t in lm.tag_ids]
            rec.log(
                f"{base}/landmarks",
                ellipsoids(centers, covs, n_sigma, colors=colors, labels=[str(t) for t in lm.tag_ids]),
                static=True,
            )
        p = np.nan_to_num(r.risk.p_collision, nan=0.0)
        logp = np.log10(np.clip(p, 1e-40, 1.0))
        segs = [[[*geo.poses[i, :2], 0.0], [*geo.poses[i + 1, :2], 0.0]] for i in range(len(geo.poses) - 1)]
        if segs:
            rec.log(f"{base}/path", rr.LineStrips3D(segs, colors=colormap(logp[:-1], -40.0, 0.0)), static=True)
        if r.navigation is not None:
            strips = [np.column_stack([s, np.zeros(len(s))]) for s in r.navigation.sample_paths]
            rec.log(f"{base}/trials", rr.LineStrips3D(strips, colors=[[255, 150, 0]], radii=0.01), static=True)
        metrics: dict[str, Any] = {str(k): v for k, v in r.row.items() if isinstance(v, (int, float))}
        rec.log(f"{base}/metrics", rr.AnyValues(**metrics), static=True)
