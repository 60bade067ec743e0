"""``import_graph``: a run folder whose ``graph`` stage comes from an existing factor graph file."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

from pipeline.artifacts import StageOutput
from pipeline.config import RecordingSettings
from pipeline.recording import close_recording, log_summary, open_recording
from pipeline.run_folder import RunFolder, source_identity, write_json_atomic
from stages.graph.config import GraphConfig
from stages.graph.g2o import read_graph_file
from stages.graph.solve_all import solve_and_write

STAGE_NAME = "graph"


def _blueprint() -> object:
    from stages.graph import blueprint

    return blueprint()


def import_graph(
    path: Path,
    out_dir: Path,
    name: str | None = None,
    cfg: GraphConfig | None = None,
    recording: RecordingSettings | None = None,
) -> Path:
    """Create ``out_dir/<name or file stem>/`` with a finished ``graph`` stage made from a g2o or GTSAM graph file.

    The graph is checked, optimised and its marginals computed as the stage does, and its artifacts,
    ``graph.rrd`` and manifest entry are written through the run folder's atomic machinery, so the
    stages after ``graph`` run on the folder as on one made from a bag.

    Args:
        path: a g2o file (2D or 3D, with landmark vertices and edges) or a GTSAM ``.graph`` dataset.
        out_dir: parent folder of the run folder.
        name: run folder name (default: the file's stem).
        cfg: graph settings (optimizer, prior sigmas, ellipse stride); defaults when None.
        recording: the shared ``rerun`` settings (n_sigma); defaults when None.

    Returns:
        The run folder.

    Raises:
        InputError: the file is missing or cannot be parsed.
        StageError: the graph is singular or unconstrained (the message names the variable).
    """
    cfg = cfg or GraphConfig()
    recording = recording or RecordingSettings()
    path = Path(path)
    problem = read_graph_file(path, cfg.prior_sigma_m, cfg.prior_sigma_rad)
    cfg = cfg.model_copy(update={"model": problem.model})
    run = RunFolder.create(Path(out_dir) / (name or path.stem), path, kind="graph")
    scratch, rrd = run.begin(STAGE_NAME)
    rec = open_recording(run.run_id, rrd, _blueprint())
    start = time.perf_counter()
    settings = cfg.model_dump(mode="json")
    try:
        summary = solve_and_write(problem, cfg, StageOutput(scratch), rec, recording.n_sigma)
        seconds = time.perf_counter() - start
        summary["imported_from"] = str(path)
        summary.setdefault("seconds", round(seconds, 3))
        log_summary(rec, STAGE_NAME, summary)
        close_recording(rec)
        write_json_atomic(scratch / "summary.json", summary)
        run.commit(STAGE_NAME)
    except BaseException:
        try:
            close_recording(rec)
        finally:
            run.abort(STAGE_NAME)
        raise
    from pipeline.runner import library_versions

    ident = source_identity(path)
    fp = hashlib.sha256(
        json.dumps(
            {
                "stage": STAGE_NAME,
                "import": ident["digest"],
                "settings": settings,
                "rerun": recording.model_dump(mode="json"),
            },
            sort_keys=True,
        ).encode()
    ).hexdigest()
    run.record(
        STAGE_NAME,
        {
            "fingerprint": fp,
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "seconds": round(seconds, 3),
            "settings": settings,
            "inputs": {},
            "source": ident,
            "imported_from": str(path.resolve()),
            "versions": library_versions(),
            "summary": summary,
        },
    )
    return run.path
