"""``import_run``: a run folder whose ``graph`` stage comes from an existing factor graph file.

The folder's source is the graph file (``source_kind: graph``); its graph stage then reads that file instead of
ingest and detect, and runs through :func:`pipeline.runner.run_stage` like every stage (``focusmap import-graph``
does exactly that): atomic output, manifest entry, fingerprint over the file's identity and the settings, skipped
when nothing changed.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import InputError
from pipeline.run_folder import RunFolder
from stages.graph.config import GRAPH_SOURCE


def import_run(path: Path, out_dir: Path, name: str | None = None) -> RunFolder:
    """Create (or reuse) ``out_dir/<name or file stem>/`` for a g2o or GTSAM graph file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"graph file {str(path)!r} not found; pass an existing .g2o or .graph file")
    return RunFolder.create(Path(out_dir) / (name or path.stem), path, kind=GRAPH_SOURCE)
