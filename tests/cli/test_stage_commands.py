"""The stage commands are built from the registry: each stage's options set its settings, and its result is
printed the way the stage says (in this process, with the stage runs replaced by recorders)."""

from __future__ import annotations

import contextlib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from typer.testing import CliRunner

import cli.app as cli_app
from pipeline.runner import StageResult
from stages import REGISTRY


@pytest.fixture
def recorded(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> dict[str, Any]:
    """What the commands would run: stage names and settings, instead of running them."""
    seen: dict[str, Any] = {}

    def run_stages(run: Any, names: list[str], settings: Any, force: bool) -> list[Any]:
        seen.update(names=names, settings=settings, force=force)
        return []

    def run_on_bag(bag: Path, out: Path, name: str | None, stages: list[str], settings: Any, force: bool) -> Any:
        seen.update(bag=bag, names=stages, settings=settings, force=force)
        return SimpleNamespace(path=out / "run", stage_entry=lambda name: None), []

    monkeypatch.setattr(cli_app, "_run_stages", run_stages)
    monkeypatch.setattr(cli_app, "_run_on_bag", run_on_bag)
    monkeypatch.setattr(cli_app, "_open_run", lambda run_dir: SimpleNamespace(path=run_dir))
    monkeypatch.setattr(cli_app, "_locked_run", lambda run_dir: contextlib.nullcontext(SimpleNamespace(path=run_dir)))
    return seen


def invoke(*args: str) -> Any:
    return CliRunner().invoke(cli_app.app, [*args])


def test_every_stage_has_its_command_in_pipeline_order() -> None:
    result = invoke("--help")
    assert result.exit_code == 0, result.output
    listed = [line.split()[1] for line in result.output.splitlines() if line.startswith("│ ") and len(line.split()) > 1]
    stage_commands = [c for c in listed if c in {s.command for s in REGISTRY}]
    assert stage_commands == [s.command for s in REGISTRY]


def test_selection_options_set_the_stage_settings(recorded: dict[str, Any], tmp_path: Path) -> None:
    result = invoke("select-measurements", str(tmp_path), "--strategy", "uniform", "--budget", "7", "--focus", "all")
    assert result.exit_code == 0, result.output
    assert recorded["names"] == ["select_measurements"]
    cfg = recorded["settings"]["select_measurements"]
    assert (cfg.strategy, cfg.budget, cfg.focus) == ("uniform", 7, "all")
    result = invoke("select-landmarks", str(tmp_path), "--budget", "3", "--set", "select_landmarks.seed=4", "-f")
    assert result.exit_code == 0, result.output
    cfg = recorded["settings"]["select_landmarks"]
    assert (cfg.budget, cfg.seed, cfg.strategy, recorded["force"]) == (3, 4, "auto", True)


def test_an_option_is_checked_like_its_setting(recorded: dict[str, Any], tmp_path: Path) -> None:
    result = invoke("select-landmarks", str(tmp_path), "--budget", "-1")
    assert result.exit_code == 1 and "names" not in recorded
    assert result.stderr.startswith("error: ") and "select_landmarks.budget" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr  # not Click's usage box
    result = invoke("select-landmarks", str(tmp_path), "--strategy", "nearest")
    assert result.exit_code == 1
    assert result.stderr.startswith("error: ") and "select_landmarks.strategy" in result.stderr


def test_ingest_and_run_take_the_recording_options(recorded: dict[str, Any], tmp_path: Path) -> None:
    camera = tmp_path / "cameras.yaml"
    camera.write_text("{}\n")
    bag = tmp_path / "x.bag"
    args = ["--start", "1.5", "--stride", "2", "--camera", str(camera), "--salvage"]
    result = invoke("ingest", str(bag), "--out", str(tmp_path / "runs"), *args)
    assert result.exit_code == 0, result.output
    cfg = recorded["settings"]["ingest"]
    assert (cfg.start_s, cfg.end_s, cfg.frame_stride, cfg.salvage) == (1.5, None, 2, True)
    assert cfg.camera_file == str(camera.resolve())
    assert recorded["names"] == ["ingest"]
    result = invoke("run", str(bag), "--until", "graph", "--end", "9")
    assert result.exit_code == 0, result.output
    assert recorded["names"] == ["ingest", "detect", "graph"]
    assert recorded["settings"]["ingest"].end_s == 9.0


def test_a_missing_camera_file_is_one_error_line(recorded: dict[str, Any], tmp_path: Path) -> None:
    result = invoke("ingest", str(tmp_path / "x.bag"), "--camera", str(tmp_path / "none.yaml"))
    assert result.exit_code == 1 and "names" not in recorded
    assert result.stderr.splitlines() == [
        f"error: camera file {str(tmp_path / 'none.yaml')!r} not found; pass an existing calibration YAML to --camera"
    ]


def test_a_stage_line_shows_the_figures_its_stage_chooses(capsys: pytest.CaptureFixture[str]) -> None:
    summary = {
        "frames": 12,
        "topics": {"image": "/cam"},
        "camera": {"width": 64},
        "odometry": 40,
        "notes": ["odometry has gaps"],
        "scans": None,
        "duration_s": 4.0,
        "start_ns": 17,
        "read_seconds": 0.5,
        "reader": "rosbags",
        "format": "ros1",
        "seconds": 1.25,
        "salvaged": {"messages": 3},
    }
    cli_app._print_result(REGISTRY["ingest"], StageResult("ingest", "done", 1.25, summary))
    cli_app._print_result(REGISTRY["graph"], StageResult("graph", "skipped", 0.0, {"poses": 5, "notes": ["old"]}))
    printed = capsys.readouterr()
    assert printed.out.splitlines() == [
        "ingest               done in 1.2 s    frames=12  odometry=40  duration_s=4.0  start_ns=17  reader=rosbags  "
        "format=ros1",
        "  salvaged: {'messages': 3}",
        "graph                up to date       poses=5",
    ]
    assert printed.err.splitlines() == ["  note: odometry has gaps"]  # notes and warnings go to stderr


def test_a_run_ends_with_the_report_lines_of_its_stages(capsys: pytest.CaptureFixture[str]) -> None:
    head = {
        "case": "focus, info",
        "focused_entropy": -12.34,
        "focused_error_m": 0.0456,
        "max_collision_probability": 0.00123,
        "collision_rate": 0.05,
        "collision_ci_low": 0.01,
        "collision_ci_high": 0.1,
    }
    summary = {"report": "runs/x/evaluate/report.md", "headline": head}
    cli_app._print_headline([StageResult("graph", "skipped", 0.0, {}), StageResult("evaluate", "done", 1.0, summary)])
    assert capsys.readouterr().out.splitlines() == [
        "report: runs/x/evaluate/report.md",
        "headline (focus, info): focused entropy -12.3 nats, focused error 4.6 cm, max P(collision) 0.0012, "
        "collision rate 0.050 [0.010, 0.100]",
    ]
    cli_app._print_headline([StageResult("graph", "done", 1.0, {})])  # evaluate not run: nothing, not an old one
    assert capsys.readouterr().out == ""
    # a map that failed its health checks: the last line says its figures are doubtful
    doubtful = {**summary, "map_health_warnings": 2}
    cli_app._print_headline([StageResult("evaluate", "done", 1.0, doubtful)])
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith("the full map failed 2 health check(s)") and "doubtful" in last
    cli_app._print_headline([StageResult("evaluate", "done", 1.0, {**summary, "map_health_warnings": 0})])
    assert len(capsys.readouterr().out.splitlines()) == 2


def test_a_stage_command_ends_with_the_report_lines_of_its_stage(
    recorded: dict[str, Any], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """``focusmap evaluate RUN`` prints its report's path and headline row, as ``focusmap run`` does."""
    head = {"focused_entropy": -1.0, "focused_error_cm": 2.0, "max_p_collision": 0.01, "collision_rate": 0.0}
    summary = {"report": "runs/x/evaluate/report.md", "headline": head}
    done = [StageResult("evaluate", "done", 1.0, summary)]
    monkeypatch.setattr(cli_app, "_run_stages", lambda run, names, settings, force: done)
    result = invoke("evaluate", str(tmp_path))
    assert result.exit_code == 0, result.output
    assert "report: runs/x/evaluate/report.md" in result.stdout.splitlines()


def test_batch_takes_every_option_of_run_that_is_not_about_one_run_folder() -> None:
    import typer.main

    commands = typer.main.get_command(cli_app.app).commands  # type: ignore[attr-defined]
    flags = {name: {o for p in commands[name].params for o in p.opts if o.startswith("-")} for name in ("run", "batch")}
    one_folder = {"--name", "--reset-settings"}  # a batch file names each folder; a batch's settings are its own
    assert flags["run"] - flags["batch"] == one_folder
    assert {"--camera", "--start", "--end", "--stride", "--salvage", "--from", "--file"} <= flags["batch"]
