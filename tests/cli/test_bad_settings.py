"""Bad settings and option values: one ``error:`` line naming the key (or option) and what is allowed, exit 1.

Every case here was an internal error, an abort inside Ceres, a NaN result or Click's usage box before
the settings were validated at load (issue #15 item 6).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import BaseModel
from typer.testing import CliRunner

from cli.app import app
from pipeline.config import SHARED_SECTIONS, SettingsModel
from stages import REGISTRY
from tests.fixtures.bags import write_minimal_bag

ROOT = Path(__file__).resolve().parents[2]


def invoke(*args: str | Path) -> tuple[int, str]:
    result = CliRunner().invoke(app, [str(a) for a in args])
    return result.exit_code, result.stderr


def assert_one_error_line(code: int, stderr: str, *needles: str) -> None:
    assert code == 1, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: "), lines[0]
    for n in needles:
        assert n in lines[0], lines[0]


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["--start", "inf"], ["ingest.start_s", "finite", "0 <= value <= 1e+07"]),
        (["--end", "inf"], ["ingest.end_s", "finite", "0 < value <= 1e+07"]),
        (["--start", "1e300"], ["ingest.start_s", "1e+07"]),
        (["--stride", "0"], ["'--stride'", "greater than or equal to 1", "ingest.frame_stride"]),
        (["--stride", "two"], ["'--stride'", "integer"]),
    ],
)
def test_bad_ingest_option_is_one_error_line(tmp_path: Path, args: list[str], needles: list[str]) -> None:
    bag = write_minimal_bag(tmp_path / "ok.bag")
    code, err = invoke("ingest", bag, "--out", tmp_path / "runs", *args)
    assert_one_error_line(code, err, *needles)
    assert not (tmp_path / "runs" / "ok" / "ingest").exists()


@pytest.mark.parametrize("command", ["select-landmarks", "select-measurements"])
def test_negative_budget_is_one_error_line(tmp_path: Path, command: str) -> None:
    code, err = invoke(command, tmp_path, "--budget", "-1")
    assert_one_error_line(code, err, "'--budget'", "greater than or equal to 0", f"{command.replace('-', '_')}.budget")


@pytest.mark.parametrize(
    ("setting", "needles"),
    [
        ("graph.prior_sigma_m=1e300", ["graph.prior_sigma_m", "0 < value <= 1000"]),
        ("select_measurements.landmark_prior_sigma_m=inf", ["select_measurements.landmark_prior_sigma_m", "finite"]),
        ("select_landmarks.landmark_prior_sigma_m=.nan", ["select_landmarks.landmark_prior_sigma_m", "finite"]),
        ("evaluate.grid_resolution_m=1e-6", ["evaluate.grid_resolution_m", "0.001 <= value"]),
        ("detect.tag_size_m=inf", ["detect.tag_size_m", "finite", "0 < value <= 5"]),
        ("detect.tag_size_m=1e9", ["detect.tag_size_m", "0 < value <= 5"]),
        ("optimize.unobserved_sigma_m=inf", ["optimize.unobserved_sigma_m", "finite", "<= 1000"]),
        ("select_landmarks.control_period_s=-.inf", ["select_landmarks.control_period_s"]),
        ("rerun.n_sigma=inf", ["rerun.n_sigma", "finite"]),
        # found by the fault matrix (tests/benchmarks/bench_faults.py): an OverflowError in evaluate, and a run
        # the kernel killed for memory
        ("select_landmarks.speed_sigma_mps=1e300", ["select_landmarks.speed_sigma_mps", "<= 1000"]),
        ("select_landmarks.yaw_rate_sigma_radps=1e300", ["select_landmarks.yaw_rate_sigma_radps", "<= 1000"]),
        ("evaluate.trials=1000000000", ["evaluate.trials", "0 <= value <= 100000"]),
        ("select_landmarks.robot_radius_m=1e300", ["select_landmarks.robot_radius_m", "<= 100"]),
        ("evaluate.robot_radius_m=1e300", ["evaluate.robot_radius_m", "<= 100"]),
    ],
)
def test_bad_setting_is_one_error_line(setting: str, needles: list[str]) -> None:
    code, err = invoke("show-config", "--set", setting)
    assert_one_error_line(code, err, "--set", *needles)


def test_bad_setting_in_a_file_names_the_file(tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("detect:\n  tag_sizes: [{id: 3, size_m: .inf}]\n")
    code, err = invoke("show-config", "--config", config)
    assert_one_error_line(code, err, str(config), "detect.tag_sizes", "finite")


def test_binary_config_file_is_one_error_line(tmp_path: Path) -> None:
    config = tmp_path / "binary.yaml"
    config.write_bytes(b"\xff\xfe\x00\x89PNG\r\n\x1a\n" + bytes(range(256)))
    code, err = invoke("show-config", "--config", config)
    assert_one_error_line(code, err, "binary.yaml", "not UTF-8")


def test_binary_camera_file_is_one_error_line(tmp_path: Path) -> None:
    bag = write_minimal_bag(tmp_path / "ok.bag")
    camera = tmp_path / "binary.yaml"
    camera.write_bytes(b"\xff\xfe\x00\x89PNG\r\n\x1a\n" + bytes(range(256)))
    proc = subprocess.run(
        [sys.executable, "-m", "cli.app", "ingest", str(bag), "--out", str(tmp_path / "runs"), "--camera", str(camera)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert_one_error_line(proc.returncode, proc.stderr, "binary.yaml", "not UTF-8", "--camera")
    assert "Traceback" not in proc.stderr


def test_unknown_option_keeps_the_usage(tmp_path: Path) -> None:
    """How a command is called (an unknown option, a missing argument) is Click's to show, with the usage."""
    code, err = invoke("ingest", tmp_path / "x.bag", "--bogus", "1")
    assert code == 2
    assert "Usage:" in err


def _models() -> list[type[BaseModel]]:
    """Every settings model: the sections and the models nested in their fields."""
    seen: list[type[BaseModel]] = []
    todo: list[type[BaseModel]] = [*REGISTRY.models().values(), *SHARED_SECTIONS.values()]
    while todo:
        model = todo.pop()
        if model in seen:
            continue
        seen.append(model)
        for info in model.model_fields.values():
            for arg in (*getattr(info.annotation, "__args__", ()), info.annotation):
                for inner in (arg, *getattr(arg, "__args__", ())):
                    if isinstance(inner, type) and issubclass(inner, BaseModel):
                        todo.append(inner)
    return seen


def test_every_settings_model_rejects_non_finite_numbers() -> None:
    models = _models()
    assert len(models) > len(SHARED_SECTIONS) + 6  # the sections and detect's nested TagSize
    for model in models:
        assert issubclass(model, SettingsModel), model
        assert model.model_config.get("allow_inf_nan") is False, model


# --- every SECTION.KEY named to the user exists ----------------------------------------------------------
KEY = re.compile(r"\b([a-z_]+)\.([a-z_]+)=")
"""``SECTION.KEY=`` as help texts, hints and docs write a setting."""


def _named_keys(text: str) -> set[tuple[str, str]]:
    return {(s, k) for s, k in KEY.findall(text) if s in _sections()}


def _sections() -> dict[str, type[BaseModel]]:
    return {**REGISTRY.models(), **SHARED_SECTIONS}


def _help_texts() -> str:
    commands = [[], *([name] for name in ("run", "show-config", "batch", "import-graph", "info", "view"))]
    commands += [[s.command] for s in REGISTRY]
    out = []
    for cmd in commands:
        result = CliRunner().invoke(app, [*cmd, "--help"], terminal_width=1000)
        assert result.exit_code == 0, (cmd, result.output)
        out.append(result.output)
    return "\n".join(out)


def _source_and_docs() -> str:
    files = [*ROOT.glob("cli/*.py"), *ROOT.glob("pipeline/*.py"), *ROOT.glob("stages/**/*.py")]
    files += [*ROOT.glob("configs/*.yaml"), *ROOT.glob("docs/*.md"), ROOT / "README.md"]
    return "\n".join(p.read_text() for p in files)


def test_help_texts_name_settings() -> None:
    """The check below has something to check: the --set help cites an example key."""
    assert _named_keys(_help_texts())


@pytest.mark.parametrize("where", ["help", "source"])
def test_every_named_setting_exists(where: str) -> None:
    text = _help_texts() if where == "help" else _source_and_docs()
    named = _named_keys(text)
    assert named
    sections = _sections()
    missing = sorted(f"{s}.{k}" for s, k in named if k not in sections[s].model_fields)
    assert not missing, f"keys named in {where} that are no settings: {missing}"
