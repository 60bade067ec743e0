"""The shared tag scale ``s`` of the graph stage: exact Jacobians, the factor table round trip, estimation
of a shared range error against odometry, and what later stages see (keys, fixed factors, reduced graphs)."""

from __future__ import annotations

import json
from pathlib import Path

import gtsam
import numpy as np
import pyarrow as pa
import pytest
from gtsam.symbol_shorthand import L, X

from pipeline.artifacts import StageInput
from pipeline.config import load_settings
from pipeline.errors import StageError
from pipeline.registry import Registry
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages import graph as graph_stage
from stages.estimation.linear_system import LinearSystem
from stages.geometry import pose3_to_vector
from stages.graph import GraphConfig, build_reduced, load_graph
from stages.graph.build import build_problem
from stages.graph.factors import (
    SCALE_KEY,
    FactorRow,
    build_graph,
    make_factor,
    rows_to_table,
    scaled_bearing_range_error,
    scaled_between_error,
    table_to_rows,
)
from stages.graph.problem import GraphProblem
from stages.graph.solve import check_problem, marginal_covariances, optimise
from tests.fixtures.synthetic_runs import synthetic_run
from tests.fixtures.upstream import seed_upstream, stand_in

H = 1e-6


def _central(f, x0_dim: int) -> np.ndarray:
    cols = []
    for i in range(x0_dim):
        d = np.zeros(x0_dim)
        d[i] = H
        cols.append((f(d) - f(-d)) / (2 * H))
    return np.column_stack(cols)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planar_jacobians_match_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = gtsam.Pose2(*rng.normal(size=2), rng.uniform(-3, 3))
    point = rng.normal(size=2) * 3
    s = 1 + 0.01 * rng.normal()
    b, r = rng.uniform(-3, 3), rng.uniform(0.5, 5)
    _, J = scaled_bearing_range_error(pose, point, s, b, r)
    fx = _central(lambda d: scaled_bearing_range_error(pose.retract(d), point, s, b, r)[0], 3)
    fl = _central(lambda d: scaled_bearing_range_error(pose, point + d, s, b, r)[0], 2)
    fs = _central(lambda d: scaled_bearing_range_error(pose, point, s + d[0], b, r)[0], 1)
    for got, want in zip(J, (fx, fl, fs), strict=True):
        np.testing.assert_allclose(got, want, atol=1e-7)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_3d_jacobians_match_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a = gtsam.Pose3.Expmap(rng.normal(size=6))
    b = gtsam.Pose3.Expmap(rng.normal(size=6) * 2)
    measured = a.between(b).compose(gtsam.Pose3.Expmap(0.1 * rng.normal(size=6)))
    s = 1 + 0.01 * rng.normal()
    _, J = scaled_between_error(a, b, s, measured)
    fa = _central(lambda d: scaled_between_error(a.retract(d), b, s, measured)[0], 6)
    fb = _central(lambda d: scaled_between_error(a, b.retract(d), s, measured)[0], 6)
    fs = _central(lambda d: scaled_between_error(a, b, s + d[0], measured)[0], 1)
    for got, want in zip(J, (fa, fb, fs), strict=True):
        np.testing.assert_allclose(got, want, atol=1e-6)


def test_at_unit_scale_the_factors_equal_gtsams_own() -> None:
    """At s = 1 the scaled factors have the error and (pose, landmark) Jacobians of the native factors."""
    rng = np.random.default_rng(4)
    x, lk = int(X(0)), int(L(3))
    # planar
    cov2 = np.array([[1e-4, 2e-5], [2e-5, 4e-4]])
    row = FactorRow("tag", "BearingRangeFactor2D", (x, lk, SCALE_KEY), np.array([0.4, 2.5]), cov2)
    v = gtsam.Values()
    v.insert(x, gtsam.Pose2(0.2, -0.1, 0.3))
    v.insert(lk, np.array([2.0, 1.6]))
    v.insert(SCALE_KEY, 1.0)
    native = gtsam.BearingRangeFactor2D(x, lk, gtsam.Rot2(0.4), 2.5, gtsam.noiseModel.Gaussian.Covariance(cov2))
    ours = make_factor(row)
    assert isinstance(ours, gtsam.CustomFactor)
    assert ours.error(v) == pytest.approx(native.error(v), rel=1e-12)
    np.testing.assert_allclose(ours.linearize(v).jacobian()[0][:, :5], native.linearize(v).jacobian()[0], atol=1e-12)
    # 3d
    a, b = gtsam.Pose3.Expmap(rng.normal(size=6)), gtsam.Pose3.Expmap(rng.normal(size=6))
    meas = a.between(b).compose(gtsam.Pose3.Expmap(0.05 * rng.normal(size=6)))
    cov6 = np.diag(rng.uniform(0.01, 0.1, 6) ** 2)
    row = FactorRow("tag", "BetweenFactorPose3", (x, lk, SCALE_KEY), pose3_to_vector(meas), cov6)
    v = gtsam.Values()
    v.insert(x, a)
    v.insert(lk, b)
    v.insert(SCALE_KEY, 1.0)
    native = gtsam.BetweenFactorPose3(x, lk, meas, gtsam.noiseModel.Gaussian.Covariance(cov6))
    ours = make_factor(row)
    assert ours.error(v) == pytest.approx(native.error(v), rel=1e-9)
    np.testing.assert_allclose(ours.linearize(v).jacobian()[0][:, :12], native.linearize(v).jacobian()[0], atol=1e-9)


def test_factor_table_round_trip() -> None:
    x, lk = int(X(2)), int(L(9))
    rows = [
        FactorRow("scale_prior", "PriorFactorDouble", (SCALE_KEY,), np.ones(1), np.array([[0.005**2]])),
        FactorRow(
            "tag", "BearingRangeFactor2D", (x, lk, SCALE_KEY), np.array([0.3, 1.7]), np.diag([1e-4, 4e-4]), tag_id=9
        ),
    ]
    table = rows_to_table(rows)
    assert table.column("key_names").to_pylist() == [["s0"], ["x2", "l9", "s0"]]
    back = table_to_rows(pa.Table.from_pylist(table.to_pylist(), schema=table.schema))
    v = gtsam.Values()
    v.insert(x, gtsam.Pose2(0.1, 0.2, 0.3))
    v.insert(lk, np.array([1.5, 1.0]))
    v.insert(SCALE_KEY, 1.004)
    for a, b in zip(rows, back, strict=True):
        assert (a.kind, a.type, a.keys) == (b.kind, b.type, b.keys)
        assert make_factor(a).error(v) == pytest.approx(make_factor(b).error(v), rel=1e-14)


def _scaled_detections(table: pa.Table, k: float) -> pa.Table:
    """Every detection's camera-to-tag translation times ``k`` (a tag printed 1/k as large)."""
    T = [np.asarray(t, dtype=float).reshape(4, 4).copy() for t in table.column("T_camera_tag").to_pylist()]
    for m in T:
        m[:3, 3] *= k
    idx = table.column_names.index("T_camera_tag")
    col = pa.array([m.ravel().tolist() for m in T], type=table.schema.field(idx).type)
    return table.set_column(idx, "T_camera_tag", col)


@pytest.mark.parametrize("model", ["planar", "3d"])
def test_shared_range_error_is_estimated_against_odometry(model: str) -> None:
    """Ranges 1 % short move the estimated scale by the odometry's share of the scale information.

    The scale is a linear-Gaussian unknown to first order: its estimate moves by ``w Δ`` for a shared range
    change ``Δ``, with ``w = 1 − σ_post² / σ_prior²`` the weight of the data (odometry) against the prior.
    """
    sim = synthetic_run(seed=2, loops=1.0)
    sigma = 0.005
    est = {}
    for k in (1.0, 0.99):
        det = _scaled_detections(sim.detections, k)
        p = build_problem(det, sim.odometry, sim.extrinsics, GraphConfig(model=model, tag_scale_sigma=sigma))
        check_problem(p)
        g = build_graph(p.rows)
        sol = optimise(p, g)
        marg = marginal_covariances(p, g, sol.values, [SCALE_KEY])
        est[k] = (sol.values.atDouble(SCALE_KEY), float(np.sqrt(marg[SCALE_KEY][0, 0])))
    s_sig = est[0.99][1]
    assert 0 < s_sig < sigma
    w = 1 - (s_sig / sigma) ** 2
    assert w > 0.1  # the odometry informs the scale
    shift = est[0.99][0] - est[1.0][0]
    assert shift == pytest.approx(w * (1 / 0.99 - 1), rel=0.2), (shift, w)


def test_scale_does_not_join_disconnected_parts() -> None:
    """Two tags tied only through the shared scale are still reported as not connected."""
    x0, x1, l5 = int(X(0)), int(X(1)), int(L(5))
    rows = [
        FactorRow("prior", "PriorFactorPose2", (x0,), np.zeros(3), np.eye(3) * 1e-6),
        FactorRow("scale_prior", "PriorFactorDouble", (SCALE_KEY,), np.ones(1), np.array([[1e-4]])),
        FactorRow("tag", "BearingRangeFactor2D", (x1, l5, SCALE_KEY), np.array([0.1, 2.0]), np.eye(2) * 0.01, tag_id=5),
        FactorRow("tag", "BearingRangeFactor2D", (x1, l5, SCALE_KEY), np.array([0.1, 2.0]), np.eye(2) * 0.01, tag_id=5),
    ]
    initial = gtsam.Values()
    initial.insert(x0, gtsam.Pose2())
    initial.insert(x1, gtsam.Pose2(1, 0, 0))
    initial.insert(l5, np.array([3.0, 0.2]))
    initial.insert(SCALE_KEY, 1.0)
    types = {x0: "Pose2", x1: "Pose2", l5: "Point2", SCALE_KEY: "Scale"}
    p = GraphProblem("planar", rows, initial, types, [x0, x1], [0, 10**9], {5: l5})
    assert p.describe(SCALE_KEY) == "the tag scale s"
    with pytest.raises(StageError, match=r"not connected to the first pose, starting with pose 1"):
        check_problem(p)


def test_stage_artifacts_and_what_later_stages_see(tmp_path: Path) -> None:
    sim = synthetic_run(seed=3, loops=0.5)
    reg = Registry([stand_in("ingest"), stand_in("detect", "ingest"), graph_stage.STAGE])
    run = RunFolder.create(tmp_path / "run", None)
    seed_upstream(run, sim)
    run_stage(run, reg, "graph", load_settings(reg.models(), overrides=["graph.tag_scale_sigma=0.005"]))
    out = run.stage_dir("graph")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tag_scale"]["prior_sigma"] == pytest.approx(0.005)
    assert 0 < summary["tag_scale"]["sigma"] < 0.005
    assert abs(summary["tag_scale"]["value"] - 1) < 0.02

    loaded = load_graph(StageInput("graph", out))
    assert loaded.scale_key == SCALE_KEY and loaded.var_types[SCALE_KEY] == "Scale"
    assert SCALE_KEY not in loaded.pose_keys and SCALE_KEY not in loaded.landmark_keys.values()
    prior_idx = [i for i, r in enumerate(loaded.rows) if r.kind == "scale_prior"]
    assert len(prior_idx) == 1 and prior_idx[0] in set(loaded.fixed_factor_indices.tolist())
    assert prior_idx[0] not in set(loaded.tag_factor_indices.tolist())
    assert loaded.marginals[SCALE_KEY].shape == (1, 1)
    assert loaded.graph.error(loaded.values) == pytest.approx(summary["final_error"], rel=1e-9)

    # the selection stages' linearisation: the scale is one more (pose-like) column, kept in every tag factor
    system = LinearSystem.from_gtsam(
        loaded.graph, loaded.values, is_landmark=set(loaded.landmark_keys.values()).__contains__
    )
    sv = system.index_of_key(SCALE_KEY)
    assert system.variables[sv].dim == 1
    assert all(sv in system.factors[int(i)].variables for i in loaded.tag_factor_indices)

    # reduced graphs keep the scale prior, even when the caller kept only tag factors
    keep = list(loaded.fixed_factor_indices) + list(loaded.tag_factor_indices[::3])
    reduced, values = build_reduced(loaded, keep)
    assert reduced.size() == len(keep) and values.exists(SCALE_KEY)
    only_tags = list(loaded.tag_factor_indices[:5])
    reduced, values = build_reduced(loaded, only_tags)
    assert reduced.size() == len(only_tags) + 1
    assert isinstance(reduced.at(len(only_tags)), gtsam.PriorFactorDouble)

    # the old model on request
    run_stage(run, reg, "graph", load_settings(reg.models(), overrides=["graph.tag_scale_sigma=0"]), force=True)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tag_scale"] is None
    assert load_graph(StageInput("graph", out)).scale_key is None


@pytest.mark.parametrize("model", ["planar", "3d"])
def test_scale_estimate_is_unbiased_on_runs_with_exact_tags(model: str) -> None:
    """With unbiased detections the estimated scale scatters about 1 within its marginal σ, with no shared sign.

    A factor that multiplied the measured range by ``s`` (instead of dividing the predicted one) scaled the
    measurement noise by ``s``, so least squares shrank ``s``: mean z of −1.2 (planar) and −2.4 (3d) over these runs.
    """
    zs = []
    for seed in range(6):
        sim = synthetic_run(seed=seed)
        p = build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(model=model, tag_scale_sigma=0.005))
        g = build_graph(p.rows)
        sol = optimise(p, g)
        marg = marginal_covariances(p, g, sol.values, [SCALE_KEY])
        zs.append((sol.values.atDouble(SCALE_KEY) - 1) / np.sqrt(marg[SCALE_KEY][0, 0]))
    assert abs(np.mean(zs)) < 0.6, zs
    assert np.all(np.abs(zs) < 3), zs
