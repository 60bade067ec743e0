"""evaluate on a run with neither a laser nor a ground truth (a camera-only recording: nothing for the simulated robot
to collide with) ends like any other run, with one note that the navigation was skipped and why, instead of stopping
after six good stages; the headline says in words what was not computed."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipeline.config import load_settings
from pipeline.errors import StageError
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages.evaluate import headline_text, remarks, report_lines
from tests.fixtures.upstream import STAGES, seed_upstream, stand_in_registry

SMALL = (
    "select_landmarks.budget=5",
    "select_measurements.budget=15",
    "evaluate.extra_pairs=[]",
    "evaluate.plots=false",
    "evaluate.focused_poses=0",
)


def _no_walls_run(folder: Path) -> RunFolder:
    """The synthetic run (odometry and tags) without laser scans and without a ground truth beside its bag."""
    from tests.fixtures.synthetic_runs import synthetic_run

    source = folder / "run.bag"
    source.write_bytes(b"")
    run = RunFolder.create(folder / "run", source)
    seed_upstream(run, synthetic_run(seed=7, loops=0.5))
    return run


def _run_through(run: RunFolder, *overrides: str) -> dict:
    reg = stand_in_registry()
    settings = load_settings(reg.models(), overrides=[*SMALL, *overrides])
    result = None
    for name in STAGES:
        result = run_stage(run, reg, name, settings)
    assert result is not None and result.stage == "evaluate" and result.status == "done"
    return json.loads((run.stage_dir("evaluate") / "summary.json").read_text())


@pytest.fixture(scope="module")
def no_walls(tmp_path_factory: pytest.TempPathFactory) -> RunFolder:
    run = _no_walls_run(tmp_path_factory.mktemp("nowalls"))
    _run_through(run)  # evaluate.trials left at its default (100): no walls is not the user's request to navigate
    return run


def test_a_run_without_walls_finishes_evaluate_with_one_note(no_walls: RunFolder) -> None:
    text = (no_walls.stage_dir("evaluate") / "summary.json").read_text()
    summary = json.loads(text, parse_constant=lambda c: pytest.fail(f"summary.json holds {c}"))
    notes = [t for label, t in remarks(summary) if label == "note"]
    nav = [t for t in notes if "navigation" in t]
    assert len(nav) == 1, notes
    assert "not simulated" in nav[0] and "no laser scans and no ground truth" in nav[0] and "--truth" in nav[0]
    assert summary["navigation_skipped"] == "no walls" and summary["trials"] == 0
    # no figure of the headline is NaN: what was not computed is null, and the printed headline says it in words
    head = summary["headline"]
    assert math.isfinite(head["focused_entropy"]) and math.isfinite(head["focused_error_m"])
    assert head["collision_rate"] is None and head["max_collision_probability"] is None
    printed = report_lines(summary)
    assert "nan" not in " ".join(printed).lower()
    assert any("navigation not simulated (no walls)" in line for line in printed)


def test_a_run_without_walls_writes_the_report_and_the_cases(no_walls: RunFolder) -> None:
    out = no_walls.stage_dir("evaluate")
    md = (out / "report.md").read_text()
    assert (out / "report.html").is_file()
    assert "Navigation not simulated (no walls)" in md and "no laser scans and no ground truth" in md
    assert "nan" not in md.split("## ", 1)[0].lower()  # the table and the headline above the sections
    rows = pq.read_table(out / "cases.parquet").to_pylist()
    assert [r["case"] for r in rows][:6] == ["optimal", "focus_all", "focus_info", "focus_ds", "full_info", "full_ds"]
    for r in rows:  # what does not need walls is there; the navigation columns are null, not NaN
        assert math.isfinite(r["focused_entropy"]) and math.isfinite(r["error_all_m"]) and r["map_bytes"] > 0
        for col in ("collision_rate", "collision_ci_low", "collision_ci_high", "collisions", "navigation_nees"):
            assert r[col] is None, col
        assert r["trials"] == 0


def test_walls_asked_for_by_name_and_missing_stop_the_stage(tmp_path: Path) -> None:
    """``evaluate.walls=laser`` is the user's request for the laser's walls: on a run without scans it is an error
    that says so, not a silent skip."""
    run = _no_walls_run(tmp_path)
    with pytest.raises(StageError, match=r"evaluate.walls=laser but the run has no laser scans; give walls with"):
        _run_through(run, "evaluate.walls=laser")


def test_the_headline_names_what_was_not_computed() -> None:
    head = {
        "case": "focus_info",
        "focused_entropy": -10.0,
        "focused_error_m": float("nan"),
        "max_collision_probability": None,
        "collision_rate": float("nan"),
        "collision_ci_low": None,
        "collision_ci_high": None,
    }
    line = headline_text(head, "evaluate.trials=0")
    assert "nan" not in line.lower()
    assert "focused error not computed" in line and "max P(collision) not computed" in line
    assert line.endswith("navigation not simulated (evaluate.trials=0)")
