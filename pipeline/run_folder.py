"""The run folder: ``OUT/<run name>/`` with ``run.json``, ``manifest.json``, one folder and one ``.rrd`` per stage.

Stages write into ``.partial/<stage>/`` and the folder is renamed into place only when the stage
has finished, so an interrupted or failed stage leaves the previous results whole.

Whatever writes into a run folder holds its lock (:func:`run_folder_lock`, or :meth:`RunFolder.lock`
for an existing one): an exclusive ``flock`` on ``<run>/.focusmap.lock``, which the kernel releases
when the holder's process ends in any way, kill -9 included. Reading needs no lock.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import socket
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Final, NotRequired, TypedDict

from pipeline.errors import InputError
from pipeline.json_types import JSONObject

RUN_FILE = "run.json"
MANIFEST_FILE = "manifest.json"
PARTIAL_DIR = ".partial"
LOCK_FILE: Final = ".focusmap.lock"
_EDGE_BYTES = 1 << 20
_READ_ONLY: Final = (errno.EACCES, errno.EPERM, errno.EROFS)


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
    text = json.dumps(data, indent=2, sort_keys=False, default=_json_default) + "\n"
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError as err:  # a full disk: leave no torn temporary file, and name the file meant
        tmp.unlink(missing_ok=True)
        raise OSError(err.errno, err.strerror, str(path)) from err


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

    @classmethod
    def create(cls, path: Path, source: Path | None, kind: str = "bag") -> RunFolder:
        """Create (or reuse, if it is for the same source) the run folder for ``source``.

        It writes, so where another process may use the folder, call it holding :func:`run_folder_lock`.
        A reused folder is cleared of what a killed process left (:meth:`recover`).
        """
        info_path = path / RUN_FILE
        if info_path.is_file():
            run = cls(path)
            old = run.info.get("source")
            if source is not None and old is not None and Path(old).resolve() != source.resolve():
                raise InputError(
                    f"run folder {str(path)!r} belongs to {old!r}, not {str(source)!r}; choose another --out or --name"
                )
            run.recover()
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

    @contextlib.contextmanager
    def lock(
        self, *, wait_s: float = 0.0, who: str = "focusmap", then: str = "run the command again"
    ) -> Iterator[None]:
        """Hold the folder's lock (:func:`run_folder_lock`) and clear what a killed process left, to write in it."""
        with run_folder_lock(self.path, wait_s=wait_s, who=who, then=then):
            self.recover()
            yield

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
        try:
            root.mkdir(exist_ok=True)
        except OSError as err:
            if err.errno not in _READ_ONLY:
                raise
            raise InputError(
                f"cannot write in run folder {str(self.path)!r} ({err.strerror}); make it writable, "
                "or copy it and run the command on the copy"
            ) from None
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
        """Undo what a killed process left: restore a replaced folder, drop unfinished scratch output.

        Only for the holder of the folder's lock: another process's stage in progress looks just the same.
        """
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


# --- names and locks -------------------------------------------------------------------------------------
def check_run_name(name: str) -> str:
    """``name`` if it is a plain folder name (what ``--name`` may be), else an :class:`InputError`.

    No path: not blank, no ``/`` (or the system's other separator), not ``.`` or ``..``, no NUL, so the
    run folder ``OUT/<name>`` is always directly inside ``OUT``.
    """
    seps = {os.sep, os.altsep or os.sep}
    if not name.strip() or name in (".", "..") or any(c in name for c in (*seps, "\0")):
        raise InputError(
            f"--name {name!r} is not a plain folder name; give a non-empty name without '/', other than '.' "
            "and '..' (the run folder is made inside --out)"
        )
    return name


def check_out_dir(out: Path) -> Path:
    """``out`` if it can hold run folders (a folder, or absent), else an :class:`InputError`."""
    if out.exists() and not out.is_dir():
        raise InputError(
            f"--out {str(out)!r} is a file, not a folder; pass the folder that holds the run folders "
            "(it is created if absent)"
        )
    return out


def _make_folder(path: Path) -> None:
    """``path`` as a folder (with its parents), or an :class:`InputError` saying why it cannot be."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocker = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), path)
        raise InputError(
            f"cannot make run folder {str(path)!r}: {str(blocker)!r} is a file, not a folder; choose another --out"
        ) from None
    except OSError as err:
        raise InputError(
            f"cannot make run folder {str(path)!r} ({err.strerror}); choose an --out you can write in"
        ) from None
    names = {p.name for p in path.iterdir()} - {LOCK_FILE, PARTIAL_DIR}
    if names and RUN_FILE not in names:
        raise InputError(
            f"{str(path)!r} exists and is not a focusmap run folder (no {RUN_FILE}); choose another --name or --out"
        )


def _holder(text: str) -> str:
    """Who holds a lock, from its lock file's text (``host:pid what``), for an error message."""
    ident, _, what = text.strip().partition(" ")
    host, _, pid = ident.rpartition(":")
    if not pid.isdigit():
        return "another process"
    where = "" if host == socket.gethostname() else f" on {host}"
    return f"{what or 'a process'} (pid {pid}{where})"


@contextlib.contextmanager
def run_folder_lock(
    path: Path, *, wait_s: float = 0.0, who: str = "focusmap", then: str = "run the command again"
) -> Iterator[None]:
    """Hold the exclusive lock of the run folder ``path`` (made if absent) while writing in it.

    The lock is ``flock`` on ``<run>/.focusmap.lock``: the kernel releases it when the holder's process
    ends, however it ends, so a killed command never leaves a folder locked. The holder writes
    ``host:pid who`` into the file for the message another process gets. A folder nobody can write in
    (read-only) is locked through a read-only descriptor (or not at all if it has no lock file yet):
    reading an up-to-date folder then works, and the first write fails with its own clear error.
    Locks are advisory; on systems without ``fcntl`` none is taken.

    Args:
        wait_s: how long to wait for another holder to finish before giving up (0: give up at once).
        who: what the holder is, as the busy message shows it (``focusmap run``).
        then: what to do once the holder has finished, the busy message's last words.

    Raises:
        InputError: the folder is busy (another process holds the lock after ``wait_s``), or ``path``
            cannot be a run folder (a file, a folder that is not a run folder, no permission to make it).
    """
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        yield
        return
    _make_folder(path)
    lock = path / LOCK_FILE
    writable = True
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        if err.errno not in _READ_ONLY:
            raise
        writable = False
        try:
            fd = os.open(lock, os.O_RDONLY)
        except FileNotFoundError:  # a read-only folder without a lock file: nobody can lock it, or write in it
            yield
            return
    try:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    try:
                        held_by = _holder(lock.read_text())
                    except OSError:
                        held_by = "another process"
                    raise InputError(
                        f"run folder {str(path)!r} is busy: {held_by} is working in it; "
                        f"wait for it to finish (or stop it), then {then}"
                    ) from None
                time.sleep(0.2)
        if writable:
            os.ftruncate(fd, 0)
            os.write(fd, f"{socket.gethostname()}:{os.getpid()} {who}\n".encode())
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock
