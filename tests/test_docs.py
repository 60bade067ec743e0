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
