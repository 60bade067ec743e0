"""The three packages resolve inside this repository, and imports only go cli -> stages -> pipeline."""

from __future__ import annotations

import ast
from pathlib import Path

import cli
import pipeline
import stages

ROOT = Path(__file__).resolve().parents[1]


def test_packages_resolve_inside_the_repository() -> None:
    for pkg in (pipeline, stages, cli):
        assert Path(pkg.__file__).resolve().is_relative_to(ROOT), f"{pkg.__name__} imported from {pkg.__file__}"


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_layers_only_import_downwards() -> None:
    for path in (ROOT / "pipeline").rglob("*.py"):
        assert not (_imports(path) & {"stages", "cli"}), f"{path} imports upwards"
    for path in (ROOT / "stages").rglob("*.py"):
        assert "cli" not in _imports(path), f"{path} imports the CLI"


def test_production_code_does_not_import_the_tests() -> None:
    """References and generators live in tests/ (oracles, fixtures); nothing that ships may need them."""
    for pkg in ("pipeline", "stages", "cli", "sample_data"):
        for path in (ROOT / pkg).rglob("*.py"):
            assert "tests" not in _imports(path), f"{path} imports from tests/"
