"""Commands that write in a run folder: one at a time (the lock), only inside --out, nothing written if all is current.

Each command runs as its own process (``python -m cli.app``), as a user starts it; the run folder is the
minimal bag's after ``run --until ingest`` (a second each).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import signal
import stat
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline.run_folder import LOCK_FILE, run_folder_lock
from tests.fixtures.bags import write_minimal_bag
from tests.fixtures.locks import hold_in_subprocess

ROOT = Path(__file__).resolve().parents[2]
Snapshot = dict[str, tuple[int, str]]


def focusmap(*args: str | Path, preexec_fn: Callable[[], None] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cli.app", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
        preexec_fn=preexec_fn,
    )


def one_error_line(proc: subprocess.CompletedProcess[str], *needles: str) -> str:
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def snapshot(folder: Path, skip: frozenset[str] = frozenset()) -> Snapshot:
    """Every file and folder under ``folder``: its modification time and, for a file, a hash of its bytes."""
    out: Snapshot = {str(folder): (folder.stat().st_mtime_ns, "")}
    for p in sorted(folder.rglob("*")):
        if p.name in skip:
            continue
        digest = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else ""
        out[str(p.relative_to(folder))] = (p.stat().st_mtime_ns, digest)
    return out


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The minimal bag and ``OUT`` with its run folder ``ok`` after ``run --until ingest``."""
    tmp = tmp_path_factory.mktemp("guard")
    bag = write_minimal_bag(tmp / "ok.bag")
    proc = focusmap("run", bag, "--out", tmp / "runs", "--until", "ingest")
    assert proc.returncode == 0, proc.stderr
    return bag, tmp / "runs"


@pytest.fixture
def out(made: tuple[Path, Path], tmp_path: Path) -> Path:
    """A fresh copy of ``OUT`` for a test that may change it."""
    return Path(shutil.copytree(made[1], tmp_path / "runs"))


@pytest.fixture
def bag(made: tuple[Path, Path]) -> Path:
    return made[0]


# --- one command at a time -------------------------------------------------------------------------------
def test_a_second_command_on_a_busy_folder_says_so_and_writes_nothing(bag: Path, out: Path) -> None:
    run_dir = out / "ok"
    with run_folder_lock(run_dir, who="focusmap run"):
        before = snapshot(out)
        commands = [
            ("run", bag, "--out", out, "--until", "ingest", "--force", "--set", "ingest.end_s=0.1"),
            ("ingest", bag, "--out", out, "--force"),
            ("detect", run_dir, "--set", "detect.workers=1"),
        ]
        for args in commands:
            proc = focusmap(*args)
            line = one_error_line(proc, f"run folder {str(run_dir)!r} is busy", f"(pid {os.getpid()})")
            assert "focusmap run" in line and "wait for it to finish" in line, line
        assert snapshot(out) == before  # settings.json, the manifest, the stage folders, the lock file: untouched


def test_import_graph_on_a_busy_folder_says_so(tmp_path: Path) -> None:
    graph = tmp_path / "tiny.g2o"
    graph.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 100 0 0 100 0 100\n")
    with run_folder_lock(tmp_path / "runs" / "tiny", who="focusmap import-graph"):
        before = snapshot(tmp_path / "runs")
        one_error_line(focusmap("import-graph", graph, "--out", tmp_path / "runs"), "is busy")
        assert snapshot(tmp_path / "runs") == before


def test_a_command_after_a_killed_holder_proceeds(bag: Path, out: Path) -> None:
    holder = hold_in_subprocess(out / "ok")
    try:
        one_error_line(focusmap("run", bag, "--out", out, "--until", "ingest"), "is busy", f"(pid {holder.pid})")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    proc = focusmap("run", bag, "--out", out, "--until", "ingest")
    assert proc.returncode == 0, proc.stderr
    assert "up to date" in proc.stdout


# --- where a run folder may be ----------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["../../escaped", "ABSOLUTE", "", ".", "..", "a/b"])
def test_name_must_be_a_plain_folder_name(bag: Path, tmp_path: Path, name: str) -> None:
    work = tmp_path / "work"
    work.mkdir()
    if name == "ABSOLUTE":
        name = str(tmp_path / "elsewhere")
    before = sorted(p.name for p in tmp_path.iterdir())
    one_error_line(focusmap("run", bag, "--out", work / "runs", "--until", "ingest", "--name", name), "--name")
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert not any(work.iterdir())


def test_out_naming_a_file_is_one_error_line(bag: Path, tmp_path: Path) -> None:
    file = tmp_path / "notes.txt"
    file.write_text("keep me\n")
    one_error_line(focusmap("run", bag, "--out", file, "--until", "ingest"), repr(str(file)), "is a file")
    one_error_line(focusmap("ingest", bag, "--out", file / "sub"), repr(str(file)), "is a file")
    assert file.read_text() == "keep me\n"


# --- nothing to do, nothing written ----------------------------------------------------------------------------
def test_an_up_to_date_run_writes_nothing_but_its_name_in_the_lock(bag: Path, out: Path) -> None:
    before = snapshot(out, skip=frozenset({LOCK_FILE}))
    proc = focusmap("run", bag, "--out", out, "--until", "ingest")
    assert proc.returncode == 0, proc.stderr
    assert "up to date" in proc.stdout
    assert snapshot(out, skip=frozenset({LOCK_FILE})) == before


def _drop_root_override() -> None:
    """In the child, before it starts Python: give up root's power to write files whose mode forbids it."""
    libc = ctypes.CDLL(None, use_errno=True)
    pr_capbset_drop, cap_dac_override, cap_dac_read_search = 24, 1, 2
    for cap in (cap_dac_override, cap_dac_read_search):
        if libc.prctl(pr_capbset_drop, cap, 0, 0, 0) != 0:
            os._exit(97)


def _as_a_user_who_cannot_write(read_only: Path) -> Callable[[], None] | None:
    """How to start a process that ``chmod a-w`` stops: as it is, or (as root) without the capabilities that
    let root write anyway; skips where neither works."""
    if os.geteuid() != 0:
        return None
    probe = subprocess.run(
        [sys.executable, "-c", f"open({str(read_only / 'probe')!r}, 'w')"], preexec_fn=_drop_root_override
    )
    if probe.returncode == 0 or probe.returncode == 97:
        pytest.skip("running as root, and root's capabilities cannot be dropped here: chmod would not stop a write")
    return _drop_root_override


@pytest.mark.parametrize("with_lock_file", [True, False], ids=["lock-file", "no-lock-file"])
def test_a_read_only_out_with_every_stage_up_to_date(bag: Path, out: Path, with_lock_file: bool) -> None:
    if not with_lock_file:  # a folder made before the lock existed
        (out / "ok" / LOCK_FILE).unlink()
    modes = {p: p.stat().st_mode for p in [out, *out.rglob("*")]}
    for p in modes:
        p.chmod(stat.S_IMODE(modes[p]) & ~0o222)
    try:
        as_user = _as_a_user_who_cannot_write(out)
        before = snapshot(out)
        proc = focusmap("run", bag, "--out", out, "--until", "ingest", preexec_fn=as_user)
        assert proc.returncode == 0, proc.stderr
        assert "up to date" in proc.stdout
        # a stage that has to write: one line, and still nothing written
        proc = focusmap("detect", out / "ok", "--set", "detect.workers=1", preexec_fn=as_user)
        one_error_line(proc, f"cannot write in run folder {str(out / 'ok')!r}")
        proc = focusmap("run", bag, "--out", out, "--name", "new", "--until", "ingest", preexec_fn=as_user)
        one_error_line(proc, f"cannot make run folder {str(out / 'new')!r}")
        assert snapshot(out) == before
    finally:
        for p, mode in modes.items():
            p.chmod(stat.S_IMODE(mode))
