"""A run folder keeps its settings; the tag size re-runs detect and what follows; import-graph goes through the runner.

On a 6-second slice of the bundled office bag (about 30 frames), through the command line in-process.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli.app import app
from pipeline.run_folder import RunFolder

ROOT = Path(__file__).resolve().parents[2]
BAG = ROOT / "sample_data" / "office" / "office.bag"


def focusmap(*args: str | Path) -> str:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


def statuses(output: str) -> dict[str, str]:
    """Stage name to 'done' or 'skipped' from the printed result lines."""
    out = {}
    for line in output.splitlines():
        parts = line.split()
        if parts and parts[0] in ("ingest", "detect", "graph", "select_landmarks"):
            out[parts[0]] = "skipped" if "up to date" in line else "done"
    return out


@pytest.fixture(scope="module")
def sliced(tmp_path_factory) -> Path:
    """``OUT``, with ``OUT/office`` made by ``run --until detect --end 6 --set detect.tag_size_m=0.2``."""
    out = tmp_path_factory.mktemp("sticky")
    text = focusmap("run", BAG, "--out", out, "--until", "detect", "--end", "6", "--set", "detect.tag_size_m=0.2")
    assert statuses(text) == {"ingest": "done", "detect": "done"}
    assert "settings:" not in text  # a new folder: nothing stored to compare with
    return out


def test_a_second_run_keeps_the_folders_settings_and_says_so(sliced: Path) -> None:
    text = focusmap("run", BAG, "--out", sliced, "--until", "detect")
    assert statuses(text) == {"ingest": "skipped", "detect": "skipped"}
    kept = [line for line in text.splitlines() if line.startswith("settings: keeping")]
    assert len(kept) == 1 and "detect.tag_size_m=0.2" in kept[0] and "ingest.end_s=6.0" in kept[0]
    stored = json.loads((sliced / "office" / "settings.json").read_text())
    assert stored["detect"]["tag_size_m"] == 0.2


def test_the_tag_size_reruns_detect_and_what_follows_and_the_change_is_printed(sliced: Path) -> None:
    run = RunFolder(sliced / "office")
    focusmap("run", BAG, "--out", sliced, "--until", "graph")
    z_small = json.loads((run.stage_dir("graph") / "summary.json").read_text())
    text = focusmap("run", BAG, "--out", sliced, "--until", "graph", "--set", "detect.tag_size_m=0.4")
    assert "settings: detect.tag_size_m 0.2 -> 0.4 (--set)" in text.splitlines()
    assert statuses(text) == {"ingest": "skipped", "detect": "done", "graph": "done"}
    assert run.stage_entry("detect")["settings"]["tag_size_m"] == 0.4
    assert json.loads((run.stage_dir("graph") / "summary.json").read_text()) != z_small
    # back to the defaults: the change is printed as well
    text = focusmap("run", BAG, "--out", sliced, "--until", "detect", "--reset-settings", "--end", "6")
    assert "settings: detect.tag_size_m 0.4 -> 0.162 (defaults)" in text.splitlines()
    assert not any(line.startswith("settings: ingest") for line in text.splitlines())
    assert statuses(text) == {"ingest": "skipped", "detect": "done"}


def test_a_setting_of_a_stage_the_command_does_not_run_is_said_to_be_unused(sliced: Path) -> None:
    focusmap("run", BAG, "--out", sliced, "--until", "select-landmarks", "--end", "6")
    text = focusmap("graph", sliced / "office", "--set", "select_landmarks.budget=3")
    assert any(
        line.startswith("settings: select_landmarks.budget 30 -> 3 (--set); not used") for line in text.splitlines()
    )
    stored = json.loads((sliced / "office" / "settings.json").read_text())
    assert stored["select_landmarks"]["budget"] == 30  # what its artifacts were made with


def test_run_until_does_not_print_an_older_evaluate(sliced: Path) -> None:
    run = RunFolder(sliced / "office")
    run.stage_dir("evaluate").mkdir(exist_ok=True)
    head = {"case": "focus_info", "focused_entropy": 1.0, "focused_error_m": 0.1}
    run.record("evaluate", {"fingerprint": "old", "summary": {"report": "old/report.html", "headline": head}})
    text = focusmap("run", BAG, "--out", sliced, "--until", "detect")
    assert "report:" not in text and "headline" not in text


G2O = """VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 0
VERTEX_SE2 2 2 0 0
EDGE_SE2 0 1 1 0 0 100 0 0 100 0 100
EDGE_SE2 1 2 1 0 0 100 0 0 100 0 100
EDGE_SE2 0 2 2.1 0 0 100 0 0 100 0 100
"""


def test_import_graph_goes_through_the_runner(tmp_path: Path) -> None:
    graph_file = tmp_path / "tiny.g2o"
    graph_file.write_text(G2O)
    out = tmp_path / "runs"
    first = focusmap("import-graph", graph_file, "--out", out)
    assert "graph" in first and "up to date" not in first
    run = RunFolder(out / "tiny")
    entry = run.stage_entry("graph")
    assert entry["fingerprint"] and entry["source"]["kind"] == "graph" and entry["inputs"] == {}
    assert entry["summary"]["imported_from"] == str(graph_file.resolve())
    assert (run.path / "graph.rrd").is_file()
    assert "up to date" in focusmap("import-graph", graph_file, "--out", out)
    graph_file.write_text(G2O.replace("2.1 0 0", "1.9 0 0"))  # the file changed: the stage re-runs
    again = focusmap("import-graph", graph_file, "--out", out)
    assert "up to date" not in again
    assert run.stage_entry("graph")["fingerprint"] != entry["fingerprint"]
