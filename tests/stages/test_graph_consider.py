"""The odometry calibration's uncertainty in graphs built from its corrected rows (stages/graph/consider.py).

A run whose wheels are off is calibrated by the graph stage, which writes ``calibration.npz``. Covariances computed
again from the corrected rows (the reduced graphs of optimize and evaluate, the risk model's cross covariances) must
hold the calibration's uncertainty as the graph stage's own marginals do: the full graph re-solved reproduces them,
and a reduced graph's added term matches the scatter of its solutions re-solved under calibrations drawn from it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pipeline.artifacts import StageInput
from pipeline.config import load_settings
from pipeline.registry import Registry
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages import graph as graph_stage
from stages.columns import STAMP_NS, TAG_ID
from stages.detect.artifacts import DETECTIONS
from stages.graph.calibration import planar_corrected_factors
from stages.graph.consider import OdometryCalibration
from stages.graph.factors import build_graph
from stages.graph.load import LoadedGraph, load_graph
from stages.graph.solve import marginal_covariances, optimise
from stages.optimize import solve_reduced
from stages.risk import LandmarkMap, RiskParams, map_covariances, path_geometry
from tests.fixtures.room import synthetic_scans
from tests.fixtures.synthetic_runs import synthetic_run
from tests.fixtures.upstream import seed_upstream, stand_in

WHEEL = (0.03, -0.02, 0.02)
"""Distance 3 % long, turns 2 % short, 0.02 rad per metre (as test_graph_calibration)."""


def _calibrated_run(tmp: Path, overrides: list[str]) -> tuple[RunFolder, LoadedGraph]:
    sim = synthetic_run(seed=0, loops=2.0, wheel_errors=WHEEL)
    reg = Registry([stand_in("ingest"), stand_in("detect", "ingest"), graph_stage.STAGE])
    source = tmp / "run.bag"
    source.write_bytes(b"")
    run = RunFolder.create(tmp / "run", source)
    seed_upstream(run, sim, synthetic_scans(sim))
    run_stage(run, reg, "graph", load_settings(reg.models(), None, ["graph.odometry_calibration=true", *overrides]))
    return run, load_graph(StageInput("graph", run.stage_dir("graph")))


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunFolder, LoadedGraph]:
    """A synthetic run with wheel errors through the graph stage with the calibration on, loaded back."""
    return _calibrated_run(tmp_path_factory.mktemp("consider"), [])


def _xy_sigmas(marginals: dict[int, np.ndarray], keys: list[int]) -> np.ndarray:
    return np.array([np.sqrt(np.diag(np.asarray(marginals[k])[:2, :2])) for k in keys])


def test_the_stage_writes_the_calibration_and_a_run_without_one_has_none(calibrated, tmp_path: Path) -> None:
    run, loaded = calibrated
    cal = loaded.calibration
    assert cal is not None
    summary = StageInput("graph", run.stage_dir("graph")).summary["odometry_calibration"]
    assert cal.value == pytest.approx(
        [summary[k]["value"] for k in ("distance_scale", "yaw_rate_scale", "yaw_bias_rad_per_m")]
    )
    assert np.sqrt(np.diag(cal.covariance)) == pytest.approx(
        [summary[k]["sigma"] for k in ("distance_scale", "yaw_rate_scale", "yaw_bias_rad_per_m")], rel=1e-6
    )
    odometry = [i for i, r in enumerate(loaded.rows) if r.kind == "odometry"]
    assert cal.factor_index.tolist() == odometry
    assert cal.jacobian.shape == (len(odometry), 3, 3)
    # a longer driven increment depends more on the distance scale: the corrected x is the driven x / k_d, so the
    # factor's error (prediction less measurement) grows by x / k_d per unit of k_d (to the few per cent that the
    # increment's turn and the whitening's own change with c add)
    x = np.array([loaded.rows[i].measurement[0] for i in odometry])
    moving = x > 0.01
    rel = cal.jacobian[moving, 0, 0] / (x[moving] / cal.value[0]) - 1
    assert np.median(np.abs(rel)) < 0.02 and np.max(np.abs(rel)) < 0.1


def test_the_full_graph_rebuilt_from_its_rows_has_the_stage_marginals_again(calibrated) -> None:
    """``H⁻¹ + S Σ_c Sᵀ`` of the corrected graph is the joint system's marginal (the Schur complement of ``c``)."""
    _, loaded = calibrated
    keys = sorted(loaded.landmark_keys.values())
    bare = marginal_covariances(loaded, loaded.graph, loaded.values, keys)
    term = loaded.consider_term()
    assert term is not None
    with_term = term.add_to_marginals(bare)
    stage = _xy_sigmas(loaded.marginals, keys)
    assert _xy_sigmas(with_term, keys) == pytest.approx(stage, rel=1e-5)
    assert np.max(stage / _xy_sigmas(bare, keys)) > 1.05  # the term matters here: without it, σ 5 % or more short
    # evaluate's case 1 (every landmark, every measurement) and optimize solve the same rows: the same marginals
    tags = [i for i, r in enumerate(loaded.rows) if r.kind == "tag"]
    red = solve_reduced(loaded, list(loaded.landmark_keys), tags, initialise_from="full_solution")
    assert red.consider is not None
    assert _xy_sigmas(red.marginals, keys) == pytest.approx(stage, rel=1e-4)
    uncalibrated = solve_reduced(
        dataclasses.replace(loaded, calibration=None), list(loaded.landmark_keys), tags, initialise_from="full_solution"
    )
    assert uncalibrated.consider is None
    assert _xy_sigmas(uncalibrated.marginals, keys) == pytest.approx(_xy_sigmas(bare, keys), rel=1e-4)


def test_the_3d_model_gets_the_stage_marginals_again_too(tmp_path: Path) -> None:
    """Pose3 odometry rows (6-dimensional errors, the calibration acting on their planar part)."""
    _, loaded = _calibrated_run(tmp_path, ["graph.model=3d"])
    assert loaded.model == "3d" and loaded.calibration is not None
    assert loaded.calibration.jacobian.shape[1:] == (6, 3)
    keys = sorted(loaded.landmark_keys.values())
    bare = marginal_covariances(loaded, loaded.graph, loaded.values, keys)
    term = loaded.consider_term()
    assert term is not None
    with_term = term.add_to_marginals(bare)
    for k in keys:  # (the term is under 1 % of σ here, but without it these fail: rel 1e-4)
        assert with_term[k] == pytest.approx(loaded.marginals[k], rel=1e-4, abs=1e-12)


def test_the_risk_models_joint_covariance_agrees_with_the_marginals(calibrated) -> None:
    """map_covariances' joint (from sparse solves on the corrected graph) has the stage's marginals on its diagonal
    once the term is added; without it, the calibrated map's cross covariances and marginals disagree."""
    run, loaded = calibrated
    detections = DETECTIONS.read(StageInput("detect", run.stage_dir("detect")), columns=[STAMP_NS, TAG_ID])
    geometry = path_geometry(loaded, None, None, detections, RiskParams())
    lm = LandmarkMap.from_graph(loaded)
    for term, agrees in ((loaded.consider_term(), True), (None, False)):
        _, joint = map_covariances(loaded, loaded.graph, loaded.values, loaded.marginals, lm, geometry, term)
        diag = np.array([np.sqrt(np.diag(joint[2 * r : 2 * r + 2, 2 * r : 2 * r + 2])) for r in range(len(lm.tag_ids))])
        stage = np.array([np.sqrt(np.diag(c[:2, :2])) for c in lm.covariances])
        assert np.allclose(diag, stage, rtol=1e-5) is agrees


def test_a_reduced_graphs_term_matches_monte_carlo_over_the_calibration(calibrated) -> None:
    """Half the landmarks, all their measurements: re-solve with the odometry corrected at calibrations drawn from
    N(ĉ, Σ_c) (the raw increments recovered from the corrected rows); the solutions' scatter is ``S Σ_c Sᵀ``."""
    _, loaded = calibrated
    cal = loaded.calibration
    assert isinstance(cal, OdometryCalibration)
    focused = sorted(loaded.landmark_keys)[::2]
    tags = [i for i, r in enumerate(loaded.rows) if r.kind == "tag"]
    red = solve_reduced(loaded, focused, tags, initialise_from="full_solution")
    assert red.consider is not None
    odometry = [i for i, r in enumerate(red.problem.rows) if r.kind == "odometry"]
    Z = np.array([red.problem.rows[i].measurement[:3] for i in odometry])
    C = np.array([red.problem.rows[i].covariance for i in odometry])
    M = Z.copy()  # raw increments: the fixed point of the correction (it turns and scales them a little)
    for _ in range(50):
        M = M + (Z - planar_corrected_factors(M, C, cal.value)[0])
    assert planar_corrected_factors(M, C, cal.value)[0] == pytest.approx(Z, abs=1e-12)
    rng = np.random.default_rng(7)
    keys = [red.problem.landmark_keys[t] for t in focused]
    draws = []
    for c in rng.multivariate_normal(cal.value, cal.covariance, size=150):
        Zc = planar_corrected_factors(M, C, c)[0]  # the covariances stay at ĉ's: the term moves means only
        rows = list(red.problem.rows)
        for i, z in zip(odometry, Zc, strict=True):
            rows[i] = dataclasses.replace(rows[i], measurement=z)
        problem = dataclasses.replace(red.problem, rows=rows, initial=red.solution.values)
        values = optimise(problem, build_graph(rows)).values
        draws.append(np.concatenate([np.asarray(values.atPoint2(k)) for k in keys]))
    scatter = np.cov(np.array(draws).T)
    predicted = red.consider.joint(keys)
    ratio = np.trace(scatter) / np.trace(predicted)
    assert 0.8 < ratio < 1.25  # 150 draws: the trace of a sample covariance is within ~±12 % (1 σ of ~6 %)
    # and per landmark, not only in total
    per = np.array([scatter[2 * j, 2 * j] + scatter[2 * j + 1, 2 * j + 1] for j in range(len(keys))])
    pred = np.array([predicted[2 * j, 2 * j] + predicted[2 * j + 1, 2 * j + 1] for j in range(len(keys))])
    assert np.corrcoef(per, pred)[0, 1] > 0.95
