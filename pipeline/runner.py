"""Run stages: check inputs, skip what is up to date, write atomically, record the manifest."""

from __future__ import annotations

import functools
import hashlib
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
from pipeline.code import code_digest, package_dirs
from pipeline.config import Settings
from pipeline.context import StageContext
from pipeline.errors import StageError, write_error
from pipeline.lazy import LazyCallable
from pipeline.memory import freeze_live_objects, release_freed_memory
from pipeline.recording import close_recording, log_summary, open_recording, run_blueprint, save_blueprint
from pipeline.registry import Registry
from pipeline.run_folder import RunFolder, SourceEntry, outside_identity, source_identity, write_json_atomic
from pipeline.stage import AnyStage, Summary


def _headers(name: str, field: str) -> list[str]:
    """The values of ``field`` in the installed distribution's metadata headers, read as text (the email parser
    ``importlib.metadata`` uses costs a few ms per package, and a stage records about twenty).

    Raises:
        metadata.PackageNotFoundError: ``name`` is not installed.
    """
    text = metadata.distribution(name).read_text("METADATA") or ""
    values = []
    for line in text.splitlines():
        if not line:  # the headers end at the first empty line
            break
        key, sep, value = line.partition(":")
        if sep and key == field:
            values.append(value.strip())
    return values


def _runtime_requirements() -> list[str]:
    """Names of focusmap's installed runtime dependencies (its package metadata, extras left out)."""
    try:
        requires = _headers("focusmap", "Requires-Dist")
    except metadata.PackageNotFoundError:
        return []
    names = (re.match(r"[A-Za-z0-9_.\-]+", r) for r in requires if "extra ==" not in r)
    return sorted({m.group(0).lower() for m in names if m})


def library_versions() -> dict[str, str]:
    """Versions of Python and of every runtime dependency (the libraries whose behaviour shapes the results)."""
    versions = {"python": platform.python_version(), "focusmap": __version__}
    for lib in _runtime_requirements():
        try:
            found = _headers(lib, "Version")
            versions[lib] = found[0] if found else metadata.version(lib)
        except metadata.PackageNotFoundError:
            versions[lib] = "absent"
    return versions


@dataclass
class StageResult:
    """What happened to one stage."""

    stage: str
    status: str  # "done" or "skipped"
    seconds: float
    summary: Summary = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    """Why the result may not be what a full run would give (an input made from older upstream results)."""


def code_version(stage: AnyStage) -> str:
    """The stage's declared version plus a digest of the project code it can run.

    The digest covers the stage's own sub-package (the package of its ``run`` function, e.g. ``stages.evaluate``)
    and every module of that top-level package and of ``pipeline`` that it reaches by imports
    (:func:`pipeline.code.code_digest`), so an edit re-runs the stages that use the edited module and no other.
    """
    return f"{stage.version}:{_stage_code_digest(stage.run.__module__)[:16]}"


@functools.cache
def _stage_code_digest(module: str) -> str:
    parent = module.rpartition(".")[0]
    root = parent if "." in parent else module
    try:
        packages = package_dirs({root.split(".")[0], __name__.split(".")[0]})
        return code_digest([root], packages)
    except (ValueError, ImportError, SyntaxError):  # e.g. a stage defined in a script: hash that file alone
        path = getattr(sys.modules.get(module), "__file__", None)
        return hashlib.sha256(Path(path).read_bytes() if path else module.encode()).hexdigest()


def _seal(base: str, outside: dict[str, str | None]) -> str:
    """The recorded fingerprint: the inputs-and-settings fingerprint, plus the outside files the stage read."""
    if not outside:
        return base
    return hashlib.sha256(json.dumps({"base": base, "outside": outside}, sort_keys=True).encode()).hexdigest()


def fingerprint(run: RunFolder, registry: Registry, name: str, settings: Settings) -> str:
    """Hash of the stage, its code version, its settings, its inputs' fingerprints and its source file.

    The files outside the run folder that the stage reports reading (``ctx.outside_file``) are added when it
    has run (:func:`is_current`), since only the stage knows which they are.
    """
    stage = registry[name]
    required, optional = stage.inputs_on(run.source_kind)
    inputs: dict[str, str | None] = {}
    for dep in (*required, *optional):
        entry = run.stage_entry(dep)
        inputs[dep] = entry["fingerprint"] if entry else None
    payload = {
        "stage": stage.name,
        "version": code_version(stage),
        "focusmap": __version__,
        "settings": settings[stage.name].model_dump(mode="json"),
        "rerun": settings.rerun.model_dump(mode="json"),
        "inputs": inputs,
        "source": _source(run, stage),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _source(run: RunFolder, stage: AnyStage) -> SourceEntry | None:
    if not stage.reads_source(run.source_kind) or run.source is None or not run.source.exists():
        return None
    return SourceEntry(**source_identity(run.source), kind=run.source_kind)


def is_current(run: RunFolder, registry: Registry, name: str, settings: Settings) -> bool:
    """Whether the stage's finished results match what running it now would produce.

    Besides the fingerprint of settings, code and inputs, every outside file the stage read when it ran must be
    as it was then (and one that was absent must still be absent).
    """
    entry = run.stage_entry(name)
    if entry is None:
        return False
    outside = {p: outside_identity(p) for p in entry.get("outside_files") or {}}
    return entry.get("fingerprint") == _seal(fingerprint(run, registry, name, settings), outside)


def stale_inputs(run: RunFolder, registry: Registry, name: str) -> list[str]:
    """The upstream stages, at any depth, whose results were made from older results of their own inputs.

    A stage run alone reads what is in the folder; if an input stage was made before its own input changed
    (``select-landmarks --budget 10`` and then ``optimize`` without ``select-measurements``), the result mixes
    two versions. Each line names the stale stage, what changed under it, and the command that fixes it.
    """
    lines: list[str] = []
    seen: set[str] = set()
    required, optional = registry[name].inputs_on(run.source_kind)
    todo = [*required, *optional]
    while todo:
        dep = todo.pop(0)
        entry = run.stage_entry(dep)
        if dep in seen or entry is None:
            continue
        seen.add(dep)
        recorded = entry.get("inputs") or {}
        for up, fp in recorded.items():
            now = run.stage_entry(up)
            if now is not None and fp is not None and now.get("fingerprint") != fp:
                lines.append(
                    f"{dep} was made from an older {up}; run 'focusmap {registry[dep].command} {run.path}' "
                    "(or 'focusmap run') for results from one version"
                )
                break
        required, optional = registry[dep].inputs_on(run.source_kind)
        todo.extend((*required, *optional))
    return lines


def run_stage(
    run: RunFolder, registry: Registry, name: str, settings: Settings, force: bool = False, progress: bool = False
) -> StageResult:
    """Run one stage unless its results are current; its outputs appear whole or not at all.

    ``progress``: draw the stage's progress bars (on stderr).
    """
    stage = registry[name]
    required, optional = stage.inputs_on(run.source_kind)
    for dep in required:
        if run.stage_entry(dep) is None:
            raise StageError(
                f"stage {stage.command!r} needs {dep!r}, which has not run in {str(run.path)!r}; "
                f"run 'focusmap {registry[dep].command} {run.path}' first"
            )
    if stage.reads_source(run.source_kind) and run.source is not None and not run.source.exists():
        raise StageError(f"source recording {str(run.source)!r} of run {run.path.name!r} no longer exists")
    warnings = stale_inputs(run, registry, name)
    entry = run.stage_entry(name)
    if not force and entry is not None and is_current(run, registry, name, settings):
        return StageResult(stage.name, "skipped", 0.0, entry.get("summary", {}), warnings)
    fp = fingerprint(run, registry, name, settings)
    scratch, rrd = run.begin(stage.name)
    parts: list[tuple[str, Any]] | None = None
    try:
        parts = [(s.name, s.blueprint()) for s in registry if s.blueprint is not None]
        blueprint = run_blueprint(parts, active=stage.name)
    except Exception:  # a layout problem must not stop a stage; the viewer then lays out itself
        blueprint = None
    rec = open_recording(run.run_id, rrd, blueprint)
    start = time.perf_counter()
    try:
        if isinstance(stage.run, LazyCallable):
            stage.run.target  # noqa: B018 - import the stage's libraries now, to freeze them below
        release_freed_memory()  # what earlier stages left is collected, not frozen
        freeze_live_objects()
        ctx = StageContext(
            run=run,
            stage=stage,
            settings=settings.only(stage.name),
            output=StageOutput(scratch),
            rec=rec,
            show_progress=progress,
        )
        summary = dict(stage.run(ctx, settings[stage.name]) or {})
        release_freed_memory()
        seconds = time.perf_counter() - start
        summary.setdefault("seconds", round(seconds, 3))
        log_summary(rec, stage.name, summary)
        close_recording(rec)
        write_json_atomic(scratch / "summary.json", summary)
        run.commit(stage.name)
    except BaseException as err:
        try:
            close_recording(rec)
        except OSError:
            pass  # the stage's own error says more; its output goes anyway
        finally:
            run.abort(stage.name)
        failed = write_error(err, run.path)
        if failed is not None:  # a full or read-only disk: one line naming the file, earlier results untouched
            raise failed from err
        raise
    outside = dict(sorted(ctx.outside_files.items()))
    try:
        run.record(
            stage.name,
            {
                "fingerprint": _seal(fp, outside),
                "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "code": code_version(stage),
                "seconds": round(seconds, 3),
                "settings": settings[stage.name].model_dump(mode="json"),
                "inputs": {d: (run.stage_entry(d) or {}).get("fingerprint") for d in (*required, *optional)},
                "source": _source(run, stage),
                "outside_files": outside,
                "versions": library_versions(),
                "summary": summary,
            },
        )
    except OSError as err:  # the stage's folder is in place but unrecorded: the next command re-runs it
        failed = write_error(err, run.path)
        if failed is None:
            raise
        raise failed from err
    try:
        finished = [s.name for s in registry if run.rrd_path(s.name).exists()]
        if parts is not None and blueprint is not None and finished and finished[-1] == stage.name:
            save_blueprint(blueprint, run.path / BLUEPRINT_FILE)  # the same layout: built once
        else:
            write_run_blueprint(run, registry)
    except Exception as err:  # a layout problem (or no room for it) must not fail a finished stage
        notes = summary.setdefault("notes", [])
        if isinstance(notes, list):
            notes.append(f"run blueprint not written: {err}")
    return StageResult(stage.name, "done", seconds, summary, warnings)


BLUEPRINT_FILE = "focusmap.rbl"


def write_run_blueprint(run: RunFolder, registry: Registry) -> None:
    """``RUN/focusmap.rbl``: a tab per finished stage, so ``rerun RUN/*.rrd RUN/focusmap.rbl`` shows them all."""
    finished = [s for s in registry if run.rrd_path(s.name).exists()]
    parts = [(s.name, s.blueprint()) for s in registry if s.blueprint is not None]
    bp = run_blueprint(parts, active=finished[-1].name if finished else None)
    if bp is not None:
        save_blueprint(bp, run.path / BLUEPRINT_FILE)


def write_resolved_settings(run: RunFolder, settings: Settings) -> None:
    """Keep the last resolved settings beside the manifest, for people reading the run folder.

    Call it holding the run folder's lock; nothing is written when the file already holds these settings.
    """
    path = run.path / "settings.json"
    now = settings.dump()
    try:
        if json.loads(path.read_text()) == now:
            return
    except (OSError, ValueError):
        pass
    write_json_atomic(path, now)
