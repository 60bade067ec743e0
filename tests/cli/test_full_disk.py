"""A full disk (or any failed write): one ``error:`` line naming the path, exit 1, no hang; earlier results whole."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import rerun.blueprint as rrb

from pipeline import recording
from pipeline.errors import WriteError, write_error

FOCUSMAP = [sys.executable, "-m", "cli.app"]
ROOT = Path(__file__).resolve().parents[2]
BAG = ROOT / "sample_data" / "office" / "office.bag"


def focusmap(*args: str | Path) -> subprocess.CompletedProcess[str]:
    # the timeout only guards against a hang; no wall time is asserted
    return subprocess.run([*FOCUSMAP, *map(str, args)], capture_output=True, text=True, cwd=ROOT, timeout=600)


def _mount_problem(path: Path) -> str | None:
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "mounting a small tmpfs needs root"
    proc = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=48m", "tmpfs", str(path)], capture_output=True, text=True
    )
    if proc.returncode != 0:
        return f"cannot mount a tmpfs here: {proc.stderr.strip() or proc.returncode}"
    return None


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 48 MB file system of its own, unmounted afterwards."""
    disk = tmp_path / "disk"
    disk.mkdir()
    problem = _mount_problem(disk)
    if problem is not None:
        pytest.skip(problem)
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def _fill(disk: Path, leave_kib: int) -> None:
    """Take all but ``leave_kib`` of the free space."""
    st = os.statvfs(disk)
    free = st.f_bavail * st.f_frsize
    with open(disk / "filler", "wb") as f:
        f.truncate(0)
        chunk = b"\0" * (1 << 20)
        todo = free - leave_kib * 1024
        while todo > 0:
            f.write(chunk[: min(len(chunk), todo)])
            todo -= len(chunk)


def _assert_write_error(proc: subprocess.CompletedProcess[str], path: Path) -> None:
    assert proc.returncode == 1, (proc.returncode, proc.stderr)
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: cannot write "), proc.stderr
    assert str(path) in last, last
    assert "No space left" in last, last
    assert "Traceback" not in proc.stderr
    assert "internal error" not in proc.stderr


@pytest.mark.skipif(not BAG.exists(), reason="sample_data/office/office.bag is not in this checkout")
def test_full_disk_fails_the_stage_and_keeps_earlier_results(small_disk: Path) -> None:
    done = focusmap("ingest", BAG, "--out", small_disk)
    assert done.returncode == 0, done.stderr
    run = small_disk / "office"
    before = {p.name: p.read_bytes() for p in (run / "ingest").iterdir()}
    manifest = json.loads((run / "manifest.json").read_text())
    _fill(small_disk, leave_kib=256)

    proc = focusmap("detect", run)  # detect writes far more than 256 KiB

    _assert_write_error(proc, run)
    assert {p.name: p.read_bytes() for p in (run / "ingest").iterdir()} == before
    assert json.loads((run / "manifest.json").read_text()) == manifest
    assert not (run / "detect").exists()
    assert not (run / "detect.rrd").exists()
    assert not (run / ".partial").exists() or not any((run / ".partial").iterdir())


@pytest.mark.skipif(not BAG.exists(), reason="sample_data/office/office.bag is not in this checkout")
def test_full_disk_before_the_first_stage(small_disk: Path) -> None:
    _fill(small_disk, leave_kib=512)

    proc = focusmap("ingest", BAG, "--out", small_disk)

    _assert_write_error(proc, small_disk)
    assert not (small_disk / "office" / "ingest").exists()


def test_write_error_names_the_file_and_the_way_out(tmp_path: Path) -> None:
    full = write_error(OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "a.parquet")), tmp_path)
    assert isinstance(full, WriteError)
    assert str(tmp_path / "a.parquet") in str(full) and "free space" in str(full) and "--out" in str(full)
    unnamed = write_error(OSError(errno.ENOSPC, "Error writing bytes. Detail: [errno 28] ..."), tmp_path)
    assert unnamed is not None and repr(str(tmp_path)) in str(unnamed) and "No space left on device" in str(unnamed)
    # reading a file elsewhere that is not readable is no write failure
    assert write_error(PermissionError(errno.EACCES, "Permission denied", "/etc/shadow"), tmp_path) is None
    assert write_error(PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "x")), tmp_path) is not None
    assert write_error(FileNotFoundError(errno.ENOENT, "No such file", str(tmp_path / "x")), tmp_path) is None
    assert write_error(ValueError("no"), tmp_path) is None


def test_blueprint_write_failure_returns_at_once_and_keeps_the_old_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bp = rrb.Blueprint(rrb.Spatial3DView(origin="/"))
    path = tmp_path / "focusmap.rbl"
    recording.save_blueprint(bp, path)
    old = path.read_bytes()
    assert old.startswith(b"RRF")

    class FullFile:
        def __init__(self, *args: object, **kwargs: object) -> None:
            pass

        def __enter__(self) -> FullFile:
            return self

        def __exit__(self, *exc: object) -> None:
            pass

        def write(self, data: bytes) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(recording, "open", FullFile, raising=False)
    with pytest.raises(OSError) as caught:
        recording.save_blueprint(bp, path)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(path)
    assert path.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["focusmap.rbl"]


def test_recording_write_failure_raises_and_leaves_no_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "stage.rrd"
    rec = recording.open_recording("run-id", path)
    rec.log("/x", recording.rr.TextLog("hello"))

    def full(*args: object, **kwargs: object) -> object:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(recording, "open", full, raising=False)
    with pytest.raises(OSError) as caught:
        recording.close_recording(rec)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(path)
    assert not path.exists()
