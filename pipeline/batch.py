"""Batch execution: the pipeline over many recordings, in local worker processes or on a Dask cluster.

One task per recording. A task runs the requested stages of the registry on the recording's run
folder (``OUT/<run name>``, named as ``focusmap run`` names it, or by a longer path suffix when
two recordings share that name: :func:`run_names`) with :func:`pipeline.runner.run_stage`,
so up-to-date stages are skipped and every stage appears whole or not at all. A task never raises:
whatever goes wrong becomes a ``failed`` :class:`Outcome` with a one-line reason, and the other
recordings go on.

Two back-ends run the same :func:`run_task`:

- :func:`run_local`: at most ``workers`` child processes at a time, one process per recording, so a
  crash (a segfault in a native library, the OOM killer) fails that recording only. Children die
  with the batch process (:mod:`pipeline.workers`), draw no progress bars (only the batch's own bar is drawn),
  and take the run folder's lock (:func:`pipeline.run_folder.run_folder_lock`, as every command that writes in a
  run folder does), waiting up to ``LOCK_WAIT_S`` for it, so two processes never work on one run folder.
- :func:`run_dask`: the tasks on an existing ``dask.distributed`` cluster. The run folders are
  written by the workers, so ``OUT`` must be storage every worker sees at the same path.

Nothing here knows about robotics: the stages come from a registry named by an import spec
(``"stages:REGISTRY"``), resolved in the worker, and the recording check that ``focusmap run``
does before creating a run folder is another spec (``preflight``).
"""

from __future__ import annotations

import contextlib
import glob
import importlib
import multiprocessing
import multiprocessing.connection
import os
import signal
import socket
import sys
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.context import SpawnProcess
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, Literal

import pyarrow as pa

from pipeline.batch_file import BatchEntry, BatchFileError
from pipeline.config import Settings
from pipeline.errors import InputError, PipelineError
from pipeline.json_types import JSONValue
from pipeline.registry import Headline, Registry
from pipeline.run_folder import RunFolder, StageEntry, run_folder_lock
from pipeline.workers import ignore_interrupts, interrupts_held, spawn_context, start_worker

if TYPE_CHECKING:
    from rich.console import Console

Status = Literal["done", "skipped", "failed"]

SUMMARY_FILE: Final = "batch_summary.parquet"
ERRORS_FILE: Final = "batch_errors.log"
LOCK_WAIT_S: Final = 60.0

OutcomeCallback = Callable[["Outcome"], None]


@dataclass(frozen=True)
class BatchTask:
    """One recording to run: everything a worker needs, picklable, with absolute paths.

    Attributes:
        recording: the recording (a bag file or a ROS 2 bag folder).
        run_dir: its run folder, ``OUT/<run name>``.
        stages: names of the stages to run, in order.
        settings: the recording's resolved settings (the batch's, or its own from a batch file).
        force: re-run stages even if they are up to date.
        registry: ``"module:attribute"`` of the :class:`~pipeline.registry.Registry`.
        preflight: optional ``"module:function"`` called with the recording's path before the run
            folder is created; it raises a :class:`~pipeline.errors.PipelineError` for a file that
            is no recording, so such a file leaves no run folder behind (as in ``focusmap run``).
    """

    recording: str
    run_dir: str
    stages: tuple[str, ...]
    settings: Settings
    force: bool = False
    registry: str = "stages:REGISTRY"
    preflight: str | None = None

    @property
    def run(self) -> str:
        """The run folder's name."""
        return Path(self.run_dir).name


@dataclass
class Outcome:
    """What happened to one recording.

    Attributes:
        recording: the recording's path.
        run: the run folder's name.
        run_dir: the run folder.
        status: ``done`` (at least one stage ran, all finished), ``skipped`` (every stage was up to
            date) or ``failed``.
        reason: the one-line reason of a failure, else None.
        failed_stage: the stage that was running when it failed, if any.
        seconds: wall time of the task in this batch.
        stages_run: the stages that ran in this batch (not skipped).
        stages: per stage whose finished result is current: its manifest ``fingerprint``,
            ``finished``, ``seconds`` and ``summary``.
        host: ``hostname:pid`` of the process that ran the task.
        traceback: the traceback of an unexpected exception (internal errors only).
    """

    recording: str
    run: str
    run_dir: str
    status: Status
    reason: str | None = None
    failed_stage: str | None = None
    seconds: float = 0.0
    stages_run: list[str] = field(default_factory=list)
    stages: dict[str, StageEntry] = field(default_factory=dict)
    host: str = ""
    traceback: str | None = None


# --- planning ---------------------------------------------------------------------------------------
_GLOB_CHARS: Final = frozenset("*?[")


def collect_recordings(patterns: Sequence[str]) -> list[Path]:
    """The recordings named by paths and glob patterns, in the order given, each once.

    An existing path is taken as it is (even if it contains glob characters); anything else is a
    glob pattern (``**`` recurses) whose matches are taken in sorted order.

    Raises:
        InputError: when a path does not exist or a pattern matches nothing.
    """
    found: list[Path] = []
    seen: set[Path] = set()
    for pattern in patterns:
        path = Path(pattern).expanduser()
        if path.exists():
            matches = [path]
        elif _GLOB_CHARS & set(pattern):
            matches = [Path(m) for m in sorted(glob.glob(str(path), recursive=True))]
            if not matches:
                raise InputError(
                    f"no recording matches {pattern!r}; check the pattern (quote it to let focusmap expand it)"
                )
        else:
            raise InputError(
                f"recording {pattern!r} does not exist; pass bag files, ROS 2 bag folders or glob patterns"
            )
        for match in matches:
            key = match.resolve()
            if key not in seen:
                seen.add(key)
                found.append(match)
    if not found:
        raise InputError("no recordings given; pass bag files, ROS 2 bag folders or glob patterns")
    return found


def run_name(recording: Path) -> str:
    """The run folder name ``focusmap run`` gives a recording: a folder's name or a file's stem."""
    base = recording.resolve()
    return base.name if base.is_dir() else base.stem


def _name_parts(recording: Path) -> tuple[str, ...]:
    """The resolved path's folders (without the root) and the recording's run name, outermost first."""
    base = recording.resolve()
    return (*(p for p in base.parent.parts if p != base.anchor), run_name(recording))


def run_names(recordings: Sequence[Path]) -> list[str | None]:
    """Run folder names for a batch: ``focusmap run``'s name, made unique by the shortest distinguishing path suffix.

    A recording whose name no other one shares keeps it (``OUT/<stem>``). Recordings that share one get the
    shortest suffix of their resolved path that none of the others ends with, joined by ``_``: ``a/run_bag``
    and ``b/run_bag`` become ``a_run_bag`` and ``b_run_bag``; ``x/a/day.bag`` beside ``y/a/day.bag`` and
    ``z/b/day.bag`` gives ``x_a_day``, ``y_a_day`` and ``b_day``. The names depend only on the recordings'
    paths, so the same batch run again gets the same folders. None where nothing distinguishes a recording
    (the same one listed twice).
    """
    parts = [_name_parts(r) for r in recordings]
    groups: dict[str, list[int]] = {}
    for i, p in enumerate(parts):
        groups.setdefault(p[-1], []).append(i)
    names: list[str | None] = [p[-1] for p in parts]
    for members in groups.values():
        if len(members) < 2:
            continue
        for i in members:
            names[i] = None
            for k in range(2, len(parts[i]) + 1):
                suffix = parts[i][-k:]
                if all(parts[j][-k:] != suffix for j in members if j != i):
                    names[i] = "_".join(suffix)
                    break
    return names


def plan_tasks(
    recordings: Sequence[Path | BatchEntry],
    out: Path,
    stages: Sequence[str],
    settings: Settings,
    *,
    force: bool = False,
    registry: str = "stages:REGISTRY",
    preflight: str | None = None,
    problems: Sequence[str] = (),
) -> list[BatchTask]:
    """One task per recording, in order, in run folder ``OUT/<name>`` (:func:`run_names`, or the entry's name).

    ``settings`` are those of every recording given as a path or as an entry without settings of its own.
    ``problems`` are those found earlier (a batch file's, :func:`pipeline.batch_file.read_batch_file`): they
    are reported with those of the names.

    Raises:
        BatchFileError: ``problems`` and those of the names, one per line, before anything runs: a recording
            listed twice without names, two recordings that would share a run folder (a given name that
            another recording's name takes).
    """
    out = out.expanduser().resolve()
    entries = [r if isinstance(r, BatchEntry) else BatchEntry(Path(r)) for r in recordings]
    derived = run_names([e.recording for e in entries if e.name is None])
    names: list[str | None] = []
    for e in entries:
        names.append(e.name if e.name is not None else derived.pop(0))
    problems = list(problems)
    unnamed: set[Path] = set()
    for e, name in zip(entries, names, strict=True):
        key = e.recording.resolve()
        if name is None and key not in unnamed:
            unnamed.add(key)
            problems.append(
                f"recording {str(e.recording)!r}: no path suffix tells it from another recording of the batch (or it "
                "is listed twice); give each its own name in a batch file"
            )
    by_name: dict[str, list[BatchEntry]] = {}
    for e, name in zip(entries, names, strict=True):
        if name is not None:
            by_name.setdefault(name, []).append(e)
    for name, clash in by_name.items():
        if len(clash) > 1:
            shown = ", ".join(f"{c.where} ({c.recording})" if c.where else repr(str(c.recording)) for c in clash)
            problems.append(
                f"duplicate name {name!r}: {shown} would all write run folder {str(out / name)!r}; "
                "give them different names in a batch file"
            )
    if problems:
        raise BatchFileError(problems)
    return [
        BatchTask(
            recording=str(e.recording.resolve()),
            run_dir=str(out / name),
            stages=tuple(stages),
            settings=e.settings if e.settings is not None else settings,
            force=force,
            registry=registry,
            preflight=preflight,
        )
        for e, name in zip(entries, names, strict=True)
        if name is not None
    ]


# --- one task ----------------------------------------------------------------------------------------
def resolve_spec(spec: str) -> Any:
    """The object named by ``"module:attribute"`` (``"stages:REGISTRY"``)."""
    module, _, attr = spec.partition(":")
    if not module or not attr:
        raise ValueError(f"expected 'module:attribute', got {spec!r}")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    if isinstance(err, PipelineError):
        return text or type(err).__name__
    return f"internal error {type(err).__name__}: {text} (traceback in {ERRORS_FILE} beside the summary)"


def _host() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _outcome_entry(entry: StageEntry) -> StageEntry:
    """What an outcome keeps of a manifest entry: its fingerprint, finish time, seconds and summary."""
    kept = StageEntry()
    if "fingerprint" in entry:
        kept["fingerprint"] = entry["fingerprint"]
    if "finished" in entry:
        kept["finished"] = entry["finished"]
    if "seconds" in entry:
        kept["seconds"] = entry["seconds"]
    if "summary" in entry:
        kept["summary"] = entry["summary"]
    return kept


def _current_entries(
    run: RunFolder, registry: Registry, stages: Sequence[str], settings: Settings
) -> dict[str, StageEntry]:
    """Manifest entries of the stages whose finished results are current (stale ones are left out)."""
    from pipeline.runner import is_current

    entries: dict[str, StageEntry] = {}
    manifest = run.manifest()["stages"]
    for name in stages:
        try:
            current = is_current(run, registry, name, settings)
        except Exception:  # a broken manifest entry or a vanished source: not current
            current = False
        if current:
            entries[name] = _outcome_entry(manifest[name])
    return entries


def run_task(task: BatchTask) -> Outcome:
    """Run one recording's stages in this process; never raises (except on KeyboardInterrupt).

    The same as ``focusmap run RECORDING --out OUT --until LAST``: the preflight check, the run
    folder (created or reused), the resolved settings beside the manifest, then each stage through
    :func:`pipeline.runner.run_stage`, which skips up-to-date stages and commits each stage atomically.
    """
    from pipeline.runner import run_stage, write_resolved_settings

    start = time.perf_counter()
    outcome = Outcome(recording=task.recording, run=task.run, run_dir=task.run_dir, status="failed", host=_host())
    run: RunFolder | None = None
    registry: Registry | None = None
    current: str | None = None
    try:
        registry = resolve_spec(task.registry)
        if task.preflight:
            resolve_spec(task.preflight)(Path(task.recording))
        with run_folder_lock(Path(task.run_dir), wait_s=LOCK_WAIT_S, who="focusmap batch", then="run the batch again"):
            run = RunFolder.create(Path(task.run_dir), Path(task.recording))
            write_resolved_settings(run, task.settings)
            for name in task.stages:
                current = name
                result = run_stage(run, registry, name, task.settings, force=task.force, progress=False)
                if result.status == "done":
                    outcome.stages_run.append(name)
            current = None
            outcome.stages = _current_entries(run, registry, task.stages, task.settings)
        outcome.status = "done" if outcome.stages_run else "skipped"
    except Exception as err:
        outcome.reason = _one_line(err)
        outcome.failed_stage = current
        if not isinstance(err, PipelineError):
            outcome.traceback = traceback.format_exc()
        if run is not None and registry is not None:
            with contextlib.suppress(Exception):
                outcome.stages = _current_entries(run, registry, task.stages, task.settings)
    outcome.seconds = round(time.perf_counter() - start, 3)
    return outcome


def failed_outcome(task: BatchTask, reason: str) -> Outcome:
    """A failed outcome for a task that produced none (its worker died, the batch was interrupted)."""
    return Outcome(recording=task.recording, run=task.run, run_dir=task.run_dir, status="failed", reason=reason)


# --- local back-end -------------------------------------------------------------------------------------
def _child_main(task: BatchTask, conn: multiprocessing.connection.Connection) -> None:
    """Entry point of a local worker process: run the task, send the outcome back.

    The worker dies with the batch process (:mod:`pipeline.workers`). It takes Ctrl-C while it runs
    the task, to abort its stage cleanly and report it interrupted (a Ctrl-C that came while it was
    starting counts too), and ignores it while it hands the outcome back.
    """
    try:
        start_worker(interrupts=True)
        outcome = run_task(task)
        ignore_interrupts()
    except KeyboardInterrupt:
        ignore_interrupts()
        outcome = failed_outcome(task, "interrupted; finished stages are kept, the interrupted one left no output")
    conn.send(outcome)
    conn.close()


def _describe_exit(code: int | None) -> str:
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"the worker process died ({name})"
    return f"the worker process exited with code {code} without a result"


def _ready(conns: Iterable[Connection], timeout: float | None = None) -> list[Connection]:
    """``multiprocessing.connection.wait`` for pipe connections: those with something to read, in its order."""
    return [c for c in multiprocessing.connection.wait(list(conns), timeout) if isinstance(c, Connection)]


def run_local(tasks: Sequence[BatchTask], workers: int, on_outcome: OutcomeCallback | None = None) -> list[Outcome]:
    """Run the tasks in at most ``workers`` child processes at a time, one process per recording.

    Returns the outcomes in task order. A child that dies without a result (a crash) fails its
    recording only. On KeyboardInterrupt the running children get a few seconds to abort their
    stage cleanly, are then terminated, and the interrupt propagates.
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    ctx = spawn_context()
    queue = deque(enumerate(tasks))
    running: dict[Connection, tuple[int, SpawnProcess, BatchTask]] = {}
    results: list[Outcome | None] = [None] * len(tasks)

    def finish(conn: Connection) -> None:
        i, proc, task = running.pop(conn)
        try:
            outcome: Outcome | None = conn.recv()
        except (EOFError, OSError):
            outcome = None
        conn.close()
        proc.join()
        done = outcome if outcome is not None else failed_outcome(task, _describe_exit(proc.exitcode))
        results[i] = done
        if on_outcome is not None:
            on_outcome(done)

    try:
        while queue or running:
            while queue and len(running) < workers:
                i, task = queue.popleft()
                with interrupts_held():  # the child starts deaf to Ctrl-C; one meant for us comes once it is recorded
                    recv, send = ctx.Pipe(duplex=False)
                    proc = ctx.Process(target=_child_main, args=(task, send), name=f"focusmap-batch:{task.run}")
                    proc.start()
                    send.close()
                    running[recv] = (i, proc, task)
            for conn in _ready(running):
                finish(conn)
    except BaseException:
        deadline = time.monotonic() + 5.0
        while running and time.monotonic() < deadline:  # children got the same SIGINT: let them abort cleanly
            for conn in _ready(running, timeout=0.2):
                with contextlib.suppress(Exception):
                    finish(conn)
        for _, proc, _ in running.values():
            proc.terminate()
        for _, proc, _ in running.values():
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
        raise
    return [r for r in results if r is not None]


# --- dask back-end --------------------------------------------------------------------------------------
def _allow_child_processes() -> None:
    """Let a task start processes of its own inside a Dask worker.

    Worker processes started by a nanny are daemonic, and ``multiprocessing`` refuses to start
    children from a daemonic process; stages such as detect run their own process pool. The nanny
    still kills the worker process when it restarts it; the stage pools end with their parent.
    """
    proc = multiprocessing.current_process()
    if proc.daemon:
        proc._config["daemon"] = False  # type: ignore[attr-defined]


def _dask_entry(task: BatchTask) -> Outcome:
    """What a Dask worker runs: child processes allowed, then :func:`run_task` (which draws no progress bars)."""
    _allow_child_processes()
    return run_task(task)


def run_dask(
    tasks: Sequence[BatchTask],
    scheduler: str,
    on_outcome: OutcomeCallback | None = None,
    connect_timeout_s: float = 30.0,
) -> list[Outcome]:
    """Run the tasks on the ``dask.distributed`` cluster at ``scheduler`` (``tcp://host:8786``).

    The run folders are written by the workers: every path (recordings, ``OUT``) must mean the same
    storage on every worker. A task lost with its worker more often than the cluster allows
    (``KilledWorker``) fails its recording only.

    Raises:
        InputError: when the scheduler cannot be reached or has no workers.
    """
    try:
        from distributed import Client, as_completed
    except ImportError as err:
        raise InputError(
            "--scheduler needs dask.distributed; install it with: pip install 'dask[distributed]'"
        ) from err
    try:
        client = Client(scheduler, timeout=connect_timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as err:
        raise InputError(
            f"cannot reach the Dask scheduler at {scheduler!r} ({' '.join(str(err).split())}); "
            "start one with 'dask scheduler' and workers with 'dask worker ADDRESS', or drop --scheduler"
        ) from None
    results: list[Outcome | None] = [None] * len(tasks)
    with client:
        try:
            client.wait_for_workers(1, timeout=connect_timeout_s)
        except (OSError, TimeoutError):
            raise InputError(
                f"the Dask scheduler at {scheduler!r} has no workers; start some with 'dask worker {scheduler}'"
            ) from None
        token = f"{os.getpid()}-{time.time_ns()}"
        futures = {
            client.submit(_dask_entry, task, key=f"focusmap-batch-{task.run}-{i}-{token}", pure=False, retries=0): i
            for i, task in enumerate(tasks)
        }
        try:
            for future in as_completed(futures, loop=client.loop):
                i = futures[future]
                try:
                    outcome: Outcome = future.result()
                except Exception as err:  # the task never returned: KilledWorker, cancelled, unpicklable...
                    outcome = failed_outcome(tasks[i], f"dask: {type(err).__name__}: {' '.join(str(err).split())}")
                results[i] = outcome
                if on_outcome is not None:
                    on_outcome(outcome)
        except BaseException:
            client.cancel(list(futures))
            raise
    return [r for r in results if r is not None]


# --- the batch -------------------------------------------------------------------------------------------
@dataclass
class BatchResult:
    """The outcomes of a batch, in task order, and whether it was interrupted."""

    outcomes: list[Outcome]
    interrupted: bool = False

    @property
    def failed(self) -> int:
        """How many recordings failed."""
        return sum(o.status == "failed" for o in self.outcomes)


def run_batch(
    tasks: Sequence[BatchTask],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = False,
) -> BatchResult:
    """Run every task, locally (``workers`` processes, default the number of cores) or on a Dask cluster.

    Draws one overall progress bar when ``progress`` (the workers draw none). On KeyboardInterrupt the
    recordings without an outcome are listed as failed ("interrupted") and ``interrupted`` is set; finished
    stages are kept in every case.
    """
    from pipeline.progress import new_progress

    results: dict[int, Outcome] = {}
    index = {(t.recording, t.run_dir): i for i, t in enumerate(tasks)}
    interrupted = False
    bar = new_progress(progress)
    with bar:
        bar_task = bar.add_task(f"batch of {len(tasks)}", total=len(tasks))

        def on_outcome(outcome: Outcome) -> None:
            results[index[(outcome.recording, outcome.run_dir)]] = outcome
            failed = sum(o.status == "failed" for o in results.values())
            label = f"batch of {len(tasks)}" + (f" ({failed} failed)" if failed else "")
            bar.update(bar_task, advance=1, description=label)

        try:
            if not tasks:
                pass
            elif scheduler:
                run_dask(tasks, scheduler, on_outcome)
            else:
                run_local(tasks, max(1, min(workers or os.cpu_count() or 1, len(tasks))), on_outcome)
        except KeyboardInterrupt:
            interrupted = True
    outcomes = [
        results.get(i) or failed_outcome(t, "interrupted before it finished; run the batch again to finish it")
        for i, t in enumerate(tasks)
    ]
    return BatchResult(outcomes, interrupted)


# --- summary -------------------------------------------------------------------------------------------
def _headline(stages: Mapping[str, StageEntry], column: str, headline: Headline) -> int | float | None:
    candidates, dtype = headline.places, pa.type_for_alias(headline.dtype)
    fallback = tuple((stage, column) for stage in reversed(list(stages)))
    for stage, key in (*candidates, *fallback):
        node: JSONValue = (stages.get(stage) or StageEntry()).get("summary") or {}
        *parents, leaf = key.split(".")
        for part in parents:  # dotted keys reach into nested summaries ("headline.collision_rate")
            node = node.get(part) if isinstance(node, dict) else None
            if not isinstance(node, dict):
                break
        if not isinstance(node, dict) or leaf not in node:
            continue
        value = node[leaf]
        if isinstance(value, list | tuple) and pa.types.is_integer(dtype):
            return len(value)
        if isinstance(value, bool) or not isinstance(value, int | float):
            continue
        return int(value) if pa.types.is_integer(dtype) else float(value)
    return None


def summary_schema(stages: Sequence[str], registry: Registry) -> pa.Schema:
    """Columns of ``batch_summary.parquet`` for a batch of ``stages`` (headline columns from ``registry``)."""
    fields: list[tuple[str, pa.DataType]] = [
        ("recording", pa.string()),
        ("run", pa.string()),
        ("run_dir", pa.string()),
        ("status", pa.string()),
        ("reason", pa.string()),
        ("failed_stage", pa.string()),
        ("seconds", pa.float64()),
        ("stages_run", pa.list_(pa.string())),
        ("host", pa.string()),
        *((f"seconds_{s}", pa.float64()) for s in stages),
        *((name, pa.type_for_alias(h.dtype)) for name, h in registry.headlines.items()),
    ]
    return pa.schema(fields)


def summary_table(outcomes: Sequence[Outcome], stages: Sequence[str], registry: Registry) -> pa.Table:
    """One row per recording: status, reason, times and the headline figures (null where absent).

    ``seconds`` is the task's wall time in this batch; ``seconds_<stage>`` is the time the stage's
    current result took when it was computed (also for a stage skipped as up to date), null when the
    stage has no current result.
    """
    schema = summary_schema(stages, registry)
    rows = []
    for o in outcomes:
        row: dict[str, object] = {
            "recording": o.recording,
            "run": o.run,
            "run_dir": o.run_dir,
            "status": o.status,
            "reason": o.reason,
            "failed_stage": o.failed_stage,
            "seconds": o.seconds,
            "stages_run": list(o.stages_run),
            "host": o.host or None,
        }
        for s in stages:
            secs = (o.stages.get(s) or {}).get("seconds")
            row[f"seconds_{s}"] = float(secs) if isinstance(secs, int | float) else None
        for name, h in registry.headlines.items():
            row[name] = _headline(o.stages, name, h)
        rows.append(row)
    return pa.Table.from_pylist(rows, schema=schema)


def write_summary(table: pa.Table, out: Path) -> Path:
    """Write ``OUT/batch_summary.parquet`` atomically (temporary name, then rename)."""
    import pyarrow.parquet as pq

    out.mkdir(parents=True, exist_ok=True)
    path = out / SUMMARY_FILE
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path


def write_errors(outcomes: Sequence[Outcome], out: Path) -> Path | None:
    """Write the tracebacks of unexpected failures to ``OUT/batch_errors.log`` (removed when there are none)."""
    path = out / ERRORS_FILE
    crashes = [o for o in outcomes if o.traceback]
    if not crashes:
        path.unlink(missing_ok=True)
        return None
    text = "".join(
        f"== {o.recording} (run {o.run}, stage {o.failed_stage}, {o.host})\n{o.traceback}\n" for o in crashes
    )
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def _fmt(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1e-2 or abs(value) >= 1e4 else f"{value:.2f}"
    return str(value)


def print_summary(table: pa.Table, registry: Registry, console: Console | None = None) -> None:
    """Print the summary as a rich table: per recording its status, times, headline figures and reason.

    Headline columns that are null for every recording are left out; labels come from ``registry``.
    """
    from rich.console import Console
    from rich.table import Table

    console = console or Console(highlight=False, width=None if sys.stdout.isatty() else 200)
    data = table.to_pylist()
    stage_cols = [c for c in table.column_names if c.startswith("seconds_")]
    head_cols = [c for c in registry.headlines if c in table.column_names and any(r[c] is not None for r in data)]
    short = {**registry.short_names, **{c: h.short for c, h in registry.headlines.items() if h.short}}
    view = Table(title=f"batch: {len(data)} recordings", title_justify="left", pad_edge=False, padding=(0, 1))
    view.add_column("run", overflow="fold")
    view.add_column("status")
    view.add_column("s", justify="right")
    for c in stage_cols:
        view.add_column(short.get(c.removeprefix("seconds_"), c.removeprefix("seconds_")), justify="right")
    for c in head_cols:
        view.add_column(short.get(c, c.replace("_", " ")), justify="right")
    colours = {"done": "green", "skipped": "cyan", "failed": "bold red"}
    for r in data:
        status = r["status"] + (f" ({r['failed_stage']})" if r["failed_stage"] else "")
        view.add_row(
            r["run"],
            f"[{colours.get(r['status'], 'white')}]{status}[/]",
            _fmt(r["seconds"]),
            *(_fmt(r[c]) for c in stage_cols),
            *(_fmt(r[c]) for c in head_cols),
        )
    console.print(view)
    legend = [
        f"{short[k]} = {k.replace('_', ' ')}"
        for k in (*registry.headlines, *(c.removeprefix("seconds_") for c in stage_cols))
        if k in short and (k in head_cols or f"seconds_{k}" in stage_cols)
    ]
    console.print("[dim]stage columns: seconds the current result took; " + "; ".join(legend) + "[/]")
    for r in data:
        if r["reason"]:
            console.print(f"[bold red]{r['run']}[/]: {r['reason']}", soft_wrap=True)
    counts = {s: sum(r["status"] == s for r in data) for s in ("done", "skipped", "failed")}
    console.print(", ".join(f"{n} {s}" for s, n in counts.items()))
