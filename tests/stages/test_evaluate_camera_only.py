"""evaluate on a run without laser whose trajectory is too long for mutual information (TagSLAM's test_14:
2,417 poses in 3D): the focus every case is scored on falls back to the user's own landmark pick, with a warning,
instead of stopping the stage (before, such a run could not be evaluated with any setting but a raised limit)."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.run_folder import RunFolder
from tests.fixtures.office import run_select


def test_a_camera_only_run_above_the_mutual_information_limit_is_scored_on_its_own_pick(
    office_run: Path, tmp_path: Path
) -> None:
    from tests.fixtures.graphs import import_graph

    run = RunFolder(import_graph(office_run / "graph" / "graph.g2o", tmp_path, "imported"))
    small = ["select_landmarks.max_trajectory_dim=10", "select_landmarks.budget=5"]
    picked = run_select(run, "select_landmarks", ["select_landmarks.strategy=uniform", *small])
    assert picked["status"] == "ok"
    tags = json.loads((run.stage_dir("select_landmarks") / "focused.json").read_text())["tag_ids"]
    run_select(run, "select_measurements", small)
    run_select(run, "optimize", small)
    s = run_select(run, "evaluate", [*small, "evaluate.trials=0", "evaluate.realisations=0"])
    assert s["focused_tag_ids"] == tags
    focus_lines = [w for w in s["warnings"] if w.startswith("focus:")]
    assert len(focus_lines) == 1 and "no laser" in focus_lines[0] and "uniform pick" in focus_lines[0]
    assert "select_landmarks.max_trajectory_dim=10" in focus_lines[0]
    # the extra pairs on the dense information are skipped with their own lines, the Table I cases all ran
    assert any(w.startswith("case mutual-information+information skipped") for w in s["warnings"])
    assert {"focus_info", "focus_all", "full_info"} <= set(s["cases"])
