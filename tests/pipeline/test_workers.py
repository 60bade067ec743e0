"""Worker processes die with the command that started them, and a Ctrl-C prints one line (pipeline/workers.py).

Every command runs in a session of its own, so "its processes" are the processes of that session: the
command, detect's pool workers, batch's workers and their pools, the multiprocessing resource tracker. The
5 s below are a timeout for them to go, not a measured time.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline.config import load_settings
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages import REGISTRY
from tests.fixtures.office import SAMPLE

ROOT = Path(__file__).resolve().parents[2]
SETS = ("--set", "detect.workers=2", "--set", "detect.tag_size_m=0.16")
_SIGINT_BIT = 1 << (signal.SIGINT - 1)

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds processes through /proc")


def _focusmap(*args: str) -> list[str]:
    """``focusmap ARGS`` as a user runs it: the console script beside the interpreter when there is one."""
    script = shutil.which("focusmap", path=str(Path(sys.executable).parent))
    return [sys.executable, script, *args] if script else [sys.executable, "-c", "from cli.app import main; main()"]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"}


def _start(cmd: list[str], stderr: Path) -> subprocess.Popen[str]:
    """``cmd`` in a session of its own (its pid is the session id), as a terminal runs a command.

    Its stderr goes to a file, not a pipe: a surviving worker would hold a pipe open, and reading it would hang.
    """
    with stderr.open("w") as err:
        return subprocess.Popen(
            cmd,
            env=_env(),
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=err,
            text=True,
            start_new_session=True,
            preexec_fn=_as_from_a_terminal,
        )


def _as_from_a_terminal() -> None:
    """SIGINT as a terminal's foreground command gets it: default action. The child would otherwise inherit this test
    process's disposition, and when the whole suite runs, an earlier in-process test can leave SIGINT ignored here
    (seen in fresh CI environments: the command then ran through the Ctrl-C with exit 0)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _session(sid: int) -> dict[int, tuple[int, str, bool]]:
    """The live processes of session ``sid``: pid -> (parent pid, command line, whether it ignores SIGINT)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            status = (entry / "status").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # ended meanwhile
            continue
        state, ppid, session = fields[0], int(fields[1]), int(fields[3])
        if session != sid or state in ("Z", "X"):
            continue
        ignored = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigIgn:")), 16)
        found[int(entry.name)] = (ppid, cmdline, bool(ignored & _SIGINT_BIT))
    return found


def _pool_workers(sid: int, *, running: bool) -> list[int]:
    """Pool workers in session ``sid`` (spawned interpreters ignoring SIGINT); all of them unless ``running``.

    A worker ignores SIGINT once it runs its own code (``start_worker``), after its imports.
    """
    workers = []
    for pid, (_, cmdline, ignores) in _session(sid).items():
        if "spawn_main" in cmdline and (ignores or not running):
            workers.append(pid)
    return workers


def _wait_for(
    proc: subprocess.Popen[str], stderr: Path, what: str, ready: Callable[[], bool], timeout_s: float = 90.0
) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready():
        if proc.poll() is not None:
            pytest.fail(f"the command ended (exit {proc.returncode}) before {what}: {stderr.read_text()[-2000:]}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"no {what} within {timeout_s:.0f} s")
        time.sleep(0.05)


def _survivors(sid: int, timeout_s: float = 5.0) -> dict[int, tuple[int, str, bool]]:
    """The processes of session ``sid`` still alive after waiting up to ``timeout_s`` for them to end (killed then)."""
    deadline = time.monotonic() + timeout_s
    while (left := _session(sid)) and time.monotonic() < deadline:
        time.sleep(0.05)
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    return left


@pytest.fixture(scope="module")
def office(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The office sample ingested (575 frames: detect with two workers runs for several seconds)."""
    run = RunFolder.create(tmp_path_factory.mktemp("workers") / "office", SAMPLE)
    run_stage(run, REGISTRY, "ingest", load_settings(REGISTRY.models(), None, []), progress=False)
    return run.path


def test_killed_detect_takes_its_pool_and_the_resource_tracker_with_it(office: Path, tmp_path: Path) -> None:
    err = tmp_path / "stderr"
    proc = _start(_focusmap("detect", str(office), "--force", *SETS), err)
    _wait_for(proc, err, "two detect workers at work", lambda: len(_pool_workers(proc.pid, running=True)) == 2)
    assert len(_session(proc.pid)) >= 4, "expected the command, two workers and the resource tracker"
    proc.kill()
    proc.wait()
    assert not _survivors(proc.pid), "processes of the killed command still alive after 5 s"


@pytest.mark.parametrize("inherited", ["default", "blocked"])
def test_ctrl_c_while_detect_workers_start_prints_one_line(office: Path, tmp_path: Path, inherited: str) -> None:
    """A terminal's Ctrl-C reaches every process of the command; the workers are still importing their libraries.

    ``blocked``: the command inherits SIGINT blocked (from a parent that held it while starting it, as this very
    test process may after an in-process test started workers): it must still take the Ctrl-C."""
    stderr = tmp_path / "stderr"
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT}) if inherited == "blocked" else None
    try:
        proc = _start(_focusmap("detect", str(office), "--force", *SETS), stderr)
    finally:
        if held is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
    _wait_for(proc, stderr, "two detect workers", lambda: len(_pool_workers(proc.pid, running=False)) == 2)
    os.killpg(proc.pid, signal.SIGINT)
    proc.wait(timeout=120)
    err = stderr.read_text()
    assert proc.returncode == 130, err
    assert [line for line in err.splitlines() if line.strip()] == [
        "error: interrupted; finished stages are kept, the interrupted one left no output"
    ], err
    assert not _survivors(proc.pid)
    assert not (office / "detect").exists(), "the interrupted stage left output"


def test_killed_batch_takes_its_workers_and_their_pools_with_it(tmp_path: Path) -> None:
    bags = []
    for name in ("a.bag", "b.bag"):
        bags.append(tmp_path / name)
        shutil.copyfile(SAMPLE, bags[-1])
    out = tmp_path / "runs"
    cmd = _focusmap("batch", *map(str, bags), "--out", str(out), "--until", "detect", "--workers", "2", *SETS)
    err = tmp_path / "stderr"
    proc = _start(cmd, err)
    # Two batch workers (SIGINT taken: they abort their stage on Ctrl-C), each with a detect pool of two.
    _wait_for(proc, err, "a detect pool at work", lambda: len(_pool_workers(proc.pid, running=True)) >= 2)
    proc.kill()
    proc.wait()
    assert not _survivors(proc.pid), "processes of the killed batch still alive after 5 s"


_STARTER = """
import sys, time
from pipeline import workers

def child(kernel: bool) -> None:
    if not kernel:
        workers._kernel_kills_orphans = lambda: False  # the watchdog thread, as where prctl does not exist
    workers.start_worker()
    time.sleep(120)

if __name__ == "__main__":
    workers.spawn_context().Process(target=child, args=(sys.argv[1] == "kernel",)).start()
    time.sleep(120)
"""


@pytest.mark.parametrize("how", ["kernel", "watchdog"])
def test_a_worker_dies_with_its_parent(how: str, tmp_path: Path) -> None:
    """Both ways of :func:`pipeline.workers.die_with_parent`: the kernel's parent-death signal, the watchdog thread."""
    script = tmp_path / "starter.py"
    script.write_text(textwrap.dedent(_STARTER))
    proc = _start([sys.executable, str(script), how], tmp_path / "stderr")
    _wait_for(proc, tmp_path / "stderr", "a started worker", lambda: len(_pool_workers(proc.pid, running=True)) == 1)
    proc.kill()
    proc.wait()
    assert not _survivors(proc.pid), f"the worker outlived its parent ({how})"
