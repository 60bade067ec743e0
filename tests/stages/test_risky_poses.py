"""Focused poses (Mu et al. eq. 23 with W beyond the landmarks): the riskiest keyframes' poses join the focused set."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.artifacts import StageInput
from pipeline.errors import StageError
from stages.estimation.measurement_selection import focused_entropy
from stages.graph.load import load_graph
from stages.risk import riskiest_keyframes
from stages.select_measurements import SelectMeasurementsConfig, choose, focused_variables, linear_system
from tests.fixtures.office import copy_run, run_select


def test_riskiest_keyframes_keep_apart_and_skip_the_unknown() -> None:
    stamps = (np.arange(10) * 0.5e9).astype(np.int64)
    maha = np.array([9.0, 1.0, 1.5, 8.0, np.inf, 0.5, 7.0, 3.0, np.inf, 2.0])
    # by eq. 20: 5 (0.5), 1 (1.0), then 2 (1.5) is within 1 s of 1, so 9 (2.0)
    assert riskiest_keyframes(maha, stamps, 3, 1.0) == [1, 5, 9]
    assert riskiest_keyframes(maha, stamps, 10, 0.0) == [0, 1, 2, 3, 5, 6, 7, 9]  # never the inf ones
    assert riskiest_keyframes(maha, stamps, 0, 1.0) == []


def test_focused_poses_change_what_is_kept_and_the_entropy_covers_them(office_run: Path, tmp_path: Path) -> None:
    """With the riskiest keyframes' poses focused, the greedy keeps measurements that also localise those poses:
    their entropy is lower than with the landmarks alone at the same budget, and the run records which poses."""
    run = copy_run(office_run, tmp_path)
    run_select(run, "select_landmarks", ["select_landmarks.budget=10", "select_landmarks.max_replay_steps=0"])
    plain = run_select(run, "select_measurements", ["select_measurements.budget=20"])
    plain_idx = pq.read_table(run.stage_dir("select_measurements") / "selected.parquet").column("factor_index")
    s = run_select(run, "select_measurements", ["select_measurements.budget=20", "select_measurements.focus_poses=5"])
    sel = json.loads((run.stage_dir("select_measurements") / "selection.json").read_text())
    poses = sel["focused_pose_indices"]
    assert len(poses) == 5 and poses == sorted(poses) and s["status"] == "ok"
    risk = pq.read_table(run.stage_dir("select_landmarks") / "risk.parquet").to_pydict()
    maha = np.asarray(risk["mahalanobis_focused"])
    assert maha[poses].max() <= np.sort(maha[np.isfinite(maha)])[40]  # among the riskiest
    kept = pq.read_table(run.stage_dir("select_measurements") / "selected.parquet").column("factor_index").to_pylist()
    assert kept != plain_idx.to_pylist()
    loaded = load_graph(StageInput("graph", run.path / "graph"))
    system = linear_system(loaded)
    tags = sel["focused_tag_ids"]
    pose_vars = [system.index_of_key(loaded.pose_keys[i]) for i in poses]
    base = [int(i) for i in loaded.fixed_factor_indices]
    h_with = focused_entropy(system, base + kept, pose_vars)
    h_plain = focused_entropy(system, base + plain_idx.to_pylist(), pose_vars)
    assert h_with < h_plain  # the risky poses are better localised
    both = focused_variables(loaded, system, tags) + pose_vars
    assert focused_entropy(system, base + kept, both) == pytest.approx(s["entropy_after"], abs=1e-3)
    assert plain["entropy_after"] != s["entropy_after"]


def test_focused_poses_need_the_risk(office_run: Path, tmp_path: Path) -> None:
    run = copy_run(office_run, tmp_path)
    with pytest.raises(StageError, match="focus_poses"):
        run_select(run, "select_measurements", ["select_measurements.focus_poses=3", "select_measurements.focus=all"])
    loaded = load_graph(StageInput("graph", run.path / "graph"))
    choice = choose(loaded, None, SelectMeasurementsConfig(focus="all", budget=5), focus_pose_indices=[3, 40])
    assert choice.focused_pose_indices == [3, 40] and len(choice.factor_indices) == 5
