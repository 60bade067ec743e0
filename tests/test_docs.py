"""The documentation generated from code stays in step with it."""

from __future__ import annotations

from pathlib import Path

from stages import REGISTRY
from stages.contracts import artifact_sets, render

ROOT = Path(__file__).resolve().parents[1]


def test_artifacts_doc_is_the_rendering_of_the_declarations() -> None:
    committed = (ROOT / "docs" / "artifacts.md").read_text()
    assert committed == render(), "docs/artifacts.md is stale: run 'python -m stages.contracts > docs/artifacts.md'"


def test_every_declared_stage_is_in_pipeline_order_and_names_its_files_once() -> None:
    sets = artifact_sets()
    stages = [s.stage for s in sets]
    assert stages == [s for s in REGISTRY.names if s in stages]
    assert {"select_landmarks", "select_measurements", "optimize", "evaluate"} <= set(stages)
    for s in sets:
        files = [spec.file for spec in s.specs]
        assert len(files) == len(set(files)), f"{s.stage} declares a file twice: {files}"


def test_readme_quick_start_is_two_commands_and_ci_runs_the_second() -> None:
    """The README promises two commands (install and run the sample; install the test extras and test), and
    .ci/run extracts the second by position: a third line in the block would make CI run the wrong one."""
    import re
    import subprocess

    root = Path(__file__).resolve().parents[1]
    block = re.search(r"## Quick start\n\n```sh\n(.*?)```", (root / "README.md").read_text(), re.S)
    assert block is not None
    lines = [ln for ln in block.group(1).splitlines() if ln.strip()]
    assert len(lines) == 2, lines
    assert "focusmap run sample_data/" in lines[0] and "pytest" in lines[1]
    awk = re.search(r"awk '([^']*)'", (root / ".ci" / "run").read_text())
    assert awk is not None
    got = subprocess.run(["awk", awk.group(1), str(root / "README.md")], capture_output=True, text=True, check=True)
    assert got.stdout.strip() == lines[1]
