"""Run stages: check inputs, skip what is up to date, write atomically, record the manifest."""

from __future__ import annotations

import functools
import hashlib
import importlib
import json
import platform
import re
import sys
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from pipeline import __version__
from pipeline.artifacts import StageOutput
from pipeline.config import Settings
from pipeline.context import StageContext
from pipeline.errors import StageError
from pipeline.recording import close_recording, log_summary, open_recording, run_blueprint, save_blueprint
from pipeline.registry import Registry
from pipeline.run_folder import RunFolder, source_identity, write_json_atomic
from pipeline.stage import Stage


def _runtime_requirements() -> list[str]:
    """Names of focusmap's installed runtime dependencies (its package metadata, extras left out)."""
    try:
        requires = metadata.requires("focusmap") or []
    except metadata.PackageNotFoundError:
        return []
    names = (re.match(r"[A-Za-z0-9_.\-]+", r) for r in requires if "extra ==" not in r)
    return sorted({m.group(0).lower() for m in names if m})


def library_versions() -> dict[str, str]:
    """Versions of Python and of every runtime dependency (the libraries whose behaviour shapes the results)."""
    versions = {"python": platform.python_version(), "focusmap": __version__}
    for lib in _runtime_requirements():
        try:
            versions[lib] = metadata.version(lib)
        except metadata.PackageNotFoundError:
            versions[lib] = "absent"
    return versions


@dataclass
class StageResult:
    """What happened to one stage."""

    stage: str
    status: str  # "done" or "skipped"
    seconds: float
    summary: dict[str, Any] = field(default_factory=dict)


@functools.cache
def _code_digest(package: str) -> str:
    """Hash of every Python source file of a top-level package: a changed stage re-runs."""
    module = sys.modules.get(package) or importlib.import_module(package)
    root = Path(module.__file__ or "").parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def code_version(stage: Stage) -> str:
    """The stage's declared version plus a digest of the code it runs."""
    package = stage.run.__module__.split(".")[0]
    return f"{stage.version}:{_code_digest(package)[:16]}"


def fingerprint(run: RunFolder, registry: Registry, name: str, settings: Settings) -> str:
    """Hash of the stage, its code version, its settings, its inputs' fingerprints and its source file."""
    stage = registry[name]
    inputs: dict[str, Any] = {}
    for dep in (*stage.inputs, *stage.optional_inputs):
        entry = run.stage_entry(dep)
        inputs[dep] = entry["fingerprint"] if entry else None
    payload = {
        "stage": stage.name,
        "version": code_version(stage),
        "focusmap": __version__,
        "settings": settings[stage.name].model_dump(mode="json"),
        "rerun": settings.rerun.model_dump(mode="json"),
        "inputs": inputs,
        "source": source_identity(run.source) if stage.needs_source and run.source else None,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def is_current(run: RunFolder, registry: Registry, name: str, settings: Settings) -> bool:
    """Whether the stage's finished results match what running it now would produce."""
    entry = run.stage_entry(name)
    return entry is not None and entry.get("fingerprint") == fingerprint(run, registry, name, settings)


def run_stage(
    run: RunFolder, registry: Registry, name: str, settings: Settings, force: bool = False, progress: bool = False
) -> StageResult:
    """Run one stage unless its results are current; its outputs appear whole or not at all.

    ``progress``: draw the stage's progress bars (on stderr).
    """
    stage = registry[name]
    for dep in stage.inputs:
        if run.stage_entry(dep) is None:
            raise StageError(
                f"stage {stage.command!r} needs {dep!r}, which has not run in {str(run.path)!r}; "
                f"run 'focusmap {registry[dep].command} {run.path}' first"
            )
    if stage.needs_source and run.source is not None and not run.source.exists():
        raise StageError(f"source recording {str(run.source)!r} of run {run.path.name!r} no longer exists")
    fp = fingerprint(run, registry, name, settings)
    entry = run.stage_entry(name)
    if not force and entry is not None and entry.get("fingerprint") == fp:
        return StageResult(stage.name, "skipped", 0.0, entry.get("summary", {}))
    scratch, rrd = run.begin(stage.name)
    try:
        blueprint = run_blueprint(
            [(s.name, s.blueprint()) for s in registry if s.blueprint is not None], active=stage.name
        )
    except Exception:  # a layout problem must not stop a stage; the viewer then lays out itself
        blueprint = None
    rec = open_recording(run.run_id, rrd, blueprint)
    start = time.perf_counter()
    try:
        ctx = StageContext(
            run=run, stage=stage, settings=settings, output=StageOutput(scratch), rec=rec, show_progress=progress
        )
        summary = dict(stage.run(ctx, settings[stage.name]) or {})
        seconds = time.perf_counter() - start
        summary.setdefault("seconds", round(seconds, 3))
        log_summary(rec, stage.name, summary)
        close_recording(rec)
        write_json_atomic(scratch / "summary.json", summary)
        run.commit(stage.name)
    except BaseException:
        try:
            close_recording(rec)
        finally:
            run.abort(stage.name)
        raise
    run.record(
        stage.name,
        {
            "fingerprint": fp,
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "code": code_version(stage),
            "seconds": round(seconds, 3),
            "settings": settings[stage.name].model_dump(mode="json"),
            "inputs": {d: (run.stage_entry(d) or {}).get("fingerprint") for d in stage.inputs},
            "source": source_identity(run.source) if stage.needs_source and run.source else None,
            "versions": library_versions(),
            "summary": summary,
        },
    )
    try:
        write_run_blueprint(run, registry)
    except Exception as err:  # a layout problem must not fail a finished stage
        summary.setdefault("notes", []).append(f"run blueprint not written: {err}")
    return StageResult(stage.name, "done", seconds, summary)


BLUEPRINT_FILE = "focusmap.rbl"


def write_run_blueprint(run: RunFolder, registry: Registry) -> None:
    """``RUN/focusmap.rbl``: a tab per finished stage, so ``rerun RUN/*.rrd RUN/focusmap.rbl`` shows them all."""
    finished = [s for s in registry if run.rrd_path(s.name).exists()]
    parts = [(s.name, s.blueprint()) for s in registry if s.blueprint is not None]
    bp = run_blueprint(parts, active=finished[-1].name if finished else None)
    if bp is not None:
        save_blueprint(bp, run.path / BLUEPRINT_FILE)


def write_resolved_settings(run: RunFolder, settings: Settings) -> None:
    """Keep the last resolved settings beside the manifest, for people reading the run folder."""
    write_json_atomic(run.path / "settings.json", settings.dump())
