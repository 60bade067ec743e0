"""select_measurements on the office sample: artifacts, recording, edge cases, and fast == reference greedy."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.artifacts import StageInput
from pipeline.errors import StageError
from pipeline.run_folder import RunFolder
from stages.estimation.linear_system import Factor, LinearSystem
from stages.estimation.measurement_selection import focused_entropy, select_information
from stages.graph.load import load_graph
from stages.select_measurements import SelectMeasurementsConfig, choose, focused_variables, linear_system
from stages.select_measurements.core import base_information, focused_covariances
from tests.fixtures.office import copy_run, rrd_rows, run_select
from tests.fixtures.shared_data import need_shared
from tests.oracles.measurement_selection import reference_greedy


@pytest.fixture(scope="module")
def loaded(office_run: Path):
    """The office run's full graph."""
    return load_graph(StageInput("graph", office_run / "graph"))


@pytest.fixture(scope="module")
def system(loaded):
    """The full graph linearised at its solution."""
    return linear_system(loaded)


def _selected_run(office_run: Path, tmp_path: Path, budget: int = 8) -> RunFolder:
    run = copy_run(office_run, tmp_path)
    run_select(run, "select_landmarks", [f"select_landmarks.budget={budget}", "select_landmarks.max_replay_steps=0"])
    return run


def test_stage_outputs_and_recording(office_run: Path, tmp_path: Path, loaded, system) -> None:
    run = _selected_run(office_run, tmp_path)
    K = 25
    s = run_select(run, "select_measurements", [f"select_measurements.budget={K}"])
    focused = json.loads((run.stage_dir("select_landmarks") / "focused.json").read_text())["tag_ids"]
    table = pq.read_table(run.stage_dir("select_measurements") / "selected.parquet").to_pydict()
    assert table["step"] == list(range(K)) and len(set(table["factor_index"])) == K
    assert all(loaded.rows[i].kind == "tag" and loaded.rows[i].tag_id in focused for i in table["factor_index"])
    assert table["tag_id"] == [loaded.rows[i].tag_id for i in table["factor_index"]]
    assert s["strategy"] == "information" and s["budget"] == K and s["status"] == "ok"
    assert s["candidates"] == sum(1 for r in loaded.rows if r.kind == "tag" and r.tag_id in focused)
    assert s["entropy_after"] < s["entropy_before"]
    # the exact entropy after the picks, and the running one's drift from it: small on the sample (no warning)
    assert abs(s["entropy_drift_nats"]) < 0.05 and "warnings" not in s
    assert s["entropy_before"] - s["entropy_after"] - s["entropy_drift_nats"] == pytest.approx(sum(table["gain"]))
    base = [int(i) for i in loaded.fixed_factor_indices]
    fv = focused_variables(loaded, system, focused)
    assert focused_entropy(system, base + table["factor_index"], fv) == pytest.approx(s["entropy_after"], abs=1e-3)
    assert focused_entropy(system, base, fv) == pytest.approx(s["entropy_before"], abs=1e-6)
    assert s["factors_kept"] == len(base) + K

    rows, steps = rrd_rows(run.rrd_path("select_measurements"))
    for entity in (
        "/select_measurements/path",
        "/select_measurements/candidates",
        "/select_measurements/kept",
        "/select_measurements/landmarks/focused",
        "/select_measurements/summary",
    ):
        assert rows[entity] >= 1, entity
    assert steps["/select_measurements/pick"] == K
    assert steps["/select_measurements/entropy"] == K + 1  # before the first pick and after every pick
    assert steps["/select_measurements/gain"] == K
    assert steps["/select_measurements/landmarks/focused"] >= 2  # ellipsoids shrink over the replayed steps


def test_budget_edges_and_missing_stage_one(office_run: Path, tmp_path: Path) -> None:
    run = copy_run(office_run, tmp_path)
    with pytest.raises(StageError, match="focusmap select-landmarks"):
        run_select(run, "select_measurements", [])
    assert not run.stage_dir("select_measurements").exists()
    run_select(run, "select_landmarks", ["select_landmarks.budget=0", "select_landmarks.max_replay_steps=0"])
    with pytest.raises(StageError, match="no focused landmarks"):
        run_select(run, "select_measurements", [])
    run_select(run, "select_landmarks", ["select_landmarks.budget=3", "select_landmarks.max_replay_steps=0"])
    s = run_select(run, "select_measurements", ["select_measurements.budget=0"])
    assert s["status"] == "budget_zero" and s["selected"] == 0 and "budget 0" in s["message"]
    assert s["entropy_after"] == pytest.approx(s["entropy_before"])
    s = run_select(
        run, "select_measurements", ["select_measurements.budget=100000", "select_measurements.max_replay_steps=2"]
    )
    assert s["status"] == "budget_exceeds_candidates" and s["selected"] == s["candidates"] and "all" in s["message"]


def test_focus_all_without_stage_one(office_run: Path, tmp_path: Path) -> None:
    run = copy_run(office_run, tmp_path)
    s = run_select(
        run,
        "select_measurements",
        [
            "select_measurements.focus=all",
            "select_measurements.strategy=uniform",
            "select_measurements.budget=30",
            "select_measurements.max_replay_steps=2",
        ],
    )
    graph_summary = json.loads((run.stage_dir("graph") / "summary.json").read_text())
    assert s["focus"] == "all" and s["focused_landmarks"] == graph_summary["landmarks"]
    assert s["candidates"] == graph_summary["tag_measurements"]
    assert s["selected"] == 30 and s["entropy_after"] < s["entropy_before"]


def test_strategies_by_api(loaded, system) -> None:
    focused = sorted(loaded.landmark_keys)[:6]
    K = 12
    out = {}
    for strategy in ("information", "leverage", "uniform", "random", "all"):
        c = choose(loaded, focused, SelectMeasurementsConfig(strategy=strategy, budget=K, leverage_draws=2), system)
        out[strategy] = c
        assert len(set(c.factor_indices)) == (c.n_candidates if strategy == "all" else K), strategy
        assert set(c.factor_indices) <= set(c.candidates)
        assert c.entropy_after < c.entropy_before
    print(
        "\nfocused entropy after K=12 of",
        out["all"].n_candidates,
        "candidates (6 landmarks):",
        {k: round(v.entropy_after, 2) for k, v in out.items()},
    )
    for strategy in ("leverage", "uniform", "random"):
        assert out["information"].entropy_after <= out[strategy].entropy_after + 1e-9
    keep = out["information"].keep_factor_indices(loaded)
    assert len(keep) == len(loaded.fixed_factor_indices) + K


def test_fast_information_equals_reference_on_sample_subgraph(loaded, system) -> None:
    """Fast greedy == dense reference (same picks, order, gains) on the first 40 keyframes of the sample."""
    n = 40
    poses = {system.index_of_key(k) for k in loaded.pose_keys[:n]}
    if loaded.scale_key is not None:  # the shared tag scale joins every tag factor; keep its prior with them
        poses.add(system.index_of_key(loaded.scale_key))
    base_full = [int(i) for i in loaded.fixed_factor_indices if set(system.factors[int(i)].variables) <= poses]
    cand_full = [int(i) for i in loaded.tag_factor_indices if system.factors[int(i)].variables[0] in poses]
    # the sub-graph as its own small system, so the dense reference stays small
    used = sorted({v for f in base_full + cand_full for v in system.factors[f].variables})
    remap = {v: k for k, v in enumerate(used)}
    factors = [
        Factor(tuple(remap[v] for v in system.factors[f].variables), system.factors[f].jacobian, system.factors[f].kind)
        for f in base_full + cand_full
    ]
    sub = LinearSystem([system.variables[v] for v in used], factors)
    base = list(range(len(base_full)))
    cands = list(range(len(base_full), len(factors)))
    lms = sorted({sub.factors[c].variables[1] for c in cands})
    focused = lms[: max(2, len(lms) // 2)]
    budget = 8
    system = sub
    fast = select_information(system, cands, focused, budget, base)
    ref_picks, ref_gains = reference_greedy(system, cands, focused, budget, base)
    assert fast.picks == ref_picks
    np.testing.assert_allclose(fast.gains, ref_gains, rtol=1e-6, atol=1e-8)


def test_replay_with_the_base_information_assembled_once(loaded, system) -> None:
    """focused_covariances with the base's information assembled once (the replay) == assembled every step."""
    choice = choose(loaded, sorted(loaded.landmark_keys)[:5], SelectMeasurementsConfig(budget=6), system)
    focused = focused_variables(loaded, system, choice.focused_tag_ids)
    base = [int(i) for i in loaded.fixed_factor_indices]
    base_info = base_information(system, base, 100.0)
    for k in (0, 3, 6):
        picks = choice.factor_indices[:k]
        blocks, h = focused_covariances(system, base, picks, focused, 100.0)
        once, h_once = focused_covariances(system, base, picks, focused, 100.0, base_info=base_info)
        assert h_once == pytest.approx(h, abs=1e-9)
        for a, b in zip(blocks, once, strict=True):
            np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)
    assert h_once == pytest.approx(choice.entropy_after, abs=1e-6)


def test_example_1_with_its_tag_surveyed_to_a_centimetre_and_a_radian_selects_and_optimises(tmp_path: Path) -> None:
    """TagSLAM's example_1 (one camera, no odometry, the poses hung on tag 0 of the surveyed body) with the body's and
    the tag's pose noise at 1e-2 m and 1 rad (the file has 1e-4 m and 1e-5 rad): select_measurements keeps 200 of
    the 758 candidates without an internal error and without the drift warning (its running entropy within 1e-3
    nats of the exact one), and optimize's marginals are finite and positive definite. The stage stopped with
    "internal error LinAlgError: Matrix is not positive definite" there (and drifted -70.9 nats with the file's
    own noise at the default budget)."""
    import subprocess
    import sys

    import yaml

    folder = need_shared("tagslam-examples/example_1")
    config = yaml.safe_load((folder / "config" / "tagslam.yaml").read_text())
    perch = next(b["perch"] for b in config["bodies"] if "perch" in b)
    for pose in [perch["pose"], *(t["pose"] for t in perch["tags"])]:
        pose["position_noise"] = {"x": 1e-2, "y": 1e-2, "z": 1e-2}
        pose["rotation_noise"] = {"x": 1.0, "y": 1.0, "z": 1.0}
    tags = tmp_path / "tagslam.yaml"
    tags.write_text(yaml.safe_dump(config))
    root = Path(__file__).resolve().parents[2]
    cmd = [
        *(sys.executable, "-m", "cli.app", "run", str(folder / "tag_detections.bag"), "--out", str(tmp_path / "runs")),
        *("--name", "ex1", "--until", "optimize", "--camera", str(folder / "config" / "cameras.yaml")),
        *("--extrinsics", str(folder / "config" / "camera_poses.yaml"), "--tags", str(tags)),
        *("--set", "select_measurements.budget=200"),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=root)
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = tmp_path / "runs" / "ex1"
    s = json.loads((run / "select_measurements" / "summary.json").read_text())
    assert s["selected"] == 200 and s["candidates"] == 758
    assert abs(s["entropy_drift_nats"]) < 1e-3 and "warnings" not in s
    marginals = np.load(run / "optimize" / "marginals.npz")
    for cov, dim in zip(marginals["covariance"], marginals["dims"], strict=True):
        block = cov[:dim, :dim]
        assert np.all(np.isfinite(block)) and np.linalg.eigvalsh(0.5 * (block + block.T)).min() > 0
