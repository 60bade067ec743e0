"""The run folder's lock: one holder at a time, released when the holder dies (kill -9 included), plain names only."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from pipeline.errors import InputError
from pipeline.run_folder import (
    LOCK_FILE,
    RunFolder,
    check_out_dir,
    check_run_name,
    run_folder_lock,
)
from tests.fixtures.locks import hold_in_subprocess

ROOT = Path(__file__).resolve().parents[2]


def test_a_second_holder_is_told_the_folder_is_busy_and_by_whom(tmp_path: Path) -> None:
    run_dir = tmp_path / "r"
    with run_folder_lock(run_dir, who="focusmap run"):
        assert (run_dir / LOCK_FILE).read_text().split()[1:] == ["focusmap", "run"]
        with pytest.raises(InputError) as busy, run_folder_lock(run_dir):
            pytest.fail("two holders of one run folder")
    text = str(busy.value)
    assert f"run folder {str(run_dir)!r} is busy: focusmap run (pid {os.getpid()})" in text
    assert "then run the command again" in text
    with run_folder_lock(run_dir):  # let go: the next one gets it
        pass


def test_the_lock_is_released_when_its_holder_is_killed(tmp_path: Path) -> None:
    run_dir = tmp_path / "r"
    holder = hold_in_subprocess(run_dir)
    try:
        with pytest.raises(InputError, match=rf"busy: focusmap test \(pid {holder.pid}\)"), run_folder_lock(run_dir):
            pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with run_folder_lock(run_dir):  # at once: the kernel dropped the dead process's lock
        pass


def test_a_waiting_holder_gets_the_lock_when_the_other_lets_go(tmp_path: Path) -> None:
    run_dir = tmp_path / "r"
    holder = hold_in_subprocess(run_dir, seconds=0.5)
    try:
        assert not (run_dir / "let-go").exists()
        with run_folder_lock(run_dir, wait_s=120):
            assert (run_dir / "let-go").exists()  # it waited for the other to finish
    finally:
        holder.kill()
        holder.wait()


def test_opening_to_read_leaves_another_process_stage_in_progress_alone(tmp_path: Path) -> None:
    run = RunFolder.create(tmp_path / "r", None)
    scratch, _ = run.begin("s")  # what a stage of another process has written so far
    (scratch / "half.json").write_text("{}")
    RunFolder(run.path).manifest()
    assert (scratch / "half.json").is_file()
    with run.lock():  # the lock holder may clear it: nobody else can be writing
        assert not run.partial_root.exists()


@pytest.mark.parametrize("name", ["", " ", ".", "..", "../x", "../../x", "a/b", "/abs", "/", "x\0y"])
def test_a_run_name_is_a_plain_folder_name(name: str) -> None:
    with pytest.raises(InputError, match="is not a plain folder name"):
        check_run_name(name)


@pytest.mark.parametrize("name", ["office", "run-2", "a b", "..x", "x.."])
def test_plain_names_pass(name: str) -> None:
    assert check_run_name(name) == name


def test_out_naming_a_file_is_refused(tmp_path: Path) -> None:
    file = tmp_path / "f"
    file.write_text("x")
    with pytest.raises(InputError, match="is a file, not a folder"):
        check_out_dir(file)
    assert check_out_dir(tmp_path / "absent") == tmp_path / "absent"
    with pytest.raises(InputError, match=rf"{str(file)!r} is a file, not a folder"), run_folder_lock(file / "r"):
        pass
    assert file.read_text() == "x"


def test_a_folder_that_is_not_a_run_folder_is_not_taken(tmp_path: Path) -> None:
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "code.py").write_text("x = 1\n")
    with pytest.raises(InputError, match="is not a focusmap run folder"), run_folder_lock(tmp_path / "src"):
        pass
    assert [p.name for p in (tmp_path / "src").iterdir()] == ["code.py"]
