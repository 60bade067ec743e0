"""The graph stage: structure, accuracy, marginals, failures, import of existing graphs, recording, reload."""

from __future__ import annotations

import dataclasses
import json
from collections import Counter
from pathlib import Path

import gtsam
import numpy as np
import pyarrow.parquet as pq
import pytest
from gtsam.symbol_shorthand import L, X

from pipeline.artifacts import StageInput
from pipeline.config import load_settings
from pipeline.contracts import TableSpec
from pipeline.errors import InputError, StageError
from pipeline.registry import Registry
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages import graph as graph_stage
from stages.geometry import (
    bearing_range_to_relative_position_2d,
    interpolate_pose2,
    interpolate_pose3,
    relative_position_to_bearing_range_2d,
)
from stages.graph import GraphConfig, build_reduced, load_graph
from stages.graph.artifacts import ARTIFACTS as GRAPH_ARTIFACTS
from stages.graph.build import build_problem
from stages.graph.factors import SCALE_KEY, FactorRow, build_graph
from stages.graph.g2o import g2o_metadata, read_graph_file, side_file, write_g2o
from stages.graph.problem import VAR_DIMS, GraphProblem
from stages.graph.solve import check_problem, marginal_covariances, optimise
from tests.fixtures.graphs import import_graph
from tests.fixtures.shared_data import need_shared
from tests.fixtures.synthetic_runs import synthetic_run
from tests.fixtures.upstream import seed_upstream, stand_in


@pytest.fixture(scope="module")
def sim():
    return synthetic_run(seed=3, loops=1.0)


def _solve(problem: GraphProblem):
    check_problem(problem)
    g = build_graph(problem.rows)
    sol = optimise(problem, g)
    return g, sol, marginal_covariances(problem, g, sol.values, list(problem.var_types))


def _truth_in_map(sim, problem: GraphProblem) -> dict[int, np.ndarray]:
    x0 = sim.true_pose_at(np.array([problem.pose_stamps_ns[0]]))[0]
    c, s = np.cos(x0[2]), np.sin(x0[2])
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x0[:2]
    Tinv = np.linalg.inv(T)
    return {tag: (Tinv @ sim.tags_world[tag])[:3, 3] for tag in problem.landmark_keys}


# ------------------------------------------------------------------ geometry


def test_se2_se3_interpolation_is_on_the_group() -> None:
    a, b = gtsam.Pose2(0, 0, 0), gtsam.Pose2(0, 2, np.pi / 2)
    mid = interpolate_pose2(a, b, 0.5)
    assert mid.theta() == pytest.approx(np.pi / 4)
    assert interpolate_pose2(a, b, 1.0).equals(b, 1e-9)
    A = gtsam.Pose3(gtsam.Rot3.Yaw(0.0), np.zeros(3))
    B = gtsam.Pose3(gtsam.Rot3.Yaw(1.0), np.array([1.0, 1.0, 0.0]))
    m3 = interpolate_pose3(A, B, 0.25)
    assert m3.rotation().yaw() == pytest.approx(0.25)
    assert interpolate_pose3(A, B, 1.0).equals(B, 1e-9)


def test_bearing_range_conversion_round_trips() -> None:
    C = np.array([[0.02, 0.005], [0.005, 0.01]])
    b, r, Cbr = relative_position_to_bearing_range_2d([1.5, -0.7], C)
    p, C2 = bearing_range_to_relative_position_2d(b, r, Cbr)
    np.testing.assert_allclose(p, [1.5, -0.7])
    np.testing.assert_allclose(C2, C, atol=1e-12)


# ------------------------------------------------------------------ structure and accuracy


@pytest.mark.parametrize("model", ["planar", "3d"])
def test_structure_counts(sim, model: str) -> None:
    p = build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(model=model, tag_scale_sigma=0.005))
    kinds = Counter(r.kind for r in p.rows)
    n_det = sim.detections.num_rows
    tags = set(sim.detections.column("tag_id").to_pylist())
    det_stamps = set(sim.detections.column("stamp_ns").to_pylist())
    assert kinds["prior"] == 1
    assert kinds["tag"] == n_det
    assert kinds["odometry"] == len(p.pose_keys) - 1
    assert len(p.landmark_keys) == len(tags)
    assert set(p.pose_stamps_ns) >= det_stamps  # a keyframe at every frame that saw a tag
    assert len(p.pose_keys) > len(det_stamps)  # plus odometry keyframes where none was seen
    assert p.pose_stamps_ns == sorted(p.pose_stamps_ns)
    assert p.info["odometry_noise"] == "messages"
    # the shared tag scale: one variable, one prior, the third key of every tag factor
    assert kinds["scale_prior"] == 1
    assert p.scale_key == SCALE_KEY and p.var_types[SCALE_KEY] == "Scale"
    assert all(r.keys[2] == SCALE_KEY for r in p.rows if r.kind == "tag")
    assert SCALE_KEY not in p.pose_keys and SCALE_KEY not in p.landmark_keys.values()
    assert len(p.var_types) == len(p.pose_keys) + len(tags) + 1
    old = build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(model=model, tag_scale_sigma=0.0))
    assert old.scale_key is None and "scale_prior" not in {r.kind for r in old.rows}
    assert len(old.var_types) == len(p.pose_keys) + len(tags) and all(
        len(r.keys) == 2 for r in old.rows if r.kind == "tag"
    )
    lm_type = "Point2" if model == "planar" else "Pose3"
    assert {p.var_types[k] for k in p.landmark_keys.values()} == {lm_type}


@pytest.mark.parametrize("model", ["planar", "3d"])
def test_optimised_map_near_truth(sim, model: str) -> None:
    p = build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(model=model))
    _, sol, marg = _solve(p)
    assert sol.final_error < sol.initial_error
    truth = _truth_in_map(sim, p)
    err = []
    for tag, key in p.landmark_keys.items():
        est = (
            np.asarray(sol.values.atPoint2(key))
            if model == "planar"
            else np.asarray(sol.values.atPose3(key).translation())[:2]
        )
        err.append(np.linalg.norm(est - truth[tag][:2]))
        assert np.all(np.linalg.eigvalsh(marg[key]) > 0)
    assert np.sqrt(np.mean(np.square(err))) < 0.15


def test_settings_noise_and_optimizers(sim) -> None:
    base = build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(odometry_noise="settings"))
    assert base.info["odometry_noise"] == "settings"
    finals = []
    for opt in ("lm", "gn", "dogleg"):
        sol = optimise(base, optimizer=opt)
        finals.append(sol.final_error)
    assert max(finals) - min(finals) < 1e-3 * max(finals)
    robust = build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(robust_kernel="huber"))
    assert {r.robust for r in robust.rows if r.kind == "tag"} == {"huber"}
    optimise(robust)


def test_without_odometry_uses_motion_prior(sim) -> None:
    p = build_problem(sim.detections, None, sim.extrinsics, GraphConfig(model="3d"))
    kinds = Counter(r.kind for r in p.rows)
    assert kinds["motion_prior"] == len(p.pose_keys) - 1 and kinds["odometry"] == 0
    assert "no odometry" in p.info["note"]
    _solve(p)


def test_marginals_equal_inverse_of_information() -> None:
    run = synthetic_run(seed=1, loops=0.3)
    p = build_problem(run.detections, run.odometry, run.extrinsics, GraphConfig())
    g, sol, marg = _solve(p)
    keys = list(p.var_types)
    ordering = gtsam.Ordering()
    for k in keys:
        ordering.push_back(k)
    H, _ = g.linearize(sol.values).hessian(ordering)
    cov = np.linalg.inv(H)
    dims = [VAR_DIMS[p.var_types[k]] for k in keys]
    offs = np.concatenate([[0], np.cumsum(dims)])
    for i, k in enumerate(keys):
        block = cov[offs[i] : offs[i + 1], offs[i] : offs[i + 1]]
        np.testing.assert_allclose(marg[k], block, rtol=1e-6, atol=1e-12)


# ------------------------------------------------------------------ failures


def _tiny_problem(rows: list[FactorRow], values: dict[int, object], types: dict[int, str]) -> GraphProblem:
    initial = gtsam.Values()
    for k, v in values.items():
        initial.insert(k, v)
    poses = [k for k in types if types[k].startswith("Pose")]
    lms = {gtsam.Symbol(k).index(): k for k in types if not types[k].startswith("Pose")}
    return GraphProblem("planar", rows, initial, types, poses, [i * 10**9 for i in range(len(poses))], lms)


def test_disconnected_part_is_named() -> None:
    x0, x1, l5 = int(X(0)), int(X(1)), int(L(5))
    rows = [
        FactorRow("prior", "PriorFactorPose2", (x0,), np.zeros(3), np.eye(3) * 1e-6),
        FactorRow("tag", "BearingRangeFactor2D", (x1, l5), np.array([0.1, 2.0]), np.eye(2) * 0.01, tag_id=5),
        FactorRow("tag", "BearingRangeFactor2D", (x1, l5), np.array([0.1, 2.0]), np.eye(2) * 0.01, tag_id=5),
    ]
    p = _tiny_problem(
        rows,
        {x0: gtsam.Pose2(), x1: gtsam.Pose2(1, 0, 0), l5: np.array([3.0, 0.2])},
        {x0: "Pose2", x1: "Pose2", l5: "Point2"},
    )
    with pytest.raises(StageError, match=r"not connected to the first pose, starting with pose 1 \(t=1\.000 s"):
        check_problem(p)


def test_nan_measurement_is_named() -> None:
    x0, l7 = int(X(0)), int(L(7))
    rows = [
        FactorRow("prior", "PriorFactorPose2", (x0,), np.zeros(3), np.eye(3) * 1e-6),
        FactorRow("tag", "BearingRangeFactor2D", (x0, l7), np.array([np.nan, 2.0]), np.eye(2), tag_id=7, stamp_ns=5),
    ]
    p = _tiny_problem(rows, {x0: gtsam.Pose2(), l7: np.array([2.0, 0.0])}, {x0: "Pose2", l7: "Point2"})
    with pytest.raises(StageError, match=r"tag 7 at stamp_ns 5.*NaN"):
        check_problem(p)


def test_indeterminant_system_names_the_variable() -> None:
    """Passes the structural checks (pose 1 has two measurements), but both are of the same tag, so GTSAM
    finds pose 1 free to turn about it."""
    x0, x1, l3 = int(X(0)), int(X(1)), int(L(3))
    br = np.array([0.0, 2.0])
    rows = [
        FactorRow("prior", "PriorFactorPose2", (x0,), np.zeros(3), np.eye(3) * 1e-6),
        FactorRow("tag", "BearingRangeFactor2D", (x0, l3), br, np.eye(2) * 1e-4, tag_id=3),
        FactorRow("tag", "BearingRangeFactor2D", (x1, l3), np.array([0.0, 1.0]), np.eye(2) * 1e-4, tag_id=3),
        FactorRow("tag", "BearingRangeFactor2D", (x1, l3), np.array([0.0, 1.0]), np.eye(2) * 1e-4, tag_id=3),
    ]
    p = _tiny_problem(
        rows,
        {x0: gtsam.Pose2(), x1: gtsam.Pose2(1, 0, 0), l3: np.array([2.0, 0.0])},
        {x0: "Pose2", x1: "Pose2", l3: "Point2"},
    )
    p.row_cameras = [None, "/left/tags", "/right/tags", "/right/tags"]
    check_problem(p)
    with pytest.raises(StageError, match=r"singular near (pose 1 \(t=1\.000 s|tag 3)") as err:
        _solve(p)
    # what holds it is named: the pose's one tag, its two sightings and the camera, or the tag's from two poses
    line = str(err.value)
    assert (
        ", which sees tag 3 (2 sighting(s) by camera /right/tags)" in line
        or ", seen 3 time(s) from 2 pose(s) by cameras /left/tags, /right/tags" in line
    ), line


def test_no_usable_detections(sim) -> None:
    with pytest.raises(StageError, match="no usable tag detections"):
        build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(max_reprojection_px=0.1))


# ------------------------------------------------------------------ import

EXPECTED = {
    # file: (model, poses, landmarks, factors by kind); a prior on the first pose is added
    "example.graph": ("planar", 95, 24, {"prior": 1, "odometry": 94, "tag": 422}),
    "w100.graph": ("planar", 100, 0, {"prior": 1, "odometry": 99, "loop": 201}),
    "pose2example.txt": ("planar", 11, 0, {"prior": 1, "odometry": 10, "loop": 2}),
    "pose3example.txt": ("3d", 5, 0, {"prior": 1, "odometry": 4, "loop": 2}),
    "toyExample.g2o": ("3d", 5, 0, {"prior": 1, "odometry": 4, "loop": 2}),
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_import_every_shared_graph(tmp_path: Path, name: str) -> None:
    model, n_poses, n_lm, kinds = EXPECTED[name]
    run = import_graph(need_shared(f"slam-graphs/{name}"), tmp_path, None)
    summary = json.loads((run / "graph" / "summary.json").read_text())
    assert (summary["model"], summary["poses"], summary["landmarks"]) == (model, n_poses, n_lm)
    assert summary["factors_by_kind"] == kinds
    assert summary["final_error"] <= summary["initial_error"]
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["stages"]["graph"]["summary"]["poses"] == n_poses
    assert (run / "graph.rrd").is_file() and RunFolder(run).stage_entry("graph") is not None
    loaded = load_graph(StageInput("graph", run / "graph"))
    assert loaded.model == model and len(loaded.pose_keys) == n_poses
    assert loaded.graph.error(loaded.values) == pytest.approx(summary["final_error"], rel=1e-9)
    if name == "w100.graph":
        assert summary["equivalences_ignored"] == 40


def test_import_matches_gtsam_loader() -> None:
    path = need_shared("slam-graphs/example.graph")
    p = read_graph_file(path)
    g = build_graph(p.rows)
    ref_graph, ref_values = gtsam.load2D(str(path))
    values = gtsam.Values()
    for k, t in p.var_types.items():
        idx = gtsam.Symbol(k).index()
        if t == "Pose2":
            values.insert(k, ref_values.atPose2(idx))
        else:
            values.insert(k, ref_values.atPoint2(k))
    ours = sum(g.at(i).error(values) for i in range(g.size()) if p.rows[i].kind != "prior")
    assert ours == pytest.approx(ref_graph.error(ref_values), rel=1e-9)


def test_import_bad_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        import_graph(tmp_path / "missing.g2o", tmp_path, None)
    bad = tmp_path / "bad.g2o"  # a prior line: focusmap's g2o reader, which needs every vertex
    bad.write_text("VERTEX_SE2 0 0 0 0\nEDGE_PRIOR_SE2 0 0 0 0 1 0 0 1 0 1\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(InputError, match="vertex 1, which the file does not define"):
        import_graph(bad, tmp_path, None)
    assert not (tmp_path / "bad").exists() or RunFolder(tmp_path / "bad").stage_entry("graph") is None
    garbled = tmp_path / "garbled.g2o"
    garbled.write_text("VERTEX_SE2 0 zero 0 0\n")
    with pytest.raises(InputError, match=r"garbled\.g2o:1"):
        read_graph_file(garbled)


def test_g2o_written_by_the_stage_reads_back(sim, tmp_path: Path) -> None:
    """Ours reads it back with its side file; GTSAM's readG2o reads every edge but the priors (no comment lines)."""
    for model in ("planar", "3d"):
        p = build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(model=model, tag_scale_sigma=0.005))
        g, sol, _ = _solve(p)
        text = write_g2o(p, sol.values)
        meta = g2o_metadata(p, sol.values)
        back_path = tmp_path / f"roundtrip_{model}.g2o"
        back_path.write_text(text)
        side_file(back_path).write_text(json.dumps(meta))
        back = read_graph_file(back_path)
        assert len(back.pose_keys) == len(p.pose_keys)
        assert sorted(back.landmark_keys) == sorted(p.landmark_keys)
        assert Counter(r.kind for r in back.rows)["tag"] == Counter(r.kind for r in p.rows)["tag"]
        err_back = build_graph(back.rows).error(back.initial)
        # g2o has no shared scale: the tag measurements are written at the estimated s, its prior is left out
        assert meta["tag_scale"] == pytest.approx(sol.values.atDouble(SCALE_KEY), rel=1e-12)
        prior_err = sum(g.at(i).error(sol.values) for i, r in enumerate(p.rows) if r.kind == "scale_prior")
        assert err_back == pytest.approx(g.error(sol.values) - prior_err, rel=1e-3)
        assert "#" not in text
        n_priors = sum(r.kind == "prior" for r in p.rows)
        assert meta["edges"] == len(p.rows) - 1 and meta["priors"] == n_priors
        ref_graph, ref_values = gtsam.readG2o(str(back_path), model == "3d")
        assert ref_graph.size() == meta["edges_gtsam_reads"] == len(p.rows) - 1 - n_priors
        assert ref_values.size() == len(p.pose_keys) + len(p.landmark_keys)
        if model == "3d":  # Pose3 tags: g2o holds the factors exactly, GTSAM's optimum on the file is ours
            prior = p.rows[0]
            noise = gtsam.noiseModel.Gaussian.Covariance(prior.covariance)
            ref_graph.add(gtsam.PriorFactorPose3(0, p.kind(prior.keys[0]).from_vector(prior.measurement), noise))
            ref = gtsam.LevenbergMarquardtOptimizer(ref_graph, ref_values).optimize()
            assert ref_graph.error(ref) == pytest.approx(g.error(sol.values) - prior_err, rel=1e-4)


# ------------------------------------------------------------------ the stage in a run folder


def _stage_run(tmp_path: Path, sim, overrides: list[str] = ()) -> RunFolder:
    reg = Registry([stand_in("ingest"), stand_in("detect", "ingest"), graph_stage.STAGE])
    run = RunFolder.create(tmp_path / "run", None)
    seed_upstream(run, sim)
    settings = load_settings(reg.models(), overrides=overrides)
    run_stage(run, reg, "graph", settings)
    return run


def test_stage_end_to_end_and_reload(tmp_path: Path, sim) -> None:
    run = _stage_run(tmp_path, sim)
    out = run.stage_dir("graph")
    required = {spec.file for spec in GRAPH_ARTIFACTS.specs if not spec.optional}
    assert {p.name for p in out.iterdir()} == required | {"summary.json"}  # not calibrated: no calibration.npz
    for spec in GRAPH_ARTIFACTS.specs:
        if isinstance(spec, TableSpec):
            assert pq.read_schema(out / spec.file).equals(spec.schema), spec.file
    summary = json.loads((out / "summary.json").read_text())
    factors = pq.read_table(out / "factors.parquet").to_pydict()
    assert len(factors["index"]) == summary["factors"]
    tag_rows = [i for i, k in enumerate(factors["kind"]) if k == "tag"]
    assert len(tag_rows) == sim.detections.num_rows
    assert all(factors["tag_id"][i] is not None and factors["stamp_ns"][i] is not None for i in tag_rows)
    lms = pq.read_table(out / "landmarks.parquet").to_pydict()
    assert set(lms["tag_id"]) == set(sim.detections.column("tag_id").to_pylist())
    assert all(len(c) == 9 for c in lms["position_cov"])
    tum = (out / "trajectory.tum").read_text().splitlines()
    assert len(tum) == summary["poses"] and len(tum[0].split()) == 8

    loaded = load_graph(StageInput("graph", out))
    assert loaded.model == "planar" and len(loaded.rows) == summary["factors"]
    assert loaded.graph.error(loaded.values) == pytest.approx(summary["final_error"], rel=1e-9)
    lin = loaded.graph.linearize(loaded.values)
    assert lin.size() == summary["factors"]
    keep = list(loaded.fixed_factor_indices) + list(loaded.tag_factor_indices[::2])
    reduced, values = build_reduced(loaded, keep)
    assert reduced.size() == len(keep)
    params = gtsam.LevenbergMarquardtParams()
    gtsam.LevenbergMarquardtOptimizer(reduced, values, params).optimize()

    # the recording, read back
    from rerun.chunk import RrdReader

    rows: Counter[str] = Counter()
    for chunk in RrdReader(run.rrd_path("graph")).stream():
        rows[str(chunk.entity_path)] += chunk.num_rows
    for entity in (
        "/graph/path",
        "/graph/dead_reckoning",
        "/graph/landmarks",
        "/graph/pose_covariance",
        "/graph/tag_edges",
        "/graph/summary",
    ):
        assert rows[entity] >= 1, entity


def test_stage_failure_leaves_no_artifacts(tmp_path: Path, sim) -> None:
    with pytest.raises(StageError):
        _stage_run(tmp_path, sim, ["graph.max_reprojection_px=0.1"])
    run = RunFolder(tmp_path / "run")
    assert run.stage_entry("graph") is None and not run.stage_dir("graph").exists()


def test_an_old_detections_table_names_detect_to_rerun(tmp_path: Path, sim) -> None:
    old = dataclasses.replace(sim, detections=sim.detections.drop_columns(["pose_cov"]))
    with pytest.raises(
        InputError, match=r"detect/detections\.parquet lacks columns \['pose_cov'\]; re-run 'focusmap detect"
    ):
        _stage_run(tmp_path, old)


def test_an_old_graph_folder_names_the_stage_to_rerun(tmp_path: Path, sim) -> None:
    out = _stage_run(tmp_path, sim).stage_dir("graph")
    factors = pq.read_table(out / "factors.parquet")
    pq.write_table(factors.drop_columns(["robust_k"]), out / "factors.parquet")
    with pytest.raises(
        InputError, match=r"graph/factors\.parquet lacks columns \['robust_k'\]; re-run 'focusmap graph"
    ):
        load_graph(StageInput("graph", out))
    pq.write_table(factors, out / "factors.parquet")
    with np.load(out / "values.npz") as arrays:
        kept = {k: arrays[k] for k in arrays.files if k != "initial"}
    np.savez(out / "values.npz", **kept)
    old_arrays = r"optimize/values\.npz lacks arrays \['initial'\]; re-run 'focusmap optimize RUN --force'"
    with pytest.raises(InputError, match=old_arrays):
        load_graph(StageInput("optimize", out))  # optimize's reduced graph is read the same way
