"""select_landmarks on the committed office sample: artifacts, recording, the collision claim, edge cases, no laser.

The sample (``sample_data/office``) is ingested, detected and graphed once per session (the ``office_run``
fixture of ``tests/stages/conftest.py``); each test that runs a stage works on a copy.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.artifacts import StageInput
from pipeline.errors import StageError
from pipeline.run_folder import RunFolder
from stages.graph.load import load_graph
from stages.risk import RiskParams, path_geometry
from stages.select_landmarks import LandmarkInputs, SelectLandmarksConfig, choose
from tests.fixtures.office import TRUTH, copy_run, rrd_rows, run_select


def region_of_tags() -> dict[int, str]:
    """Ground-truth region of every tag: corridor (walls 2-4), door (walls 1 and 5 within 1.5 m of it), room."""
    truth = json.loads(TRUTH.read_text())
    out = {}
    for tag in truth["tags"]:
        y = tag["position"][1]
        if tag["wall"] in (2, 3, 4):
            out[tag["id"]] = "corridor"
        elif tag["wall"] in (1, 5) and abs(y - 3.0) < 1.5:
            out[tag["id"]] = "door"
        else:
            out[tag["id"]] = "room"
    return out


@pytest.fixture(scope="module")
def inputs(office_run: Path) -> LandmarkInputs:
    """The office run's inputs, loaded once (no run folder needed)."""
    path = office_run
    loaded = load_graph(StageInput("graph", path / "graph"))
    ingest = StageInput("ingest", path / "ingest")
    T_bl = np.asarray(ingest.read_json("extrinsics.json")["sensors"]["laser"]["T_base_sensor"])
    detections = StageInput("detect", path / "detect").read_table("detections.parquet", columns=["stamp_ns", "tag_id"])
    return LandmarkInputs.from_pieces(loaded, ingest.read_table("scans.parquet"), T_bl, detections)


def test_stage_outputs_and_recording(office_run: Path, tmp_path: Path) -> None:
    run = copy_run(office_run, tmp_path)
    budget = 8
    summary = run_select(run, "select_landmarks", [f"select_landmarks.budget={budget}"])
    out = run.stage_dir("select_landmarks")
    focused = json.loads((out / "focused.json").read_text())
    assert focused["strategy"] == "collision" and focused["budget"] == budget and focused["status"] == "ok"
    assert len(focused["tag_ids"]) == budget == len(set(focused["tag_ids"])) == len(focused["scores"])
    landmarks = pq.read_table(run.stage_dir("graph") / "landmarks.parquet").column("tag_id").to_pylist()
    assert set(focused["tag_ids"]) <= set(landmarks)
    risk = pq.read_table(out / "risk.parquet").to_pydict()
    poses = pq.read_table(run.stage_dir("graph") / "poses.parquet").num_rows
    for col in (
        "stamp_ns",
        "x",
        "y",
        "z",
        "sigma_star",
        "clearance_m",
        "p_collision_all",
        "p_collision_focused",
        "mahalanobis_all",
        "mahalanobis_focused",
    ):
        assert len(risk[col]) == poses, col
    assert all(len(s) == 4 for s in risk["sigma_star"])
    assert np.all(np.diff(risk["stamp_ns"]) >= 0)
    clearance = np.array(risk["clearance_m"])
    assert 0.3 < np.nanmin(clearance) < 1.0  # the robot keeps about 0.45 m from the walls
    p_f, p_a = np.array(risk["p_collision_focused"]), np.array(risk["p_collision_all"])
    assert summary["p_collision_max_focused"] == pytest.approx(p_f.max(), rel=1e-9)
    assert summary["p_collision_max_all"] <= summary["p_collision_max_focused"] <= summary["p_collision_max_none"]
    assert np.all(np.isfinite(p_a)) and np.all((p_f >= 0) & (p_f <= 1))
    assert focused["scores"][-1] == pytest.approx(p_f.max(), rel=1e-6)  # collision score: max P after the pick

    rows, steps = rrd_rows(run.rrd_path("select_landmarks"))
    for entity in (
        "/select_landmarks/path",
        "/select_landmarks/path_all",
        "/select_landmarks/obstacles",
        "/select_landmarks/sigma_star",
        "/select_landmarks/landmarks/selected",
        "/select_landmarks/landmarks/unselected",
        "/select_landmarks/summary",
        "/select_landmarks/risk/all",
        "/select_landmarks/risk/focused",
    ):
        assert rows[entity] >= 1, entity
    assert steps["/select_landmarks/pick"] == budget  # one pick per greedy step
    assert steps["/select_landmarks/path"] == budget + 1  # step 0 (nothing picked) and after every pick
    assert steps["/select_landmarks/max_collision_log10"] == budget + 1


def test_collision_focuses_on_corridor_and_door(inputs: LandmarkInputs) -> None:
    """Mu et al.'s claim on the sample: the budget goes to the narrow passages, and the max risk drops most."""
    region = region_of_tags()
    budget = 15
    all_tags = [int(t) for t in inputs.landmarks.tag_ids]
    share_all = np.mean([region[t] != "room" for t in all_tags])
    results = {}
    for strategy in ("collision", "uniform", "random"):
        c = choose(inputs, SelectLandmarksConfig(strategy=strategy, budget=budget))
        assert c.risk_focused is not None
        share = np.mean([region[t] != "room" for t in c.tag_ids])
        results[strategy] = (share, c.risk_focused.max, c.risk_focused.min_z)
    print(f"\nshare of corridor+door: all landmarks {share_all:.2f} ({len(all_tags)})")
    for k, (share, mx, z) in results.items():
        print(f"{k:10s} budget {budget}: share {share:.2f}  max P {mx:.3g}  smallest margin {z:.1f} sigma")
    assert results["collision"][0] > max(share_all, results["uniform"][0], results["random"][0])
    # the riskiest step's margin in sigma (P = Phi(-z) underflows here): collision's is the widest
    assert results["collision"][2] > results["uniform"][2]
    assert results["collision"][2] > results["random"][2]


def test_budget_edges(office_run: Path, tmp_path: Path) -> None:
    run = copy_run(office_run, tmp_path)
    s = run_select(run, "select_landmarks", ["select_landmarks.budget=0"])
    focused = json.loads((run.stage_dir("select_landmarks") / "focused.json").read_text())
    assert s["status"] == "budget_zero" and focused["tag_ids"] == [] and "budget 0" in s["message"]
    assert s["p_collision_max_focused"] == pytest.approx(s["p_collision_max_none"])
    s = run_select(
        run,
        "select_landmarks",
        ["select_landmarks.budget=500", "select_landmarks.strategy=uniform", "select_landmarks.max_replay_steps=3"],
    )
    focused = json.loads((run.stage_dir("select_landmarks") / "focused.json").read_text())
    assert s["status"] == "budget_exceeds_landmarks" and len(focused["tag_ids"]) == s["landmarks"]
    assert "exceeds" in s["message"]


def test_strategies_by_api(inputs: LandmarkInputs) -> None:
    n = len(inputs.landmarks.tag_ids)
    for strategy in ("mutual-information", "leverage", "uniform", "random"):
        c = choose(inputs, SelectLandmarksConfig(strategy=strategy, budget=6, leverage_draws=1), with_risk=False)
        assert c.status == "ok" and len(set(c.tag_ids)) == 6, strategy
    c = choose(inputs, SelectLandmarksConfig(strategy="all"), with_risk=False)
    assert sorted(c.tag_ids) == sorted(int(t) for t in inputs.landmarks.tag_ids) and c.budget == n
    a = choose(inputs, SelectLandmarksConfig(strategy="random", budget=6, seed=3), with_risk=False)
    b = choose(inputs, SelectLandmarksConfig(strategy="random", budget=6, seed=3), with_risk=False)
    assert a.tag_ids == b.tag_ids
    gains = choose(inputs, SelectLandmarksConfig(strategy="mutual-information", budget=6), with_risk=False).scores
    assert all(g1 >= g2 - 1e-9 for g1, g2 in itertools.pairwise(gains))  # submodular: gains fall


@pytest.mark.parametrize("strategy", ["mutual-information", "leverage", "collision"])
def test_a_budget_at_or_above_the_landmarks_takes_them_all_without_a_greedy(
    inputs: LandmarkInputs, strategy: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Budget ≥ landmarks: every landmark, at once (the greedy would end with the same set after L steps, each of
    which costs a dense update of the trajectory information: minutes on a 3D graph)."""
    import stages.select_landmarks.core as core

    def no_greedy(*args: object, **kwargs: object) -> None:
        raise AssertionError("the greedy ran")

    for name in ("select_mutual_information", "select_landmark_leverage", "collision_greedy"):
        monkeypatch.setattr(core, name, no_greedy)
    n = len(inputs.landmarks.tag_ids)
    for budget, status in ((n, "ok"), (n + 5, "budget_exceeds_landmarks")):
        c = choose(inputs, SelectLandmarksConfig(strategy=strategy, budget=budget), with_risk=False)
        assert sorted(c.tag_ids) == sorted(int(t) for t in inputs.landmarks.tag_ids)
        assert c.status == status, c.message


def test_visibility_window_and_no_laser(inputs: LandmarkInputs) -> None:
    loaded = inputs.loaded
    narrow = path_geometry(loaded, None, None, None, RiskParams(visibility_window_s=0.0))
    assert not narrow.has_laser and np.all(np.isnan(narrow.clearance_m))
    assert narrow.visible.sum() <= inputs.geometry.visible.sum()
    no_laser = LandmarkInputs.from_pieces(loaded, None)
    with pytest.raises(StageError, match=r"needs laser scans.*mutual-information"):
        choose(no_laser, SelectLandmarksConfig(strategy="collision", budget=3))


def test_import_graph_run(office_run: Path, tmp_path: Path) -> None:
    """A run made by import-graph (graph only): non-collision strategies work, collision says why it cannot."""
    from tests.fixtures.graphs import import_graph

    run_dir = import_graph(office_run / "graph" / "graph.g2o", tmp_path, "imported")
    run = RunFolder(run_dir)
    s = run_select(run, "select_landmarks", ["select_landmarks.strategy=uniform", "select_landmarks.budget=5"])
    assert s["status"] == "ok" and s["laser"] is False and "note" in s
    risk = pq.read_table(run.stage_dir("select_landmarks") / "risk.parquet").to_pydict()
    assert np.all(np.isnan(risk["p_collision_focused"]))
    with pytest.raises(StageError, match="import-graph"):
        run_select(run, "select_landmarks", ["select_landmarks.strategy=collision"])
    # the failed run left the earlier result whole
    assert json.loads((run.stage_dir("select_landmarks") / "focused.json").read_text())["strategy"] == "uniform"


def test_alg2_on_the_sample_equals_the_reference(inputs: LandmarkInputs) -> None:
    """Alg. 2 on the sample's path (the robot model's steps, the recording's visibility and laser margins) picks as
    the one-candidate-at-a-time Kalman reference does; the local covariances are never wider than the marginals."""
    from stages.risk import step_margins
    from stages.select_landmarks.core import collision_greedy
    from tests.oracles.collision import select_collision_reference

    geo, params = inputs.geometry, inputs.params
    lm = dataclasses.replace(inputs.landmarks, local=None, joint=None)
    fast = collision_greedy(geo, lm, 3, params)
    col = {int(t): c for c, t in enumerate(geo.tag_ids)}
    visible = geo.visible[geo.steps.keyframe][:, [col[int(t)] for t in lm.tag_ids]]
    margin, normals = step_margins(geo, params)
    slow = select_collision_reference(
        geo.noise.A,
        geo.noise.Q,
        geo.noise.P0,
        geo.steps.poses,
        lm.positions,
        lm.covariances,
        visible,
        margin,
        normals,
        3,
        geo.sigmas,
    )
    assert fast.picks == slow.picks
    np.testing.assert_allclose(fast.extra["z_after"], slow.extra["z_after"], rtol=1e-6)
    local = inputs.landmarks
    assert local.local is not None and local.joint is not None
    held = local.local
    assert len(held.rows) > 0 and np.isfinite(held.covariances).all()
    seen = {
        (int(t), r)
        for r, tag in enumerate(local.tag_ids.tolist())
        for t in np.flatnonzero(geo.visible[:, col[int(tag)]])
    }
    assert set(zip(held.keyframes.tolist(), held.rows.tolist(), strict=True)) == seen  # every pair the path sees
    r = held.rows
    tr_local = np.trace(held.covariances, axis1=1, axis2=2)
    tr_marg = np.trace(local.covariances[r], axis1=1, axis2=2)
    print(f"local / marginal trace: median {np.median(tr_local / tr_marg):.3f}")
    assert np.all(tr_local <= tr_marg * (1 + 1e-6))  # conditioning never adds uncertainty
    assert np.median(tr_local / tr_marg) < 0.9


def test_auto_runs_collision_with_laser_and_mutual_information_or_uniform_without(inputs: LandmarkInputs) -> None:
    """The default strategy needs no second run on a camera-only recording: collision where the run has laser
    scans, mutual information without, uniform when the trajectory is too long for mutual information; each the
    same pick as the strategy set by hand."""
    from stages.select_landmarks.core import auto_strategy

    with_laser = choose(inputs, SelectLandmarksConfig(budget=3), with_risk=False)
    by_hand = choose(inputs, SelectLandmarksConfig(strategy="collision", budget=3), with_risk=False)
    assert with_laser.strategy == "collision" and with_laser.tag_ids == by_hand.tag_ids
    no_laser = LandmarkInputs.from_pieces(inputs.loaded, None)
    mi = choose(no_laser, SelectLandmarksConfig(budget=3), with_risk=False)
    assert mi.strategy == "mutual-information"
    assert mi.tag_ids == choose(no_laser, SelectLandmarksConfig(strategy="mutual-information", budget=3)).tag_ids
    short = SelectLandmarksConfig(budget=3, max_trajectory_dim=10)
    uniform = choose(no_laser, short, with_risk=False)
    assert uniform.strategy == "uniform"
    assert uniform.tag_ids == choose(no_laser, short.model_copy(update={"strategy": "uniform"})).tag_ids
    assert "max_trajectory_dim=10" in auto_strategy(no_laser, short)[1]
