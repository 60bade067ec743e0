"""Check, optimise, compute marginals, write and log: the common tail of the stage, from a recording or a file."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
import rerun as rr

from pipeline.artifacts import StageOutput
from pipeline.errors import StageError
from stages.graph.calibration import (
    CalibrationResult,
    calibrate,
    calibration_test,
    implausible,
    map_shift,
    shift_warning,
    tested,
)
from stages.graph.calibration import applies as calibration_applies
from stages.graph.config import GraphConfig
from stages.graph.consider import OdometryCalibration
from stages.graph.factors import build_graph
from stages.graph.health import graph_health, scale_check, strict_error
from stages.graph.outputs import log_recording, write_artifacts
from stages.graph.problem import GraphProblem
from stages.graph.solve import Solution, check_problem, marginal_covariances, optimise
from stages.graph.tag_motion import size_warning


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
    t1 = time.perf_counter()
    solved = _solve(problem, cfg)
    health = _health(solved, cfg)
    _calibration_checks(solved, health, cfg)
    dropped: list[int] = []
    while (
        cfg.moved_tags == "drop" and health["checks"]["moved_tags"].get("tags") and len(dropped) < cfg.max_dropped_tags
    ):
        worst = int(health["checks"]["moved_tags"]["tags"][0])
        dropped.append(worst)
        problem = _without_tag(solved.problem, worst)
        check_problem(problem)
        solved = _solve(problem, cfg)
        health = _health(solved, cfg)
        _calibration_checks(solved, health, cfg)
    if dropped:
        health["warnings"].insert(
            0,
            f"dropped the measurements of {len(dropped)} tag(s) that moved (graph.moved_tags=drop): "
            + ", ".join(str(t) for t in dropped),
        )
    if cfg.strict and not health["ok"]:
        raise StageError(strict_error("graph", health))
    problem, solution, marginals = solved.problem, solved.solution, solved.marginals
    t3 = time.perf_counter()
    summary = write_artifacts(out, problem, solution, marginals)
    if solved.applied is not None:
        solved.applied.write(out)
    if rec is not None:
        log_recording(rec, problem, solution, marginals, n_sigma, cfg.pose_ellipse_stride, solved.calibration_moves)
    summary.update(problem.info)
    summary["health"] = health
    if cfg.moved_tags == "drop":
        summary["dropped_moved_tags"] = dropped
    if solved.calibration is not None:
        summary["odometry_calibration"] = solved.calibration
    summary["timing_s"] = {
        "check_and_build": round(t1 - t0, 4),
        "optimise": round(solved.seconds[0], 4),
        "marginals": round(solved.seconds[1], 4),
        "health_and_drops": round(t3 - t1 - sum(solved.seconds), 4),
        "write": round(time.perf_counter() - t3, 4),
    }
    return summary


@dataclass
class _Solved:
    problem: GraphProblem
    graph: gtsam.NonlinearFactorGraph
    solution: Solution
    marginals: dict[int, np.ndarray]
    calibration: dict[str, Any] | None
    seconds: tuple[float, float]
    """Optimise and marginals (the calibration's joint solve counts as optimise)."""
    calibration_moves: dict[int, np.ndarray] = field(default_factory=dict)
    """Each landmark's map-frame move under the calibration test's step, by key (when ``auto`` left it off)."""
    applied: OdometryCalibration | None = None
    """The calibration applied to the odometry rows, for ``calibration.npz``."""


def _solve(problem: GraphProblem, cfg: GraphConfig) -> _Solved:
    """Optimise (with the odometry calibration when asked, or when ``auto`` finds systematic errors) and take every
    marginal. With ``noise_estimate: auto`` and the odometry's noise from the settings (its messages' covariances
    zero or absent), the settings' noise is first brought to the data's level (:func:`settings_noise_estimated`),
    and the calibration test runs on that."""
    t0 = time.perf_counter()
    if calibration_applies(problem, cfg):
        result = calibrate(problem, cfg)
        seconds = (time.perf_counter() - t0, 0.0)
        return _calibrated(result, seconds)
    graph = build_graph(problem.rows)
    solution = optimise(problem, graph, cfg.optimizer, cfg.max_iterations, cfg.relative_error_tol)
    solved, noise = problem, None
    if settings_noise_estimated(problem, cfg):
        off = cfg.model_copy(update={"odometry_calibration": False, "noise_estimate": "odometry"})
        noise = calibrate(problem, off, initial=solution.values)
        solved, graph, solution = noise.problem, noise.graph, noise.solution
    decision: dict[str, Any] | None = None
    steps: dict[int, np.ndarray] = {}
    if tested(problem, cfg):
        try:
            decision, steps = calibration_test(solved, graph, solution.values, cfg)
        except RuntimeError as err:  # GTSAM: the joint system with the calibration is singular here
            decision = {
                "setting": "auto",
                "applied": False,
                "rejected": False,
                "skipped": True,
                "reason": "not tested: the graph with the calibration cannot be solved ("
                + " ".join(str(err).split()).split(". ")[0]
                + "); see the health checks",
            }
        if decision["applied"]:
            result = calibrate(problem, cfg, initial=solution.values)
            far = implausible(result.calibration.value, cfg)
            if far is None:
                result.summary["decision"] = decision
                seconds = (time.perf_counter() - t0, 0.0)
                return _calibrated(result, seconds)
            # the test's step was a wheel's, but the calibration went where no wheel is: keep the uncalibrated map
            decision.update(applied=False, rejected=True, reason=_far_calibration(far, "was left off"))
    t1 = time.perf_counter()
    if noise is not None:
        marginals = noise.marginals
    else:
        marginals = marginal_covariances(solved, graph, solution.values, list(solved.var_types))
    moves: dict[int, np.ndarray] = {}
    if decision is not None and steps:
        decision["map_shift"], moves = map_shift(solved, solution.values, marginals, steps)
        if _scale_rests_on_wheels(solved, solution.values, marginals, decision, cfg):
            try:
                result = calibrate(problem, cfg, initial=solution.values)
            except RuntimeError as err:  # GTSAM: the joint system with the calibration is singular here
                decision["not_applied"] = (
                    "the graph with the calibration cannot be solved ("
                    + " ".join(str(err).split()).split(". ")[0]
                    + ")"
                )
            else:
                far = implausible(result.calibration.value, cfg)
                if far is None:
                    decision.update(applied=True, reason=_shift_reason(decision))
                    result.summary["decision"] = decision
                    return _calibrated(result, (time.perf_counter() - t0, 0.0))
                decision.update(rejected=True, reason=_far_calibration(far, "was left off"))
    calibration: dict[str, Any] | None = None if noise is None else dict(noise.summary)
    if decision is not None:
        calibration = {**(calibration or {}), "estimated": False, "decision": decision}
    seconds = (t1 - t0, time.perf_counter() - t1)
    return _Solved(solved, graph, solution, marginals, calibration, seconds, moves)


def _scale_rests_on_wheels(
    problem: GraphProblem,
    values: gtsam.Values,
    marginals: dict[int, np.ndarray],
    decision: dict[str, Any],
    cfg: GraphConfig,
) -> bool:
    """``auto``: the yaw test left the calibration off, yet its step would move the landmarks beyond their own σ
    (:func:`stages.graph.calibration.shift_warning`) while neither the tags' motion against the odometry's
    (``tag_size``) nor the shared tag scale (``tag_scale``) names a wrong tag size or a collapsed map. Fixing the
    wheels at their nominal values would then claim a map scale the data do not confirm; estimating them with their
    priors carries that freedom into the covariances instead (an independent simulator's office: 11.6 cm, NEES/dof
    5.9 left off; 5.5 cm, 1.1 calibrated; docs/graph.md)."""
    if shift_warning(decision, cfg) is None:
        return False
    size = problem.info.get("tag_size_m")
    if scale_check(problem, values, marginals, size)[1] is not None:
        return False  # the shared tag scale names a wrong size (or a collapsed map): not the wheels' to fix
    return size_warning(problem.info.get("tag_odometry_ratio") or {}, size) is None


def _shift_reason(decision: dict[str, Any]) -> str:
    shift = decision["map_shift"]
    return (
        f"the map's scale rests on the wheels: the yaw test did not call for the calibration "
        f"({decision['statistic']:.1f} <= {decision['threshold']:g}), but its step would move the landmarks by "
        f"{shift['mean_d2_per_dim'] ** 0.5:.1f} of their sigma (median {100 * shift['median_shift_m']:.1f} cm), so the "
        "wheels were calibrated with the map: their distance scale and the tag size share one degree of freedom, and "
        "the covariances now carry it (graph.odometry_calibration=false accepts the wheels as they are)"
    )


def settings_noise_estimated(problem: GraphProblem, cfg: GraphConfig) -> bool:
    """Whether ``noise_estimate: auto`` scales the odometry's noise even without the calibration: when that noise
    is the settings' guess (``odometry_noise`` = settings, the messages' covariances zero or absent), whose level
    and shape (translation against heading) only the data can tell. Measured on zero-covariance worlds without wheel
    errors: landmark RMSE 1.40 → 1.19 cm and 5.58 → 4.10 cm, NEES/2 0.29 → 1.97 and 0.26 → 1.90 (docs/graph.md)."""
    return cfg.noise_estimate == "auto" and problem.info.get("odometry_noise") == "settings"


def _calibrated(result: CalibrationResult, seconds: tuple[float, float]) -> _Solved:
    return _Solved(
        result.problem,
        result.graph,
        result.solution,
        result.marginals,
        result.summary,
        seconds,
        applied=result.calibration if result.summary.get("estimated") else None,
    )


def _health(s: _Solved, cfg: GraphConfig) -> dict[str, Any]:
    return graph_health(
        s.problem,
        s.graph,
        s.solution.values,
        s.marginals,
        s.solution.iterations,
        cfg.max_iterations,
        "graph",
        s.problem.info.get("tag_size_m"),
    )


def _calibration_checks(s: _Solved, health: dict[str, Any], cfg: GraphConfig) -> None:
    """The checks of the odometry calibration. ``odometry_calibration`` fails when the odometry disagrees with the
    tags in a way no wheel calibration explains (:func:`stages.graph.calibration.implausible`): ``auto``'s test
    step, or its calibrated result (then left off, :func:`_solve`), or a calibration set on that ended there (then
    kept). ``wheel_scale`` fails when the calibration stayed off but would have moved the map beyond its σ
    (:func:`stages.graph.calibration.shift_warning`; not when the ``tag_scale`` check has already named a wrong tag
    size, the likelier cause then)."""
    decision = (s.calibration or {}).get("decision") or {}
    if s.applied is not None and (far := implausible(s.applied.value, cfg)):
        reason = _far_calibration(far, "is kept (graph.odometry_calibration=true)")  # set on: warn, keep it
        health["checks"]["odometry_calibration"] = {"ok": False, "reason": reason}
        health["warnings"].append(reason)
        health["ok"] = False
    calibrated = s.applied is not None or bool(decision.get("applied"))
    summary = s.calibration or {}
    last = (summary.get("history") or [{}])[-1]
    if calibrated and summary.get("converged") is False and (unsettled := _unsettled(summary, last)) is not None:
        health["checks"]["calibration_converged"] = {"ok": False, "reason": unsettled}
        health["warnings"].append(unsettled)
        health["ok"] = False
    if decision.get("rejected"):
        health["checks"]["odometry_calibration"] = {"ok": False, "reason": decision["reason"]}
        health["warnings"].append(decision["reason"])
        health["ok"] = False
    shift = decision.get("map_shift")
    if shift is None:
        return
    warning = shift_warning(decision, cfg) if health["checks"]["tag_scale"]["ok"] else None
    health["checks"]["wheel_scale"] = {"ok": warning is None, "max": cfg.calibration_shift_max, **shift}
    if warning is not None:
        health["warnings"].append(warning)
        health["ok"] = False


UNSETTLED_STEP_SIGMAS = 0.5
"""A calibration whose last step moved it by more than this many of its σ was still moving (one σ is what the data
can tell; a step of half that is not noise)."""
UNSETTLED_NOISE_CHANGE = 0.25
"""A noise scale whose last round changed it by more than this (log ratio) was still moving."""


def _unsettled(summary: dict[str, Any], last: dict[str, Any]) -> str | None:
    """The warning for a calibration that stopped at its round cap while still moving (None when only the last
    fraction of its tolerance was left: then its values and noise scales are where the data put them)."""
    step, change = last.get("step_sigmas", 0.0), last.get("noise_scale_change", 0.0)
    if step <= UNSETTLED_STEP_SIGMAS and change <= UNSETTLED_NOISE_CHANGE:
        return None
    return (
        f"the odometry calibration did not settle in {summary.get('iterations')} rounds "
        f"(graph.calibration_max_iterations; its last step {step:.2f} σ, its noise scales changing by "
        f"{100 * change:.0f} %): the map rests on a calibration that was still moving, and its covariances may not "
        "cover that; raise graph.calibration_max_iterations, or set graph.odometry_calibration=false to accept the "
        "wheels as they are"
    )


def _far_calibration(far: str, what: str) -> str:
    return (
        f"the odometry calibration came out where no wheel error is ({far}), so it {what}: the tags, the camera "
        "model or the extrinsics disagree with the odometry (see the tag_size check), or the wheels are broken"
    )


def _without_tag(problem: GraphProblem, tag_id: int) -> GraphProblem:
    """The problem without the tag's measurements (and so without the tag), its notes kept."""
    rows = [r for r in problem.rows if not (r.kind == "tag" and r.tag_id == tag_id)]
    reduced = problem.restricted(rows, problem.initial)
    reduced.info = dict(problem.info)
    return reduced
