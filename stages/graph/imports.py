"""``import_graph``: a run folder whose ``graph`` stage comes from an existing factor graph file.

The folder's source is the graph file (``source_kind: graph``); the graph stage then reads that file instead of
ingest and detect, and runs through :func:`pipeline.runner.run_stage` like every stage: atomic output, manifest
entry, fingerprint over the file's identity and the settings, skipped when nothing changed.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pipeline.config import RecordingSettings, Settings
from pipeline.errors import InputError
from pipeline.registry import Registry
from pipeline.run_folder import RunFolder
from pipeline.runner import StageResult, run_stage
from stages.graph.config import GRAPH_SOURCE, GraphConfig


def import_run(path: Path, out_dir: Path, name: str | None = None) -> RunFolder:
    """Create (or reuse) ``out_dir/<name or file stem>/`` for a g2o or GTSAM graph file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"graph file {str(path)!r} not found; pass an existing .g2o or .graph file")
    return RunFolder.create(Path(out_dir) / (name or path.stem), path, kind=GRAPH_SOURCE)


def import_graph(
    path: Path,
    out_dir: Path,
    name: str | None = None,
    cfg: GraphConfig | None = None,
    recording: RecordingSettings | None = None,
    force: bool = False,
) -> Path:
    """Create ``out_dir/<name or file stem>/`` with a finished ``graph`` stage made from a g2o or GTSAM graph file.

    Args:
        path: a g2o file (2D or 3D, with landmark vertices and edges) or a GTSAM ``.graph`` dataset.
        out_dir: parent folder of the run folder.
        name: run folder name (default: the file's stem).
        cfg: graph settings (optimizer, prior sigmas, ellipse stride); defaults when None.
        recording: the shared ``rerun`` settings (n_sigma); defaults when None.
        force: re-run even when the stage is up to date.

    Returns:
        The run folder.

    Raises:
        InputError: the file is missing or cannot be parsed.
        StageError: the graph is singular or unconstrained (the message names the variable).
    """
    run = import_run(path, out_dir, name)
    settings = Settings({"graph": cfg or GraphConfig(), "rerun": recording or RecordingSettings()}, {})
    run_graph(run, settings, force)
    return run.path


def run_graph(run: RunFolder, settings: Settings, force: bool = False) -> StageResult:
    """Run the graph stage of an imported run through the runner (the CLI runs it with the whole registry)."""
    from stages.graph import STAGE

    alone = dataclasses.replace(STAGE, inputs=(), optional_inputs=())  # what it reads on a graph-file run anyway
    return run_stage(run, Registry([alone]), "graph", settings, force=force)
