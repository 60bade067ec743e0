"""Self-calibrating odometry (stages/graph/calibration.py) on image-free runs with systematic wheel errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.graph.build import build_problem
from stages.graph.calibration import PARAMETERS, applies, calibrate, corrected_factor, corrected_increment
from stages.graph.config import GraphConfig
from stages.graph.factors import build_graph
from stages.graph.solve import marginal_covariances, optimise
from tests.fixtures.synthetic_runs import SyntheticRun, synthetic_run

WHEEL = (0.03, -0.02, 0.02)
"""Distance 3 % long, turns 2 % short, 0.02 rad per metre."""
TRUE = np.array([1 + WHEEL[0], 1 + WHEEL[1], WHEEL[2]])


def _landmark_nees(run: SyntheticRun, problem, values, marginals) -> float:
    x0, y0, yaw0 = run.true_pose_at(np.asarray(problem.pose_stamps_ns[:1]))[0]
    R0 = np.array([[math.cos(yaw0), -math.sin(yaw0)], [math.sin(yaw0), math.cos(yaw0)]])
    out = []
    for tag, key in problem.landmark_keys.items():
        e = np.asarray(values.atPoint2(key)) - (run.tags_world[tag][:2, 3] - [x0, y0]) @ R0
        out.append(float(e @ np.linalg.solve(marginals[key], e)) / 2)
    return float(np.mean(out))


def test_correction_inverts_the_wheel_errors() -> None:
    """An arc driven with known wheel errors is reported wrong; the correction at the true calibration gives it back."""
    k_d, k_w, b = TRUE
    # an arc of 0.4 m turning 0.3 rad: chord at half the angle
    s_true, th_true = 0.4, 0.3
    chord = 2 * s_true / th_true * math.sin(th_true / 2)
    true = np.array([chord * math.cos(th_true / 2), chord * math.sin(th_true / 2), th_true])
    th_rep = k_w * th_true + b * s_true
    chord_rep = k_d * 2 * s_true / th_rep * math.sin(th_rep / 2)
    reported = np.array([chord_rep * math.cos(th_rep / 2), chord_rep * math.sin(th_rep / 2), th_rep])
    fixed = corrected_increment(reported, TRUE, "planar")
    assert np.abs(fixed - true).max() < 2e-4  # the arc's length vs its chord's x: second order
    assert np.abs(reported - true).max() > 5e-3
    assert np.allclose(corrected_increment(reported, np.array([1.0, 1.0, 0.0]), "planar"), reported)
    # the covariance goes with the increment: a 3 % shorter increment has 3 % smaller translation sigmas
    _, cov = corrected_factor(reported, np.diag([1e-4, 1e-4, 1e-4]), np.array([1.03, 1.0, 0.0]), "planar")
    assert np.sqrt(cov[0, 0]) == pytest.approx(0.01 / 1.03, rel=1e-3)


@pytest.fixture(scope="module")
def wheel_run() -> SyntheticRun:
    return synthetic_run(seed=0, loops=2.0, wheel_errors=WHEEL)


def _solve(run: SyntheticRun, cfg: GraphConfig):
    problem = build_problem(run.detections, run.odometry, run.extrinsics, cfg)
    if applies(problem, cfg):
        r = calibrate(problem, cfg)
        return r.problem, r.solution.values, r.marginals, r.summary
    graph = build_graph(problem.rows)
    sol = optimise(problem, graph)
    return problem, sol.values, marginal_covariances(problem, graph, sol.values, list(problem.var_types)), {}


# the synthetic tags are exactly the size the graph assumes: no tag scale, so the map's scale is the odometry's
EXACT_TAG_SCALE = 0.0


def test_calibration_recovers_wheel_errors_and_honest_landmarks(wheel_run: SyntheticRun) -> None:
    before = _solve(
        wheel_run, GraphConfig(odometry_calibration=False, noise_estimate="off", tag_scale_sigma=EXACT_TAG_SCALE)
    )
    assert _landmark_nees(wheel_run, *before[:3]) > 2.5  # overconfident without the calibration
    problem, values, marginals, summary = _solve(
        wheel_run, GraphConfig(odometry_calibration=True, noise_estimate="odometry", tag_scale_sigma=EXACT_TAG_SCALE)
    )
    for name, truth in zip(PARAMETERS, TRUE, strict=True):
        est = summary[name]
        assert abs(est["value"] - truth) < 3 * est["sigma"], (name, est, truth)
        assert est["sigma"] < 0.3 * est["prior_sigma"]  # the data, not the prior, decide
    assert 0.5 <= _landmark_nees(wheel_run, problem, values, marginals) <= 2.0
    assert summary["converged"]
    assert 0.5 < summary["odometry_covariance_scale"] < 2.0  # the messages' covariances are right here


def test_noise_estimate_repairs_zero_covariances() -> None:
    """Messages with all-zero covariances fall back to the settings' noise (5 % of the distance: pessimistic);
    the odometry noise estimate scales it to the data."""
    run = synthetic_run(seed=0, loops=2.0, wheel_errors=WHEEL, odom_cov_scale=0.0)
    problem, values, marginals, summary = _solve(
        run, GraphConfig(odometry_calibration=True, noise_estimate="odometry", tag_scale_sigma=EXACT_TAG_SCALE)
    )
    assert problem.info["odometry_noise"] == "settings"
    assert summary["odometry_covariance_scale"] < 0.5
    assert summary["odometry_chi2_per_redundancy"] == pytest.approx(1.0, abs=0.1)
    for name, truth in zip(PARAMETERS, TRUE, strict=True):
        assert abs(summary[name]["value"] - truth) < 3 * summary[name]["sigma"], name
    assert 0.5 <= _landmark_nees(run, problem, values, marginals) <= 2.0


def test_auto_turns_the_calibration_on_for_wheel_errors_only(wheel_run: SyntheticRun) -> None:
    """The default (``odometry_calibration: auto``) solves without, tests the yaw calibration's step against its
    covariance, and re-solves with the calibration and the noise estimate only when the data reject the
    uncalibrated odometry; a clean run keeps the uncalibrated solution bit for bit."""
    from stages.graph import remarks
    from stages.graph.solve_all import _solve as stage_solve

    cfg = GraphConfig(tag_scale_sigma=EXACT_TAG_SCALE)
    assert cfg.odometry_calibration == "auto" and cfg.noise_estimate == "auto"
    problem = build_problem(wheel_run.detections, wheel_run.odometry, wheel_run.extrinsics, cfg)
    on = stage_solve(problem, cfg)
    assert on.calibration is not None
    decision = on.calibration["decision"]
    assert decision["applied"] and decision["statistic"] > cfg.calibration_test_threshold
    assert "systematic errors" in decision["reason"]
    assert on.calibration["noise_estimate"] == "odometry"  # auto: the noise estimate runs with the calibration
    for name, truth in zip(PARAMETERS, TRUE, strict=True):
        assert abs(on.calibration[name]["value"] - truth) < 3 * on.calibration[name]["sigma"], name
    assert 0.5 <= _landmark_nees(wheel_run, on.problem, on.solution.values, on.marginals) <= 2.0
    notes = remarks({"odometry_calibration": on.calibration})
    assert any(kind == "note" and "graph.odometry_calibration=auto" in text for kind, text in notes)

    clean = synthetic_run(seed=0, loops=2.0)
    problem = build_problem(clean.detections, clean.odometry, clean.extrinsics, cfg)
    off = stage_solve(problem, cfg)
    assert off.calibration is not None and off.calibration["estimated"] is False
    assert not off.calibration["decision"]["applied"]
    assert off.calibration["decision"]["statistic"] < cfg.calibration_test_threshold
    assert not remarks({"odometry_calibration": off.calibration})
    plain = stage_solve(problem, cfg.model_copy(update={"odometry_calibration": False}))
    assert plain.calibration is None
    for key in problem.var_types:
        assert np.array_equal(off.marginals[key], plain.marginals[key])
    assert off.solution.final_error == plain.solution.final_error


def test_auto_skips_its_test_on_recordings_too_long_for_it(wheel_run: SyntheticRun) -> None:
    """Above graph.calibration_test_max_poses keyframes the test (quadratic in them) is not run: the calibration stays
    off, the solution is the uncalibrated one bit for bit, and a note names the setting that turns it on."""
    from stages.graph import remarks
    from stages.graph.solve_all import _solve as stage_solve

    cfg = GraphConfig(tag_scale_sigma=EXACT_TAG_SCALE)
    problem = build_problem(wheel_run.detections, wheel_run.odometry, wheel_run.extrinsics, cfg)
    short = cfg.model_copy(update={"calibration_test_max_poses": len(problem.pose_keys) - 1})
    skipped = stage_solve(problem, short)
    assert skipped.calibration is not None and skipped.calibration["estimated"] is False
    decision = skipped.calibration["decision"]
    assert decision["skipped"] and not decision["applied"] and "statistic" not in decision
    plain = stage_solve(problem, cfg.model_copy(update={"odometry_calibration": False}))
    assert skipped.solution.final_error == plain.solution.final_error
    notes = remarks({"odometry_calibration": skipped.calibration})
    assert any(k == "note" and "graph.odometry_calibration=true" in t for k, t in notes)


def test_auto_is_not_fooled_by_overconfident_covariances() -> None:
    """Clean odometry whose covariances are 10x too small: the plain Wald statistic of the yaw calibration is near
    the threshold (every residual looks 3x too large), but divided by the odometry's own variance factor it is
    the clean run's again, so the calibration stays off."""
    from stages.graph.calibration import calibration_test

    cfg = GraphConfig(tag_scale_sigma=EXACT_TAG_SCALE)
    stats = []
    for scale in (1.0, 0.1):
        run = synthetic_run(seed=0, loops=2.0, odom_cov_scale=scale)
        problem = build_problem(run.detections, run.odometry, run.extrinsics, cfg)
        graph = build_graph(problem.rows)
        sol = optimise(problem, graph)
        stats.append(calibration_test(problem, graph, sol.values, cfg))
    assert stats[1]["wald"] > 5 * stats[0]["wald"]
    assert stats[1]["odometry_chi2_per_redundancy"] > 5
    assert stats[1]["statistic"] < 0.5 * cfg.calibration_test_threshold
    assert not any(s["applied"] for s in stats)
