"""The run folder: ``OUT/<run name>/`` with ``run.json``, ``manifest.json``, one folder and one ``.rrd`` per stage.

Stages write into ``.partial/<stage>/`` and the folder is renamed into place only when the stage
has finished, so an interrupted or failed stage leaves the previous results whole.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
from pathlib import Path
from typing import NotRequired, TypedDict

from pipeline.errors import InputError
from pipeline.json_types import JSONObject

RUN_FILE = "run.json"
MANIFEST_FILE = "manifest.json"
PARTIAL_DIR = ".partial"
_EDGE_BYTES = 1 << 20


class RunInfo(TypedDict):
    """``run.json``: what the run folder is for."""

    run_id: str
    name: str
    source: str | None
    source_kind: NotRequired[str]
    """``bag`` or ``graph``; absent in folders made before import-graph existed (a bag)."""
    created: str


class SourceIdentity(TypedDict):
    """A cheap identity of an input file or folder (:func:`source_identity`)."""

    path: str
    bytes: int
    files: int
    digest: str


class SourceEntry(SourceIdentity):
    """The source file a stage read, as its manifest entry records it."""

    kind: str
    """The run's source kind (``bag``, ``graph``)."""


class StageEntry(TypedDict, total=False):
    """A finished stage in ``manifest.json`` (what :func:`pipeline.runner.run_stage` records)."""

    fingerprint: str
    finished: str
    code: str
    seconds: float
    settings: JSONObject
    inputs: dict[str, str | None]
    source: SourceEntry | None
    outside_files: dict[str, str | None]
    versions: dict[str, str]
    summary: JSONObject


class Manifest(TypedDict):
    """``manifest.json``: the run id and every finished stage's entry."""

    run_id: str
    stages: dict[str, StageEntry]


def write_json_atomic(path: Path, data: object) -> None:
    """Write JSON to a temporary name beside ``path`` and rename it into place."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False, default=_json_default) + "\n")
    os.replace(tmp, path)


def _json_default(obj: object) -> object:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def source_identity(path: Path) -> SourceIdentity:
    """A cheap identity of an input file or folder: names, sizes, mtimes and a hash of each file's ends."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    digest = hashlib.sha256()
    total = 0
    for f in files:
        st = f.stat()
        total += st.st_size
        digest.update(f"{f.relative_to(path) if path.is_dir() else f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
        with f.open("rb") as fh:
            digest.update(fh.read(_EDGE_BYTES))
            if st.st_size > 2 * _EDGE_BYTES:
                fh.seek(-_EDGE_BYTES, os.SEEK_END)
                digest.update(fh.read(_EDGE_BYTES))
    return {"path": str(path.resolve()), "bytes": total, "files": len(files), "digest": digest.hexdigest()}


def outside_identity(path: str) -> str | None:
    """The identity of a file outside the run folder that a stage read (None: it is absent)."""
    p = Path(path)
    return source_identity(p)["digest"] if p.exists() else None


class RunFolder:
    """One recorded run's working folder."""

    def __init__(self, path: Path) -> None:
        self.path = path
        info_path = path / RUN_FILE
        if not info_path.is_file():
            raise InputError(
                f"{str(path)!r} is not a focusmap run folder (no {RUN_FILE}); "
                "create one with 'focusmap ingest BAG --out DIR' or 'focusmap import-graph FILE --out DIR'"
            )
        self.info: RunInfo = json.loads(info_path.read_text())
        self.recover()

    @classmethod
    def create(cls, path: Path, source: Path | None, kind: str = "bag") -> RunFolder:
        """Create (or reuse, if it is for the same source) the run folder for ``source``."""
        info_path = path / RUN_FILE
        if info_path.is_file():
            run = cls(path)
            old = run.info.get("source")
            if source is not None and old is not None and Path(old).resolve() != source.resolve():
                raise InputError(
                    f"run folder {str(path)!r} belongs to {old!r}, not {str(source)!r}; choose another --out or --name"
                )
            return run
        path.mkdir(parents=True, exist_ok=True)
        info: RunInfo = {
            "run_id": str(uuid.uuid4()),
            "name": path.name,
            "source": str(source.resolve()) if source is not None else None,
            "source_kind": kind,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        write_json_atomic(info_path, info)
        manifest: Manifest = {"run_id": info["run_id"], "stages": {}}
        write_json_atomic(path / MANIFEST_FILE, manifest)
        return cls(path)

    @property
    def run_id(self) -> str:
        """The recording id shared by every stage's ``.rrd``."""
        return str(self.info["run_id"])

    @property
    def source(self) -> Path | None:
        """The recording this run was made from, if any."""
        src = self.info.get("source")
        return Path(src) if src else None

    @property
    def source_kind(self) -> str:
        """What the source is: ``bag`` (a recording) or ``graph`` (a factor-graph file, from import-graph)."""
        return str(self.info.get("source_kind") or "bag")

    @property
    def partial_root(self) -> Path:
        """Where unfinished stage outputs live until they are renamed into place."""
        return self.path / PARTIAL_DIR

    def stage_dir(self, stage: str) -> Path:
        """The finished artifacts of ``stage``."""
        return self.path / stage

    def rrd_path(self, stage: str) -> Path:
        """The finished recording of ``stage``."""
        return self.path / f"{stage}.rrd"

    # manifest -----------------------------------------------------------------------------------
    def manifest(self) -> Manifest:
        """The run's manifest: per stage, its fingerprint, time taken, summary and versions."""
        path = self.path / MANIFEST_FILE
        if not path.is_file():
            return {"run_id": self.run_id, "stages": {}}
        manifest: Manifest = json.loads(path.read_text())
        return manifest

    def stage_entry(self, stage: str) -> StageEntry | None:
        """The manifest entry of a finished stage whose folder exists, else None."""
        entry = self.manifest()["stages"].get(stage)
        if entry is None or not self.stage_dir(stage).is_dir():
            return None
        return entry

    def record(self, stage: str, entry: StageEntry) -> None:
        """Store a finished stage's manifest entry."""
        manifest = self.manifest()
        manifest["stages"][stage] = entry
        write_json_atomic(self.path / MANIFEST_FILE, manifest)

    def forget(self, stage: str) -> None:
        """Drop a stage from the manifest (its folder stays until replaced)."""
        manifest = self.manifest()
        if manifest["stages"].pop(stage, None) is not None:
            write_json_atomic(self.path / MANIFEST_FILE, manifest)

    # atomic stage output --------------------------------------------------------------------------
    def begin(self, stage: str) -> tuple[Path, Path]:
        """Fresh scratch folder and recording path for ``stage``."""
        root = self.partial_root
        root.mkdir(exist_ok=True)
        scratch = root / stage
        if scratch.exists():
            shutil.rmtree(scratch)
        scratch.mkdir()
        rrd = root / f"{stage}.rrd"
        rrd.unlink(missing_ok=True)
        return scratch, rrd

    def commit(self, stage: str) -> None:
        """Move a finished stage's scratch folder and recording into place, replacing the old ones."""
        root = self.partial_root
        scratch, rrd = root / stage, root / f"{stage}.rrd"
        final = self.stage_dir(stage)
        old = root / f"{stage}.old"
        if old.exists():
            shutil.rmtree(old)
        if final.exists():
            os.replace(final, old)
        os.replace(scratch, final)
        if rrd.exists():
            os.replace(rrd, self.rrd_path(stage))
        if old.exists():
            shutil.rmtree(old)
        self._tidy()

    def abort(self, stage: str) -> None:
        """Throw away a failed stage's scratch output."""
        root = self.partial_root
        shutil.rmtree(root / stage, ignore_errors=True)
        (root / f"{stage}.rrd").unlink(missing_ok=True)
        self._tidy()

    def recover(self) -> None:
        """Undo what a killed process left: restore a replaced folder, drop unfinished scratch output."""
        root = self.partial_root
        if not root.is_dir():
            return
        for old in root.glob("*.old"):
            final = self.stage_dir(old.name[: -len(".old")])
            if not final.exists():
                os.replace(old, final)
            else:
                shutil.rmtree(old, ignore_errors=True)
        for item in root.iterdir():
            if item.is_dir():
                shutil.rmtree(item, ignore_errors=True)
            else:
                item.unlink(missing_ok=True)
        self._tidy()

    def _tidy(self) -> None:
        root = self.partial_root
        if root.is_dir() and not any(root.iterdir()):
            root.rmdir()
