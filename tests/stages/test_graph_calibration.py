"""Self-calibrating odometry (stages/graph/calibration.py) on image-free runs with systematic wheel errors."""

from __future__ import annotations

import math

import gtsam
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
        stats.append(calibration_test(problem, graph, sol.values, cfg)[0])
    assert stats[1]["wald"] > 5 * stats[0]["wald"]
    assert stats[1]["odometry_chi2_per_redundancy"] > 5
    assert stats[1]["statistic"] < 0.5 * cfg.calibration_test_threshold
    assert not any(s["applied"] for s in stats)


def _checked(run: SyntheticRun, cfg: GraphConfig):
    """The stage's solve and its health block with the calibration's checks, as ``solve_and_write`` makes them."""
    from stages.graph.solve_all import _calibration_checks, _health
    from stages.graph.solve_all import _solve as stage_solve

    problem = build_problem(run.detections, run.odometry, run.extrinsics, cfg)
    solved = stage_solve(problem, cfg)
    health = _health(solved, cfg)
    _calibration_checks(solved, health, cfg)
    return solved, health


def test_a_wheel_distance_error_the_yaw_test_misses_is_calibrated_when_the_map_rests_on_it() -> None:
    """A wheel 3 % long with exact tags: the yaw test has nothing to find, but its joint step would move the
    landmarks by several of their σ, so the uncalibrated map's covariances would not hold its own error. ``auto``
    then calibrates the wheels with the map (one note says why): the distance scale comes out near 1.03 and the
    landmarks' NEES falls to about 1, where the uncalibrated map's is several. A larger
    ``graph.calibration_shift_max`` leaves it off and quiet; a clean run is left off with no warning. (Before:
    the calibration stayed off with a ``wheel_scale`` warning, and the map kept its error.)"""
    from stages.graph import remarks

    long_wheel = synthetic_run(seed=0, loops=2.0, wheel_errors=(0.03, 0.0, 0.0))
    cfg = GraphConfig(tag_scale_sigma=EXACT_TAG_SCALE)
    solved, health = _checked(long_wheel, cfg)
    assert solved.calibration is not None
    decision = solved.calibration["decision"]
    assert decision["applied"] and decision["statistic"] < cfg.calibration_test_threshold
    assert decision["map_shift"]["mean_d2_per_dim"] > 1.5 * cfg.calibration_shift_max
    assert "rests on the wheels" in decision["reason"]
    assert abs(solved.calibration["distance_scale"]["value"] - 1.03) < 3 * solved.calibration["distance_scale"]["sigma"]
    assert health["checks"]["wheel_scale"]["ok"] and health["ok"], health["warnings"]
    summary = {"odometry_calibration": solved.calibration, "health": health}
    assert any(k == "note" and "rests on the wheels" in t for k, t in remarks(summary))
    calibrated = _landmark_nees(long_wheel, solved.problem, solved.solution.values, solved.marginals)
    plain, values, marginals, _ = _solve(long_wheel, cfg.model_copy(update={"odometry_calibration": False}))
    uncalibrated = _landmark_nees(long_wheel, plain, values, marginals)
    assert calibrated < 2.0 < uncalibrated
    # a larger threshold keeps it off, and the check quiet; the figures stay in the summary
    quiet_solved, quiet = _checked(long_wheel, cfg.model_copy(update={"calibration_shift_max": 1e6}))
    assert not quiet_solved.calibration["decision"]["applied"]  # type: ignore[index]
    assert quiet["checks"]["wheel_scale"]["ok"] and quiet["ok"]

    clean_solved, clean = _checked(synthetic_run(seed=0, loops=2.0), cfg)
    assert not clean_solved.calibration["decision"]["applied"]  # type: ignore[index]
    assert clean["checks"]["wheel_scale"]["ok"] and clean["checks"]["wheel_scale"]["mean_d2_per_dim"] < 1.0
    assert clean["ok"], clean["warnings"]


def _odometry_truth_mean_square(run: SyntheticRun, problem) -> np.ndarray:
    """Per dimension (x, y, θ), the mean square of each odometry factor's error at the true poses over its stated σ
    (1 where the stated noise is right)."""
    stamp = dict(zip(problem.pose_keys, problem.pose_stamps_ns, strict=True))
    out = []
    for row in problem.rows:
        if row.kind != "odometry":
            continue
        a, b = (run.true_pose_at(np.array([stamp[k]]))[0] for k in row.keys)
        truth = gtsam.Pose2(*a).between(gtsam.Pose2(*b))
        out.append(gtsam.Pose2(*row.measurement).localCoordinates(truth) / np.sqrt(np.diag(row.covariance)))
    return np.mean(np.square(out), axis=0)


def test_settings_noise_is_brought_to_the_data_per_dimension_without_the_calibration() -> None:
    """Zero message covariances and exact wheels: the settings' noise (translation isotropic, 5 % of the distance)
    is far too large, and larger sideways than forwards for a wheeled robot. ``noise_estimate: auto`` scales it to
    the data although the calibration stays off, one level per dimension: the heading's noise then matches its
    errors at the truth, and the landmarks are no longer several times pessimistic."""
    from stages.graph import remarks
    from stages.graph.solve_all import _solve as stage_solve

    run = synthetic_run(seed=0, loops=2.0, odom_cov_scale=0.0)
    cfg = GraphConfig(tag_scale_sigma=EXACT_TAG_SCALE)
    problem = build_problem(run.detections, run.odometry, run.extrinsics, cfg)
    assert problem.info["odometry_noise"] == "settings"
    scaled = stage_solve(problem, cfg)
    cal = scaled.calibration
    assert cal is not None and cal["estimated"] is False and not cal["decision"]["applied"]
    lam_x, lam_y, lam_th = cal["odometry_covariance_scale_by_dimension"]
    assert lam_y < 0.5 * lam_x  # the settings overstate the sideways noise more than the forward one
    assert max(lam_x, lam_th) < 0.5  # and both are overstated
    assert scaled.applied is None  # no calibration to carry downstream
    plain = stage_solve(problem, cfg.model_copy(update={"noise_estimate": "off"}))
    nees_scaled = _landmark_nees(run, scaled.problem, scaled.solution.values, scaled.marginals)
    nees_plain = _landmark_nees(run, plain.problem, plain.solution.values, plain.marginals)
    assert nees_plain < 0.35 and 0.4 < nees_scaled < 2.0 and nees_scaled > 1.8 * nees_plain
    heading_scaled = _odometry_truth_mean_square(run, scaled.problem)[2]
    heading_plain = _odometry_truth_mean_square(run, plain.problem)[2]
    assert heading_plain < 0.4 and 0.5 < heading_scaled < 2.0
    notes = remarks({**problem.info, "odometry_calibration": cal})
    assert any(kind == "note" and "graph.noise_estimate=auto" in text for kind, text in notes)
